"""Results store: one directory per run. This module alone reads and writes it.

Layout::

    RUN_DIR/run.json             environment of the whole run (commit, dirty, date, host, python,
                                 package versions, devices, scenario, settings, command line)
    RUN_DIR/results.jsonl        one record per case (lsbench/results/record.py, docs/record.md),
                                 appended as each case finishes
    RUN_DIR/results.jsonl.fresh  the records of a `--fresh` run until it finishes (RunResults)
    RUN_DIR/run.lock             flock'ed while a run writes the folder; says who holds it
    RUN_DIR/<images>             heatmaps etc., referenced from records by relative path

Durability: each record is one write and an fsync, so a kill -9 loses at most the case in flight;
a killed run can leave a half-written last line, which readers skip (with a warning) and the next
append starts a new line after. A resumed case appends a second record of its key: the later one
wins, and the run compacts the file when it ends (one line per case again).
"""
from __future__ import annotations

import fcntl
import json
import os
import socket
import warnings
from pathlib import Path

from lsbench.results.record import REQUIRED_FIELDS

RUN_INFO = "run.json"
RESULTS = "results.jsonl"
FRESH_RESULTS = RESULTS + ".fresh"
LOCK = "run.lock"


class ResultsError(RuntimeError):
    """A run folder that cannot be written (or is in use): one-line message naming the path."""


def write_run_info(run_dir, info: dict) -> Path:
    """Write RUN_DIR/run.json atomically (a reader never sees half a file; write_lines)."""
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    path = run_dir / RUN_INFO
    write_lines(path, [json.dumps(info, indent=2, sort_keys=True, default=str)])
    return path


def _json_default(o):
    import numpy as np

    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


def encode_record(record: dict) -> str:
    """One line of results.jsonl (numpy scalars and arrays as plain JSON)."""
    return json.dumps(record, default=_json_default) + "\n"


def append_record(run_dir, record: dict, name: str = RESULTS) -> None:
    """Append one record to RUN_DIR/name as a single line: one write, flushed and fsync'ed."""
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    line = encode_record(record)
    with open(run_dir / name, "a+b") as f:
        # A run killed mid-write leaves a last line without its newline: start a new line, or
        # this record would be glued to the fragment and lost with it.
        if f.tell() > 0:
            f.seek(-1, os.SEEK_END)
            if f.read(1) != b"\n":
                line = "\n" + line
        f.write(line.encode())
        f.flush()
        os.fsync(f.fileno())


def _parse_lines(path: Path, warn):
    """(line text, record or None) for every non-blank line; warn(message) for each line that is
    not a record: not JSON (a truncated last line of a killed run), not an object, or without
    the REQUIRED_FIELDS."""
    lines = path.read_text(errors="replace").splitlines()
    for i, line in enumerate(lines):
        if not line.strip():
            continue
        try:
            rec = json.loads(line)
        except json.JSONDecodeError:
            where = "truncated last line" if i == len(lines) - 1 else f"line {i + 1} is not JSON"
            warn(f"{path}: {where} skipped (interrupted run?)")
            yield line, None
            continue
        if not isinstance(rec, dict):
            warn(f"{path}: line {i + 1} is not a record (a JSON {type(rec).__name__}); skipped")
            rec = None
        elif missing := [f for f in REQUIRED_FIELDS if not isinstance(rec.get(f), str)]:
            warn(f"{path}: line {i + 1} lacks {', '.join(missing)}; skipped")
            rec = None
        yield line, rec


def _warn(message: str) -> None:
    warnings.warn(message, stacklevel=3)


def read_records(path, warn=_warn) -> list[dict]:
    """Records of a results file, one per key (the later record of a key wins: a resumed case),
    in the order the cases were last written. Lines that are no record are skipped; warn(message)
    names each one (default: a UserWarning)."""
    path = Path(path)
    if not path.is_file():
        return []
    by_key: dict[str, dict] = {}
    for _, rec in _parse_lines(path, warn):
        if rec is not None:
            by_key.pop(rec["key"], None)
            by_key[rec["key"]] = rec
    return list(by_key.values())


def write_lines(path: Path, lines: list[str]) -> None:
    """Replace `path` by these lines atomically: written beside, fsync'ed, renamed over it."""
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w") as f:
        f.writelines(line if line.endswith("\n") else line + "\n" for line in lines)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    dir_fd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(dir_fd)  # the rename itself survives a crash
    finally:
        os.close(dir_fd)


def compact(path: Path) -> None:
    """Rewrite a results file atomically as one line per case: the last record of each key, in
    the order read_records gives; superseded records and lines that are no record (fragments of
    a killed run, named by the warnings of the run's first read) go."""
    if not path.is_file() or path.stat().st_size == 0:
        return
    parsed = list(_parse_lines(path, lambda _msg: None))
    last = {rec["key"]: i for i, (_, rec) in enumerate(parsed) if rec is not None}
    keep = [line for i, (line, rec) in enumerate(parsed) if rec is not None and last[rec["key"]] == i]
    if len(keep) != len(parsed) or not path.read_bytes().endswith(b"\n"):
        write_lines(path, keep)


def check_writable(run_dir: Path, fresh: bool) -> None:
    """Fail before any case runs (ResultsError naming the path) when the run could not store what
    it measures: results.jsonl (or the --fresh side file) not a writable file, or the folder not
    writable."""
    targets = [run_dir / RESULTS] + ([run_dir / FRESH_RESULTS] if fresh else [])
    for path in targets:
        if path.exists():
            if not path.is_file():
                raise ResultsError(f"cannot write results to {path}: not a file")
            try:
                open(path, "ab").close()
            except OSError as exc:
                raise ResultsError(f"cannot write results to {path}: {exc.strerror or exc}") from None
    # run.json and compaction write beside and rename; a new results.jsonl is created
    if not os.access(run_dir, os.W_OK | os.X_OK):
        raise ResultsError(f"cannot write results to {targets[-1]}: folder {run_dir} is not writable")


class RunLock:
    """Exclusive lock on a run folder (fcntl.flock on RUN_DIR/run.lock) for as long as a run
    writes it: a second run into the same folder fails at once, naming the holder. The kernel
    drops the lock when the holder's process ends, however it ends (kill -9 included)."""

    def __init__(self, run_dir, command: str):
        self.path = Path(run_dir) / LOCK
        self.command = command
        self.fd: int | None = None

    def __enter__(self) -> "RunLock":
        try:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            raise ResultsError(f"cannot lock {self.path}: {exc.strerror or exc}") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _read_holder(fd)
            os.close(fd)
            raise ResultsError(f"{self.path.parent} is in use by another run ({holder}); wait for it "
                               "or choose another --out") from None
        import datetime as _dt

        holder = {"pid": os.getpid(), "host": socket.gethostname(), "command": self.command,
                  "since": _dt.datetime.now().astimezone().isoformat(timespec="seconds")}
        os.ftruncate(fd, 0)
        os.pwrite(fd, (json.dumps(holder) + "\n").encode(), 0)
        os.fsync(fd)
        self.fd = fd
        return self

    def __exit__(self, *exc) -> None:
        if self.fd is not None:
            os.ftruncate(self.fd, 0)  # nobody holds it now
            fcntl.flock(self.fd, fcntl.LOCK_UN)
            os.close(self.fd)
            self.fd = None


def _read_holder(fd: int) -> str:
    try:
        h = json.loads(os.pread(fd, 65536, 0) or b"{}")
        return f"pid {h['pid']} on {h['host']} since {h['since']}: {h['command']}"
    except (OSError, ValueError, KeyError, TypeError):
        return "holder not yet written"


class RunResults:
    """The records of a run folder while a run (holding its RunLock) writes it.

    A plain run appends to results.jsonl and may reuse the records there (`earlier`); when it
    ends, however it ends short of kill -9, the file is compacted to one record per case.
    A --fresh run reuses nothing: it appends to results.jsonl.fresh, and only when every case is
    done does results.jsonl become the fresh records plus the earlier records of cases this run
    did not have, in one rename. Until then results.jsonl is untouched: interrupting a --fresh
    run loses no earlier result (its finished cases stay in results.jsonl.fresh, which the next
    --fresh run starts anew)."""

    def __init__(self, run_dir, fresh: bool, warn=_warn):
        self.run_dir = Path(run_dir)
        self.fresh = fresh
        self.results = self.run_dir / RESULTS
        self.side = self.run_dir / FRESH_RESULTS
        self.stale_fresh = False
        if fresh:
            self.earlier: dict[str, dict] = {}
            write_lines(self.side, [])
        else:
            self.earlier = {r["key"]: r for r in read_records(self.results, warn)}
            self.stale_fresh = self.side.is_file() and self.side.stat().st_size > 0
        self.written = 0

    def append(self, record: dict) -> None:
        path = self.side if self.fresh else self.results
        try:
            append_record(self.run_dir, record, path.name)
        except OSError as exc:
            raise ResultsError(f"cannot write results to {path}: {exc.strerror or exc} "
                               f"(the record of {record.get('key')} is lost)") from None
        self.written += 1

    def finish(self, complete: bool) -> str:
        """End the run: compact, or (a complete --fresh run) supersede results.jsonl. Returns
        one sentence on where the records are ("" for a complete run that superseded nothing:
        the command prints the results path itself)."""
        if not self.fresh:
            compact(self.results)
            return "" if complete else f"finished cases are kept in {self.results}"
        if not complete:
            return (f"{self.results} is unchanged (the --fresh run did not finish); its "
                    f"{self.written} finished cases are in {self.side}")
        fresh = read_records(self.side)
        keys = {r["key"] for r in fresh}
        kept = [r for r in read_records(self.results, lambda _m: None) if r["key"] not in keys]
        write_lines(self.results, [encode_record(r) for r in kept + fresh])
        self.side.unlink()
        return f"{self.results} now holds this run's records" + (
            f" and {len(kept)} earlier ones of cases it did not run" if kept else "")


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
