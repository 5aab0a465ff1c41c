"""`lsbench compare-commits REV_A REV_B SCENARIO`: run a scenario at two revisions and compare."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from lsbench.commands.compare import add_verdict_arguments
from lsbench.inputs.checks import integer, writable_folder

NAME = "compare-commits"
HELP = "run a scenario at two git revisions and compare"


def setup_arguments(sub) -> None:
    q = sub.add_parser(NAME, help=HELP,
                       description="Create temporary git worktrees at REV_A and REV_B, run SCENARIO in each "
                                   "(with its own code, and $SCENES = this checkout's scenes folder), then "
                                   "compare REV_A (base) with REV_B (head).")
    q.add_argument("rev_a", metavar="REV_A")
    q.add_argument("rev_b", metavar="REV_B")
    q.add_argument("scenario", metavar="SCENARIO")
    add_verdict_arguments(q)
    q.add_argument("--processes", type=processes_flag, default=1, metavar="K|auto",
                   help="run the scenario K times at each revision (alternating), each run one sample "
                        "per case: repeats across processes and builds (default 1: the repeats of one "
                        "run); auto: as many as a lone slowdown needs to be flaggable at --alpha over "
                        "the scenario's cases (Holm)")
    q.add_argument("--out", type=writable_folder, default=None, metavar="DIR",
                   help="where both runs go (default reports/compare-A-B-TIME)")
    q.set_defaults(func=run)


def processes_flag(text: str):
    """argparse `type=` for --processes: an integer >= 1, or auto."""
    return text if text == "auto" else integer(1).flag(text)


def run(args) -> int:
    from lsbench.compare.commits import compare_commits, processes_needed
    from lsbench.compare.verdicts import format_table, write_compare_html

    try:
        if args.processes == "auto":
            args.processes, cases = processes_needed(args.scenario, args.alpha)
            print(f"--processes auto: {args.processes} runs per revision ({cases} cases, alpha {args.alpha:g})",
                  file=sys.stderr)
        res = compare_commits(args.rev_a, args.rev_b, args.scenario, factor=args.factor,
                              out_dir=args.out, alpha=args.alpha, only_common=args.only_common,
                              processes=args.processes)
    except (ValueError, RuntimeError, subprocess.CalledProcessError) as exc:
        msg = getattr(exc, "stderr", None) or exc
        print(f"lsbench compare-commits: error: {str(msg).strip()}", file=sys.stderr)
        return 2
    print(format_table(res))
    print(f"wrote {write_compare_html(res, Path(res.folder) / 'compare.html')}")
    return res.exit_code
