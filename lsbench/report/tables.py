"""The thesis' (Delgado Krämer 2019) tables (chapter 6) of one run, as HTML: one pivot table per backend and device,
structures as columns in catalogue order.

- Table 1: FPS (and rays/s) per structure x resolution, per scene.
- Table 2: bytes of the plain structures (MiB; per-buffer breakdown on hover).
- Table 3: Line Space structures x N x resolution (FPS, rays/s, MiB). Failed cells are red and
  say why (Table 3 of the thesis has '-' where a case did not run; here the reason is shown).
"""
from __future__ import annotations

import html
from collections import OrderedDict

from lsbench.backends.structures import display_order
from lsbench.report.format import fmt_mib, fmt_num, fmt_pct, fmt_si
from lsbench.report.records import (has_line_space, resolution_label, resolution_order,
                                    scene_name, succeeded)

e = html.escape


def _fail_cell(rec) -> str:
    reason = str(rec.get("reason") or "failed")
    short = reason.strip().splitlines()[-1] if reason.strip() else "failed"
    if len(short) > 110:
        short = short[:107] + "…"
    return f"<td class='fail' title='{e(reason)}'>failed: {e(short)}</td>"


def _agree_note(rec, min_agree: float | None) -> tuple[str, str]:
    a = rec.get("agreement")
    if a is None or a >= 1:
        return "", ""
    cls = "warn" if min_agree is not None and a < min_agree else ""
    return f"<br><span class='small'>agree {fmt_pct(a)}</span>", cls


def _perf_cell(rec, min_agree: float | None, memory=False) -> str:
    if not succeeded(rec):
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


def _mem_cell(rec) -> str:
    if not succeeded(rec):
        return _fail_cell(rec)
    allocated = sum((b.get("allocated") or 0) for b in (rec.get("buffers") or {}).values()
                    if isinstance(b, dict))
    extra = ""
    if allocated and rec.get("memory_bytes") and allocated > rec["memory_bytes"] * 1.001:
        extra = f"<br><span class='small'>alloc {fmt_mib(allocated)}</span>"
    return (f"<td title='{e(_buffers_title(rec))}'><b>{e(fmt_mib(rec.get('memory_bytes')))}</b>"
            f"{extra}</td>")


_ROW_EXTRAS = [  # (header, value): fields that split rows when they vary inside one table
    ("rays", lambda r: r.get("rays", "")),
    ("image", lambda r: f"{r.get('width')}x{r.get('height')}"),
    ("LS min cand.", lambda r: r.get("ls_min_candidates")),
]


def pivot_table(records, row_dims, col_fn, col_sort, cell_fn) -> str:
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
    for header, fn in _ROW_EXTRAS:
        if len({str(fn(r)) for r in records}) > 1:
            dims.append((header, lambda r, fn=fn: str(fn(r)), lambda v: (len(v), v)))
    return dims + list(tail)


SCENE_DIM = ("scene", scene_name, lambda v: v)
RES_DIM = ("res.", lambda r: resolution_label(r.get("resolution")),  # finest first
           lambda v: -resolution_order(v.rstrip("³"))[0])
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
                               display_order, cell) + "</div>")
    out.append("</div>")
    return out


def thesis_tables(records, min_agree: float | None) -> list[str]:
    """Tables 1-3 with their headings; min_agree (None: the run states no rate threshold)
    marks the cases below it amber."""
    out = []
    plain = [r for r in records if not has_line_space(r)]
    ls = [r for r in records if has_line_space(r)]
    image = sorted({f"{r.get('width')}×{r.get('height')}" for r in records})
    no_plain = "No plain-structure cases in this run."

    out.append("<h2 id='table1'>Table 1 — performance of the structures (FPS)</h2>")
    out.append(f"<p>Bold: frames per second at {e(', '.join(image))} (one ray per pixel for "
               f"primary rays; FPS = rays/s ÷ rays per frame); below it rays/s. Median of the "
               f"timed repeats. Red: the case failed, with its reason (hover for the full text)."
               + (f" Amber: agreement with Embree below {min_agree:g}." if min_agree is not None else "")
               + "</p>")
    out += _backend_tables(plain, no_plain, ([SCENE_DIM], [RES_DIM]), lambda r: _perf_cell(r, min_agree))

    out.append("<h2 id='table2'>Table 2 — memory of the structures (MiB)</h2>")
    out.append("<p>Bytes used by the structure's buffers (scene triangles excluded where the "
               "runner reports them apart); hover a cell for the per-buffer breakdown. "
               "'alloc' shows where more was allocated than used.</p>")
    out += _backend_tables(plain, no_plain, ([SCENE_DIM], [RES_DIM]), _mem_cell)

    out.append("<h2 id='table3'>Table 3 — Line Space structures × N × resolution</h2>")
    out.append("<p>FPS (bold), rays/s and MiB per case; N is the Line Space shaft constant "
               "(15·N⁴ shafts per voxel). Red cells say why a case did not run.</p>")
    out += _backend_tables(ls, "No Line Space cases in this run.", ([SCENE_DIM], [N_DIM, RES_DIM]),
                           lambda r: _perf_cell(r, min_agree, memory=True))
    return out
