"""The results database across commits (asv's results/ as the model): plain files, no server.
This module alone knows its layout (docs/history.md); the run files inside it are written and
read by lsbench/results/store.py like any run folder.

Layout::

    HISTORY/history.json                         {"format": 1}: what layout this folder holds
    HISTORY/<machine>/machine.json               host, platform, CPU, devices per backend (last seen)
    HISTORY/<machine>/<commit12>[-dirty]/<run>/  one run, as lsbench run left it:
        run.json                                 its run.json, plus "history": where the commit
                                                 sits (order, commit_time, subject) and where the
                                                 run came from (source, appended)
        results.jsonl                            its records (one per case)

<machine> is the host name (a slug); the device is per record, so a series is (machine, case
key, device): figures of two devices are never one series. <run> is the run's date, scenario
and a hash of its records, so appending the same run twice replaces it instead of counting its
repeats twice. A commit's position is `order` = the number of commits it contains (git
rev-list --count): along one line of history that is exactly the sequence, and it needs no git
at read time. Each run of a commit is one process per case (lsbench runs every case in its own
worker), so several runs at one commit are repeats across processes.
"""
from __future__ import annotations

import datetime as _dt
import hashlib
import json
import shutil
import subprocess
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lsbench.report.format import slug
from lsbench.results import store

FORMAT = 1
MARKER = "history.json"
MACHINE_INFO = "machine.json"
PAGE = "index.html"  # the history page, written by `lsbench history` and `run --history`
MACHINE_FIELDS = ("host", "machine", "platform", "processor", "cpu_count")


class HistoryError(RuntimeError):
    """A folder that is no history database, or a run that cannot go into one (one line)."""


@dataclass
class CommitInfo:
    sha: str
    order: int | None = None        # commits reachable from it (git rev-list --count)
    commit_time: int | None = None  # committer time, seconds since the epoch
    subject: str = ""


def commit_info(sha: str, repo_dir) -> CommitInfo:
    """Where `sha` sits in repo_dir's history; a CommitInfo with only the sha outside git."""
    def git(*args):
        try:
            p = subprocess.run(["git", "-C", str(repo_dir), *args], capture_output=True, text=True,
                               timeout=60)
        except (OSError, subprocess.TimeoutExpired):
            return None
        return p.stdout.strip() if p.returncode == 0 else None

    count = git("rev-list", "--count", sha)
    shown = git("show", "-s", "--format=%ct%x00%s", sha)
    info = CommitInfo(sha=sha, order=int(count) if count and count.isdigit() else None)
    if shown and "\0" in shown:
        t, info.subject = shown.split("\0", 1)
        info.commit_time = int(t) if t.isdigit() else None
    return info


def open_history(path, create: bool = False) -> Path:
    """The database folder (made when `create`); HistoryError when it holds something else."""
    path = Path(path)
    marker = path / MARKER
    if marker.is_file():
        fmt = json.loads(marker.read_text()).get("format")
        if fmt != FORMAT:
            raise HistoryError(f"{path}: history format {fmt}, this lsbench reads {FORMAT}")
        return path
    if not create:
        raise HistoryError(f"{path}: no history database here (no {MARKER})")
    if path.exists() and any(path.iterdir()):
        raise HistoryError(f"{path}: not empty and no history database (no {MARKER}); choose another folder")
    path.mkdir(parents=True, exist_ok=True)
    store.write_lines(marker, [json.dumps({"format": FORMAT})])
    return path


def _run_id(info: dict, records: list[dict]) -> str:
    digest = hashlib.sha256("".join(store.encode_record(r) for r in records).encode()).hexdigest()[:10]
    date = str(info.get("date") or "")[:19].replace(":", "").replace("-", "")
    return slug(date or "undated", store.scenario_name(info) or "run", digest)


def append_run(history_dir, run_dir, repo_dir=None, source: str = "run") -> Path:
    """Copy one run folder's run.json and records into the database, under its machine and
    commit; returns the stored run's folder. repo_dir (default: none) is the git repository that
    places the commit in the sequence; without it the run has no order and sorts by date."""
    hist = open_history(history_dir, create=True)
    info, records = store.read_run(run_dir)
    if not records:
        raise HistoryError(f"{run_dir}: no records to append")
    commit = info.get("commit") or records[0].get("commit")
    if not commit or commit == "unknown":
        raise HistoryError(f"{run_dir}: the run names no commit; a history needs one")
    dirty = bool(info.get("dirty") if info.get("dirty") is not None else records[0].get("dirty"))
    ci = commit_info(commit, repo_dir) if repo_dir is not None else CommitInfo(sha=commit)
    machine = slug(info.get("host") or "unknown-host")
    machine_dir = hist / machine
    machine_dir.mkdir(exist_ok=True)
    minfo = {k: info.get(k) for k in MACHINE_FIELDS}
    minfo["devices"] = store.run_devices(info, records)
    store.write_lines(machine_dir / MACHINE_INFO, [json.dumps(minfo, indent=2, sort_keys=True)])

    dest = machine_dir / (commit[:12] + ("-dirty" if dirty else "")) / _run_id(info, records)
    if dest.exists():
        shutil.rmtree(dest)  # the same run appended again: replaced, not counted twice
    stored = dict(info, history={
        "commit": commit, "dirty": dirty, "order": ci.order, "commit_time": ci.commit_time,
        "subject": ci.subject, "source": source, "from": str(Path(run_dir).resolve()),
        "appended": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")})
    store.write_run_info(dest, stored)
    store.write_lines(dest / store.RESULTS, [store.encode_record(r) for r in records])
    return dest


@dataclass
class StoredRun:
    machine: str
    path: Path
    info: dict
    records: list[dict]

    @property
    def meta(self) -> dict:
        return self.info.get("history") or {}

    @property
    def commit(self) -> str:
        return self.meta.get("commit") or self.info.get("commit") or ""

    @property
    def sort_key(self) -> tuple:
        m = self.meta
        order = m.get("order")
        return (order if order is not None else 1 << 60, m.get("commit_time") or 0,
                str(self.info.get("date") or ""), self.path.name)


def read_history(history_dir) -> list[StoredRun]:
    """Every stored run, oldest commit first (by order, then commit time, then run date)."""
    hist = open_history(history_dir)
    runs = []
    for machine_dir in sorted(p for p in hist.iterdir() if (p / MACHINE_INFO).is_file()):
        for commit_dir in sorted(p for p in machine_dir.iterdir() if p.is_dir()):
            for run_dir in sorted(p for p in commit_dir.iterdir() if p.is_dir()):
                info, records = store.read_run(run_dir)
                runs.append(StoredRun(machine_dir.name, run_dir, info, records))
    runs.sort(key=lambda r: r.sort_key)
    return runs


def repeat_rays_per_second(rec: dict) -> np.ndarray:
    """Per-repeat rays/s of one record (ray_count / each repeat's trace time); the record's
    rays_per_second alone when it has no repeat times; empty when neither. (compare's samples
    too: lsbench/compare/verdicts.py.)"""
    rays = rec.get("ray_count")
    times = np.asarray([t for t in rec.get("trace_seconds_all") or [] if t is not None and t > 0], dtype=float)
    if rays and len(times):
        return float(rays) / times
    rps = rec.get("rays_per_second")
    return np.asarray([rps] if rps else [], dtype=float)


@dataclass
class CommitPoint:
    """One case at one commit: every run (process) there, pooled."""
    commit: str
    dirty: bool
    subject: str
    order: int | None
    process_figures: list[float] = field(default_factory=list)  # each run's rays/s (STATISTICS)
    repeats: list[float] = field(default_factory=list)           # every repeat of every run
    agreements: list[float] = field(default_factory=list)
    failed: list[str] = field(default_factory=list)              # reasons of failed runs

    @property
    def label(self) -> str:
        return self.commit[:10] + ("+dirty" if self.dirty else "")

    @property
    def rays_per_second(self) -> float | None:
        """The commit's figure: the median over its runs of each run's figure."""
        return float(np.median(self.process_figures)) if self.process_figures else None

    @property
    def spread(self) -> tuple[float, float] | None:
        """(low, high) of the figure: interquartile range of the repeats of all its runs."""
        if not self.repeats:
            return None
        q1, q3 = np.percentile(self.repeats, [25, 75])
        return float(q1), float(q3)

    @property
    def agreement(self) -> float | None:
        return min(self.agreements) if self.agreements else None


SeriesKey = tuple  # (machine, case key, device)

# One run's figure of a case from its repeats' rays/s. "median" is the record's own
# rays_per_second. "best" is the fastest repeat: on a shared machine interference only ever
# slows a repeat down, so the minimum time estimates the undisturbed speed and is the most
# stable figure there (Chen & Revels 2016, "Robust benchmarking in noisy environments").
STATISTICS = {"median": np.median, "best": np.max}


def series(runs: list[StoredRun], statistic: str = "median") -> dict[SeriesKey, list[CommitPoint]]:
    """Per (machine, case key, device): the case's CommitPoints, in the runs' commit order; each
    run's figure is the STATISTICS[statistic] of its repeats."""
    figure = STATISTICS[statistic]
    out: dict[SeriesKey, dict[tuple, CommitPoint]] = {}
    for run in runs:
        m = run.meta
        ckey = (run.commit, bool(m.get("dirty")))
        for rec in run.records:
            device = rec.get("device") or store.record_device(rec, run.info)[0] or "?"
            points = out.setdefault((run.machine, rec["key"], device), {})
            p = points.get(ckey)
            if p is None:
                p = points[ckey] = CommitPoint(commit=run.commit, dirty=ckey[1],
                                               subject=m.get("subject", ""), order=m.get("order"))
            if rec.get("status") != "ok":
                p.failed.append(rec.get("reason") or "failed")
                continue
            rps = repeat_rays_per_second(rec)
            if len(rps):
                p.process_figures.append(float(figure(rps)))
                p.repeats.extend(float(x) for x in rps)
            if rec.get("agreement") is not None:
                p.agreements.append(float(rec["agreement"]))
    return {k: list(v.values()) for k, v in out.items()}


def runs_at(history_dir, machine: str, sha: str, scenario: str | None) -> int:
    """How many runs of `scenario` (its name; None: any) at commit sha, clean, the database
    holds for machine."""
    commit_dir = Path(history_dir) / machine / sha[:12]
    if not commit_dir.is_dir():
        return 0
    n = 0
    for run_dir in commit_dir.iterdir():
        if run_dir.is_dir() and (run_dir / store.RUN_INFO).is_file():
            info, _ = store.read_run(run_dir)
            n += scenario is None or store.scenario_name(info) == scenario
    return n
