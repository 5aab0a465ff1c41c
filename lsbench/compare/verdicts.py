"""Regression comparison between two runs: case diffs, verdicts, text and HTML output.

Cases are matched by their `key`. Per case: ratio of rays/s (head / base) with its interval,
ratio of bytes, change in agreement. Verdicts:

- speed: a regression only when head is slower than base by more than `factor` AND a one-sided
  Mann-Whitney U test (lsbench/compare/stats.py) says the slowdown is real at the run's stated
  false-alarm rate. `alpha` is the family-wise rate for the whole run, not per case: the cases'
  p values are corrected with Holm's step-down procedure (Holm 1979). Holm rather than
  Benjamini-Hochberg because `compare` answers one yes/no question per run (exit 1 on any
  regression), so what must be bounded is the chance that a run without a real change fails at
  all (the family-wise error), which Holm bounds under any dependence between cases (they share
  one machine, so their noise is correlated); BH bounds the expected share of false flags among
  the flagged, which is not the gate's question. The disjoint-ranges rule of earlier versions is
  gone: with 3 against 3 repeats it is exactly U = 0, p = 0.05 per case, uncorrected.
- samples: a run gives each case's repeats (one process). When both sides bring two or more
  runs of a case (compare-commits --processes, or --base-also/--head-also), each run's median
  is one sample instead: the spread across processes is larger than within one (`lsbench
  stability`), and repeats of one process are not independent samples of that spread.
- power: the smallest p the exact test can give for m and n samples is 1/C(m+n, m); the output
  says whether Holm's strictest level alpha/K (K cases tested) is reachable, how many samples
  per side it needs, and per case the smallest slowdown its samples could show (their spread,
  rescaled; lsbench.compare.stats.detectable_ratio), past the factor.
- spread: every row gives the ratio's Hodges-Lehmann estimate and Moses interval (90 % where the
  samples allow, else the coverage they reach, e.g. 3 against 3: min..max of the 9 pairwise
  ratios, 90 %).
- A case with a single sample on a side has no spread to go on: there the factor alone decides
  (marked n=1; outside the false-alarm rate).
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

from lsbench.compare.stats import (detectable_ratio, mann_whitney_less, min_p_value, ratio_interval,
                                   samples_needed)
from lsbench.report.format import fmt_si, text_table
from lsbench.results.history import repeat_rays_per_second
from lsbench.results.store import format_commit, read_run, record_device, run_devices

DEFAULT_FACTOR = 1.1
DEFAULT_ALPHA = 0.05  # family-wise false-alarm rate of a whole run (Holm over its cases)
CI_COVERAGE = 0.9
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
    ranges_disjoint: bool | None = None  # head's fastest sample slower than base's slowest
    n_base: int = 0                    # samples: repeats of one run, or one median per run
    n_head: int = 0
    units: str = "repeats"             # what a sample is: "repeats" or "processes"
    ratio_ci: tuple | None = None      # (estimate, low, high, coverage) of head/base rays/s
    detectable: float | None = None    # smallest slowdown its samples could show (rays/s ratio)
    holm_level: float | None = None    # the level its p met or missed in Holm's procedure
    significant: bool = False          # slower at the run's false-alarm rate (after Holm)
    samples: tuple = ()                # (base samples, head samples) of rays/s
    base_rps: float | None = None      # the figures the ratio compares (median over runs)
    head_rps: float | None = None
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
    n_base_runs: int = 1
    n_head_runs: int = 1
    # Where the comparison's own files (compare.html) go: the head run's folder, or the folder
    # that holds both sides' runs (compare-commits). base_dir / head_dir are display names.
    folder: str | None = None

    @property
    def tested(self) -> list[CaseDiff]:
        """The cases in Holm's family: a U test on two or more samples per side."""
        return [c for c in self.cases if c.p_value is not None and min(c.n_base, c.n_head) >= 2]

    def power_lines(self) -> list[str]:
        """What this run's verdicts can and cannot say: the false-alarm rate per run, whether
        its samples can reach Holm's strictest level, the smallest detectable change."""
        tested = self.tested
        k = len(tested)
        lines = [f"false alarms: at most {self.alpha:g} per run (family-wise, Holm over the {k} cases "
                 f"with a U test), not per case; a slowdown counts past the factor {self.factor:g} "
                 f"(rays/s ratio < {1 / self.factor:.3f})"]
        if not k:
            return lines
        sizes = sorted({(c.n_base, c.n_head, c.units) for c in tested})
        strictest = self.alpha / k
        for m, n, units in sizes:
            pmin = min_p_value(m, n)
            head = (f"{m} vs {n} {units} per case: smallest possible p {pmin:.3g}, Holm's strictest "
                    f"level {self.alpha:g}/{k} = {strictest:.3g}")
            if pmin <= strictest:
                lines.append(head + ": a slowdown can be flagged")
            else:  # Holm starts at alpha/K: if the smallest p cannot pass it, nothing can
                need = samples_needed(strictest)
                lines.append(head + f": NO speed regression can be flagged; {need} {units} per "
                             f"side are needed (more repeats, or compare-commits --processes)")
        det = [c.detectable for c in tested if c.detectable is not None]
        if det:
            lines.append(f"smallest detectable change (mdc: a lone case at level {strictest:.3g}, each "
                         f"with its own spread): rays/s ratio {max(det):.3f} (best case) .. "
                         f"{float(np.median(det)):.3f} (median) .. {min(det):.3f} (worst)"
                         + (f", {k - len(det)} cases none" if len(det) < k else "")
                         + f"; flagged is a ratio below both its mdc and {1 / self.factor:.3f}")
        return lines

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


def _samples(recs: list[dict]) -> tuple[np.ndarray, str]:
    """(samples of rays/s, what a sample is) of one case over one side's runs: its repeats when
    one run has it, else one median per run (repeats across processes)."""
    ok = [r for r in recs if r.get("status") == "ok"]
    per_run = [repeat_rays_per_second(r) for r in ok]
    per_run = [x for x in per_run if len(x)]
    if len(per_run) >= 2:
        return np.asarray([float(np.median(x)) for x in per_run]), "processes"
    return (per_run[0] if per_run else np.asarray([], dtype=float)), "repeats"


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


def _diff_case(c: CaseDiff, factor: float, base_recs: list[dict], head_recs: list[dict]) -> None:
    """Figures and the deterministic verdicts of one case in both runs; the speed verdict waits
    for the whole run's p values (_speed_verdicts)."""
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

    sb, units_b = _samples(base_recs)
    sh, units_h = _samples(head_recs)
    if units_b != units_h:  # one run on one side, several on the other: compare like with like
        sb = np.concatenate([repeat_rays_per_second(r) for r in base_recs if r.get("status") == "ok"] or [[]])
        sh = np.concatenate([repeat_rays_per_second(r) for r in head_recs if r.get("status") == "ok"] or [[]])
        units_b = "repeats"
    c.units = units_b
    c.n_base, c.n_head = len(sb), len(sh)
    c.samples = (sb, sh)
    if len(sb) and len(sh):
        c.ranges_disjoint = bool(sh.max() < sb.min())
        _, c.p_value = mann_whitney_less(sh, sb)
        c.ratio_ci = ratio_interval(sh, sb, CI_COVERAGE)
    rb, rh = _rps(b), _rps(h)
    if len(base_recs) > 1 or len(head_recs) > 1:  # several runs: the median of their samples
        rb, rh = (float(np.median(sb)), float(np.median(sh))) if len(sb) and len(sh) else (None, None)
    c.base_rps, c.head_rps = rb, rh
    if rb and rh:
        c.speed_ratio = rh / rb
    if c.speed_ratio is not None and c.speed_ratio > factor:
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


def _speed_verdicts(cases: list[CaseDiff], factor: float, alpha: float) -> None:
    """Holm's step-down over the cases with two or more samples per side: sorted by p, the i-th
    smallest (0-based) is significant while p <= alpha / (K - i); a case is a speed regression
    when significant and slower than the factor allows. Cases with one sample on a side are
    decided by the factor alone (no spread to test, no part in the false-alarm rate)."""
    tested = sorted((c for c in cases if c.p_value is not None and min(c.n_base, c.n_head) >= 2),
                    key=lambda c: c.p_value)
    k = len(tested)
    rejecting = True
    for i, c in enumerate(tested):
        c.holm_level = alpha / (k - i)
        rejecting = rejecting and c.p_value <= c.holm_level
        c.significant = rejecting
        c.detectable = detectable_ratio(c.samples[1], c.samples[0], alpha / k)
    for c in cases:
        if c.speed_ratio is None or c.speed_ratio * factor >= 1.0:
            continue
        if c.p_value is not None and min(c.n_base, c.n_head) < 2:
            c.verdicts.append("speed")
            c.notes.append("n=1: the factor alone decides")
        elif c.significant:
            c.verdicts.append("speed")
        else:
            c.notes.append("slower, within noise" + (
                f" (p {c.p_value:.3g} > Holm level {c.holm_level:.3g})" if c.holm_level else ""))


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


def _read_side(dirs) -> tuple[list[str], dict, list[dict], dict[str, list[dict]]]:
    """(folders, run.json of the first, every record, records per key over all runs)."""
    dirs = [dirs] if isinstance(dirs, (str, Path)) else list(dirs)
    info: dict = {}
    recs: list[dict] = []
    by: dict[str, list[dict]] = {}
    for d in dirs:
        run_info, run_recs = read_run(d)
        info = info or run_info
        recs += run_recs
        for r in run_recs:
            if "key" in r:
                by.setdefault(r["key"], []).append(r)
    return [str(d) for d in dirs], info, recs, by


def _shown_record(recs: list[dict]) -> dict:
    """The record a row shows of a case in one side's runs: its first ok one, else its first."""
    return next((r for r in recs if r.get("status") == "ok"), recs[0])


def compare_runs(base_dir, head_dir, factor: float = DEFAULT_FACTOR,
                 alpha: float = DEFAULT_ALPHA, only_common: bool = False) -> CompareResult:
    """Compare head with base; each is a run folder or a list of run folders of one commit
    (repeats across processes: a case in several runs gets one sample per run)."""
    base_dirs, base_info, base_recs, base_all = _read_side(base_dir)
    head_dirs, head_info, head_recs, head_all = _read_side(head_dir)
    base_by = {k: _shown_record(v) for k, v in base_all.items()}
    head_by = {k: _shown_record(v) for k, v in head_all.items()}
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
            _diff_case(c, factor, base_all[key], head_all[key])
        cases.append(c)
    _speed_verdicts([c for c in cases if c.comparable and not c.refused], factor, alpha)
    for c in cases:
        if not verdicts_given and (c.in_both or c.verdicts):
            c.comparable = False
            if c.verdicts:
                c.notes.append("would be: " + ",".join(c.verdicts) + " (different devices)")
            c.verdicts = []
    for label, dirs, recs in (("base", base_dirs, base_recs), ("head", head_dirs, head_recs)):
        if not recs:
            warnings.append(f"{label} run {', '.join(dirs)} has no records")
    def name(dirs):
        return dirs[0] + (f" (+{len(dirs) - 1} more runs)" if len(dirs) > 1 else "")

    return CompareResult(name(base_dirs), name(head_dirs), factor, alpha, base_info, head_info,
                         cases, warnings, verdicts_given, only_common, len(base_dirs), len(head_dirs),
                         folder=head_dirs[0])


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
    if c.significant:
        s += "*"
    if min(c.n_base, c.n_head) <= 1:
        s += " n=1"
    return s


def _fmt_ci(c: CaseDiff) -> str:
    if c.ratio_ci is None or min(c.n_base, c.n_head) < 2:
        return "-"
    _, lo, hi, cov = c.ratio_ci
    return f"{lo:.3f}-{hi:.3f} ({cov * 100:.0f}%)"


def _fmt_n(c: CaseDiff) -> str:
    if not (c.n_base or c.n_head):
        return "-"
    return f"{c.n_base}v{c.n_head}" + ("p" if c.units == "processes" else "")


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
            fmt_si(c.base_rps or _rps(c.base)) if c.base else "-",
            fmt_si(c.head_rps or _rps(c.head)) if c.head else "-",
            _fmt_ratio(c.speed_ratio), _fmt_ci(c), _fmt_n(c), _fmt_p(c),
            _fmt_ratio(c.detectable) if c.detectable is not None else "-", _fmt_ratio(c.bytes_ratio),
            _fmt_delta(c.agreement_delta), _verdict(c, res.only_common), "; ".join(notes),
        ])
    return rows


HEADER = ["case", "status", "base rays/s", "head rays/s", "speed", "speed CI", "n", "p", "mdc",
          "bytes", "d agree", "verdict", "notes"]
NUMERIC_COLUMNS = {2, 3, 4, 5, 6, 7, 8, 9, 10}
LEGEND = ("speed = head/base rays/s, speed CI = its Moses interval (coverage), n = samples base v "
          "head (p: one per process), p = one-sided U test head slower (* = significant after "
          "Holm), mdc = smallest detectable rays/s ratio, bytes = head/base")


def format_table(res: CompareResult) -> str:
    lines = [f"base: {res.base_dir} ({format_commit(res.base_info.get('commit'), res.base_info.get('dirty'))})",
             f"head: {res.head_dir} ({format_commit(res.head_info.get('commit'), res.head_info.get('dirty'))})",
             f"factor {res.factor}, alpha {res.alpha} per run ({LEGEND})"]
    lines += res.power_lines()
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
    out.append(f"<p>factor {res.factor}, alpha {res.alpha} per run; {e(LEGEND)}; a slowdown counts "
               f"only past the factor and when the one-sided Mann-Whitney test is significant "
               f"after Holm's correction across the cases.</p>")
    out += [f"<p class='power'>{e(line)}</p>" for line in res.power_lines()]
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
