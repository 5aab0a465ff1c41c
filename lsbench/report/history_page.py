"""The history page: per case, rays/s over the commits (each run's median, the interquartile
range of all its repeats, the fitted levels of the step model) and agreement, as SVG charts
(matplotlib, no pyplot), with every step named by its commit range and linked to the stored
runs of the commits on either side."""
from __future__ import annotations

import html
import os
from pathlib import Path

import numpy as np

from lsbench.compare.history import CaseHistory
from lsbench.report.format import fmt_si, slug

CHARTS = "history-charts"


def _rel(path: Path, start: Path) -> str:
    return Path(os.path.relpath(path, start)).as_posix()


def _chart(case: CaseHistory, path: Path) -> Path:
    from matplotlib.figure import Figure  # no pyplot: no global state, no display needed

    pts = case.points
    x = np.arange(len(pts))
    fig = Figure(figsize=(9.0, 3.6), dpi=100)
    ax, ax2 = fig.subplots(2, 1, sharex=True, gridspec_kw={"height_ratios": [3, 1]})
    measured = [i for i, p in enumerate(pts) if p.rays_per_second]
    if measured:
        lo = [pts[i].rays_per_second - pts[i].spread[0] for i in measured]
        hi = [pts[i].spread[1] - pts[i].rays_per_second for i in measured]
        ax.errorbar(measured, [pts[i].rays_per_second for i in measured],
                    yerr=[np.maximum(lo, 0), np.maximum(hi, 0)], fmt="o", color="#1f77b4",
                    ms=4, capsize=3, label="commit (median of its runs), IQR of repeats")
        multi = [i for i in measured if len(pts[i].process_figures) > 1]
        for i in multi:
            ax.plot([i] * len(pts[i].process_figures), pts[i].process_figures, ".", color="#7f7f7f",
                    ms=3, label="each run" if i == multi[0] else None)
        if case.fit is not None:
            ax.step(measured, case.fit.levels, where="post", color="#d62728", lw=1.2,
                    label="fitted levels")
    for s in case.steps:
        a, b = pts.index(s.last_good), pts.index(s.first_suspect)
        ax.axvspan(a, b, color="#d62728" if s.kind == "slowdown" else "#2ca02c", alpha=0.12)
        ax.annotate(f"x{s.ratio:.2f}", ((a + b) / 2, s.first_suspect.rays_per_second),
                    ha="center", va="bottom", fontsize=8)
    for i, p in enumerate(pts):
        if p.failed and not p.rays_per_second:
            ax.axvline(i, color="#999", ls=":", lw=1)
    ax.set_ylabel("rays/s")
    ax.yaxis.set_major_formatter(lambda v, _pos: fmt_si(v))
    ax.legend(fontsize=7, loc="lower left", bbox_to_anchor=(0.0, 1.0), ncol=3, frameon=False)
    ax.grid(alpha=0.3)
    agree = [(i, p.agreement) for i, p in enumerate(pts) if p.agreement is not None]
    if agree:
        ax2.plot([i for i, _ in agree], [a for _, a in agree], "s-", color="#2ca02c", ms=3)
    ax2.set_ylabel("agreement", fontsize=8)
    ax2.grid(alpha=0.3)
    ax2.set_xticks(x)
    ax2.set_xticklabels([p.commit[:7] for p in pts], rotation=60, fontsize=7, family="monospace")
    fig.suptitle(f"{case.key} [{case.device}]", fontsize=9, y=1.03)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, bbox_inches="tight")
    return path


def history_link(info: dict, out_dir: Path) -> list[str]:
    """For a run's report: a link to the page of the history database the run went to
    (run.json's history_dir, set by `lsbench run --history`), when that page exists."""
    from lsbench.results.history import PAGE

    page = Path(info.get("history_dir") or "") / PAGE
    if not info.get("history_dir") or not page.is_file():
        return []
    return [f"<p class='history'>This run is in the history across commits: "
            f"<a href='{html.escape(_rel(page, out_dir))}'>history page</a></p>"]


def write_history_page(cases: list[CaseHistory], run_dirs: dict[tuple, list[Path]], path, factor: float,
                       summary: str = "", statistic: str = "median") -> Path:
    """Write the page to `path` and its charts beside it (history-charts/). run_dirs: (machine,
    commit sha) -> the stored runs of it, linked from the tables."""
    path = Path(path)
    out_dir = path.parent
    e = html.escape
    commits = {p.commit for c in cases for p in c.points}
    n_slow = sum(len(c.slowdowns) for c in cases)
    out = ["<!DOCTYPE html><html><head><meta charset='utf-8'><title>lsbench history</title>",
           "<style>body{font-family:sans-serif;margin:2em;color:#222;max-width:1100px}"
           "table{border-collapse:collapse;font-size:13px;margin:.5em 0}td,th{border:1px solid #ccc;"
           "padding:3px 6px;text-align:left}th{background:#eee}td.n{text-align:right}"
           "tr.slowdown td{background:#fdd}tr.speed-up td{background:#dfd}"
           "code{font-size:12px}img{max-width:100%}section{margin-bottom:2em}"
           "pre{background:#f6f6f6;padding:.5em;font-size:11px;overflow-x:auto}</style>",
           "</head><body><h1>lsbench history</h1>",
           f"<p>{len(cases)} cases over {len(commits)} commits; <b>{n_slow} slowdowns</b>. A commit's "
           f"rays/s is the median over its runs of each run's {e(statistic)} repeat. Steps come from "
           f"a piecewise-constant fit of log rays/s over the whole sequence (penalised, "
           f"<code>lsbench/compare/steps.py</code>); a step past the factor {factor:g} is a "
           f"slowdown or speed-up. A step's range <code>A..B</code>: A is the last commit at the old "
           f"level, B the first at the new one; the change is in the commits of "
           f"<code>git log A..B</code>.</p>"]
    out.append("<h2 id='steps'>Steps</h2><table><tr><th>case</th><th>device</th><th>kind</th>"
               "<th>ratio</th><th>commit range</th><th>first commit at the new level</th></tr>")
    any_step = False
    for c in cases:
        for s in c.steps:
            any_step = True
            links = " ".join(
                f"<a href='{e(_rel(d / 'results.jsonl', out_dir))}'>{e(p.commit[:10])}</a>"
                for p in (s.last_good, s.first_suspect) for d in run_dirs.get((c.machine, p.commit), [])[:1])
            out.append(f"<tr class='{e(s.kind)}'><td><a href='#{e(slug(c.machine, c.key, c.device))}'>"
                       f"{e(c.key)}</a></td><td>{e(c.device)}</td><td>{e(s.kind)}</td>"
                       f"<td class='n'>{s.ratio:.3f}</td><td><code>{e(s.commit_range)}</code> ({links})</td>"
                       f"<td>{e(s.first_suspect.subject)}</td></tr>")
    if not any_step:
        out.append("<tr><td colspan='6'>no step in any case</td></tr>")
    out.append("</table>")
    charts_dir = out_dir / CHARTS
    for c in cases:
        anchor = slug(c.machine, c.key, c.device)
        chart = _chart(c, charts_dir / f"{anchor}.svg")
        href = e(_rel(chart, out_dir))
        out.append(f"<section id='{e(anchor)}'><h2>{e(c.key)}</h2><p>{e(c.machine)}, {e(c.device)}; noise "
                   f"{c.fit.sigma * 100 if c.fit else 0:.1f} % per commit (log rays/s)</p>"
                   f"<a href='{href}'><img src='{href}' alt='rays/s over commits: {e(c.key)}'></a>")
        out.append("<table><tr><th>commit</th><th>subject</th><th>runs</th><th>rays/s</th>"
                   "<th>IQR of repeats</th><th>agreement</th><th>stored runs</th></tr>")
        for p in c.points:
            spread = p.spread
            links = " ".join(f"<a href='{e(_rel(d / 'results.jsonl', out_dir))}'>{i + 1}</a>"
                             for i, d in enumerate(run_dirs.get((c.machine, p.commit), [])))
            out.append(f"<tr><td><code>{e(p.label)}</code></td><td>{e(p.subject[:80])}</td>"
                       f"<td class='n'>{len(p.process_figures)}{' + failed' if p.failed else ''}</td>"
                       f"<td class='n'>{fmt_si(p.rays_per_second)}</td>"
                       f"<td class='n'>{'-' if spread is None else fmt_si(spread[0]) + ' - ' + fmt_si(spread[1])}</td>"
                       f"<td class='n'>{'-' if p.agreement is None else f'{p.agreement:.6f}'}</td>"
                       f"<td>{links}</td></tr>")
        out.append("</table></section>")
    if summary:
        out.append(f"<h2>Text summary</h2><pre>{e(summary)}</pre>")
    out.append("</body></html>")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(out))
    return path
