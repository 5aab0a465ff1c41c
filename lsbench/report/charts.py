"""The report's charts (matplotlib, no pyplot: no global state, no display needed): rays/s per
case of one workload against Embree's, rays/s against memory and speed against accuracy (each
with its Pareto front), build time against memory, the spread of the timing repeats. Each chart
function takes the records of one group (a scene, a workload) and writes one SVG (what the page
shows: sharp at any zoom) and a PNG beside it, or returns None when no record has what it plots."""
from __future__ import annotations

import math
from collections import defaultdict
from pathlib import Path

import numpy as np

from lsbench.backends.structures import display_order
from lsbench.report.format import fmt_si
from lsbench.report.records import case_label, resolution_label, resolution_order, scene_name, succeeded

STRUCTURE_COLORS = {
    "grid": "#1f77b4", "svo": "#ff7f0e", "esvo": "#2ca02c",
    "grid-ls": "#6baed6", "svo-ls": "#fdae6b", "esvo-ls": "#74c476",
}
EXTRA_COLORS = ["#9467bd", "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22", "#17becf"]
BACKEND_MARKERS = {"glsl": "o", "opencl": "s"}


def structure_color(structure, _extra={}) -> str:
    """The structure's colour; names outside the catalogue get the next spare one, kept."""
    if structure in STRUCTURE_COLORS:
        return STRUCTURE_COLORS[structure]
    if structure not in _extra:
        _extra[structure] = EXTRA_COLORS[len(_extra) % len(EXTRA_COLORS)]
    return _extra[structure]


def _figure(w=8.0, h=5.0):
    from matplotlib.figure import Figure  # no pyplot: no global state, no display needed
    fig = Figure(figsize=(w, h), dpi=100)
    return fig


def _save(fig, path: Path) -> Path:
    """path.svg and path.png; returns the SVG's path."""
    path.parent.mkdir(parents=True, exist_ok=True)
    svg = path.with_suffix(".svg")
    import matplotlib

    # text stays text (searchable, selectable, smaller); no date: same run, same file
    with matplotlib.rc_context({"svg.fonttype": "none"}):
        fig.savefig(svg, bbox_inches="tight", metadata={"Date": None})
    fig.savefig(path.with_suffix(".png"), bbox_inches="tight")
    return svg


def pareto_front(points):
    """Indices of the points not dominated when minimizing x (disagreement, memory) and
    maximizing y (rays/s); sorted by x."""
    order = sorted(range(len(points)), key=lambda i: (points[i][0], -points[i][1]))
    front, best = [], -math.inf
    for i in order:
        if points[i][1] > best:
            front.append(i)
            best = points[i][1]
    return front


def _log_formatter(fmt):
    """Labels where matplotlib's LogFormatter would put one (minor ticks too when the axis spans
    few decades), written by fmt: plain 0.06 or 2 M instead of 6x10^-2."""
    from matplotlib.ticker import LogFormatter

    class Fmt(LogFormatter):
        def __call__(self, x, pos=None):
            return fmt(x) if x > 0 and super().__call__(x, pos) else ""
    return Fmt(labelOnlyBase=False, minor_thresholds=(1.5, 0.6))


def _si_formatter():
    return _log_formatter(fmt_si)


def _plain_formatter():
    return _log_formatter(lambda x: f"{x:g}")


def _legend_handles(structures, backends):
    from matplotlib.lines import Line2D
    h = [Line2D([], [], ls="", marker="o", color=structure_color(s), label=s) for s in structures]
    h += [Line2D([], [], ls="", marker=BACKEND_MARKERS.get(b, "^"), color="#555", mfc="none",
                 label=b) for b in backends]
    return h


PER_MILLION = 1e6


def disagreements_per_million(rec) -> float:
    """Rays that disagree with Embree (missed, extra, wrong, distance; ties agree) per million."""
    n = rec.get("ray_count") or 0
    bad = sum(int(rec.get(k) or 0) for k in ("missed", "extra", "wrong", "distance"))
    return PER_MILLION * bad / n if n else 0.0


def _front_line(ax, xs, ys, front, labels, right):
    """The Pareto front as a step line, its points ringed and labelled."""
    fx, fy = xs[front], ys[front]
    # each front point is the fastest at its x or better
    ax.step(np.append(fx, right), np.append(fy, fy[-1]), where="post", color="crimson", lw=1.2, zorder=2,
            label="Pareto front")
    ax.scatter(fx, fy, s=140, facecolors="none", edgecolors="crimson", linewidths=1.5, zorder=4)
    for k, i in enumerate(front):
        ax.annotate(labels[i], (xs[i], ys[i]), textcoords="offset points",
                    xytext=(6, 6 if k % 2 == 0 else -12), fontsize=7, color="crimson")


def _embree_line(ax, recs):
    """Embree on the CPU, same rays: the reference every structure is checked against."""
    emb = [float(r["embree_rays_per_second"]) for r in recs if r.get("embree_rays_per_second")]
    if emb:
        ax.axhline(float(np.median(emb)), color="#444", ls="--", lw=1, zorder=1,
                   label=f"Embree (CPU) {fmt_si(float(np.median(emb)), 'rays/s')}")


def _cases_scatter(ax, recs, xs, ys):
    for r, x, y in zip(recs, xs, ys):
        ax.scatter([x], [y], color=structure_color(r.get("structure")), s=36, zorder=3,
                   marker=BACKEND_MARKERS.get(r.get("backend"), "^"), edgecolors="k", linewidths=0.4)


def _finish(ax, recs, title):
    ax.set_yscale("log")
    ax.set_ylabel("rays/s (log)")
    ax.yaxis.set_major_formatter(_si_formatter())
    ax.yaxis.set_minor_formatter(_si_formatter())
    ax.set_title(title, fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    structures = sorted({r.get("structure") for r in recs}, key=display_order)
    backends = sorted({r.get("backend") for r in recs})
    handles = _legend_handles(structures, backends) + ax.get_legend_handles_labels()[0]
    ax.legend(handles=handles, fontsize=7, loc="center left", bbox_to_anchor=(1.01, 0.5))


def chart_speed_accuracy(records, path: Path, title: str):
    """x: disagreements per million rays (0, then log: one in a million and a thousand in a
    million are different findings), unexplained ones crossed out in red. When every case
    agrees on every ray, x is the largest distance error against Embree instead (|t - t_Embree|,
    the precision a structure's traversal keeps), and the chart says so and ranks the speeds."""
    recs = [r for r in records if succeeded(r) and r.get("rays_per_second") and r.get("agreement") is not None]
    if not recs:
        return None
    xs = np.array([disagreements_per_million(r) for r in recs])
    ys = np.array([float(r["rays_per_second"]) for r in recs])
    all_agree = not xs.any()
    linthresh, xlabel = 1.0, "rays that disagree with Embree per million (0, then log; ties agree)"
    if all_agree:
        dts = np.array([float(r.get("max_abs_dt") or 0.0) for r in recs])
        if dts.any():
            xs = dts
            linthresh = float(dts[dts > 0].min()) / 2
            xlabel = (f"largest |t − t_Embree| of the case (scene units; 0, then log from {linthresh:.1g}): "
                      "every ray agrees, so this is the accuracy left")
    fig = _figure(9, 5.5)
    ax = fig.add_subplot(1, 1, 1)
    _cases_scatter(ax, recs, xs, ys)
    bad = [i for i, r in enumerate(recs) if (r.get("unexplained") or 0) > 0]
    if bad:
        ax.scatter(xs[bad], ys[bad], marker="x", s=90, color="red", zorder=5, label="unexplained disagreements")
    right = max(10 * linthresh, float(xs.max()) * 3)
    _front_line(ax, xs, ys, pareto_front(list(zip(xs, ys))), [case_label(r) for r in recs], right)
    _embree_line(ax, recs)
    ax.set_xscale("symlog", linthresh=linthresh)
    ax.set_xlim(left=-0.3 * linthresh, right=right)
    ax.set_xlabel(xlabel, fontsize=8 if all_agree else 10)
    if all_agree:
        best, slow = int(np.argmax(ys)), int(np.argmin(ys))
        ax.text(0.98, 0.04, f"all {len(recs)} cases agree with Embree on every ray;\n{case_label(recs[best])} "
                f"is fastest, {ys[best] / ys[slow]:.3g}× the slowest ({case_label(recs[slow])})",
                transform=ax.transAxes, ha="right", va="bottom", fontsize=8,
                bbox={"facecolor": "white", "edgecolor": "#999", "alpha": 0.9})
    _finish(ax, recs, title)
    return _save(fig, path)


def chart_rays_memory(records, path: Path, title: str):
    """rays/s against the structure's memory (log-log), the Pareto front (no other case is
    faster with less memory) labelled by structure, resolution and N: the trade-off of the Line
    Space structures, which buy speed with 20-80x the memory."""
    recs = [r for r in records if succeeded(r) and r.get("rays_per_second") and r.get("memory_bytes")]
    if not recs:
        return None
    xs = np.array([r["memory_bytes"] / 2 ** 20 for r in recs])
    ys = np.array([float(r["rays_per_second"]) for r in recs])
    fig = _figure(9, 5.5)
    ax = fig.add_subplot(1, 1, 1)
    _cases_scatter(ax, recs, xs, ys)
    _front_line(ax, xs, ys, pareto_front(list(zip(xs, ys))), [case_label(r) for r in recs], float(xs.max()) * 2)
    _embree_line(ax, recs)
    ax.set_xscale("log")
    ax.set_xlabel("memory of the structure (MiB, log)")
    ax.xaxis.set_major_formatter(_plain_formatter())
    ax.xaxis.set_minor_formatter(_plain_formatter())
    _finish(ax, recs, title)
    return _save(fig, path)


def chart_workload(records, path: Path, title: str):
    """One workload: rays/s of every case as bars, one panel per scene, Embree's rays/s on the
    same rays as the dashed reference line."""
    recs = [r for r in records if succeeded(r) and r.get("rays_per_second")]
    if not recs:
        return None
    scenes = sorted({scene_name(r) for r in recs})
    sizes = [sum(scene_name(r) == s for r in recs) for s in scenes]
    fig = _figure(9, 1.0 + sum(0.24 * n + 0.9 for n in sizes))
    fig.set_layout_engine("constrained")  # panel titles, tick labels and the title never overlap
    axes = fig.subplots(len(scenes), 1, squeeze=False, gridspec_kw={"height_ratios": sizes})[:, 0]
    for ax, scene in zip(axes, scenes):
        rs = sorted((r for r in recs if scene_name(r) == scene),
                    key=lambda r: (display_order(r.get("structure")), r.get("ls_n") or 0,
                                   resolution_order(r.get("resolution")), r.get("backend", "")))
        ys = np.arange(len(rs))
        speeds = [r["rays_per_second"] for r in rs]
        # linear from 0: a bar's length is its speed (a log axis would make lengths meaningless)
        ax.barh(ys, speeds, color=[structure_color(r.get("structure")) for r in rs],
                edgecolor=["k" if r.get("backend") == "opencl" else "none" for r in rs], height=0.7)
        for y, v in zip(ys, speeds):
            ax.annotate(fmt_si(v), (v, y), xytext=(3, 0), textcoords="offset points", va="center", fontsize=6)
        ax.set_yticks(ys)
        ax.set_yticklabels([case_label(r) for r in rs], fontsize=7)
        ax.invert_yaxis()
        emb = [float(r["embree_rays_per_second"]) for r in rs if r.get("embree_rays_per_second")]
        if emb:
            ax.axvline(float(np.median(emb)), color="#444", ls="--", lw=1.2,
                       label=f"Embree (CPU) {fmt_si(float(np.median(emb)), 'rays/s')}")
            ax.legend(fontsize=7, loc="lower right")
        from matplotlib.ticker import FuncFormatter

        ax.set_xlim(0, max(speeds + emb) * 1.12)
        ax.xaxis.set_major_formatter(FuncFormatter(lambda x, _: fmt_si(x) if x else "0"))
        ax.grid(True, axis="x", alpha=0.3)
        ax.set_title(f"{scene} — {rs[0].get('ray_count')} rays", fontsize=9, loc="left")
    axes[-1].set_xlabel("rays/s (black edge: opencl)")
    fig.suptitle(title, fontsize=10)
    return _save(fig, path)


def chart_build_memory(records, path: Path, title: str):
    recs = [r for r in records if succeeded(r) and r.get("memory_bytes") and r.get("build_seconds")]
    if not recs:
        return None
    fig = _figure(9, 5.5)
    ax = fig.add_subplot(1, 1, 1)
    by_struct = defaultdict(list)
    for r in recs:
        by_struct[(r.get("structure"), r.get("backend"), r.get("ls_n") or 0)].append(r)
    for (s, b, n), rs in sorted(by_struct.items(), key=lambda kv: (display_order(kv[0][0]), kv[0][1], kv[0][2])):
        rs = sorted(rs, key=lambda r: resolution_order(r.get("resolution")))
        mx = [r["memory_bytes"] / 2 ** 20 for r in rs]
        by = [r["build_seconds"] for r in rs]
        ax.plot(mx, by, marker=BACKEND_MARKERS.get(b, "^"), color=structure_color(s), lw=0.8,
                ls="-" if not n else (0, (1 + n, 1 + n)), ms=5, alpha=0.85)
        last = rs[-1]
        ax.annotate(f"{resolution_label(last.get('resolution'))}", (mx[-1], by[-1]), fontsize=6,
                    textcoords="offset points", xytext=(3, 2), color=structure_color(s))
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("memory (MiB, log)")
    ax.set_ylabel("build time (s, log)")
    for axis in (ax.xaxis, ax.yaxis):
        axis.set_major_formatter(_plain_formatter())
        axis.set_minor_formatter(_plain_formatter())
    ax.set_title(title + " — lines join resolutions of one structure/backend/N", fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    structures = sorted({r.get("structure") for r in recs}, key=display_order)
    backends = sorted({r.get("backend") for r in recs})
    ax.legend(handles=_legend_handles(structures, backends), fontsize=7, loc="center left",
              bbox_to_anchor=(1.01, 0.5))
    return _save(fig, path)


def chart_repeats(records, path: Path, title: str):
    recs = [r for r in records if succeeded(r) and (r.get("trace_seconds_all") or r.get("trace_seconds"))]
    if not recs:
        return None
    recs.sort(key=lambda r: (display_order(r.get("structure")), r.get("ls_n") or 0,
                             resolution_order(r.get("resolution")), r.get("backend", ""), r.get("rays", "")))
    h = max(2.5, 0.22 * len(recs) + 1.2)
    fig = _figure(9, h)
    ax = fig.add_subplot(1, 1, 1)
    labels = []
    for i, r in enumerate(recs):
        ts = np.asarray([t for t in (r.get("trace_seconds_all") or [r.get("trace_seconds")]) if t], float) * 1e3
        lo = r.get("trace_seconds_min", ts.min() / 1e3) * 1e3
        hi = r.get("trace_seconds_max", ts.max() / 1e3) * 1e3
        med = (r.get("trace_seconds") or float(np.median(ts)) / 1e3) * 1e3
        c = structure_color(r.get("structure"))
        ax.plot([lo, hi], [i, i], color=c, lw=2.5, alpha=0.45, solid_capstyle="butt")
        ax.scatter(ts, np.full(len(ts), i), s=9, color=c, zorder=3, alpha=0.8)
        ax.scatter([med], [i], marker="|", s=160, color="k", zorder=4)
        cv = r.get("trace_cv")
        lab = case_label(r) + (f" ({r['rays']})" if len({x.get('rays') for x in recs}) > 1 else "")
        labels.append(lab + (f"  cv {cv * 100:.1f}%" if cv is not None else ""))
    ax.set_yticks(range(len(recs)))
    ax.set_yticklabels(labels, fontsize=7)
    ax.invert_yaxis()
    ax.set_xscale("log")
    ax.xaxis.set_major_formatter(_plain_formatter())
    ax.xaxis.set_minor_formatter(_plain_formatter())
    ax.set_xlabel("trace time per repeat (ms, log): dots = repeats, bar = min…max, | = median")
    ax.set_title(title, fontsize=10)
    ax.grid(True, axis="x", which="both", alpha=0.3)
    return _save(fig, path)
