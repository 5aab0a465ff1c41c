"""The report's tables as plain data (`Table`), then written as HTML, CSV and LaTeX
(lsbench/report/export.py writes the files beside the page).

- One table per ray workload (rays and query) and backend/device: rays/s per structure, with
  Embree's rays/s on the same rays as each scene's reference row (issue 14).
- The thesis' (Delgado Krämer 2019) tables (chapter 6), one pivot table per backend and device,
  structures as columns in catalogue order:
  - Table 1: FPS (and rays/s) per structure x resolution, per scene.
  - Table 2: bytes of the plain structures (MiB; per-buffer breakdown on hover).
  - Table 3: Line Space structures x N x resolution (FPS, rays/s, MiB). Failed cells are red and
    say why (Table 3 of the thesis has '-' where a case did not run; here the reason is shown).

Every speed cell says its speed-up against Embree on the same rays (×E) and against `grid` on the
same rays, backend and resolution (×grid; the fastest grid there when that resolution has none);
each row marks its best cell (★: the fastest, or for memory the smallest).
"""
from __future__ import annotations

import html
import json
import statistics
from collections import OrderedDict
from dataclasses import dataclass, field

from lsbench.backends.structures import display_order
from lsbench.report.format import fmt_mib, fmt_num, fmt_pct, fmt_si, slug
from lsbench.report.records import (has_line_space, resolution_label, resolution_order,
                                    scene_name, succeeded)

e = html.escape
BEST_MARK = "★"
REFERENCE_LABEL = "Embree (CPU)"


@dataclass
class Cell:
    """One table cell: `lines[0]` is the figure (bold), the rest small notes under it; `value`
    ranks the row and is what the CSV holds."""

    lines: list[str]
    value: float | None = None
    css: str = ""  # fail, warn
    title: str = ""
    best: bool = False


@dataclass
class Row:
    labels: tuple[str, ...]
    cells: list[Cell | None]
    reference: bool = False  # Embree's row: one cell across every column, not ranked


@dataclass
class Table:
    name: str  # file stem of its CSV and LaTeX
    caption: str
    row_headers: list[str]
    columns: list[str]
    rows: list[Row] = field(default_factory=list)
    unit: str = ""  # of the values in the CSV
    best: str | None = "max"  # which value a row marks: max, min or None
    note: str = ""

    def mark_best(self) -> None:
        pick = {"max": max, "min": min}.get(self.best or "")
        for row in self.rows:
            values = [c.value for c in row.cells if c is not None and c.value is not None and c.css != "fail"]
            if pick is None or row.reference or len(values) < 2:
                continue
            top = pick(values)
            for c in row.cells:
                if c is not None and c.value == top and c.css != "fail":
                    c.best = True


# ---- cells ------------------------------------------------------------------------------------
def rays_identity(rec) -> tuple:
    """Which rays a case traced: by content where the record has it, else by what made them."""
    if rec.get("rays_hash"):
        return (scene_name(rec), rec["rays_hash"])
    return (scene_name(rec), rec.get("rays"), json.dumps(rec.get("ray_params") or {}, sort_keys=True),
            rec.get("width"), rec.get("height"), json.dumps(rec.get("camera"), sort_keys=True))


class Baselines:
    """The two references a speed is divided by: Embree on the same rays (timed in the same
    worker after each launch, execute.py) and `grid` on the same rays and backend."""

    def __init__(self, records):
        self.grid: dict = {}
        for r in records:
            if succeeded(r) and r.get("structure") == "grid" and r.get("rays_per_second"):
                self.grid.setdefault(self._where(r), {})[str(r.get("resolution"))] = r

    @staticmethod
    def _where(rec) -> tuple:
        return (*rays_identity(rec), rec.get("backend"), rec.get("device"))

    def grid_of(self, rec):
        """The grid case rec is measured against: same resolution, else the fastest grid."""
        by_res = self.grid.get(self._where(rec)) or {}
        if not by_res or rec.get("structure") == "grid":
            return None
        same = by_res.get(str(rec.get("resolution")))
        return same or max(by_res.values(), key=lambda g: g["rays_per_second"])

    def speedups(self, rec) -> tuple[list[str], list[str]]:
        """(short notes, hover lines): ×E and ×grid of rec's rays/s."""
        notes, titles = [], []
        speed = rec.get("rays_per_second")
        if not speed:
            return notes, titles
        if rec.get("embree_rays_per_second"):
            notes.append(f"×E {speed / rec['embree_rays_per_second']:.3g}")
            titles.append(f"Embree on the same rays: {fmt_si(rec['embree_rays_per_second'], 'rays/s')}")
        grid = self.grid_of(rec)
        if grid is not None:
            notes.append(f"×grid {speed / grid['rays_per_second']:.3g}")
            titles.append(f"grid {resolution_label(grid.get('resolution'))}: "
                          f"{fmt_si(grid['rays_per_second'], 'rays/s')}")
        return notes, titles


def fail_cell(rec) -> Cell:
    reason = str(rec.get("reason") or "failed")
    short = reason.strip().splitlines()[-1] if reason.strip() else "failed"
    if len(short) > 110:
        short = short[:107] + "…"
    return Cell([f"failed: {short}"], css="fail", title=reason)


def _agree_note(rec, min_agree: float | None) -> tuple[list[str], str]:
    a = rec.get("agreement")
    if a is None or a >= 1:
        return [], ""
    return [f"agree {fmt_pct(a)}"], "warn" if min_agree is not None and a < min_agree else ""


def speed_cell(rec, baselines: Baselines, min_agree: float | None, fps=True, memory=False) -> Cell:
    """FPS (or rays/s) in bold, then rays/s, MiB, ×E, ×grid and the agreement below 1."""
    if not succeeded(rec):
        return fail_cell(rec)
    speed = rec.get("rays_per_second")
    lines = [fmt_num(rec.get("fps")) if fps and rec.get("fps") else fmt_si(speed, "rays/s")]
    if fps and rec.get("fps"):
        lines.append(fmt_si(speed, "rays/s"))
    if memory:
        lines.append(f"{fmt_mib(rec.get('memory_bytes'))} MiB")
    notes, titles = baselines.speedups(rec)
    if notes:
        lines.append(" · ".join(notes))
    agree, css = _agree_note(rec, min_agree)
    if rec.get("image_jnd_pixels"):  # a disagreement a person would see (lsbench/oracle/image.py)
        agree.append(f"{rec['image_jnd_pixels']} px ΔE>2.3")
    return Cell(lines + agree, value=speed, css=css, title="\n".join([rec.get("key", ""), *titles]))


def _buffers_title(rec) -> str:
    lines = []
    for name, b in (rec.get("buffers") or {}).items():
        if isinstance(b, dict):
            lines.append(f"{name}: used {fmt_mib(b.get('used'))} / allocated {fmt_mib(b.get('allocated'))} MiB")
        else:
            lines.append(f"{name}: {b}")
    return "\n".join(lines)


def memory_cell(rec, baselines: Baselines) -> Cell:
    if not succeeded(rec):
        return fail_cell(rec)
    lines = [fmt_mib(rec.get("memory_bytes"))]
    allocated = sum((b.get("allocated") or 0) for b in (rec.get("buffers") or {}).values() if isinstance(b, dict))
    if allocated and rec.get("memory_bytes") and allocated > rec["memory_bytes"] * 1.001:
        lines.append(f"alloc {fmt_mib(allocated)}")
    grid = baselines.grid_of(rec)
    if grid is not None and grid.get("memory_bytes") and rec.get("memory_bytes"):
        lines.append(f"×grid {rec['memory_bytes'] / grid['memory_bytes']:.3g}")
    mib = rec["memory_bytes"] / 2 ** 20 if rec.get("memory_bytes") is not None else None
    return Cell(lines, value=mib, title=_buffers_title(rec))


# ---- pivot ------------------------------------------------------------------------------------
_ROW_EXTRAS = [  # (header, value): fields that split rows when they vary inside one table
    ("rays", lambda r: r.get("rays", "")),
    ("image", lambda r: f"{r.get('width')}x{r.get('height')}"),
    ("LS min cand.", lambda r: r.get("ls_min_candidates")),
]


def pivot(records, name, caption, row_dims, col_fn, col_sort, cell_fn, best="max", unit="",
          reference=None) -> Table:
    """One row per distinct row_dims tuple, one column per col_fn value; reference(records of a
    scene) -> Cell adds that scene's reference row after its rows (row_dims[0] is the scene)."""
    cols = sorted({col_fn(r) for r in records}, key=col_sort)
    table = Table(name, caption, [h for h, _, _ in row_dims], [str(c) for c in cols], unit=unit, best=best)
    cells: dict = OrderedDict()
    collisions = 0
    for r in records:
        rk = tuple(str(fn(r)) for _, fn, _ in row_dims)
        row = cells.setdefault(rk, {})
        collisions += col_fn(r) in row
        row[col_fn(r)] = r
    keys = sorted(cells, key=lambda rk: tuple(s(v) for (_, _, s), v in zip(row_dims, rk)))
    for i, rk in enumerate(keys):
        table.rows.append(Row(rk, [cell_fn(cells[rk][c]) if c in cells[rk] else None for c in cols]))
        last_of_scene = i + 1 == len(keys) or keys[i + 1][0] != rk[0]
        if reference is not None and last_of_scene and len(rk) > 1:
            cell = reference([r for r in records if str(row_dims[0][1](r)) == rk[0]])
            if cell is not None:
                table.rows.append(Row((rk[0], REFERENCE_LABEL) + ("",) * (len(rk) - 2), [cell], True))
    if collisions:
        table.note = (f"{collisions} cases shared a cell with another; the last one is shown (see all "
                      f"cases below).")
    table.mark_best()
    return table


def _row_dims(records, base, tail, skip=()):
    dims = list(base)
    for header, fn in _ROW_EXTRAS:
        if header not in skip and len({str(fn(r)) for r in records}) > 1:
            dims.append((header, lambda r, fn=fn: str(fn(r)), lambda v: (len(v), v)))
    return dims + list(tail)


SCENE_DIM = ("scene", scene_name, lambda v: v)
RES_DIM = ("res.", lambda r: resolution_label(r.get("resolution")),  # finest first
           lambda v: -resolution_order(v.rstrip("³"))[0])
N_DIM = ("N", lambda r: f"N={r.get('ls_n')}", lambda v: int(v[2:]) if v[2:].isdigit() else 0)


def structure_column(rec) -> str:
    """grid, svo, ..., and a Line Space structure with its N and, where set, the fewest
    candidates a cell needs for a Line Space (grid-ls N=2, svo-ls N=1 K>4)."""
    s = str(rec.get("structure", "?"))
    if not has_line_space(rec):
        return s
    k = rec.get("ls_min_candidates")
    return f"{s} N={rec.get('ls_n') or 1}" + (f" K>{k}" if k else "")


def _column_order(col: str) -> tuple:
    s, _, rest = col.partition(" N=")
    n, _, k = rest.partition(" K>")
    return (display_order(s), int(n) if n.isdigit() else 0, int(k) if k.isdigit() else 0)


def by_backend(records):
    groups: dict = OrderedDict()
    for r in sorted(records, key=lambda r: (str(r.get("backend")), str(r.get("device")))):
        groups.setdefault((r.get("backend", "?"), r.get("device") or "?"), []).append(r)
    return groups


def table_name(stem: str, backend: str, device: str, groups) -> str:
    """File stem of a table: stem and backend, and the device where a backend ran on several."""
    several = sum(b == backend for b, _ in groups) > 1
    return slug(stem, backend, device) if several else slug(stem, backend)


def embree_reference(records) -> Cell | None:
    """Embree's rays/s on the scene's rays: the median of its timings in these cases (one
    after each timed launch of each case, so the spread across cases is the load's)."""
    speeds = [float(r["embree_rays_per_second"]) for r in records
              if succeeded(r) and r.get("embree_rays_per_second")]
    if not speeds:
        return None
    med = statistics.median(speeds)
    spread = f"; {fmt_si(min(speeds))} … {fmt_si(max(speeds))}" if len(speeds) > 1 else ""
    return Cell([fmt_si(med, "rays/s"), f"median of {len(speeds)} timings{spread}"], value=med,
                title="Embree (embreex, this CPU, all cores) traced the same rays once after every timed launch")


# ---- the tables -------------------------------------------------------------------------------
def workload_label(rec) -> str:
    """A ray workload as a person names it: the set, its parameters, the query."""
    params = rec.get("ray_params") or {}
    text = str(rec.get("rays", "?"))
    if params:
        text += " (" + ", ".join(f"{k}={v}" for k, v in sorted(params.items())) + ")"
    return f"{text}, {'any hit' if rec.get('query') == 'any' else 'closest hit'}"


def workload_tables(records, baselines: Baselines, min_agree: float | None, stem: str) -> list[Table]:
    """Per backend/device: rays/s per structure (columns) x scene and resolution (rows), each
    scene's Embree row below it."""
    out = []
    groups = by_backend(records)
    for (backend, device), recs in groups.items():
        out.append(pivot(recs, table_name(stem, backend, device, groups), f"{backend} — {device}",
                         _row_dims(recs, [SCENE_DIM], [RES_DIM], skip=("LS min cand.",)), structure_column,
                         _column_order,
                         lambda r: speed_cell(r, baselines, min_agree, fps=False), unit="rays/s",
                         reference=embree_reference))
    return out


def is_camera(rec) -> bool:
    """A camera image of closest hits (the thesis' workload: FPS means something): an ok case
    with an FPS; a failed one by its ray set."""
    if rec.get("query", "closest") != "closest":
        return False
    return rec.get("fps") is not None if succeeded(rec) else rec.get("rays") == "primary"


def one_per_build(records) -> list:
    """One record per structure as built (the bytes do not depend on the rays traced): the
    first ok one, else the first."""
    chosen: dict = OrderedDict()
    for r in records:
        build = (scene_name(r), r.get("structure"), r.get("backend"), r.get("device"), str(r.get("resolution")),
                 r.get("ls_n"), r.get("ls_min_candidates"))
        if build not in chosen or (succeeded(r) and not succeeded(chosen[build])):
            chosen[build] = r
    return list(chosen.values())


def thesis_tables(records, baselines: Baselines, min_agree: float | None) -> list[tuple[str, str, str, list[Table]]]:
    """[(anchor, heading, text, tables)] of Tables 1-3; min_agree (None: the run states no rate
    threshold) marks the cases below it amber."""
    # the thesis measures camera images (FPS); the other workloads have their own sections
    camera = [r for r in records if is_camera(r)] or list(records)
    plain = [r for r in camera if not has_line_space(r)]
    ls = [r for r in camera if has_line_space(r)]
    image = sorted({f"{r.get('width')}×{r.get('height')}" for r in camera})

    def per_backend(recs, stem, dims, cell, **kw):
        groups = by_backend(recs)
        return [pivot(rs, table_name(stem, b, d, groups), f"{b} — {d}", _row_dims(rs, *dims),
                      lambda r: r.get("structure", "?"), display_order, cell, **kw) for (b, d), rs in groups.items()]

    return [
        ("table1", "Table 1 — performance of the structures (FPS)",
         f"Camera rays. Bold: frames per second at {', '.join(image)} (one ray per pixel; FPS = "
         f"rays/s ÷ rays per frame); below it rays/s, ×E = speed-up against Embree on the same rays, "
         f"×grid = against grid on the same rays and backend. Median of the timed repeats. {BEST_MARK}: "
         f"the fastest in its row. Red: the case failed, with its reason (hover for the full text)."
         + (f" Amber: agreement with Embree below {min_agree:g}." if min_agree is not None else ""),
         per_backend(plain, "table1", ([SCENE_DIM], [RES_DIM]),
                     lambda r: speed_cell(r, baselines, min_agree), unit="rays/s")),
        ("table2", "Table 2 — memory of the structures (MiB)",
         "One cell per structure as built (whatever rays it traced). Bytes used by the structure's buffers (scene triangles excluded where the runner reports "
         "them apart); hover a cell for the per-buffer breakdown. 'alloc' shows where more was "
         f"allocated than used; ×grid = against grid at the same resolution. {BEST_MARK}: the smallest "
         "in its row.",
         per_backend(one_per_build([r for r in records if not has_line_space(r)]), "table2",
                     ([SCENE_DIM], [RES_DIM]), lambda r: memory_cell(r, baselines),
                     best="min", unit="MiB")),
        ("table3", "Table 3 — Line Space structures × N × resolution",
         "FPS (bold), rays/s and MiB per case; N is the Line Space shaft constant (15·N⁴ shafts per "
         f"voxel). {BEST_MARK}: the fastest in its row. Red cells say why a case did not run.",
         per_backend(ls, "table3", ([SCENE_DIM], [N_DIM, RES_DIM]),
                     lambda r: speed_cell(r, baselines, min_agree, memory=True), unit="rays/s")),
    ]


# ---- HTML -------------------------------------------------------------------------------------
def _cell_html(cell: Cell | None, colspan: int = 1) -> str:
    if cell is None:
        return "<td class='na'>–</td>"
    css = " ".join(c for c in (cell.css, "best" if cell.best else "") if c)
    head = (f"{BEST_MARK} " if cell.best else "") + cell.lines[0]
    body = e(head) if cell.css == "fail" else f"<b>{e(head)}</b>"
    body += "".join(f"<br><span class='small'>{e(line)}</span>" for line in cell.lines[1:])
    span = f" colspan='{colspan}'" if colspan > 1 else ""
    return f"<td class='{css}'{span} title='{e(cell.title)}'>{body}</td>"


def table_html(table: Table) -> str:
    """The table with leading equal row labels merged (rowspan), like the thesis' tables."""
    n = len(table.row_headers)
    spans = [[0] * n for _ in table.rows]
    for j in range(n - 1):  # never merge the last (most specific) label
        i = 0
        while i < len(table.rows):
            k = i
            while k + 1 < len(table.rows) and table.rows[k + 1].labels[:j + 1] == table.rows[i].labels[:j + 1]:
                k += 1
            spans[i][j] = k - i + 1
            i = k + 1
    out = ["<table class='grid'><tr>"]
    out += [f"<th>{e(h)}</th>" for h in table.row_headers] + [f"<th>{e(c)}</th>" for c in table.columns]
    out.append("</tr>")
    for i, row in enumerate(table.rows):
        out.append("<tr class='ref'>" if row.reference else "<tr>")
        for j, v in enumerate(row.labels):
            if row.reference and j >= 1:  # "Embree (CPU)" across the remaining label columns
                if j == 1:
                    out.append(f"<th class='rl' colspan='{n - 1}'>{e(v)}</th>")
            elif j < n - 1:
                if spans[i][j]:
                    out.append(f"<th class='rl' rowspan='{spans[i][j]}'>{e(v)}</th>")
            else:
                out.append(f"<th class='rl'>{e(v)}</th>")
        if row.reference:
            out.append(_cell_html(row.cells[0], len(table.columns)))
        else:
            out += [_cell_html(c) for c in row.cells]
        out.append("</tr>")
    out.append("</table>")
    if table.note:
        out.append(f"<p class='small'>{e(table.note)}</p>")
    return "".join(out)


def cell_text(cell: Cell | None) -> str:
    """A cell as one line of text (LaTeX, CSV notes): its figure and notes."""
    if cell is None:
        return ""
    return "; ".join(cell.lines)

