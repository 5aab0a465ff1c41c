"""Runs and their folders as a user meets them (issue 13, items 6-11): case identity, honest
resume, atomic --fresh, the folder lock, no orphan workers, exit codes, and folders or lines
that cannot be written or read. Real drivers, tiny scenes (cornell and two-triangle OBJ files)."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
QUAD = "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3\nf 1 3 4\n"
BENT_QUAD = "v 0 0 0\nv 1 0 0.5\nv 1 1 0.5\nv 0 1 0\nf 1 2 3\nf 1 3 4\n"


def lsbench(*args, env=None, timeout=300):
    return subprocess.run([sys.executable, "-m", "lsbench", *map(str, args)], cwd=REPO, capture_output=True,
                          text=True, timeout=timeout, env=dict(os.environ, **(env or {})))


def start(*args, env=None) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "lsbench", *map(str, args)], cwd=REPO, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=dict(os.environ, **(env or {})))


def wait_for_line(proc: subprocess.Popen, needle: str) -> str:
    """Read the run's output until a line holds `needle` (the run is then past that point)."""
    seen = []
    for line in proc.stdout:
        seen.append(line)
        if needle in line:
            return line
    raise AssertionError(f"run ended without {needle!r}: {''.join(seen)}{proc.stderr.read()}")


def records(out: Path) -> list[dict]:
    return [json.loads(line) for line in (out / "results.jsonl").read_text().splitlines() if line.strip()]


def scenario(tmp_path: Path, scenes, resolutions=(4,), run: str = "", name: str = "s.toml") -> Path:
    p = tmp_path / name
    p.write_text(f'name = "runs"\n[run]\nwidth = 16\nheight = 12\nrepeats = 1\nembree_timing = false\n{run}\n'
                 f'[[cases]]\nscenes = {json.dumps([str(s) for s in scenes])}\nstructures = ["grid"]\n'
                 f'backends = ["opencl"]\nresolutions = {json.dumps(list(resolutions))}\n')
    return p


def two_folders(tmp_path: Path) -> tuple[Path, Path]:
    a, b = tmp_path / "a" / "quad.obj", tmp_path / "b" / "quad.obj"
    for path, text in ((a, QUAD), (b, BENT_QUAD)):
        path.parent.mkdir()
        path.write_text(text)
    return a, b


def children(pid: int) -> list[int]:
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            out.append(int(stat.parent.name))
    return out


def alive(pid: int) -> bool:
    """Running, not a zombie waiting for a reaper."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def worker_of(run_pid: int, timeout: float = 60) -> int:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for pid in children(run_pid):
            try:
                if b"spawn_main" in Path(f"/proc/{pid}/cmdline").read_bytes():
                    return pid
            except OSError:
                pass
        time.sleep(0.1)
    raise AssertionError("no case worker started")


# --- 6: same file name in two folders -------------------------------------------------------


def test_same_file_name_in_two_folders_is_two_cases(tmp_path):
    a, b = two_folders(tmp_path)
    out = tmp_path / "run"
    proc = lsbench("run", scenario(tmp_path, [a, b]), "--out", out)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert ": 2 cases ->" in proc.stdout
    recs = records(out)
    assert len(recs) == 2 and len({r["key"] for r in recs}) == 2 and len({r["scene_hash"] for r in recs}) == 2
    assert [r["scene_source"] for r in recs] == [str(a), str(b)]
    again = lsbench("run", scenario(tmp_path, [a, b]), "--out", out)
    assert "reusing 2 of 2 earlier records" in again.stdout, again.stdout


# --- 7: resume reuses only what still stands ------------------------------------------------


def test_changed_scene_is_rerun(tmp_path):
    a, b = two_folders(tmp_path)
    out, scen = tmp_path / "run", scenario(tmp_path, [a, b])
    assert lsbench("run", scen, "--out", out).returncode == 0
    first = {r["scene_source"]: r for r in records(out)}
    a.write_text(BENT_QUAD.replace("0.5", "0.25"))  # same path, new contents
    proc = lsbench("run", scen, "--out", out)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "reusing 1 of 2 earlier records; running 1: 1 scene changed" in proc.stdout
    assert "running (scene changed)" in proc.stdout and "done earlier (ok), reused" in proc.stdout
    now = {r["scene_source"]: r for r in records(out)}
    assert len(records(out)) == 2  # one line per case after the run
    assert now[str(a)]["scene_hash"] != first[str(a)]["scene_hash"]
    assert now[str(b)] == first[str(b)]


def test_gate_after_a_planted_defect_judges_the_clean_rerun(tmp_path):
    """Whether the gate catches the defect is tests/test_cli.py's matter; here: the record made
    with it says so, and a clean gate into the same folder measures again instead of judging it."""
    scen = scenario(tmp_path, ["cornell"], resolutions=[2])
    out = tmp_path / "gate"
    lsbench("gate", scen, "--out", out, env={"LSBENCH_PLANT_DEFECT": "drop-reference"})
    assert [r["planted_defect"] for r in records(out)] == ["drop-reference"]
    good = lsbench("gate", scen, "--out", out)
    assert good.returncode == 0, good.stdout + good.stderr
    assert "running (planted defect changed)" in good.stdout
    assert [r["planted_defect"] for r in records(out)] == [None]


def test_failed_case_is_retried_unless_kept(tmp_path):
    out, scen = tmp_path / "run", scenario(tmp_path, ["cornell"], resolutions=[4, 8])
    crashed = lsbench("run", scen, "--out", out, env={"LSBENCH_FAULT": "crash:|r4|"})
    assert crashed.returncode == 1
    kept = lsbench("run", scen, "--out", out, "--keep-failed")
    assert kept.returncode == 1 and "done earlier (failed), reused" in kept.stdout, kept.stdout
    retried = lsbench("run", scen, "--out", out)
    assert retried.returncode == 0, retried.stdout + retried.stderr
    assert "reusing 1 of 2 earlier records; running 1: 1 failed earlier" in retried.stdout
    assert [r["status"] for r in records(out)] == ["ok", "ok"]


# --- 8: --fresh supersedes atomically -------------------------------------------------------


def test_interrupted_fresh_run_keeps_every_earlier_record(tmp_path):
    out = tmp_path / "run"
    both = scenario(tmp_path, ["cornell"], resolutions=[4, 8], run="timeout_seconds = 120")
    assert lsbench("run", both, "--out", out).returncode == 0
    before = (out / "results.jsonl").read_bytes()
    only_r4 = scenario(tmp_path, ["cornell"], resolutions=[4], run="timeout_seconds = 120", name="r4.toml")
    proc = start("run", only_r4, "--out", out, "--fresh", env={"LSBENCH_FAULT": "hang:|r4|"})
    wait_for_line(proc, "r4|n0|k0: running")
    proc.send_signal(signal.SIGINT)  # Ctrl-C
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert "results.jsonl is unchanged" in err
    assert (out / "results.jsonl").read_bytes() == before
    done = lsbench("run", only_r4, "--out", out, "--fresh")
    assert done.returncode == 0, done.stdout + done.stderr
    old = {r["key"]: r for r in json.loads("[" + before.decode().strip().replace("\n", ",") + "]")}
    new = {r["key"]: r for r in records(out)}
    assert new.keys() == old.keys()  # the r8 case, not in this scenario, is still there
    r4, r8 = sorted(new, key=lambda k: "|r8|" in k)
    assert new[r8] == old[r8] and new[r4]["wall_seconds"] != old[r4]["wall_seconds"]


# --- 9: one run per folder ------------------------------------------------------------------


def test_second_run_into_the_same_folder_fails_at_once(tmp_path):
    out, scen = tmp_path / "run", scenario(tmp_path, ["cornell"], run="timeout_seconds = 120")
    first = start("run", scen, "--out", out, env={"LSBENCH_FAULT": "hang"})
    try:
        wait_for_line(first, ": running")
        t0 = time.monotonic()
        second = lsbench("run", scen, "--out", out)
        assert second.returncode == 2, second.stdout + second.stderr
        lines = second.stderr.strip().splitlines()
        assert len(lines) == 1 and "in use by another run" in lines[0], second.stderr
        assert f"pid {first.pid} on " in lines[0] and f"lsbench run {scen} --out {out}" in lines[0]
        assert "running" not in second.stdout and time.monotonic() - t0 < 60
    finally:
        first.send_signal(signal.SIGINT)
        first.communicate(timeout=60)


# --- 10: no worker outlives its run ---------------------------------------------------------


def test_kill_9_of_the_run_leaves_no_worker(tmp_path):
    scen = scenario(tmp_path, ["cornell"], run="timeout_seconds = 600")
    run = start("run", scen, "--out", tmp_path / "run", env={"LSBENCH_FAULT": "hang"})
    worker = worker_of(run.pid)
    try:
        assert alive(worker)
        run.kill()  # SIGKILL: the run cannot clean up
        run.wait(timeout=30)
        deadline = time.monotonic() + 20
        while alive(worker) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not alive(worker), "the case worker outlived its run"
    finally:
        if alive(worker):
            os.kill(worker, signal.SIGKILL)


# --- 11: exit codes -------------------------------------------------------------------------


def test_run_exits_1_when_a_case_fails_unless_allowed(tmp_path):
    scen = scenario(tmp_path, ["cornell"])
    env = {"LSBENCH_FAULT": "crash"}
    failed = lsbench("run", scen, "--out", tmp_path / "a", env=env)
    assert failed.returncode == 1 and "1 of 1 cases failed" in failed.stdout, failed.stdout + failed.stderr
    allowed = lsbench("run", scen, "--out", tmp_path / "b", "--allow-failed", env=env)
    assert allowed.returncode == 0 and records(tmp_path / "b")[0]["status"] == "failed"


# --- results that cannot be written or read --------------------------------------------------


def test_unwritable_results_fail_before_any_case(tmp_path):
    out = tmp_path / "run"
    (out / "results.jsonl").mkdir(parents=True)
    for extra in ((), ("--fresh",)):
        proc = lsbench("run", scenario(tmp_path, ["cornell"]), "--out", out, *extra)
        assert proc.returncode == 2, proc.stdout + proc.stderr
        lines = proc.stderr.strip().splitlines()
        assert len(lines) == 1 and f"{out / 'results.jsonl'}: not a file" in lines[0], proc.stderr
        assert "running" not in proc.stdout


def test_unwritable_dump_hits_fails_before_tracing(tmp_path):
    target = tmp_path / "no-such-folder" / "hits.npz"
    proc = lsbench("trace", "--scene", "cornell", "--structure", "grid", "--backend", "opencl",
                   "--resolution", "4", "--size", "16x12", "--dump-hits", target)
    assert proc.returncode == 2 and proc.stdout == "", proc.stdout + proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("lsbench: error:") and "--dump-hits" in lines[0], proc.stderr
    assert f"cannot write {target}" in lines[0]


def test_results_lines_that_are_no_record_do_not_stop_resume(tmp_path):
    out = tmp_path / "run"
    out.mkdir()
    (out / "results.jsonl").write_text('null\n[1, 2]\n{"key": 5, "status": "ok"}\n{"key": "x"}\n')
    proc = lsbench("run", scenario(tmp_path, ["cornell"]), "--out", out)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    for n, what in ((1, "is not a record"), (2, "is not a record"), (3, "lacks key"), (4, "lacks status")):
        assert f"results.jsonl: line {n} {what}" in proc.stdout, proc.stdout
    assert [r["status"] for r in records(out)] == ["ok"]
