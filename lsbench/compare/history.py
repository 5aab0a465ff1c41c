"""What the history says per case: the step model (lsbench/compare/steps.py) fitted to the whole
sequence of its commits' rays/s, each step named by its commit range, and every change of
agreement (a deterministic count ratio: no model needed, any change is named)."""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from lsbench.compare.steps import Fit, fit_steps
from lsbench.compare.verdicts import AGREEMENT_EPS, DEFAULT_FACTOR
from lsbench.report.format import fmt_si, text_table
from lsbench.results.history import CommitPoint, SeriesKey


@dataclass
class StepFound:
    first_suspect: CommitPoint   # first commit at the new level
    last_good: CommitPoint       # last commit at the old level
    ratio: float                 # new level / old level of rays/s
    kind: str                    # "slowdown", "speed-up" (past the factor) or "step"

    @property
    def commit_range(self) -> str:
        """git's notation: the commits in last_good..first_suspect are where it happened."""
        return f"{self.last_good.commit[:10]}..{self.first_suspect.commit[:10]}"

    def describe(self) -> str:
        return (f"{self.kind} x{self.ratio:.3f} ({(self.ratio - 1) * 100:+.1f} % rays/s) in "
                f"{self.commit_range} (first: {self.first_suspect.subject[:60]})")


@dataclass
class AgreementChange:
    before: CommitPoint
    after: CommitPoint

    @property
    def delta(self) -> float:
        return self.after.agreement - self.before.agreement


@dataclass
class CaseHistory:
    machine: str
    key: str
    device: str
    points: list[CommitPoint]            # every commit the case has a record at
    measured: list[CommitPoint]          # those with an ok figure (what the model sees)
    fit: Fit | None
    steps: list[StepFound] = field(default_factory=list)
    agreement_changes: list[AgreementChange] = field(default_factory=list)

    @property
    def slowdowns(self) -> list[StepFound]:
        return [s for s in self.steps if s.kind == "slowdown"]


def within_commit_sigma(points: list[CommitPoint]) -> float:
    """Typical log-spread of one commit's figure from its own runs: the standard error of the
    mean of its log run figures where a commit has several runs (across processes), else of its
    log repeats. A floor for the noise estimate only: repeats in one process understate it."""
    sds = []
    for p in points:
        if len(p.process_figures) >= 2:
            k = len(p.process_figures)
            sds.append(float(np.std(np.log(p.process_figures), ddof=1)) / math.sqrt(k))
        elif len(p.repeats) >= 2:
            sds.append(float(np.std(np.log(p.repeats), ddof=1)) / math.sqrt(len(p.repeats)))
    return float(np.median(sds)) if sds else 0.0


def analyse_case(key: SeriesKey, points: list[CommitPoint], factor: float = DEFAULT_FACTOR) -> CaseHistory:
    machine, case_key, device = key
    measured = [p for p in points if p.rays_per_second]
    fit = None
    steps = []
    if measured:
        fit = fit_steps([p.rays_per_second for p in measured], within_sigma=within_commit_sigma(measured))
        for s in fit.steps:
            kind = ("slowdown" if s.ratio * factor < 1.0 else "speed-up" if s.ratio > factor else "step")
            steps.append(StepFound(first_suspect=measured[s.after], last_good=measured[s.before],
                                   ratio=s.ratio, kind=kind))
    with_agreement = [p for p in points if p.agreement is not None]
    changes = [AgreementChange(a, b) for a, b in zip(with_agreement, with_agreement[1:])
               if abs(b.agreement - a.agreement) > AGREEMENT_EPS]
    return CaseHistory(machine, case_key, device, points, measured, fit, steps, changes)


def analyse(all_series: dict[SeriesKey, list[CommitPoint]], factor: float = DEFAULT_FACTOR) -> list[CaseHistory]:
    return [analyse_case(k, pts, factor) for k, pts in sorted(all_series.items())]


def summary_text(cases: list[CaseHistory], factor: float, statistic: str = "median") -> str:
    """One row per case (first and last figure, steps, agreement), then every step in full."""
    commits = {p.commit for c in cases for p in c.points}
    lines = [f"{len(cases)} cases over {len(commits)} commits; a commit's rays/s = the median over "
             f"its runs of each run's {statistic} repeat; steps from a piecewise-constant fit of log "
             f"rays/s over the whole sequence (lsbench/compare/steps.py); slowdown / speed-up = a "
             f"step past the factor {factor}"]
    rows = []
    for c in cases:
        first = c.measured[0] if c.measured else None
        last = c.measured[-1] if c.measured else None
        failed = sum(1 for p in c.points if p.failed and not p.rays_per_second)
        rows.append([c.key, c.device, str(len(c.points)),
                     fmt_si(first.rays_per_second) if first else "-",
                     fmt_si(last.rays_per_second) if last else "-",
                     f"{c.fit.sigma * 100:.1f} %" if c.fit else "-",
                     ", ".join(f"{s.kind} x{s.ratio:.2f} @ {s.commit_range}" for s in c.steps) or "none",
                     str(len(c.agreement_changes)), str(failed)])
    lines += text_table(["case", "device", "commits", "first rays/s", "last rays/s", "noise",
                         "steps", "agreement changes", "failed"], rows, right={2, 3, 4, 5, 7, 8},
                        max_width={0: 60, 1: 30})
    for c in cases:
        for s in c.steps:
            lines.append(f"{c.key} [{c.device}]: {s.describe()}")
        for a in c.agreement_changes:
            lines.append(f"{c.key} [{c.device}]: agreement {a.before.agreement:.6f} -> "
                         f"{a.after.agreement:.6f} in {a.before.commit[:10]}..{a.after.commit[:10]}")
    n_slow = sum(len(c.slowdowns) for c in cases)
    lines.append(f"{n_slow} slowdowns, {sum(len(c.steps) for c in cases) - n_slow} other steps, "
                 f"{sum(len(c.agreement_changes) for c in cases)} agreement changes")
    return "\n".join(lines)
