"""Results store: one directory per run.

Layout (written by lsbench.running.runner, read by report and compare)::

    RUN_DIR/run.json        environment of the whole run (commit, dirty, date, host, python,
                            package versions, devices, scenario, command line)
    RUN_DIR/results.jsonl   one JSON object per case, appended as each case finishes
    RUN_DIR/<images>        heatmaps etc., referenced from records by relative path

Records are appended while the run goes on, so a killed run can leave a half-written last
line: `read_run` drops it (with a warning) instead of failing, and the resumed run rewrites that
case. When a key appears twice (a case re-run after a resume) the later record wins.
"""
from __future__ import annotations

import json
import os
import warnings
from pathlib import Path

RUN_INFO = "run.json"
RESULTS = "results.jsonl"



def write_run_info(run_dir, info: dict) -> Path:
    """Write RUN_DIR/run.json atomically (a reader never sees half a file)."""
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    path = run_dir / RUN_INFO
    tmp = path.with_name(RUN_INFO + ".tmp")
    tmp.write_text(json.dumps(info, indent=2, sort_keys=True, default=str) + "\n")
    os.replace(tmp, path)
    return path


def append_record(run_dir, record: dict) -> None:
    """Append one case record as a single line (one write call, flushed)."""
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    line = json.dumps(record, sort_keys=True, default=str) + "\n"
    with open(run_dir / RESULTS, "a") as f:
        f.write(line)
        f.flush()


def read_records(path) -> list[dict]:
    """Records of a results.jsonl file; unparsable lines are skipped with a warning."""
    path = Path(path)
    if not path.exists():
        return []
    by_key: dict[str, dict] = {}
    anonymous: list[dict] = []
    lines = path.read_text(errors="replace").splitlines()
    for i, line in enumerate(lines):
        if not line.strip():
            continue
        try:
            rec = json.loads(line)
        except json.JSONDecodeError:
            where = "truncated last line" if i == len(lines) - 1 else f"bad line {i + 1}"
            warnings.warn(f"{path}: {where} skipped (interrupted run?)", stacklevel=2)
            continue
        if not isinstance(rec, dict):
            warnings.warn(f"{path}: line {i + 1} is not an object; skipped", stacklevel=2)
            continue
        key = rec.get("key")
        if key is None:
            anonymous.append(rec)
        else:
            by_key[str(key)] = rec  # later record of the same case wins (resumed run)
    return list(by_key.values()) + anonymous


def read_run(run_dir) -> tuple[dict, list[dict]]:
    """(run.json contents or {}, list of records) of one run directory."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise FileNotFoundError(f"no run directory {run_dir}")
    info: dict = {}
    info_path = run_dir / RUN_INFO
    if info_path.exists():
        try:
            info = json.loads(info_path.read_text())
        except json.JSONDecodeError as e:
            warnings.warn(f"{info_path}: unreadable ({e}); using empty run info", stacklevel=2)
    return info, read_records(run_dir / RESULTS)


def run_settings(info: dict) -> dict:
    """The run's [run] settings (RunSettings as a dict) from run.json; {} for runs written before
    run.json held them."""
    s = info.get("settings")
    return dict(s) if isinstance(s, dict) else {}


def run_devices(info: dict, records: list[dict]) -> dict[str, dict]:
    """{backend: {"device", "driver", "backend_version"}} of a run: what run.json says, completed
    by the records (a record's own device wins for that record: see record_device)."""
    devices: dict[str, dict] = {}
    for backend, d in (info.get("devices") or {}).items():
        devices[backend] = dict(d) if isinstance(d, dict) else {"device": d}
    for r in records:
        if not r.get("backend"):
            continue
        d = devices.setdefault(r["backend"], {})
        for f in ("device", "driver", "backend_version"):
            if r.get(f) and not d.get(f):
                d[f] = r[f]
    return devices


def record_device(rec: dict, info: dict) -> tuple[str | None, str | None]:
    """(device, driver) one record ran on: its own fields, else run.json's for its backend."""
    d = (info.get("devices") or {}).get(rec.get("backend"))
    d = d if isinstance(d, dict) else {"device": d}
    return rec.get("device") or d.get("device"), rec.get("driver") or d.get("driver")


def scenario_name(info: dict) -> str | None:
    """The scenario's name from run.json, however the runner spelled it."""
    sc = info.get("scenario")
    if isinstance(sc, dict):
        return sc.get("name") or sc.get("path")
    if info.get("scenario_name"):
        return info["scenario_name"]
    if sc:
        return Path(str(sc)).stem
    return None


def _is_run_dir(path: Path) -> bool:
    return (path / RESULTS).is_file() or (path / RUN_INFO).is_file()


def summarize_run(run_dir) -> dict:
    info, records = read_run(run_dir)
    ok = sum(1 for r in records if r.get("status") == "ok")
    devices = run_devices(info, records)
    commit = info.get("commit")
    if commit is None and records:
        commit = records[0].get("commit")
    dirty = info.get("dirty")
    if dirty is None and records:
        dirty = records[0].get("dirty")
    return {
        "dir": str(run_dir),
        "date": info.get("date", ""),
        "commit": commit,
        "dirty": dirty,
        "devices": devices,
        "scenario": scenario_name(info),
        "ok": ok,
        "failed": len(records) - ok,
    }


def list_runs(root="reports", max_depth: int = 3) -> list[dict]:
    """Summaries of every run directory under root (nested ones too, e.g. compare-commits
    output DIR/<rev>), oldest first."""
    root = Path(root)
    found: list[Path] = []
    if not root.is_dir():
        return []
    base_depth = len(root.parts)
    for dirpath, dirnames, _ in os.walk(root):
        p = Path(dirpath)
        if _is_run_dir(p):
            found.append(p)
            dirnames[:] = []  # a run's own subfolders (heatmaps, report) are not runs
            continue
        if len(p.parts) - base_depth >= max_depth:
            dirnames[:] = []
        dirnames.sort()
    runs = [summarize_run(p) for p in found]
    runs.sort(key=lambda r: (r["date"] or "", r["dir"]))
    return runs


def format_commit(commit, dirty) -> str:
    if not commit:
        return "-"
    return commit[:10] + ("+dirty" if dirty else "")


def format_devices(devices: dict) -> str:
    if not devices:
        return "-"
    parts = []
    for backend, d in sorted(devices.items()):
        name = d.get("device") if isinstance(d, dict) else d
        parts.append(f"{backend}={name}")
    return ", ".join(parts)
