"""The one formatting module: numbers for people (SI prefixes, MiB, percentages, seconds), the one
file-name slug, and the one plain-text table writer (the run summary of `lsbench run` / `trace`
and the table of `lsbench compare`). Pure functions of plain values; no record knowledge."""
from __future__ import annotations

import re
from collections.abc import Sequence

MISSING = "-"


def fmt_si(v, unit="") -> str:
    """3 significant digits with a k/M/G prefix: 1.23 Mrays/s, 950 rays/s."""
    if v is None:
        return MISSING
    v = float(v)
    for prefix, scale in (("G", 1e9), ("M", 1e6), ("k", 1e3)):
        if abs(v) >= scale:
            return f"{v / scale:.3g} {prefix}{unit}"
    return f"{v:.3g} {unit}".strip()


def fmt_num(v) -> str:
    """3 significant digits without exponent notation (2200, 62.4, 0.125)."""
    if v is None:
        return MISSING
    v = float(v)
    return f"{v:.0f}" if abs(v) >= 100 else f"{v:.3g}"


def fmt_mib(b) -> str:
    """Bytes as MiB, 3 significant digits below 100 MiB, whole MiB above."""
    if b is None:
        return MISSING
    mib = float(b) / 2 ** 20
    return f"{mib:.3g}" if mib < 100 else f"{mib:.0f}"


def fmt_seconds(s) -> str:
    if s is None:
        return MISSING
    s = float(s)
    if s >= 1:
        return f"{s:.3g} s"
    if s >= 1e-3:
        return f"{s * 1e3:.3g} ms"
    return f"{s * 1e6:.3g} µs"


def eta_text(walls: list[float], left: int) -> str:
    """"; ETA 2.1e+02 s" for a long run's progress line: the mean wall time of the cases run so
    far times the cases left ("" when none is left or none has run)."""
    if left <= 0 or not walls:
        return ""
    return f"; ETA {fmt_seconds(left * sum(walls) / len(walls))}"


def fmt_pct(a) -> str:
    """A fraction as a percentage, 4 significant digits; never "100%" unless exactly 1 (one
    ray in 20,000 that disagrees must not read as full agreement)."""
    if a is None:
        return MISSING
    if a == 1:
        return "100%"
    digits = 4
    while digits < 12 and float(f"{a * 100:.{digits}g}") >= 100:
        digits += 1
    return f"{a * 100:.{digits}g}%"


def slug(*parts, empty: str = "x") -> str:
    """File-name-safe text of parts joined by "-": runs of other characters become one "_"."""
    text = "-".join(str(p) for p in parts)
    return re.sub(r"[^A-Za-z0-9._-]+", "_", text).strip("_") or empty


def text_table(header: Sequence[str], rows: Sequence[Sequence], right: set[int] = frozenset(),
               max_width: dict[int, int] | None = None) -> list[str]:
    """Lines of a plain-text table: header, a dashed rule, one line per row.

    Columns are two spaces apart and as wide as their widest cell; the columns in `right` are
    right-aligned (numbers), the others left-aligned. `max_width` caps a column, cutting longer
    cells with "…". Trailing blanks are stripped, so a last column of notes costs no padding.
    """
    cells = [[str(c) for c in row] for row in [header, *rows]]
    widths = [max(len(row[i]) for row in cells) for i in range(len(header))]
    for i, w in (max_width or {}).items():
        widths[i] = min(widths[i], w)

    def line(row: list[str]) -> str:
        out = []
        for i, (cell, w) in enumerate(zip(row, widths)):
            if len(cell) > w:
                cell = cell[: w - 1] + "…"
            out.append(cell.rjust(w) if i in right else cell.ljust(w))
        return "  ".join(out).rstrip()

    return [line(cells[0]), "  ".join("-" * w for w in widths)] + [line(r) for r in cells[1:]]
