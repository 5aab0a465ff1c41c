"""`lsbench runs [ROOT]`: one line per stored run."""
from __future__ import annotations

NAME = "runs"
HELP = "list stored runs"


def setup_arguments(sub) -> None:
    p = sub.add_parser(NAME, help=HELP, description="List the run directories under ROOT (default reports).")
    p.add_argument("root", nargs="?", default="reports", metavar="ROOT")
    p.set_defaults(func=run)


def run(args) -> int:
    from lsbench.results.store import format_commit, format_devices, list_runs

    runs = list_runs(args.root)
    if not runs:
        print(f"no runs under {args.root}")
        return 0
    for r in runs:
        print(f"{r['dir']}  {r['date'] or '-'}  {format_commit(r['commit'], r['dirty'])}  "
              f"[{format_devices(r['devices'])}]  ok={r['ok']} failed={r['failed']}")
    return 0
