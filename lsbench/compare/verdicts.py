"""Regression comparison between two runs: case diffs, verdicts, text and HTML output.

Cases are matched by their `key`. Per case: ratio of rays/s (head / base), ratio of bytes, change
in agreement. Verdicts:

- speed: a regression only when head is slower than base by more than `factor` AND the repeats
  say the slowdown is real: either the repeat ranges do not overlap (head's best repeat is slower
  than base's worst) or a one-sided Mann-Whitney U test (lsbench/compare/stats.py) on the
  per-repeat rays/s gives p < alpha. (A run with a single repeat per case has no spread to go
  on: there the factor alone decides, and the table says n=1.) This is the approach of asv
  (airspeed velocity): a ratio threshold plus a statistical check, so noise on a shared CI
  machine does not fail the gate.
- accuracy: any drop in agreement is a regression (agreement is a count ratio: deterministic).
- failure: ok in base and failed in head, or new in head and failed.
- memory: bytes grew by more than `factor` (deterministic, so no statistics).

A key names a case, but two records under one key are the same case only when they ran on the
same inputs: a pair whose scene_hash or rays_hash differ is refused, with the reason, not
compared. The comparison fails (exit 1) on any regression or refusal, when no case is in both
runs, and when head lacks cases of base (a run that lost cases must not read as "0
regressions"; `only_common` compares the common cases only).

Runs whose cases ran on different devices get a warning and no verdicts: figures from two
devices are never compared as if they were one (DESIGN.md, Environments).
"""
from __future__ import annotations

import html
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lsbench.compare.stats import mann_whitney_less
from lsbench.report.format import fmt_si, text_table
from lsbench.results.store import format_commit, read_run, record_device, run_devices

DEFAULT_FACTOR = 1.1
DEFAULT_ALPHA = 0.01
AGREEMENT_EPS = 1e-12  # float noise of a ratio of counts, not a tolerance
INPUT_HASHES = (("scene_hash", "scene"), ("rays_hash", "ray set"))


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
    refused: str = ""  # why the two records are not one case (different inputs); "" if they are

    @property
    def regression(self) -> bool:
        return bool(self.verdicts)

    @property
    def in_both(self) -> bool:
        return self.base is not None and self.head is not None

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
    only_common: bool = False  # head lacking base's cases is then no failure

    @property
    def regressions(self) -> list[CaseDiff]:
        return [c for c in self.cases if c.regression]

    @property
    def has_regression(self) -> bool:
        return bool(self.regressions)

    @property
    def refused(self) -> list[CaseDiff]:
        return [c for c in self.cases if c.refused]

    @property
    def only_base(self) -> list[str]:
        return [c.key for c in self.cases if c.head is None]

    @property
    def only_head(self) -> list[str]:
        return [c.key for c in self.cases if c.base is None]

    @property
    def problems(self) -> list[str]:
        """Why the comparison fails, one line each; empty when it passes."""
        out = []
        if not any(c.in_both for c in self.cases):
            out.append(f"nothing matched: no case key is in both runs (base has "
                       f"{sum(c.base is not None for c in self.cases)} cases, head "
                       f"{sum(c.head is not None for c in self.cases)})")
        if self.regressions:
            out.append(f"{len(self.regressions)} regressions")
        if self.refused:
            out.append(f"{len(self.refused)} cases refused: same key, different inputs")
        if self.only_base and not self.only_common:
            out.append(f"head lacks {len(self.only_base)} of base's cases (first: "
                       f"{self.only_base[0]}); --only-common compares the common ones only")
        return out

    @property
    def exit_code(self) -> int:
        return 1 if self.problems else 0

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


def different_inputs(base: dict, head: dict) -> str:
    """Why two records of one key ran on different inputs ("" when they did not, or when a
    record does not say: a failed case may have no hashes)."""
    reasons = []
    for field_name, what in INPUT_HASHES:
        hb, hh = base.get(field_name), head.get(field_name)
        if hb and hh and hb != hh:
            reasons.append(f"{what} differs ({field_name} {hb} in base, {hh} in head)")
    return "; ".join(reasons)


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


def _one_sided_case(c: CaseDiff) -> None:
    """A case in one run only: no figures to compare, but a new case that fails is a failure."""
    c.comparable = False
    if c.base is not None:
        c.notes.append("only in base")
        return
    c.notes.append("only in head")
    if c.head.get("status") != "ok":
        c.verdicts.append("failure")
        c.notes.append(f"new and failed: {c.head.get('reason', '')}".strip())


def _environment_warnings(base_info, base_recs, head_info, head_recs, common) -> tuple[list, bool]:
    """(warnings, verdicts_given): devices per backend (run.json completed by the records) and
    per common case; a driver change is a warning only."""
    devices, drivers = set(), set()
    for base, head in common:
        (db, vb), (dh, vh) = record_device(base, base_info), record_device(head, head_info)
        if db and dh and db != dh:
            devices.add((base.get("backend"), db, dh))
        if vb and vh and vb != vh:
            drivers.add((base.get("backend"), vb, vh))
    bd, hd = run_devices(base_info, base_recs), run_devices(head_info, head_recs)
    for backend in bd.keys() & hd.keys():
        db, dh = bd[backend].get("device"), hd[backend].get("device")
        if db and dh and db != dh:
            devices.add((backend, db, dh))
    warnings = [f"different devices for {backend}: base '{db}' vs head '{dh}' — figures are not "
                f"comparable; no regression verdicts given"
                for backend, db, dh in sorted(devices, key=str)]
    warnings += [f"driver changed for {backend}: '{vb}' -> '{vh}' (timings may move for that "
                 f"reason alone)" for backend, vb, vh in sorted(drivers, key=str)]
    return warnings, not devices


def compare_runs(base_dir, head_dir, factor: float = DEFAULT_FACTOR,
                 alpha: float = DEFAULT_ALPHA, only_common: bool = False) -> CompareResult:
    base_info, base_recs = read_run(base_dir)
    head_info, head_recs = read_run(head_dir)
    base_by = {r["key"]: r for r in base_recs if "key" in r}
    head_by = {r["key"]: r for r in head_recs if "key" in r}
    common = [(base_by[k], head_by[k]) for k in base_by if k in head_by]
    warnings, verdicts_given = _environment_warnings(base_info, base_recs, head_info, head_recs,
                                                     common)

    cases: list[CaseDiff] = []
    for key in list(base_by) + [k for k in head_by if k not in base_by]:
        c = CaseDiff(key=key, base=base_by.get(key), head=head_by.get(key))
        if not c.in_both:
            _one_sided_case(c)
        elif refusal := different_inputs(c.base, c.head):
            c.comparable, c.refused = False, refusal
        else:
            _diff_case(c, factor, alpha)
        if not verdicts_given and (c.in_both or c.verdicts):
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
                         cases, warnings, verdicts_given, only_common)


# ---------------------------------------------------------------- output

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


def _verdict(c: CaseDiff, only_common: bool) -> str:
    if c.regression:
        return "REGRESSION " + ",".join(c.verdicts)
    if c.refused:
        return "REFUSED"
    if c.head is None:
        return "not compared" if only_common else "MISSING"
    if c.base is None:
        return "new"
    return "ok" if c.comparable else "no verdict"


def table_rows(res: CompareResult) -> list[list[str]]:
    rows = []
    for c in res.cases:
        notes = ([c.refused] if c.refused else []) + c.notes
        rows.append([
            c.key, c.status,
            fmt_si(_rps(c.base)) if c.base else "-",
            fmt_si(_rps(c.head)) if c.head else "-",
            _fmt_ratio(c.speed_ratio), _fmt_p(c), _fmt_ratio(c.bytes_ratio),
            _fmt_delta(c.agreement_delta), _verdict(c, res.only_common), "; ".join(notes),
        ])
    return rows


HEADER = ["case", "status", "base rays/s", "head rays/s", "speed", "p", "bytes", "d agree",
          "verdict", "notes"]
NUMERIC_COLUMNS = {2, 3, 4, 5, 6, 7}


def format_table(res: CompareResult) -> str:
    lines = [f"base: {res.base_dir} ({format_commit(res.base_info.get('commit'), res.base_info.get('dirty'))})",
             f"head: {res.head_dir} ({format_commit(res.head_info.get('commit'), res.head_info.get('dirty'))})",
             f"factor {res.factor}, alpha {res.alpha} (speed = head/base rays/s, bytes = head/base, "
             f"p = one-sided U test head slower, disj = repeat ranges apart)"]
    lines += [f"WARNING: {w}" for w in res.warnings]
    lines += text_table(HEADER, table_rows(res), right=NUMERIC_COLUMNS, max_width={0: 72})
    n_cmp = sum(1 for c in res.cases if c.in_both and not c.refused)
    summary = f"{n_cmp} cases compared, {len(res.regressions)} regressions"
    if res.refused:
        summary += f", {len(res.refused)} refused"
    if res.only_base:
        summary += f", {len(res.only_base)} only in base"
    if res.only_head:
        summary += f", {len(res.only_head)} only in head"
    if not res.verdicts_given:
        summary += " (no verdicts: different devices)"
    lines.append(summary)
    lines += [f"compare failed: {p}" for p in res.problems]
    return "\n".join(lines)


def write_compare_html(res: CompareResult, path) -> Path:
    path = Path(path)
    e = html.escape
    out = ["<!DOCTYPE html><html><head><meta charset='utf-8'><title>lsbench compare</title>",
           "<style>body{font-family:sans-serif;margin:2em;color:#222}"
           "table{border-collapse:collapse;font-size:13px}td,th{border:1px solid #ccc;"
           "padding:3px 6px;text-align:right}td.l,th{text-align:left}th{background:#eee}"
           "tr.reg td{background:#fdd}tr.nv td{background:#f4f4f4;color:#777}"
           ".warn{background:#fff3cd;border:1px solid #e0c060;padding:.5em 1em}"
           ".fail{background:#fbd5d5;border:1px solid #c33;padding:.5em 1em}</style>",
           "</head><body><h1>lsbench compare</h1>"]
    for label, d, info in (("base", res.base_dir, res.base_info), ("head", res.head_dir, res.head_info)):
        out.append(f"<p><b>{label}</b>: {e(str(d))} — commit "
                   f"{e(format_commit(info.get('commit'), info.get('dirty')))}, {e(str(info.get('date', '')))}</p>")
    out.append(f"<p>factor {res.factor}, alpha {res.alpha}; speed = head/base rays/s; "
               f"bytes = head/base; a slowdown counts only past the factor and when the repeats "
               f"are apart (disjoint ranges or one-sided Mann-Whitney p &lt; alpha).</p>")
    out += [f"<p class='warn'>{e(w)}</p>" for w in res.warnings]
    out += [f"<p class='fail'>compare failed: {e(p)}</p>" for p in res.problems]
    out.append(f"<p><b>{len(res.regressions)} regressions</b></p><table><tr>")
    out.extend(f"<th>{e(h)}</th>" for h in HEADER)
    out.append("</tr>")
    for c, row in zip(res.cases, table_rows(res)):
        cls = "reg" if c.regression or c.refused else ("nv" if not c.comparable else "")
        out.append(f"<tr class='{cls}'>" + "".join(
            f"<td class='{'' if i in NUMERIC_COLUMNS else 'l'}'>{e(v)}</td>" for i, v in enumerate(row))
            + "</tr>")
    out.append("</table></body></html>")
    path.write_text("\n".join(out))
    return path
