"""The report's charts (matplotlib, no pyplot: no global state, no display needed): speed
against accuracy with its Pareto front, build time against memory, the spread of the timing
repeats. Each chart function takes the records of one scene and writes one PNG, or returns None
when no record has what it plots."""
from __future__ import annotations

import math
from collections import defaultdict
from pathlib import Path

import numpy as np

from lsbench.backends.structures import display_order
from lsbench.report.format import fmt_si
from lsbench.report.records import case_label, resolution_label, resolution_order, succeeded

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


def _save(fig, path: Path):
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, bbox_inches="tight")
    return path


def pareto_front(points):
    """Indices of the points not dominated when minimizing x (disagreement) and maximizing y
    (rays/s); sorted by x."""
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


def chart_speed_accuracy(records, path: Path, title: str):
    recs = [r for r in records if succeeded(r) and r.get("rays_per_second") and r.get("agreement") is not None]
    if not recs:
        return None
    xs = np.array([max(0.0, 1.0 - float(r["agreement"])) for r in recs])
    ys = np.array([float(r["rays_per_second"]) for r in recs])
    fig = _figure(9, 5.5)
    ax = fig.add_subplot(1, 1, 1)
    for r, x, y in zip(recs, xs, ys):
        ax.scatter([x], [y], color=structure_color(r.get("structure")), s=36, zorder=3,
                   marker=BACKEND_MARKERS.get(r.get("backend"), "^"), edgecolors="k", linewidths=0.4)
    front = pareto_front(list(zip(xs, ys)))
    fx, fy = xs[front], ys[front]
    # step line through the front: each point is the fastest at its disagreement or better
    ax.step(np.append(fx, max(xs.max(), fx[-1]) * 1.5 + 1e-9), np.append(fy, fy[-1]),
            where="post", color="crimson", lw=1.2, zorder=2, label="Pareto front")
    ax.scatter(fx, fy, s=140, facecolors="none", edgecolors="crimson", linewidths=1.5, zorder=4)
    for k, i in enumerate(front):
        ax.annotate(case_label(recs[i]), (xs[i], ys[i]), textcoords="offset points",
                    xytext=(6, 6 if k % 2 == 0 else -12), fontsize=7, color="crimson")
    # Embree on the CPU, same rays: the reference every structure is checked against
    emb = [float(r["embree_rays_per_second"]) for r in recs if r.get("embree_rays_per_second")]
    if emb:
        ax.axhline(float(np.median(emb)), color="#444", ls="--", lw=1, zorder=1,
                   label=f"Embree (CPU) {fmt_si(float(np.median(emb)), 'rays/s')}")
    nz = xs[xs > 0]
    linthresh = float(min(nz.min() / 2, 1e-6)) if len(nz) else 1e-6
    ax.set_xscale("symlog", linthresh=linthresh)
    ax.set_xlim(left=-linthresh * 0.3, right=max(10 * linthresh, float(xs.max()) * 3))
    ax.set_yscale("log")
    ax.set_xlabel(f"disagreement with Embree, 1 − agreement (symlog, linear below {linthresh:.0e})")
    ax.set_ylabel("rays/s (log)")
    ax.yaxis.set_major_formatter(_si_formatter())
    ax.yaxis.set_minor_formatter(_si_formatter())
    ax.set_title(title, fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    structures = sorted({r.get("structure") for r in recs}, key=display_order)
    backends = sorted({r.get("backend") for r in recs})
    handles = _legend_handles(structures, backends)
    handles += ax.get_legend_handles_labels()[0]
    ax.legend(handles=handles, fontsize=7, loc="center left", bbox_to_anchor=(1.01, 0.5))
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
