"""`lsbench history HISTORY_DIR`: the results database across commits (docs/history.md): append
runs to it, backfill it for past commits, and print and write what it says (steps per case over
the whole sequence, each named by its commit range). Exit 0, or 2 for bad input or a failed
backfill run."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from lsbench.inputs.checks import integer, writable_folder

NAME = "history"
HELP = "results across commits: append, backfill, and show steps per case (text and HTML)"
PROCESSES = integer(1)


def setup_arguments(sub) -> None:
    p = sub.add_parser(NAME, help=HELP, description=(
        "Read the history database HISTORY_DIR (made when absent), after appending --append runs "
        "and running --backfill; print one row per case with the steps found over all commits, "
        "and write the HTML history page (default HISTORY_DIR/index.html)."))
    p.add_argument("history", metavar="HISTORY_DIR", type=writable_folder)
    p.add_argument("--append", action="append", default=[], metavar="RUN_DIR",
                   help="store this run folder's records under its machine and commit (repeatable)")
    p.add_argument("--backfill", nargs=2, metavar=("REV_RANGE", "SCENARIO"),
                   help="run SCENARIO at every commit of REV_RANGE (e.g. main~9..main, first parents, "
                        "oldest first) in temporary worktrees and store each run; commits already "
                        "holding --processes runs of it are skipped")
    p.add_argument("--repo", metavar="DIR", help="the git repository to backfill (default: the one "
                   "around the current directory)")
    p.add_argument("--processes", type=PROCESSES.flag, default=1, metavar="K",
                   help="backfill runs per commit: each a new process and build per case (default 1)")
    from lsbench.commands.common import FACTOR
    from lsbench.compare.verdicts import DEFAULT_FACTOR
    p.add_argument("--factor", type=FACTOR.flag, default=DEFAULT_FACTOR,
                   help="a step past this rays/s ratio is a slowdown or speed-up (default %(default)s)")
    from lsbench.results.history import STATISTICS
    p.add_argument("--statistic", choices=sorted(STATISTICS), default="median",
                   help="each run's figure of a case: the median repeat (its record's rays/s) or the "
                        "best (fastest) one, the stabler figure on a shared machine (default %(default)s)")
    p.add_argument("--html", metavar="FILE.html", help="where the page goes (default HISTORY_DIR/index.html)")
    p.set_defaults(func=run)


def run(args) -> int:
    from lsbench.compare.commits import backfill
    from lsbench.paths import source_checkout
    from lsbench.results import history

    hist = Path(args.history)
    try:
        for run_dir in args.append:
            stored = history.append_run(hist, run_dir, repo_dir=args.repo or source_checkout() or ".",
                                        source="append")
            print(f"stored {run_dir} as {stored}")
        if args.backfill:
            rev_range, scenario = args.backfill
            stored = backfill(hist, rev_range, scenario, processes=args.processes, repo_dir=args.repo)
            print(f"backfill {rev_range}: {len(stored)} runs stored")
        runs = history.read_history(hist)
    except (history.HistoryError, ValueError, RuntimeError, FileNotFoundError,
            subprocess.CalledProcessError) as exc:
        msg = getattr(exc, "stderr", None) or exc
        print(f"lsbench history: error: {str(msg).strip()}", file=sys.stderr)
        return 2
    page = write_page(hist, runs, Path(args.html) if args.html else None, args.factor, args.statistic,
                      echo=True)
    print(f"wrote {page}")
    return 0


def write_page(hist, runs=None, html=None, factor=None, statistic: str = "median", echo=False) -> Path:
    """Analyse the database and write its page (default HIST/index.html); echo prints the summary."""
    from lsbench.compare.history import analyse, summary_text
    from lsbench.compare.verdicts import DEFAULT_FACTOR
    from lsbench.report.history_page import write_history_page
    from lsbench.results import history

    hist = Path(hist)
    runs = history.read_history(hist) if runs is None else runs
    factor = factor or DEFAULT_FACTOR
    cases = analyse(history.series(runs, statistic), factor=factor)
    text = summary_text(cases, factor, statistic)
    if echo:
        print(text)
    run_dirs: dict[tuple, list[Path]] = {}
    for r in runs:
        run_dirs.setdefault((r.machine, r.commit), []).append(r.path)
    return write_history_page(cases, run_dirs, html or hist / history.PAGE, factor, text, statistic)
