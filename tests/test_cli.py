"""The command line as a user runs it: records, files, exit codes, resume, and the gate."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
RECORD_KEYS = {"scene", "structure", "backend", "resolution", "ls_n", "rays", "ray_count", "status",
               "reason", "agreement", "ties", "missed", "extra", "wrong", "max_abs_dt", "median_abs_dt",
               "build_seconds", "trace_seconds", "trace_seconds_all", "rays_per_second", "memory_bytes",
               "buffers", "device", "driver", "commit", "clock"}


def lsbench(*args, env=None, check=None, timeout=600):
    """Run the CLI; `timeout` only guards against a hang (no test here is timed)."""
    full_env = dict(os.environ, **(env or {}))
    proc = subprocess.run([sys.executable, "-m", "lsbench", *map(str, args)], cwd=REPO,
                          capture_output=True, text=True, env=full_env, timeout=timeout)
    if check is not None:
        assert proc.returncode == check, proc.stdout + proc.stderr
    return proc


@pytest.mark.parametrize("backend", ["glsl", "opencl"])
def test_trace_json_record(backend, tmp_path):
    dump = tmp_path / "hits.npz"
    proc = lsbench("trace", "--scene", "cornell", "--structure", "grid", "--backend", backend,
                   "--resolution", "16x8x12", "--size", "48x32", "--json", "--dump-hits", dump, check=0)
    rec = json.loads(proc.stdout)
    assert RECORD_KEYS <= set(rec), RECORD_KEYS - set(rec)
    assert rec["status"] == "ok" and rec["agreement"] == 1.0
    assert rec["ray_count"] == 48 * 32 and len(rec["trace_seconds_all"]) == 5
    assert rec["resolution"] == "16x8x12"
    data = np.load(dump)
    assert data["origins"].shape == (48 * 32, 3) and data["prim_ids"].dtype == np.int32
    same = data["prim_ids"] == data["embree_prim_ids"]  # the rest are ties on shared edges
    assert same.mean() > 0.95
    np.testing.assert_allclose(data["distances"][same & (data["prim_ids"] >= 0)],
                               data["embree_distances"][same & (data["prim_ids"] >= 0)], rtol=1e-5)


def test_user_ray_file(tmp_path):
    rng = np.random.default_rng(3)
    o = rng.uniform(-0.9, 0.9, (500, 3)).astype(np.float32) + np.float32([0, 1, 0])
    d = rng.normal(size=(500, 3)).astype(np.float32)
    np.savez(tmp_path / "mine.npz", origins=o, directions=d)
    proc = lsbench("trace", "--scene", "cornell", "--structure", "grid", "--backend", "opencl",
                   "--rays", tmp_path / "mine.npz", "--json", check=0)
    rec = json.loads(proc.stdout)
    assert rec["rays"].endswith("mine.npz") and rec["ray_count"] == 500
    assert rec["agreement"] == 1.0  # rays from inside the closed box: all hit, all agree
    assert rec["fps"] is None  # not an image


@pytest.mark.parametrize("args,needle", [
    (["--scene", "/nonexistent/mesh.ply"], "not found"),
    (["--scene", "no-such-builtin"], "cornell"),
    (["--scene", "cornell", "--rays", "/nonexistent.npz"], "npz"),
    (["--scene", "cornell", "--size", "12by3"], "--size"),
])
def test_bad_input_is_one_line_error(args, needle):
    proc = lsbench("trace", "--structure", "grid", "--backend", "opencl", *args)
    assert proc.returncode == 2
    assert proc.stdout == ""  # nothing that looks like a result
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("lsbench: error:"), proc.stderr
    assert needle.lower() in lines[0].lower()


def _scenario(tmp_path, body: str) -> Path:
    p = tmp_path / "s.toml"
    p.write_text(body)
    return p


SMALL = """
name = "small"
[run]
width = 40
height = 30
repeats = 2
min_agreement = 0.9999
[[cases]]
scenes = ["cornell"]
structures = ["grid"]
backends = ["glsl", "opencl"]
resolutions = [8]
"""


def test_run_writes_results_and_resumes(tmp_path):
    scen = _scenario(tmp_path, SMALL)
    out = tmp_path / "run"
    proc = lsbench("run", scen, "--out", out, check=0)
    assert "[1/2]" in proc.stdout and "[2/2]" in proc.stdout and "Mrays/s" in proc.stdout
    records = [json.loads(l) for l in (out / "results.jsonl").read_text().splitlines()]
    assert [r["backend"] for r in records] == ["glsl", "opencl"]
    assert all(r["status"] == "ok" for r in records)
    assert (out / "run.json").is_file()
    again = lsbench("run", scen, "--out", out, check=0)
    assert again.stdout.count("reused") == 2
    assert len((out / "results.jsonl").read_text().splitlines()) == 2
    lsbench("run", scen, "--out", out, "--fresh", check=0)
    assert len((out / "results.jsonl").read_text().splitlines()) == 2


def test_gate_passes_and_catches_a_planted_defect(tmp_path):
    scen = _scenario(tmp_path, SMALL)
    ok = lsbench("gate", scen, "--out", tmp_path / "a", check=0)
    assert "gate passed" in ok.stdout
    # One triangle (the most-referenced one, a visible wall half) dropped from every voxel list
    # (LSBENCH_PLANT_DEFECT): the gate must fail.
    coarse = _scenario(tmp_path, SMALL.replace("resolutions = [8]", "resolutions = [2]"))
    bad = lsbench("gate", coarse, "--out", tmp_path / "b", env={"LSBENCH_PLANT_DEFECT": "drop-reference"})
    assert bad.returncode == 1, bad.stdout + bad.stderr
    assert "GATE FAILED" in bad.stdout and "wrong" in bad.stdout
    assert bad.stdout.count("< 0.9999 (missed") == 2  # both backends caught


def test_bad_scenario_is_one_line_error(tmp_path):
    scen = _scenario(tmp_path, SMALL.replace('"grid"', '"octree9"'))
    proc = lsbench("run", scen, "--out", tmp_path / "x")
    assert proc.returncode == 2 and "unknown structure" in proc.stderr
    assert not (tmp_path / "x" / "results.jsonl").exists()


def test_ci_gate_scenario_passes():
    """The CI gate itself: every case of scenarios/ci.toml at its tolerance, on both backends."""
    from conftest import scene_path

    scene_path("sponza.ply")
    # The gate's 136 cases took 426 s alone on a 2-core machine whose llvmpipe traces at a third of
    # the development machine's speed (the eighteenth session's), and over 600 s beside other work:
    # the limit only catches a hang.
    proc = lsbench("gate", "scenarios/ci.toml", "--out", Path(os.environ.get("TMPDIR", "/tmp")) / f"ci-gate-{os.getpid()}",
                   "--fresh", timeout=2400)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-2000:]
    assert "gate passed" in proc.stdout


def test_scenario_ls_min_candidates_list_and_bad_values(tmp_path):
    from lsbench.inputs.scenario import ScenarioError, load_scenario

    block = ('[[cases]]\nscenes = ["cornell"]\nstructures = ["grid", "svo-ls"]\nbackends = ["opencl"]\n'
             'resolutions = [16]\nls_n = [1, 2]\nls_min_candidates = K\n')
    path = tmp_path / "k.toml"
    path.write_text(block.replace("K", "[0, 8]"))
    keys = [c.key for c in load_scenario(path).cases]
    # grid once (no N, no K); svo-ls for every N x K
    assert len(keys) == 1 + 2 * 2 and sum(k.endswith("|k8") for k in keys) == 2
    for bad in ('"many"', "[[1]]"):
        path.write_text(block.replace("K", bad))
        with pytest.raises(ScenarioError, match="ls_min_candidates"):
            load_scenario(path)
    # every shipped scenario parses and names registered structures only
    for shipped in (Path(__file__).resolve().parent.parent / "scenarios").glob("*.toml"):
        assert load_scenario(shipped).cases, shipped
