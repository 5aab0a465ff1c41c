"""A report table as files beside the page, for a paper or a spreadsheet: CSV (the numbers, one
row per table row, a cell's figure as its plain value and its notes in a second column) and
LaTeX (a booktabs `tabular`, the best cell of a row in bold, failed cells as `failed`).
`write_exports` writes both under OUT_DIR/tables/ and returns their paths relative to OUT_DIR."""
from __future__ import annotations

import csv
import io
from pathlib import Path

from lsbench.report.tables import BEST_MARK, Table, cell_text

LATEX_SPECIAL = {"\\": r"\textbackslash{}", "&": r"\&", "%": r"\%", "$": r"\$", "#": r"\#", "_": r"\_",
                 "{": r"\{", "}": r"\}", "~": r"\textasciitilde{}", "^": r"\textasciicircum{}",
                 "×": r"$\times$", "³": r"$^3$", "…": r"\dots{}", "★": r"$\star$", "—": "---",
                 "µ": r"$\mu$", "–": "--"}


def latex_escape(text: str) -> str:
    return "".join(LATEX_SPECIAL.get(ch, ch) for ch in str(text))


def to_csv(table: Table) -> str:
    """Header: the row labels, then per column `<column> [unit]` and `<column> notes`."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    unit = f" [{table.unit}]" if table.unit else ""
    w.writerow([*table.row_headers, *(x for c in table.columns for x in (f"{c}{unit}", f"{c} notes"))])
    for row in table.rows:
        cells = row.cells + [None] * (len(table.columns) - len(row.cells))
        values = []
        for c in cells:
            if c is None:
                values += ["", ""]
            else:
                notes = ("best; " if c.best else "") + "; ".join(c.lines[1:] if c.css != "fail" else c.lines)
                values += ["" if c.value is None else repr(float(c.value)), notes]
        w.writerow([*row.labels, *values])
    return buf.getvalue()


def to_latex(table: Table) -> str:
    """A booktabs tabular (\\usepackage{booktabs}); each cell its figure and notes on one line."""
    n, m = len(table.row_headers), len(table.columns)
    lines = [f"% {latex_escape(table.caption)} (lsbench report; {BEST_MARK} = best in row)",
             r"\begin{tabular}{" + "l" * n + "r" * m + "}", r"\toprule",
             " & ".join(latex_escape(h) for h in [*table.row_headers, *table.columns]) + r" \\", r"\midrule"]
    previous: tuple = ()
    for row in table.rows:
        labels = [("" if previous[:j + 1] == row.labels[:j + 1] and j < n - 1 else latex_escape(v))
                  for j, v in enumerate(row.labels)]
        previous = row.labels
        if row.reference:
            body = [rf"\multicolumn{{{m}}}{{c}}{{{latex_escape(cell_text(row.cells[0]))}}}"]
        else:
            body = []
            for c in row.cells:
                text = latex_escape(cell_text(c)) if c is not None else "--"
                body.append(rf"\textbf{{{text}}}" if c is not None and c.best else text)
        lines.append(" & ".join(labels + body) + r" \\")
    lines += [r"\bottomrule", r"\end{tabular}", ""]
    return "\n".join(lines)


def write_exports(table: Table, out_dir: Path) -> dict[str, str]:
    """OUT_DIR/tables/<name>.csv and .tex; {"CSV": rel path, "LaTeX": rel path}."""
    folder = Path(out_dir) / "tables"
    folder.mkdir(parents=True, exist_ok=True)
    files = {}
    for kind, ext, text in (("CSV", "csv", to_csv(table)), ("LaTeX", "tex", to_latex(table))):
        path = folder / f"{table.name}.{ext}"
        path.write_text(text)
        files[kind] = path.relative_to(out_dir).as_posix()
    return files
