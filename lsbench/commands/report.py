"""`lsbench report RUN_DIR [--out DIR]`: write the HTML report, print index.html's path; exit 2
with a one-line error when RUN_DIR is missing or holds no case record."""
from __future__ import annotations

import sys

from lsbench.inputs.checks import writable_folder

NAME = "report"
HELP = "write the HTML report of a run"


def setup_arguments(sub) -> None:
    p = sub.add_parser(NAME, help=HELP, description="Write index.html and charts for RUN_DIR.")
    p.add_argument("run_dir", metavar="RUN_DIR")
    p.add_argument("--out", type=writable_folder, default=None, metavar="DIR",
                   help="report folder (default: RUN_DIR itself; images are copied when elsewhere)")
    p.set_defaults(func=run)


def run(args) -> int:
    from lsbench.report.page import EmptyRunError, write_report

    try:
        print(write_report(args.run_dir, args.out))
    except (FileNotFoundError, EmptyRunError) as exc:  # no page of empty tables
        print(f"lsbench report: error: {exc}", file=sys.stderr)
        return 2
    return 0
