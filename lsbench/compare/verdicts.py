"""Regression comparison between two runs (or two commits).

Cases are matched by their `key`. Per case: ratio of rays/s (head / base), ratio of bytes, change
in agreement. Verdicts:

- speed: a regression only when head is slower than base by more than `factor` AND the repeats
  say the slowdown is real: either the repeat ranges do not overlap (head's best repeat is slower
  than base's worst) or a one-sided Mann-Whitney U test on the per-repeat rays/s gives
  p < alpha. (A run with a single repeat per case has no spread to go on: there the factor
  alone decides, and the table says n=1.) This is the approach of asv (airspeed velocity):
  a ratio threshold plus a statistical check, so noise on a shared CI machine does not fail
  the gate.
- accuracy: any drop in agreement is a regression (agreement is a count ratio: deterministic).
- failure: ok in base, failed in head.
- memory: bytes grew by more than `factor` (deterministic, so no statistics).

Runs whose cases ran on different devices get a warning and no verdicts: figures from two
devices are never compared as if they were one (DESIGN.md, Environments).
"""
from __future__ import annotations

import datetime as _dt
import html
import math
import os
import re
import shutil
import subprocess
import sys
import tempfile
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np

from lsbench.results.store import format_commit, read_run

DEFAULT_FACTOR = 1.1
DEFAULT_ALPHA = 0.01
AGREEMENT_EPS = 1e-12  # float noise of a ratio of counts, not a tolerance


# ---------------------------------------------------------------- Mann-Whitney U (no scipy)

@lru_cache(maxsize=None)
def _u_counts(m: int, n: int) -> tuple:
    """Number of orderings of m x's and n y's with U_x = u, u = 0..m*n (no ties).

    Recurrence on the largest value: it is an x (which then beats all n y's: U grows by n) or a
    y (U unchanged): f(m, n, u) = f(m-1, n, u-n) + f(m, n-1, u).
    """
    if m == 0 or n == 0:
        return (1,)
    a = _u_counts(m - 1, n)
    b = _u_counts(m, n - 1)
    out = [0] * (m * n + 1)
    for u, c in enumerate(a):
        out[u + n] += c
    for u, c in enumerate(b):
        out[u] += c
    return tuple(out)


def _rank(values: np.ndarray) -> np.ndarray:
    """Ranks 1..N, ties get the mean of their ranks."""
    order = np.argsort(values, kind="mergesort")
    ranks = np.empty(len(values), dtype=float)
    sorted_vals = values[order]
    i = 0
    while i < len(values):
        j = i
        while j + 1 < len(values) and sorted_vals[j + 1] == sorted_vals[i]:
            j += 1
        ranks[order[i:j + 1]] = (i + j) / 2.0 + 1.0
        i = j + 1
    return ranks


def mann_whitney_less(x, y) -> tuple[float, float]:
    """One-sided Mann-Whitney U test, alternative: x tends to be smaller than y.

    Returns (U_x, p) with U_x = #pairs x > y (+1/2 per tie). Exact null distribution when there
    are no ties and the samples are small (the usual 3..30 repeats); otherwise the normal
    approximation with tie and continuity correction.
    """
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    m, n = len(x), len(y)
    if m == 0 or n == 0:
        return float("nan"), 1.0
    both = np.concatenate([x, y])
    ranks = _rank(both)
    u_x = float(ranks[:m].sum() - m * (m + 1) / 2.0)
    has_ties = len(np.unique(both)) < len(both)
    if not has_ties and m <= 30 and n <= 30:
        counts = _u_counts(m, n)
        total = math.comb(m + n, m)
        p = sum(counts[: int(round(u_x)) + 1]) / total
        return u_x, min(1.0, p)
    mu = m * n / 2.0
    N = m + n
    _, t = np.unique(both, return_counts=True)
    tie_term = float((t ** 3 - t).sum()) / (N * (N - 1)) if N > 1 else 0.0
    var = m * n / 12.0 * ((N + 1) - tie_term)
    if var <= 0:
        return u_x, 1.0
    z = (u_x - mu + 0.5) / math.sqrt(var)
    return u_x, 0.5 * math.erfc(-z / math.sqrt(2.0))


# ---------------------------------------------------------------- comparison

@dataclass
class CaseDiff:
    key: str
    base: dict | None
    head: dict | None
    speed_ratio: float | None = None   # head rays/s / base rays/s (< 1: slower)
    bytes_ratio: float | None = None   # head bytes / base bytes
    agreement_delta: float | None = None  # head - base
    p_value: float | None = None       # one-sided U test, head slower than base
    ranges_disjoint: bool | None = None  # head's fastest repeat slower than base's slowest
    n_base: int = 0
    n_head: int = 0
    verdicts: list[str] = field(default_factory=list)  # regression kinds
    notes: list[str] = field(default_factory=list)      # improvements, info, no-verdict reasons
    comparable: bool = True

    @property
    def regression(self) -> bool:
        return bool(self.verdicts)

    @property
    def status(self) -> str:
        b = self.base.get("status", "?") if self.base else "none"
        h = self.head.get("status", "?") if self.head else "none"
        return b if b == h else f"{b}->{h}"


@dataclass
class CompareResult:
    base_dir: str
    head_dir: str
    factor: float
    alpha: float
    base_info: dict
    head_info: dict
    cases: list[CaseDiff]
    warnings: list[str]
    verdicts_given: bool  # False when the runs are from different devices

    @property
    def regressions(self) -> list[CaseDiff]:
        return [c for c in self.cases if c.regression]

    @property
    def has_regression(self) -> bool:
        return bool(self.regressions)

    @property
    def only_base(self) -> list[str]:
        return [c.key for c in self.cases if c.head is None]

    @property
    def only_head(self) -> list[str]:
        return [c.key for c in self.cases if c.base is None]

    @property
    def exit_code(self) -> int:
        return 1 if self.has_regression else 0

    def to_text(self) -> str:
        return format_table(self)


def _rps_samples(rec: dict) -> np.ndarray:
    """Per-repeat rays/s (ray_count / each repeat's trace time)."""
    times = rec.get("trace_seconds_all") or []
    rays = rec.get("ray_count")
    times = np.asarray([t for t in times if t is not None and t > 0], dtype=float)
    if rays and len(times):
        return float(rays) / times
    rps = rec.get("rays_per_second")
    return np.asarray([rps], dtype=float) if rps else np.asarray([], dtype=float)


def _rps(rec: dict) -> float | None:
    v = rec.get("rays_per_second")
    if v:
        return float(v)
    t, rays = rec.get("trace_seconds"), rec.get("ray_count")
    if t and rays:
        return float(rays) / float(t)
    return None


def _device_of(rec: dict, info: dict):
    if rec.get("device"):
        return rec.get("device")
    d = (info.get("devices") or {}).get(rec.get("backend"))
    return d.get("device") if isinstance(d, dict) else d


def _driver_of(rec: dict, info: dict):
    if rec.get("driver"):
        return rec.get("driver")
    d = (info.get("devices") or {}).get(rec.get("backend"))
    return d.get("driver") if isinstance(d, dict) else None


def _diff_case(c: CaseDiff, factor: float, alpha: float) -> None:
    b, h = c.base, c.head
    b_ok = b.get("status") == "ok"
    h_ok = h.get("status") == "ok"
    if b_ok and not h_ok:
        c.verdicts.append("failure")
        c.notes.append(f"head failed: {h.get('reason', '')}".strip())
    elif not b_ok and h_ok:
        c.notes.append("fixed (failed in base)")
    if not (b_ok and h_ok):
        return

    rb, rh = _rps(b), _rps(h)
    if rb and rh:
        c.speed_ratio = rh / rb
    sb, sh = _rps_samples(b), _rps_samples(h)
    c.n_base, c.n_head = len(sb), len(sh)
    if len(sb) and len(sh):
        c.ranges_disjoint = bool(sh.max() < sb.min())
        _, c.p_value = mann_whitney_less(sh, sb)
    if c.speed_ratio is not None and c.speed_ratio * factor < 1.0:
        real = bool(c.ranges_disjoint) or (c.p_value is not None and c.p_value < alpha)
        if real:
            c.verdicts.append("speed")
        else:
            c.notes.append("slower, within noise")
    elif c.speed_ratio is not None and c.speed_ratio > factor:
        if len(sb) and len(sh) and sh.min() > sb.max():
            c.notes.append("faster")

    mb, mh = b.get("memory_bytes"), h.get("memory_bytes")
    if mb and mh:
        c.bytes_ratio = float(mh) / float(mb)
        if c.bytes_ratio > factor:
            c.verdicts.append("memory")
        elif c.bytes_ratio * factor < 1.0:
            c.notes.append("smaller")

    ab, ah = b.get("agreement"), h.get("agreement")
    if ab is not None and ah is not None:
        c.agreement_delta = float(ah) - float(ab)
        if c.agreement_delta < -AGREEMENT_EPS:
            c.verdicts.append("accuracy")


def compare_runs(base_dir, head_dir, factor: float = DEFAULT_FACTOR,
                 alpha: float = DEFAULT_ALPHA) -> CompareResult:
    base_info, base_recs = read_run(base_dir)
    head_info, head_recs = read_run(head_dir)
    base_by = {r["key"]: r for r in base_recs if "key" in r}
    head_by = {r["key"]: r for r in head_recs if "key" in r}
    warnings: list[str] = []

    # Devices: run-level first, then per case (a record's device wins where it has one).
    mismatched_devices = set()
    for key in base_by.keys() & head_by.keys():
        db, dh = _device_of(base_by[key], base_info), _device_of(head_by[key], head_info)
        if db and dh and db != dh:
            mismatched_devices.add((base_by[key].get("backend"), db, dh))
    bd, hd = base_info.get("devices") or {}, head_info.get("devices") or {}
    for backend in bd.keys() & hd.keys():
        db = bd[backend].get("device") if isinstance(bd[backend], dict) else bd[backend]
        dh = hd[backend].get("device") if isinstance(hd[backend], dict) else hd[backend]
        if db and dh and db != dh:
            mismatched_devices.add((backend, db, dh))
    verdicts_given = not mismatched_devices
    for backend, db, dh in sorted(mismatched_devices, key=str):
        warnings.append(f"different devices for {backend}: base '{db}' vs head '{dh}' — "
                        f"figures are not comparable; no regression verdicts given")
    drivers = set()
    for key in base_by.keys() & head_by.keys():
        vb, vh = _driver_of(base_by[key], base_info), _driver_of(head_by[key], head_info)
        if vb and vh and vb != vh:
            drivers.add((base_by[key].get("backend"), vb, vh))
    for backend, vb, vh in sorted(drivers, key=str):
        warnings.append(f"driver changed for {backend}: '{vb}' -> '{vh}' (timings may move "
                        f"for that reason alone)")

    cases: list[CaseDiff] = []
    for key in list(base_by) + [k for k in head_by if k not in base_by]:
        c = CaseDiff(key=key, base=base_by.get(key), head=head_by.get(key))
        if c.base is None or c.head is None:
            c.comparable = False
            c.notes.append("only in head" if c.base is None else "only in base")
        else:
            _diff_case(c, factor, alpha)
            if not verdicts_given:
                c.comparable = False
                if c.verdicts:
                    c.notes.append("would be: " + ",".join(c.verdicts) + " (different devices)")
                c.verdicts = []
        cases.append(c)
    if not base_recs:
        warnings.append(f"base run {base_dir} has no records")
    if not head_recs:
        warnings.append(f"head run {head_dir} has no records")
    return CompareResult(str(base_dir), str(head_dir), factor, alpha, base_info, head_info,
                         cases, warnings, verdicts_given)


# ---------------------------------------------------------------- output

def _fmt_rps(v) -> str:
    if v is None:
        return "-"
    for unit, scale in (("G", 1e9), ("M", 1e6), ("k", 1e3)):
        if v >= scale:
            return f"{v / scale:.3g}{unit}"
    return f"{v:.3g}"


def _fmt_ratio(v) -> str:
    return "-" if v is None else f"{v:.3f}"


def _fmt_delta(v) -> str:
    if v is None:
        return "-"
    return "0" if abs(v) <= AGREEMENT_EPS else f"{v:+.2e}"


def _fmt_p(c: CaseDiff) -> str:
    if c.p_value is None:
        return "-"
    s = f"{c.p_value:.3g}"
    if c.ranges_disjoint:
        s += " disj"
    if min(c.n_base, c.n_head) <= 1:
        s += " n=1"
    return s


def table_rows(res: CompareResult) -> list[list[str]]:
    rows = []
    for c in res.cases:
        if c.regression:
            verdict = "REGRESSION " + ",".join(c.verdicts)
        elif not c.comparable and c.base is not None and c.head is not None:
            verdict = "no verdict"
        else:
            verdict = "ok"
        rows.append([
            c.key, c.status,
            _fmt_rps(_rps(c.base)) if c.base else "-",
            _fmt_rps(_rps(c.head)) if c.head else "-",
            _fmt_ratio(c.speed_ratio), _fmt_p(c), _fmt_ratio(c.bytes_ratio),
            _fmt_delta(c.agreement_delta), verdict, "; ".join(c.notes),
        ])
    return rows


HEADER = ["case", "status", "base rays/s", "head rays/s", "speed", "p", "bytes", "d agree",
          "verdict", "notes"]


def format_table(res: CompareResult) -> str:
    lines = [f"base: {res.base_dir} ({format_commit(res.base_info.get('commit'), res.base_info.get('dirty'))})",
             f"head: {res.head_dir} ({format_commit(res.head_info.get('commit'), res.head_info.get('dirty'))})",
             f"factor {res.factor}, alpha {res.alpha} (speed = head/base rays/s, bytes = head/base, "
             f"p = one-sided U test head slower, disj = repeat ranges apart)"]
    for w in res.warnings:
        lines.append(f"WARNING: {w}")
    rows = table_rows(res)
    widths = [max(len(HEADER[i]), *(len(r[i]) for r in rows)) if rows else len(HEADER[i])
              for i in range(len(HEADER))]
    widths[0] = min(widths[0], 72)

    def fmt(row):
        cells = []
        for i, v in enumerate(row[:-1]):
            v = v if len(v) <= widths[i] else v[: widths[i] - 1] + "…"
            cells.append(v.ljust(widths[i]) if i in (0, 1, 8) else v.rjust(widths[i]))
        return ("  ".join(cells) + ("  " + row[-1] if row[-1] else "")).rstrip()

    lines.append(fmt(HEADER))
    lines.append("  ".join("-" * w for w in widths[:-1]))
    lines.extend(fmt(r) for r in rows)
    n_reg = len(res.regressions)
    n_cmp = sum(1 for c in res.cases if c.base is not None and c.head is not None)
    summary = f"{n_cmp} cases compared, {n_reg} regressions"
    if res.only_base:
        summary += f", {len(res.only_base)} only in base"
    if res.only_head:
        summary += f", {len(res.only_head)} only in head"
    if not res.verdicts_given:
        summary += " (no verdicts: different devices)"
    lines.append(summary)
    return "\n".join(lines)


def write_compare_html(res: CompareResult, path) -> Path:
    path = Path(path)
    e = html.escape
    out = ["<!DOCTYPE html><html><head><meta charset='utf-8'><title>lsbench compare</title>",
           "<style>body{font-family:sans-serif;margin:2em;color:#222}"
           "table{border-collapse:collapse;font-size:13px}td,th{border:1px solid #ccc;"
           "padding:3px 6px;text-align:right}td.l,th{text-align:left}th{background:#eee}"
           "tr.reg td{background:#fdd}tr.nv td{background:#f4f4f4;color:#777}"
           ".warn{background:#fff3cd;border:1px solid #e0c060;padding:.5em 1em}</style>",
           "</head><body><h1>lsbench compare</h1>"]
    for label, d, info in (("base", res.base_dir, res.base_info), ("head", res.head_dir, res.head_info)):
        out.append(f"<p><b>{label}</b>: {e(str(d))} — commit "
                   f"{e(format_commit(info.get('commit'), info.get('dirty')))}, {e(str(info.get('date', '')))}</p>")
    out.append(f"<p>factor {res.factor}, alpha {res.alpha}; speed = head/base rays/s; "
               f"bytes = head/base; a slowdown counts only past the factor and when the repeats "
               f"are apart (disjoint ranges or one-sided Mann-Whitney p &lt; alpha).</p>")
    for w in res.warnings:
        out.append(f"<p class='warn'>{e(w)}</p>")
    out.append(f"<p><b>{len(res.regressions)} regressions</b></p><table><tr>")
    out.extend(f"<th>{e(h)}</th>" for h in HEADER)
    out.append("</tr>")
    for c, row in zip(res.cases, table_rows(res)):
        cls = "reg" if c.regression else ("nv" if not c.comparable else "")
        out.append(f"<tr class='{cls}'>" + "".join(
            f"<td class='{'l' if i in (0, 1, 8, 9) else ''}'>{e(v)}</td>" for i, v in enumerate(row))
            + "</tr>")
    out.append("</table></body></html>")
    path.write_text("\n".join(out))
    return path


# ---------------------------------------------------------------- compare two commits

def _git(repo, *args, check=True):
    return subprocess.run(["git", "-C", str(repo), *args], capture_output=True, text=True,
                          check=check)


def _safe(rev: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", rev).strip("_") or "rev"


def compare_commits(rev_a: str, rev_b: str, scenario, factor: float = DEFAULT_FACTOR,
                    out_dir=None, repo_dir=None, alpha: float = DEFAULT_ALPHA,
                    extra_args=(), stream=None) -> CompareResult:
    """Run SCENARIO at two revisions, each in its own temporary worktree with its own code on
    PYTHONPATH, then compare (base = rev_a, head = rev_b). The same scenario file is used for
    both (resolved against the current directory when it exists there, else taken as relative
    to each worktree). Worktrees are removed afterwards, also on failure."""
    repo_dir = Path(repo_dir or _git(".", "rev-parse", "--show-toplevel").stdout.strip()).resolve()
    shas = []
    for rev in (rev_a, rev_b):
        r = _git(repo_dir, "rev-parse", "--verify", f"{rev}^{{commit}}", check=False)
        if r.returncode != 0:
            raise ValueError(f"unknown revision {rev!r}: {r.stderr.strip()}")
        shas.append(r.stdout.strip())
    stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    out_dir = Path(out_dir or repo_dir / "reports" / f"compare-{_safe(rev_a)}-{_safe(rev_b)}-{stamp}")
    out_dir = out_dir.resolve()
    out_dir.mkdir(parents=True, exist_ok=True)
    scen = Path(scenario)
    scen_arg = str(scen.resolve()) if scen.exists() else str(scenario)

    run_dirs = []
    tmp_root = Path(tempfile.mkdtemp(prefix="lsbench-wt-"))
    try:
        for i, (rev, sha) in enumerate(zip((rev_a, rev_b), shas)):
            label = f"{'ab'[i]}-{_safe(rev)}-{sha[:10]}"
            wt = tmp_root / label
            _git(repo_dir, "worktree", "add", "--detach", str(wt), sha)
            try:
                run_dir = out_dir / label
                env = dict(os.environ)
                env["PYTHONPATH"] = str(wt) + (os.pathsep + env["PYTHONPATH"]
                                               if env.get("PYTHONPATH") else "")
                cmd = [sys.executable, "-m", "lsbench", "run", scen_arg, "--out",
                       str(run_dir), *extra_args]
                print(f"[{rev} = {sha[:10]}] {' '.join(cmd)}", file=stream or sys.stderr, flush=True)
                proc = subprocess.run(cmd, cwd=wt, env=env)
                # A run that exits non-zero (e.g. its accuracy gate failed) still leaves records
                # to compare; only a run that produced nothing is an error.
                if not (run_dir / "results.jsonl").exists():
                    raise RuntimeError(f"run at {rev} ({sha[:10]}) exited {proc.returncode} "
                                       f"and wrote no {run_dir / 'results.jsonl'}")
                run_dirs.append(run_dir)
            finally:
                _git(repo_dir, "worktree", "remove", "--force", str(wt), check=False)
    finally:
        _git(repo_dir, "worktree", "prune", check=False)
        shutil.rmtree(tmp_root, ignore_errors=True)
    return compare_runs(run_dirs[0], run_dirs[1], factor=factor, alpha=alpha)
