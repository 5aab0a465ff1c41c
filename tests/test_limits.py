"""Driver and memory limits become failed cases that name the limit, and the run goes on;
a crashing, hanging or killed run loses nothing (worker isolation, resume)."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from lsbench import backends
from lsbench.backends import BuildParams, DeviceLimitError
from lsbench.backends.structures import grid
from lsbench.inputs.scenes import load_scene

REPO = Path(__file__).resolve().parents[1]


def lsbench(*args, env=None, timeout=300):
    return subprocess.run([sys.executable, "-m", "lsbench", *map(str, args)], cwd=REPO, capture_output=True,
                          text=True, timeout=timeout, env=dict(os.environ, **(env or {})))


def records(out: Path) -> list[dict]:
    return [json.loads(line) for line in (out / "results.jsonl").read_text().splitlines() if line.strip()]


def scenario(tmp_path, cases: str, run: str = "") -> Path:
    p = tmp_path / "s.toml"
    p.write_text(f'name = "limits"\n[run]\nwidth = 16\nheight = 12\nrepeats = 1\n{run}\n{cases}')
    return p


def case(backend: str, res, structure: str = "grid") -> str:
    return (f'[[cases]]\nscenes = ["cornell"]\nstructures = ["{structure}"]\nbackends = ["{backend}"]\n'
            f'resolutions = {json.dumps(res if isinstance(res, list) else [res])}\n')


# --- driver limits in-process: the error names the limit, the device stays usable -------------


def _still_works(device):
    built = backends.build(device, "grid", load_scene("cornell"), BuildParams(resolution=(4, 4, 4)))
    assert built.stats["references"] > 0
    built.release()


def test_glsl_ssbo_limit():
    dev = backends.get_device("glsl")
    if dev.max_buffer_bytes >= 512 * 2**20:
        pytest.skip("this GL driver allows 512 MiB buffers")
    with pytest.raises(DeviceLimitError, match="GL_MAX_SHADER_STORAGE_BLOCK_SIZE"):
        backends.build(dev, "grid", load_scene("cornell"), BuildParams(resolution=(512, 512, 512)))
    _still_works(dev)


def test_glsl_raster_viewport_limit():
    dev = backends.get_device("glsl")
    limit = int(dev.ctx.info["GL_MAX_VIEWPORT_DIMS"][0])
    with pytest.raises(DeviceLimitError, match="GL_MAX_VIEWPORT_DIMS"):
        backends.build(dev, "grid", load_scene("cornell"), BuildParams(resolution=(limit + 16, 1, 1)))
    _still_works(dev)  # the check runs before any GL call: no sticky GL error afterwards


def test_glsl_work_group_limit():
    dev = backends.get_device("glsl")
    assert dev._groups(grid.TRACE_GRID, 65535 * 64) == (65535, 1)
    assert dev._groups(grid.TRACE_GRID, 65535 * 64 + 1) == (65535, 2)  # spills into y
    with pytest.raises(DeviceLimitError, match="GL_MAX_COMPUTE_WORK_GROUP_COUNT"):
        dev._groups(grid.TRACE_GRID, 65535 * 65535 * 64 + 1)
    # more items than a 32-bit gid can index: refused before anything is bound or launched
    for d in (dev, backends.get_device("opencl")):
        with pytest.raises(DeviceLimitError, match="32-bit item index"):
            d.dispatch(grid.VOXELIZE_COUNT, 2**32 + 1, {b.name: d.alloc(b.name, 64) for b in grid.VOXELIZE_COUNT.buffers},
                       load_geometry_uniforms())
    _still_works(dev)


def load_geometry_uniforms():
    lo, hi = load_scene("cornell").bounds
    return backends.GridGeometry.over_bounds(lo, hi, (4, 4, 4)).uniforms()


def test_opencl_allocation_limit():
    dev = backends.get_device("opencl")
    with pytest.raises(DeviceLimitError, match="CL_DEVICE_MAX_MEM_ALLOC_SIZE"):
        dev.alloc("too_big", dev.max_buffer_bytes + 4)
    # a grid whose count buffer alone is over the limit fails before allocating anything
    side = int(round((dev.max_buffer_bytes / 4) ** (1 / 3))) + 8
    with pytest.raises(DeviceLimitError, match="voxel_counts"):
        backends.build(dev, "grid", load_scene("cornell"), BuildParams(resolution=(side, side, side)))
    _still_works(dev)


def test_glsl_storage_block_count_limit(monkeypatch):
    """A kernel binding more storage buffers than a compute shader may (llvmpipe: 16; e.g. a Line
    Space whose arrays are split into many buffers) fails naming the limit, before the driver's
    link error, and the device stays usable."""
    from lsbench.backends.structures import linespace

    dev = backends.get_device("glsl")
    limit = int(dev.ctx.info["GL_MAX_COMPUTE_SHADER_STORAGE_BLOCKS"])
    split_array = linespace.split_array
    monkeypatch.setattr(linespace, "LS_MAX_CHUNKS", 1000)
    monkeypatch.setattr(linespace, "split_array", lambda d, base, macro, entries: split_array(
        d, base, macro, entries, limit=256))  # 64 entries per buffer
    with pytest.raises(DeviceLimitError, match=f"over the driver's {limit} .*GL_MAX_COMPUTE_SHADER_STORAGE_BLOCKS"):
        backends.build(dev, "svo-ls", load_scene("cornell"), BuildParams(resolution=(4, 4, 4), ls_n=1))
    monkeypatch.undo()
    _still_works(dev)


def test_opencl_global_memory_limit(monkeypatch):
    """PoCL hands out buffers past its global memory; the backend counts live buffers and fails
    the allocation that would pass CL_DEVICE_GLOBAL_MEM_SIZE, naming it."""
    dev = backends.get_device("opencl")
    held = dev.alloc("held", 1 << 20)
    live = sum(dev._live.values())
    monkeypatch.setattr(type(dev), "global_mem_bytes", property(lambda self: live + (1 << 20)))
    with pytest.raises(DeviceLimitError, match="CL_DEVICE_GLOBAL_MEM_SIZE"):
        dev.alloc("more", (1 << 20) + 4)
    dev.release(held)
    dev.release(dev.alloc("more", (1 << 20) + 4))  # fits once `held` is gone
    # A Line Space whose offsets alone pass the memory fails before its count pass, naming it.
    monkeypatch.setattr(type(dev), "global_mem_bytes", property(lambda self: sum(self._live.values()) + 65536))
    with pytest.raises(DeviceLimitError, match="'ls_shaft_offsets' needs .*CL_DEVICE_GLOBAL_MEM_SIZE"):
        backends.build(dev, "grid-ls", load_scene("cornell"), BuildParams(resolution=(8, 8, 8), ls_n=2))
    monkeypatch.undo()
    _still_works(dev)


def test_32bit_reference_overflow(monkeypatch, device):
    """More than 2^32 - 1 references cannot be addressed by the uint offsets: refused, not
    wrapped (simulated: the scan reports a total past 32 bits)."""
    real = device.exclusive_scan

    def huge_total(src, n, name):
        out, _ = real(src, n, name)
        return out, 2**32 + 5

    monkeypatch.setattr(device, "exclusive_scan", huge_total)
    with pytest.raises(DeviceLimitError, match="32-bit"):
        backends.build(device, "grid", load_scene("cornell"), BuildParams(resolution=(4, 4, 4)))


# --- limits in a run: failed case naming the limit, the next case still runs ------------------


def test_run_records_limit_and_goes_on(tmp_path):
    out = tmp_path / "run"
    proc = lsbench("run", scenario(tmp_path, case("glsl", 512) + case("glsl", 8)), "--out", out)
    assert proc.returncode == 1, proc.stderr  # a case failed
    first, second = records(out)
    assert first["status"] == "failed" and "GL_MAX_SHADER_STORAGE_BLOCK_SIZE" in first["reason"]
    assert first["agreement"] is None
    assert second["status"] == "ok" and second["agreement"] == 1.0
    assert "FAILED" in proc.stdout


def test_memory_budget(tmp_path):
    """A case over --memory-budget fails with a reason naming the budget; the next one runs.
    The worker's baseline (Python, numpy, PoCL) is ~1 GiB of address space here, a 700^3 grid
    adds 1.3 GiB of counts: 2000 MiB separates the two with margin on either side."""
    out = tmp_path / "run"
    proc = lsbench("run", scenario(tmp_path, case("opencl", 700) + case("opencl", 8)), "--out", out,
                   "--memory-budget", 2000, "--allow-failed")
    assert proc.returncode == 0, proc.stderr
    first, second = records(out)
    assert first["status"] == "failed", first
    assert "memory budget of 2000 MiB" in first["reason"], first["reason"]
    assert second["status"] == "ok", second["reason"]


# --- worker isolation: crash, hang, kill -9 of the run itself -----------------------------------


@pytest.mark.parametrize("fault,needle", [("crash", "worker crashed (signal SIGKILL)"), ("hang", "timed out after 20 s")])
def test_worker_fault_fails_only_that_case(tmp_path, fault, needle):
    out = tmp_path / "run"
    scen = scenario(tmp_path, case("opencl", 4) + case("opencl", 8), run="timeout_seconds = 20")
    t0 = time.monotonic()
    proc = lsbench("run", scen, "--out", out, env={"LSBENCH_FAULT": f"{fault}:|r4|"})
    assert proc.returncode == 1, proc.stderr  # a case failed
    first, second = records(out)
    assert first["status"] == "failed" and needle in first["reason"], first["reason"]
    assert second["status"] == "ok"
    assert time.monotonic() - t0 < 120


def test_killed_run_resumes_and_fresh_redoes(tmp_path):
    out = tmp_path / "run"
    scen = scenario(tmp_path, case("opencl", [2, 4, 6, 8]))
    proc = subprocess.Popen([sys.executable, "-m", "lsbench", "run", str(scen), "--out", str(out)], cwd=REPO,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    results = out / "results.jsonl"
    deadline = time.monotonic() + 180
    while time.monotonic() < deadline and proc.poll() is None:
        if results.exists() and results.read_text().count("\n") >= 1:
            break
        time.sleep(0.05)
    assert proc.poll() is None, "the run finished before it could be killed"
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    done = records(out)
    assert 1 <= len(done) < 4
    again = lsbench("run", scen, "--out", out)
    assert again.returncode == 0, again.stderr
    assert again.stdout.count("done earlier") == len(done)
    final = records(out)
    assert sorted(r["key"] for r in final) == sorted({r["key"] for r in final})  # nothing twice
    assert len(final) == 4 and all(r["status"] == "ok" for r in final)
    fresh = lsbench("run", scen, "--out", out, "--fresh")
    assert fresh.returncode == 0 and "done earlier" not in fresh.stdout
    assert len(records(out)) == 4


def test_truncated_last_line_is_not_glued_to_the_next_record(tmp_path):
    from lsbench.results.store import append_record, read_records

    path = tmp_path / "results.jsonl"
    append_record(tmp_path, {"key": "a", "status": "ok"})
    with open(path, "a") as f:
        f.write('{"key": "b", "sta')  # killed mid-write
    append_record(tmp_path, {"key": "c", "status": "ok"})
    with pytest.warns(UserWarning, match="line 2 is not JSON"):
        assert [r["key"] for r in read_records(path)] == ["a", "c"]
