"""Run a scenario: every case in its own worker process with a time limit, so a driver crash,
hang or out-of-memory ends that case only. Records are appended to results.jsonl as cases
finish; a rerun with the same output folder skips finished cases (resume)."""
from __future__ import annotations

import json
import multiprocessing as mp
import os
import signal
import time
from pathlib import Path

from lsbench.running.execute import execute, failed_record
from lsbench.inputs.scenario import Case, RunSettings, Scenario

RESULTS = "results.jsonl"


def read_records(path: Path) -> list[dict]:
    """Records of results.jsonl; a truncated last line (a run killed mid-write) is ignored."""
    out = []
    if not path.exists():
        return out
    for line in path.read_text().splitlines():
        line = line.strip()
        if not line:
            continue
        try:
            out.append(json.loads(line))
        except json.JSONDecodeError:
            continue
    return out


def append_record(path: Path, record: dict) -> None:
    # One write + fsync per record: a kill -9 loses at most the case in flight.
    line = json.dumps(record, default=_json_default) + "\n"
    with open(path, "a+b") as f:
        # A run killed mid-write leaves a last line without its newline: start a new line, or
        # this record would be glued to the fragment and lost with it.
        if f.tell() > 0:
            f.seek(-1, os.SEEK_END)
            if f.read(1) != b"\n":
                line = "\n" + line
        f.write(line.encode())
        f.flush()
        os.fsync(f.fileno())


def _json_default(o):
    import numpy as np

    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


# Reasons that mean "an allocation failed": under --memory-budget they name the budget.
_ALLOCATION_FAILURES = ("MemoryError", "OUT_OF_", "ALLOCATION_FAILURE", "GL_OUT_OF_MEMORY",
                        "Cannot allocate", "std::bad_alloc", "allocating buffer")


def budget_text(settings: RunSettings) -> str:
    return f"host memory budget of {settings.memory_budget_mb:g} MiB (--memory-budget, RLIMIT_AS)"


def _test_fault(case: Case) -> None:
    """Test-only fault injection, like LSBENCH_PLANT_DEFECT: env LSBENCH_FAULT=crash|hang, or
    crash:TEXT / hang:TEXT to hit only cases whose key contains TEXT. `crash` kills the worker
    with SIGKILL (as a driver crash or the OOM killer would), `hang` sleeps past any timeout.
    tests/test_limits.py uses it to show that the run records the case and goes on."""
    fault = os.environ.get("LSBENCH_FAULT", "")
    if not fault:
        return
    kind, _, where = fault.partition(":")
    if where and where not in case.key:
        return
    if kind == "crash":
        os.kill(os.getpid(), signal.SIGKILL)
    elif kind == "hang":
        time.sleep(10**6)


def _worker(conn, case: Case, settings: RunSettings, env: dict, heatmap_dir: str | None) -> None:
    # The parent handles Ctrl-C; a worker just dies with it.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _test_fault(case)
    if settings.memory_budget_mb:
        import resource

        limit = int(settings.memory_budget_mb * 2**20)
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    try:
        rec = execute(case, settings, env, heatmap_dir=heatmap_dir)
    except MemoryError:
        rec = failed_record(case, f"{budget_text(settings)} exceeded (MemoryError)", env)
    except Exception as exc:  # bad scene or rays: the case fails with the one-line reason
        rec = failed_record(case, f"{type(exc).__name__}: {exc}".splitlines()[0], env)
    if settings.memory_budget_mb and rec.get("status") != "ok" \
            and any(s in str(rec.get("reason")) for s in _ALLOCATION_FAILURES) \
            and "memory budget" not in str(rec.get("reason")):
        rec["reason"] = f"{rec['reason']} (under the {budget_text(settings)})"
    conn.send(rec)
    conn.close()


def run_case_isolated(case: Case, settings: RunSettings, env: dict, heatmap_dir: str | None = None) -> dict:
    ctx = mp.get_context("spawn")
    parent, child = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_worker, args=(child, case, settings, env, heatmap_dir), daemon=True)
    proc.start()
    child.close()
    rec = None
    deadline = time.monotonic() + settings.timeout_seconds
    while time.monotonic() < deadline:
        if parent.poll(0.2):
            try:
                rec = parent.recv()
            except EOFError:
                rec = None
            break
        if not proc.is_alive() and not parent.poll(0):
            break
    if rec is None:
        if proc.is_alive() and time.monotonic() < deadline:
            # the pipe closed before the deadline: the worker is dying (abort, core dump), give
            # it a moment so a crash is not reported as a timeout
            proc.join(min(10.0, max(0.0, deadline - time.monotonic())))
        if proc.is_alive():
            proc.kill()
            proc.join(5)
            return failed_record(case, f"timed out after {settings.timeout_seconds:g} s (worker killed)", env)
        proc.join(5)
        code = proc.exitcode
        what = f"signal {signal.Signals(-code).name}" if code is not None and code < 0 else f"exit code {code}"
        reason = f"worker crashed ({what}) before reporting"
        if settings.memory_budget_mb:
            # drivers abort() or segfault when malloc fails under RLIMIT_AS instead of reporting it
            reason += f"; the {budget_text(settings)} was in force: likely exceeded"
        return failed_record(case, reason, env)
    proc.join(10)
    if proc.is_alive():
        proc.kill()
    return rec


def run_scenario(scenario: Scenario, out_dir: Path, env: dict, fresh: bool = False,
                 heatmaps: bool | None = None, log=print) -> list[dict]:
    out_dir.mkdir(parents=True, exist_ok=True)
    results = out_dir / RESULTS
    if fresh and results.exists():
        results.unlink()
    done = {r.get("key"): r for r in read_records(results)}
    want_heatmaps = scenario.settings.heatmaps if heatmaps is None else heatmaps
    records = []
    total = len(scenario.cases)
    for i, case in enumerate(scenario.cases, 1):
        if case.key in done:
            log(f"[{i}/{total}] {case.key}: done earlier ({done[case.key].get('status')}), skipped")
            records.append(done[case.key])
            continue
        log(f"[{i}/{total}] {case.key}: running")
        t0 = time.perf_counter()
        heatmap_dir = str(out_dir / "heatmaps") if want_heatmaps else None
        rec = run_case_isolated(case, scenario.settings, env, heatmap_dir)
        rec["wall_seconds"] = time.perf_counter() - t0
        append_record(results, rec)
        records.append(rec)
        log(f"[{i}/{total}] {case.key}: " + progress_text(rec))
    return records


def progress_text(rec: dict) -> str:
    if rec.get("status") != "ok":
        return f"FAILED ({rec.get('wall_seconds', 0):.1f} s): {rec.get('reason')}"
    return (f"ok ({rec.get('wall_seconds', 0):.1f} s): agreement {rec['agreement']:.6f} "
            f"({rec.get('unexplained')} unexplained), "
            f"{rec['rays_per_second'] / 1e6:.2f} Mrays/s, {rec['memory_bytes'] / 2**20:.1f} MiB, "
            f"build {rec['build_seconds']:.2f} s")


def summary_table(records: list[dict]) -> str:
    from lsbench.report.format import text_table

    head = ["scene", "rays", "structure", "backend", "res", "N", "status", "agreement", "Mrays/s",
            "FPS", "MiB", "build s"]
    rows = []
    for r in records:
        ok = r.get("status") == "ok"
        rows.append([
            str(r.get("scene")), f"{r.get('rays')}@{r.get('width')}x{r.get('height')}", r.get("structure"),
            r.get("backend"), str(r.get("resolution")), str(r.get("ls_n") or "-"),
            "ok" if ok else "FAILED",
            f"{r['agreement']:.6f}" if ok else "-",
            f"{r['rays_per_second'] / 1e6:.3f}" if ok else "-",
            f"{r['fps']:.1f}" if ok and r.get("fps") else "-",
            f"{r['memory_bytes'] / 2**20:.2f}" if ok else "-",
            f"{r['build_seconds']:.3f}" if ok else "-",
        ])
    out = text_table(head, rows)
    for r in records:
        if r.get("status") != "ok":
            out.append(f"FAILED {r.get('key')}: {r.get('reason')}")
    return "\n".join(out)
