"""Static HTML report of one run: index.html + PNG charts, opens from disk (no network, no JS).

Sections follow the thesis' evaluation (chapter 6):
- Table 1: FPS (and rays/s) per structure x resolution, per scene, one table per backend.
- Table 2: bytes of the plain structures (MiB; per-buffer breakdown on hover).
- Table 3: Line Space structures x N x resolution (FPS, rays/s, MiB). Failed cells are red and
  say why (Table 3 of the thesis has '-' where a case did not run; here the reason is shown).
- Speed against accuracy: rays/s (log) against disagreement rate 1 - agreement (symlog, so
  exact agreement sits at 0), Pareto front marked and labelled.
- Build time against memory.
- Spread of the timing repeats (min / median / max and every repeat).
- Heatmap gallery (images named in the records' `heatmaps`).
- Every case in detail (counts, buffers, counters), and the full text of every failure.
"""
from __future__ import annotations

import html
import json
import math
import os
import re
import shutil
from collections import OrderedDict, defaultdict
from pathlib import Path

import numpy as np

from lsbench.results.store import format_commit, read_run, scenario_name

STRUCTURE_COLORS = {
    "grid": "#1f77b4", "svo": "#ff7f0e", "esvo": "#2ca02c",
    "grid-ls": "#6baed6", "svo-ls": "#fdae6b", "esvo-ls": "#74c476",
}
EXTRA_COLORS = ["#9467bd", "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22", "#17becf"]
BACKEND_MARKERS = {"glsl": "o", "opencl": "s"}
BROWSER_IMAGES = {".png", ".jpg", ".jpeg", ".gif", ".svg", ".webp"}
DEFAULT_MIN_AGREEMENT = 0.9999

e = html.escape


# ---------------------------------------------------------------- small helpers

def _is_ls(rec) -> bool:
    from lsbench.backends.structures import STRUCTURES

    info = STRUCTURES.get(str(rec.get("structure", "")))
    return bool(rec.get("ls_n")) or (info is not None and info.line_space)


def _ok(rec) -> bool:
    return rec.get("status") == "ok"


def _res_sort(res) -> tuple:
    dims = [int(x) for x in re.findall(r"\d+", str(res))] or [0]
    return (math.prod(dims), str(res))


def _res_label(res) -> str:
    s = str(res)
    return f"{s}³" if s.isdigit() else s


def _scene_name(rec) -> str:
    s = str(rec.get("scene", "?"))
    base = os.path.basename(s.rstrip("/")) or s
    return os.path.splitext(base)[0] if "." in base else base


def _structure_sort(name) -> tuple:
    from lsbench.backends.structures import display_order

    return display_order(name)


def _color(structure, _extra={}) -> str:
    if structure in STRUCTURE_COLORS:
        return STRUCTURE_COLORS[structure]
    if structure not in _extra:
        _extra[structure] = EXTRA_COLORS[len(_extra) % len(EXTRA_COLORS)]
    return _extra[structure]


def _slug(*parts) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", "-".join(str(p) for p in parts)).strip("_") or "x"


def fmt_si(v, unit="") -> str:
    if v is None:
        return "-"
    v = float(v)
    for prefix, scale in (("G", 1e9), ("M", 1e6), ("k", 1e3)):
        if abs(v) >= scale:
            return f"{v / scale:.3g} {prefix}{unit}"
    return f"{v:.3g} {unit}".strip()


def fmt_num(v) -> str:
    """3 significant digits without exponent notation (2200, 62.4, 0.125)."""
    if v is None:
        return "-"
    v = float(v)
    return f"{v:.0f}" if abs(v) >= 100 else f"{v:.3g}"


def fmt_mib(b) -> str:
    if b is None:
        return "-"
    mib = float(b) / 2 ** 20
    return f"{mib:.3g}" if mib < 100 else f"{mib:.0f}"


def fmt_seconds(s) -> str:
    if s is None:
        return "-"
    s = float(s)
    if s >= 1:
        return f"{s:.3g} s"
    if s >= 1e-3:
        return f"{s * 1e3:.3g} ms"
    return f"{s * 1e6:.3g} µs"


def fmt_pct(a) -> str:
    if a is None:
        return "-"
    if a == 1:
        return "100%"
    return f"{a * 100:.4g}%"


def _label(rec, with_scene=False) -> str:
    parts = [rec.get("structure", "?"), _res_label(rec.get("resolution", "?"))]
    if rec.get("ls_n"):
        parts.append(f"N={rec['ls_n']}")
    parts.append(rec.get("backend", "?"))
    if with_scene:
        parts.insert(0, _scene_name(rec))
    return " ".join(str(p) for p in parts)


def _min_agreement(info) -> float:
    for src in (info, info.get("run") or {}, info.get("scenario") if isinstance(info.get("scenario"), dict) else {}):
        if isinstance(src, dict):
            if "min_agreement" in src:
                return float(src["min_agreement"])
            if isinstance(src.get("run"), dict) and "min_agreement" in src["run"]:
                return float(src["run"]["min_agreement"])
    return DEFAULT_MIN_AGREEMENT


# ---------------------------------------------------------------- tables

def _fail_cell(rec) -> str:
    reason = str(rec.get("reason") or "failed")
    short = reason.strip().splitlines()[-1] if reason.strip() else "failed"
    if len(short) > 110:
        short = short[:107] + "…"
    return f"<td class='fail' title='{e(reason)}'>failed: {e(short)}</td>"


def _agree_note(rec, min_agree) -> tuple[str, str]:
    a = rec.get("agreement")
    if a is None or a >= 1:
        return "", ""
    cls = "warn" if a < min_agree else ""
    return f"<br><span class='small'>agree {fmt_pct(a)}</span>", cls


def _perf_cell(rec, min_agree, memory=False) -> str:
    if not _ok(rec):
        return _fail_cell(rec)
    note, cls = _agree_note(rec, min_agree)
    fps = rec.get("fps")
    body = f"<b>{fmt_num(fps)}</b>"
    body += f"<br><span class='small'>{e(fmt_si(rec.get('rays_per_second'), 'rays/s'))}</span>"
    if memory:
        body += f"<br><span class='small'>{e(fmt_mib(rec.get('memory_bytes')))} MiB</span>"
    return f"<td class='{cls}' title='{e(rec.get('key', ''))}'>{body}{note}</td>"


def _buffers_title(rec) -> str:
    bufs = rec.get("buffers") or {}
    lines = []
    for name, b in bufs.items():
        if isinstance(b, dict):
            lines.append(f"{name}: used {fmt_mib(b.get('used'))} / allocated "
                         f"{fmt_mib(b.get('allocated'))} MiB")
        else:
            lines.append(f"{name}: {b}")
    return "\n".join(lines)


def _mem_cell(rec, min_agree) -> str:
    if not _ok(rec):
        return _fail_cell(rec)
    allocated = sum((b.get("allocated") or 0) for b in (rec.get("buffers") or {}).values()
                    if isinstance(b, dict))
    extra = ""
    if allocated and rec.get("memory_bytes") and allocated > rec["memory_bytes"] * 1.001:
        extra = f"<br><span class='small'>alloc {fmt_mib(allocated)}</span>"
    return (f"<td title='{e(_buffers_title(rec))}'><b>{e(fmt_mib(rec.get('memory_bytes')))}</b>"
            f"{extra}</td>")


_ROW_EXTRAS = [  # fields that split rows when they vary inside one table
    ("rays", "rays", lambda r: r.get("rays", "")),
    ("image", "image", lambda r: f"{r.get('width')}x{r.get('height')}"),
    ("ls_min_candidates", "LS min cand.", lambda r: r.get("ls_min_candidates")),
]


def pivot_table(records, row_dims, col_fn, col_sort, cell_fn, corner="") -> str:
    """HTML table: one row per distinct row_dims tuple, one column per col_fn value.

    row_dims: list of (header, value_fn, sort_fn). Leading equal row labels are merged with
    rowspan, like the thesis' tables.
    """
    if not records:
        return ""
    cols = sorted({col_fn(r) for r in records}, key=col_sort)
    cells: dict = {}
    rows = []
    collisions = 0
    for r in records:
        rk = tuple(fn(r) for _, fn, _ in row_dims)
        if rk not in cells:
            cells[rk] = {}
            rows.append(rk)
        ck = col_fn(r)
        if ck in cells[rk]:
            collisions += 1
        cells[rk][ck] = r
    rows.sort(key=lambda rk: tuple(s(v) for (_, _, s), v in zip(row_dims, rk)))
    # rowspans for leading labels
    n = len(row_dims)
    spans = [[0] * n for _ in rows]
    for j in range(n - 1):  # never merge the last (most specific) label
        i = 0
        while i < len(rows):
            k = i
            while k + 1 < len(rows) and rows[k + 1][: j + 1] == rows[i][: j + 1]:
                k += 1
            spans[i][j] = k - i + 1
            i = k + 1
    out = ["<table class='grid'><tr>"]
    out += [f"<th>{e(h)}</th>" for h, _, _ in row_dims]
    out += [f"<th>{e(str(c))}</th>" for c in cols]
    out.append("</tr>")
    for i, rk in enumerate(rows):
        out.append("<tr>")
        for j, v in enumerate(rk):
            if j < n - 1:
                if spans[i][j]:
                    out.append(f"<th class='rl' rowspan='{spans[i][j]}'>{e(str(v))}</th>")
            else:
                out.append(f"<th class='rl'>{e(str(v))}</th>")
        for c in cols:
            rec = cells[rk].get(c)
            out.append(cell_fn(rec) if rec is not None else "<td class='na'>–</td>")
        out.append("</tr>")
    out.append("</table>")
    if collisions:
        out.append(f"<p class='small'>{collisions} cases shared a cell with another; the last "
                   f"one is shown (see all cases below).</p>")
    return "".join(out)


def _row_dims(records, base, tail):
    dims = list(base)
    for field, header, fn in _ROW_EXTRAS:
        if len({str(fn(r)) for r in records}) > 1:
            dims.append((header, lambda r, fn=fn: str(fn(r)), lambda v: (len(v), v)))
    return dims + list(tail)


SCENE_DIM = ("scene", _scene_name, lambda v: v)
RES_DIM = ("res.", lambda r: _res_label(r.get("resolution")),
           lambda v: tuple(-x for x in (_res_sort(v.rstrip("³"))[0],)))
N_DIM = ("N", lambda r: f"N={r.get('ls_n')}", lambda v: int(v[2:]) if v[2:].isdigit() else 0)


def _by_backend(records):
    groups: dict = OrderedDict()
    for r in sorted(records, key=lambda r: (str(r.get("backend")), str(r.get("device")))):
        groups.setdefault((r.get("backend", "?"), r.get("device") or "?"), []).append(r)
    return groups


def _backend_tables(records, empty_text, row_dims, cell) -> list[str]:
    """One pivot table per backend/device, side by side (structures as columns)."""
    out = [f"<p class='small'>{empty_text}</p>"] if not records else []
    out.append("<div class='side'>")
    for (backend, device), recs in _by_backend(records).items():
        out.append(f"<div><h3>{e(backend)} — {e(device)}</h3>")
        out.append(pivot_table(recs, _row_dims(recs, *row_dims), lambda r: r.get("structure", "?"),
                               _structure_sort, cell) + "</div>")
    out.append("</div>")
    return out


def _tables(records, min_agree):
    out = []
    plain = [r for r in records if not _is_ls(r)]
    ls = [r for r in records if _is_ls(r)]
    image = sorted({f"{r.get('width')}×{r.get('height')}" for r in records})
    no_plain = "No plain-structure cases in this run."

    out.append("<h2 id='table1'>Table 1 — performance of the structures (FPS)</h2>")
    out.append(f"<p>Bold: frames per second at {e(', '.join(image))} (one ray per pixel for "
               f"primary rays; FPS = rays/s ÷ rays per frame); below it rays/s. Median of the "
               f"timed repeats. Red: the case failed, with its reason (hover for the full text). "
               f"Amber: agreement with Embree below {min_agree:g}.</p>")
    out += _backend_tables(plain, no_plain, ([SCENE_DIM], [RES_DIM]), lambda r: _perf_cell(r, min_agree))

    out.append("<h2 id='table2'>Table 2 — memory of the structures (MiB)</h2>")
    out.append("<p>Bytes used by the structure's buffers (scene triangles excluded where the "
               "runner reports them apart); hover a cell for the per-buffer breakdown. "
               "'alloc' shows where more was allocated than used.</p>")
    out += _backend_tables(plain, no_plain, ([SCENE_DIM], [RES_DIM]), lambda r: _mem_cell(r, min_agree))

    out.append("<h2 id='table3'>Table 3 — Line Space structures × N × resolution</h2>")
    out.append("<p>FPS (bold), rays/s and MiB per case; N is the Line Space shaft constant "
               "(15·N⁴ shafts per voxel). Red cells say why a case did not run.</p>")
    out += _backend_tables(ls, "No Line Space cases in this run.", ([SCENE_DIM], [N_DIM, RES_DIM]),
                           lambda r: _perf_cell(r, min_agree, memory=True))
    return out


# ---------------------------------------------------------------- charts

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
    h = [Line2D([], [], ls="", marker="o", color=_color(s), label=s) for s in structures]
    h += [Line2D([], [], ls="", marker=BACKEND_MARKERS.get(b, "^"), color="#555", mfc="none",
                 label=b) for b in backends]
    return h


def chart_speed_accuracy(records, path: Path, title: str):
    recs = [r for r in records if _ok(r) and r.get("rays_per_second") and r.get("agreement") is not None]
    if not recs:
        return None
    xs = np.array([max(0.0, 1.0 - float(r["agreement"])) for r in recs])
    ys = np.array([float(r["rays_per_second"]) for r in recs])
    fig = _figure(9, 5.5)
    ax = fig.add_subplot(1, 1, 1)
    for r, x, y in zip(recs, xs, ys):
        ax.scatter([x], [y], color=_color(r.get("structure")), s=36, zorder=3,
                   marker=BACKEND_MARKERS.get(r.get("backend"), "^"), edgecolors="k", linewidths=0.4)
    front = pareto_front(list(zip(xs, ys)))
    fx, fy = xs[front], ys[front]
    # step line through the front: each point is the fastest at its disagreement or better
    ax.step(np.append(fx, max(xs.max(), fx[-1]) * 1.5 + 1e-9), np.append(fy, fy[-1]),
            where="post", color="crimson", lw=1.2, zorder=2, label="Pareto front")
    ax.scatter(fx, fy, s=140, facecolors="none", edgecolors="crimson", linewidths=1.5, zorder=4)
    for k, i in enumerate(front):
        ax.annotate(_label(recs[i]), (xs[i], ys[i]), textcoords="offset points",
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
    structures = sorted({r.get("structure") for r in recs}, key=_structure_sort)
    backends = sorted({r.get("backend") for r in recs})
    handles = _legend_handles(structures, backends)
    handles += ax.get_legend_handles_labels()[0]
    ax.legend(handles=handles, fontsize=7, loc="center left", bbox_to_anchor=(1.01, 0.5))
    return _save(fig, path)


def chart_build_memory(records, path: Path, title: str):
    recs = [r for r in records if _ok(r) and r.get("memory_bytes") and r.get("build_seconds")]
    if not recs:
        return None
    fig = _figure(9, 5.5)
    ax = fig.add_subplot(1, 1, 1)
    by_struct = defaultdict(list)
    for r in recs:
        by_struct[(r.get("structure"), r.get("backend"), r.get("ls_n") or 0)].append(r)
    for (s, b, n), rs in sorted(by_struct.items(), key=lambda kv: (_structure_sort(kv[0][0]), kv[0][1], kv[0][2])):
        rs = sorted(rs, key=lambda r: _res_sort(r.get("resolution")))
        mx = [r["memory_bytes"] / 2 ** 20 for r in rs]
        by = [r["build_seconds"] for r in rs]
        ax.plot(mx, by, marker=BACKEND_MARKERS.get(b, "^"), color=_color(s), lw=0.8,
                ls="-" if not n else (0, (1 + n, 1 + n)), ms=5, alpha=0.85)
        last = rs[-1]
        ax.annotate(f"{_res_label(last.get('resolution'))}", (mx[-1], by[-1]), fontsize=6,
                    textcoords="offset points", xytext=(3, 2), color=_color(s))
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("memory (MiB, log)")
    ax.set_ylabel("build time (s, log)")
    for axis in (ax.xaxis, ax.yaxis):
        axis.set_major_formatter(_plain_formatter())
        axis.set_minor_formatter(_plain_formatter())
    ax.set_title(title + " — lines join resolutions of one structure/backend/N", fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    structures = sorted({r.get("structure") for r in recs}, key=_structure_sort)
    backends = sorted({r.get("backend") for r in recs})
    ax.legend(handles=_legend_handles(structures, backends), fontsize=7, loc="center left",
              bbox_to_anchor=(1.01, 0.5))
    return _save(fig, path)


def chart_repeats(records, path: Path, title: str):
    recs = [r for r in records if _ok(r) and (r.get("trace_seconds_all") or r.get("trace_seconds"))]
    if not recs:
        return None
    recs.sort(key=lambda r: (_structure_sort(r.get("structure")), r.get("ls_n") or 0,
                             _res_sort(r.get("resolution")), r.get("backend", ""), r.get("rays", "")))
    h = max(2.5, 0.22 * len(recs) + 1.2)
    fig = _figure(9, h)
    ax = fig.add_subplot(1, 1, 1)
    labels = []
    for i, r in enumerate(recs):
        ts = np.asarray([t for t in (r.get("trace_seconds_all") or [r.get("trace_seconds")]) if t], float) * 1e3
        lo = r.get("trace_seconds_min", ts.min() / 1e3) * 1e3
        hi = r.get("trace_seconds_max", ts.max() / 1e3) * 1e3
        med = (r.get("trace_seconds") or float(np.median(ts)) / 1e3) * 1e3
        c = _color(r.get("structure"))
        ax.plot([lo, hi], [i, i], color=c, lw=2.5, alpha=0.45, solid_capstyle="butt")
        ax.scatter(ts, np.full(len(ts), i), s=9, color=c, zorder=3, alpha=0.8)
        ax.scatter([med], [i], marker="|", s=160, color="k", zorder=4)
        cv = r.get("trace_cv")
        lab = _label(r) + (f" ({r['rays']})" if len({x.get('rays') for x in recs}) > 1 else "")
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


# ---------------------------------------------------------------- other sections

def _kv_table(d: dict) -> str:
    rows = []
    for k, v in d.items():
        if isinstance(v, dict) and v and all(not isinstance(x, (dict, list)) for x in v.values()):
            val = ", ".join(f"{e(str(a))}={e(str(b))}" for a, b in v.items())
        elif isinstance(v, (dict, list)):
            val = f"<pre>{e(json.dumps(v, indent=1, default=str))}</pre>"
        else:
            val = e(str(v))
        rows.append(f"<tr><th class='rl'>{e(str(k))}</th><td class='l'>{val}</td></tr>")
    return "<table class='grid kv'>" + "".join(rows) + "</table>"


def _environment(info, records) -> list[str]:
    out = ["<h2 id='env'>Environment</h2>"]
    if not info:
        out.append("<p class='warn'>No run.json in this run directory.</p>")
    top = OrderedDict()
    for k in ("date", "commit", "dirty", "host", "machine", "platform", "processor", "cpu_count",
              "python", "scenario", "scenario_name", "scenario_path", "command", "command_line"):
        if k in info:
            top[k] = info[k]
    if "commit" in top:
        top["commit"] = format_commit(info.get("commit"), info.get("dirty"))
        top.pop("dirty", None)
    for k, v in info.items():
        if k not in top and k not in ("devices", "dirty"):
            top[k] = v
    out.append(_kv_table(top))
    # devices: from run.json, completed by the records (backend version)
    devs: dict = OrderedDict()
    for backend, d in (info.get("devices") or {}).items():
        devs[backend] = dict(d) if isinstance(d, dict) else {"device": d}
    for r in records:
        d = devs.setdefault(r.get("backend", "?"), {})
        for f in ("device", "driver", "backend_version"):
            if r.get(f) and not d.get(f):
                d[f] = r[f]
    if devs:
        out.append("<h3>Devices</h3><table class='grid'><tr><th>backend</th><th>device</th>"
                   "<th>driver</th><th>backend version</th></tr>")
        for b, d in devs.items():
            out.append(f"<tr><th class='rl'>{e(str(b))}</th><td class='l'>{e(str(d.get('device', '-')))}</td>"
                       f"<td class='l'>{e(str(d.get('driver', '-')))}</td>"
                       f"<td class='l'>{e(str(d.get('backend_version', '-')))}</td></tr>")
        out.append("</table>")
    commits = {(r.get("commit"), r.get("dirty")) for r in records if r.get("commit")}
    if len(commits) > 1:
        out.append("<p class='warn'>Records in this run come from more than one commit: "
                   + e(", ".join(format_commit(c, d) for c, d in sorted(commits, key=str))) + "</p>")
    return out


def _gallery(records, run_dir: Path, out_dir: Path) -> list[str]:
    out = ["<h2 id='heatmaps'>Heatmaps</h2>"]
    items = [(r, name, rel) for r in records for name, rel in (r.get("heatmaps") or {}).items()]
    if not items:
        out.append("<p class='small'>No heatmaps in this run (they are written by profiling runs "
                   "with work counters).</p>")
        return out
    same = run_dir.resolve() == out_dir.resolve()
    out.append("<div class='gallery'>")
    for r, name, rel in items:
        src = run_dir / rel
        if not src.exists():
            out.append(f"<figure class='missing'><div>missing: {e(str(rel))}</div>"
                       f"<figcaption>{e(_label(r, True))}<br>{e(name)}</figcaption></figure>")
            continue
        if same:
            href = Path(rel).as_posix()
        else:  # copy so the report folder stands alone
            dest = out_dir / "heatmaps" / _slug(rel)
            dest.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dest)
            href = dest.relative_to(out_dir).as_posix()
        if src.suffix.lower() in BROWSER_IMAGES:
            body = f"<a href='{e(href)}'><img src='{e(href)}' alt='{e(name)}' loading='lazy'></a>"
        else:
            body = f"<div><a href='{e(href)}'>{e(src.name)}</a> (open in an image viewer)</div>"
        out.append(f"<figure>{body}<figcaption>{e(_label(r, True))}<br>{e(name)}</figcaption></figure>")
    out.append("</div>")
    return out


DETAIL_COLS = [
    ("scene", lambda r: _scene_name(r)), ("rays", lambda r: r.get("rays", "")),
    ("structure", lambda r: r.get("structure", "")), ("backend", lambda r: r.get("backend", "")),
    ("res.", lambda r: _res_label(r.get("resolution", ""))), ("N", lambda r: r.get("ls_n") or ""),
    ("status", lambda r: r.get("status", "")),
    ("agreement", lambda r: fmt_pct(r.get("agreement"))),
    ("agree/tie/miss/extra/wrong", lambda r: "/".join(str(r.get(k, "-")) for k in ("agree", "ties", "missed", "extra", "wrong")) if _ok(r) else ""),
    ("max |dt|", lambda r: f"{r['max_abs_dt']:.2g}" if r.get("max_abs_dt") is not None else "-"),
    ("build", lambda r: fmt_seconds(r.get("build_seconds"))),
    ("trace min", lambda r: fmt_seconds(r.get("trace_seconds_min"))),
    ("median", lambda r: fmt_seconds(r.get("trace_seconds"))),
    ("max", lambda r: fmt_seconds(r.get("trace_seconds_max"))),
    ("cv", lambda r: f"{r['trace_cv'] * 100:.1f}%" if r.get("trace_cv") is not None else "-"),
    ("n", lambda r: len(r.get("trace_seconds_all") or [])),
    ("clock", lambda r: r.get("clock", "")),
    ("rays/s", lambda r: fmt_si(r.get("rays_per_second"))),
    ("FPS", lambda r: fmt_num(r.get("fps"))),
    ("MiB", lambda r: fmt_mib(r.get("memory_bytes"))),
]


def _details(records, min_agree) -> list[str]:
    out = ["<h2 id='cases'>All cases</h2><p>Hover a row for its case key; 'show' opens its "
           "buffers and counters.</p><div class='scroll'><table class='grid detail'><tr>"]
    out += [f"<th>{e(h)}</th>" for h, _ in DETAIL_COLS] + ["<th>buffers, counters</th></tr>"]
    for r in records:
        cls = "fail" if not _ok(r) else ("warn" if (r.get("agreement") or 0) < min_agree else "")
        out.append(f"<tr class='{cls}' title='{e(r.get('key', ''))}'>")
        out += [f"<td>{e(str(fn(r)))}</td>" for _, fn in DETAIL_COLS]
        extra = {k: r.get(k) for k in ("buffers", "stats") if r.get(k)}
        if not _ok(r):
            extra["reason"] = r.get("reason", "")
        extra["key"] = r.get("key")
        out.append(f"<td class='l'><details><summary>show</summary><pre>"
                   f"{e(json.dumps(extra, indent=1, default=str))}</pre></details></td></tr>")
    out.append("</table></div>")
    failed = [r for r in records if not _ok(r)]
    if failed:
        out.append("<h2 id='failures'>Failures</h2>")
        for r in failed:
            out.append(f"<h4>{e(_label(r, True))} <span class='small'>({e(str(r.get('rays', '')))})</span></h4>"
                       f"<pre class='failtext'>{e(str(r.get('reason', '')))}</pre>")
    return out


CSS = """
body{font-family:system-ui,-apple-system,'Segoe UI',Roboto,sans-serif;margin:1.5em 2em;color:#222;
 max-width:1400px}
h1{margin-bottom:.2em} h2{border-bottom:2px solid #ddd;padding-bottom:.2em;margin-top:1.8em}
nav a{margin-right:1em}
table.grid{border-collapse:collapse;font-size:13px;margin:.5em 0 1em}
table.grid td,table.grid th{border:1px solid #ccc;padding:3px 7px;text-align:right;vertical-align:top}
table.grid th{background:#f0f0f0;text-align:center}
table.grid th.rl{text-align:left;background:#f7f7f7}
table.grid td.l{text-align:left}
table.kv td{max-width:900px}
td.fail,tr.fail td{background:#fbd5d5;color:#8a1010;text-align:left;max-width:260px;font-size:12px}
td.warn,tr.warn td{background:#fff1c7}
td.na{color:#aaa;text-align:center}
.small{font-size:11px;color:#555}
.warn{background:#fff3cd;border:1px solid #e0c060;padding:.4em .8em}
pre{margin:0;font-size:11px;white-space:pre-wrap}
pre.failtext{background:#fbeaea;padding:.5em;border-left:3px solid #c33;max-height:20em;overflow:auto}
.gallery{display:flex;flex-wrap:wrap;gap:12px}
figure{margin:0;width:260px;font-size:11px}
figure img{width:260px;image-rendering:pixelated;border:1px solid #ccc}
figure.missing div{height:80px;background:#eee;display:flex;align-items:center;justify-content:center}
img.chart{max-width:100%;border:1px solid #eee;margin:.3em 0}
table.detail{font-size:11px}
table.detail td{white-space:nowrap}
table.detail tr.fail td{max-width:none}
table.detail pre{white-space:pre}
.scroll{overflow-x:auto}
.side{display:flex;flex-wrap:wrap;gap:0 2.5em;align-items:flex-start}
"""


def write_report(run_dir, out_dir=None) -> Path:
    """Write OUT_DIR/index.html (default OUT_DIR = RUN_DIR) with charts under OUT_DIR/charts/.
    Returns the path of index.html."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise FileNotFoundError(f"no run directory {run_dir}")
    out_dir = Path(out_dir) if out_dir else run_dir
    out_dir.mkdir(parents=True, exist_ok=True)
    charts_dir = out_dir / "charts"
    if charts_dir.exists():  # stale charts of an earlier report of the same run
        for p in charts_dir.glob("*.png"):
            p.unlink()
    info, records = read_run(run_dir)
    min_agree = _min_agreement(info)
    ok = sum(1 for r in records if _ok(r))

    title = f"lsbench report — {scenario_name(info) or run_dir.name}"
    out = [f"<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'><title>{e(str(title))}</title>",
           f"<style>{CSS}</style></head><body>",
           f"<h1>{e(str(title))}</h1>",
           f"<p>{e(str(run_dir))} · {e(str(info.get('date', '')))} · commit "
           f"{e(format_commit(info.get('commit'), info.get('dirty')))} · "
           f"<b>{ok}</b> cases ok, <b>{len(records) - ok}</b> failed</p>",
           "<nav><a href='#env'>Environment</a><a href='#table1'>Table 1 FPS</a>"
           "<a href='#table2'>Table 2 memory</a><a href='#table3'>Table 3 Line Space</a>"
           "<a href='#speed'>Speed vs accuracy</a><a href='#build'>Build vs memory</a>"
           "<a href='#repeats'>Repeats</a><a href='#heatmaps'>Heatmaps</a>"
           "<a href='#cases'>All cases</a></nav>"]
    out += _environment(info, records)
    out += _tables(records, min_agree)

    def scene_groups(key_fn):
        g: dict = OrderedDict()
        for r in sorted(records, key=lambda r: key_fn(r)):
            g.setdefault(key_fn(r), []).append(r)
        return g

    out.append("<h2 id='speed'>Speed against accuracy</h2>")
    out.append("<p>One marker per case (colour: structure, shape: backend). Up is faster, left "
               "agrees better with Embree (0 = every ray agrees). Ringed and labelled: the Pareto "
               "front — no other case is both faster and at least as accurate.</p>")
    any_chart = False
    for (scene, rays), recs in scene_groups(lambda r: (_scene_name(r), str(r.get("rays", "")))).items():
        p = chart_speed_accuracy(recs, charts_dir / f"speed_accuracy_{_slug(scene, rays)}.png",
                                 f"{scene} — rays '{rays}'")
        if p:
            any_chart = True
            out.append(f"<img class='chart' src='{e(p.relative_to(out_dir).as_posix())}' alt='speed vs accuracy {e(scene)}'>")
    if not any_chart:
        out.append("<p class='small'>No successful case to plot.</p>")

    out.append("<h2 id='build'>Build time against memory</h2>")
    any_chart = False
    for scene, recs in scene_groups(_scene_name).items():
        p = chart_build_memory(recs, charts_dir / f"build_memory_{_slug(scene)}.png", scene)
        if p:
            any_chart = True
            out.append(f"<img class='chart' src='{e(p.relative_to(out_dir).as_posix())}' alt='build vs memory {e(scene)}'>")
    if not any_chart:
        out.append("<p class='small'>No successful case to plot.</p>")

    out.append("<h2 id='repeats'>Spread of the timing repeats</h2>")
    out.append("<p>Every timed repeat of every case: a wide bar means a noisy measurement "
               "(compare uses these repeats to tell a real slowdown from noise).</p>")
    any_chart = False
    for scene, recs in scene_groups(_scene_name).items():
        p = chart_repeats(recs, charts_dir / f"repeats_{_slug(scene)}.png", scene)
        if p:
            any_chart = True
            out.append(f"<img class='chart' src='{e(p.relative_to(out_dir).as_posix())}' alt='repeats {e(scene)}'>")
    if not any_chart:
        out.append("<p class='small'>No successful case to plot.</p>")

    out += _gallery(records, run_dir, out_dir)
    out += _details(records, min_agree)
    out.append("</body></html>")
    index = out_dir / "index.html"
    index.write_text("\n".join(out))
    return index
