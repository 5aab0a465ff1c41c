"""The stability of timing figures (`lsbench stability`): one case run several times in this
process and in fresh worker processes, and the spread of its median trace and build times within
and across both groups."""
from __future__ import annotations

import statistics

def spread(records: list[dict], field: str = "trace_seconds") -> dict:
    """Spread of one timing field over repeated runs of a case (failed runs listed, not counted)."""
    values = [float(r[field]) for r in records if r.get("status") == "ok" and r.get(field) is not None]
    failed = [r.get("reason") for r in records if r.get("status") != "ok"]
    if not values:
        return {"runs": len(records), "ok": 0, "values": [], "failed": failed}
    med = statistics.median(values)
    mean = statistics.fmean(values)
    out = {
        "runs": len(records), "ok": len(values), "values": values, "median": med,
        "min": min(values), "max": max(values),
        # (max - min) / median: how far two runs of the same case can lie apart.
        "spread": (max(values) - min(values)) / med if med > 0 else 0.0,
        "cv": statistics.pstdev(values) / mean if len(values) > 1 and mean > 0 else 0.0,
        "failed": failed,
    }
    if field == "trace_seconds":
        cvs = [float(r["trace_cv"]) for r in records if r.get("status") == "ok" and r.get("trace_cv") is not None]
        out["within_run_cv"] = cvs  # each run's CV over its own repeats
        out["within_run_cv_mean"] = statistics.fmean(cvs) if cvs else None
    return out


def timing_stability(case, settings, runs: int = 3, env: dict | None = None, log=None) -> dict:
    """Run `case` `runs` times in this process (execute: build + trace + timing each time) and
    `runs` times each in a fresh worker process (runner.run_case_isolated), and return the spread
    of the median trace time (and build time) within each group and across both."""
    from lsbench.running.execute import execute
    from lsbench.running.runner import run_case_isolated

    log = log or (lambda *a: None)
    env = env or {}
    in_proc, cross = [], []
    for i in range(runs):
        rec = execute(case, settings, env)
        log(f"in-process run {i + 1}/{runs}: " + _brief(rec))
        in_proc.append(rec)
    for i in range(runs):
        rec = run_case_isolated(case, settings, env)
        log(f"separate process {i + 1}/{runs}: " + _brief(rec))
        cross.append(rec)
    ok = [r for r in in_proc + cross if r.get("status") == "ok"]
    first = ok[0] if ok else (in_proc + cross)[0]
    result = {
        "case": case.key, "runs": runs, "repeats": settings.repeats, "warmup": settings.warmup,
        "device": first.get("device"), "driver": first.get("driver"), "clock": first.get("clock"),
        "ray_count": first.get("ray_count"),
        "in_process": spread(in_proc), "cross_process": spread(cross), "all": spread(in_proc + cross),
        "build_in_process": spread(in_proc, "build_seconds"),
        "build_cross_process": spread(cross, "build_seconds"),
    }
    a, b = result["in_process"].get("median"), result["cross_process"].get("median")
    # > 1: a fresh process is slower (or faster, < 1) than the one that already ran the case.
    result["cross_over_in_process_median"] = b / a if a and b else None
    return result


def _brief(rec: dict) -> str:
    if rec.get("status") != "ok":
        return f"FAILED: {rec.get('reason')}"
    return (f"trace median {rec['trace_seconds'] * 1e3:.3f} ms (cv {rec['trace_cv'] * 100:.1f}%), "
            f"build {rec['build_seconds'] * 1e3:.1f} ms")


def stability_text(result: dict) -> str:
    lines = [f"timing stability of {result['case']} on {result.get('device')} ({result.get('clock')}), "
             f"{result['runs']} runs x {result['repeats']} repeats"]
    for label, key in (("trace, same process", "in_process"), ("trace, separate processes", "cross_process"),
                       ("trace, all runs", "all"), ("build, same process", "build_in_process"),
                       ("build, separate processes", "build_cross_process")):
        s = result[key]
        if not s.get("ok"):
            lines.append(f"  {label:27s} no successful run: {s.get('failed')}")
            continue
        extra = ""
        if s.get("within_run_cv_mean") is not None:
            extra = f"  within-run cv {s['within_run_cv_mean'] * 100:.1f}%"
        lines.append(f"  {label:27s} median {s['median'] * 1e3:9.3f} ms  min {s['min'] * 1e3:9.3f}  "
                     f"max {s['max'] * 1e3:9.3f}  spread {s['spread'] * 100:5.1f}%  cv {s['cv'] * 100:5.1f}%{extra}")
    r = result.get("cross_over_in_process_median")
    if r:
        lines.append(f"  separate / same process median: {r:.3f}")
    return "\n".join(lines)
