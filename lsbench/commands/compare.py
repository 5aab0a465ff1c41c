"""`lsbench compare BASE_RUN HEAD_RUN`: match two runs' cases by key; exit 1 on a regression, a
refused case (same key, different scene or rays), when nothing matched, or when head lacks
base's cases (unless --only-common). --base-also / --head-also add more runs of the same commit:
each run's median is then one sample (repeats across processes). The output states the run's
false-alarm rate and the smallest change its samples can detect (lsbench/compare/verdicts.py)."""
from __future__ import annotations

import sys
from pathlib import Path

NAME = "compare"
HELP = "compare two runs; exit 1 on a regression, a refused or a missing case"


def add_verdict_arguments(p) -> None:
    """--factor, --alpha and --only-common, shared with compare-commits."""
    from lsbench.commands.common import ALPHA, FACTOR
    from lsbench.compare.verdicts import DEFAULT_ALPHA, DEFAULT_FACTOR

    p.add_argument("--factor", type=FACTOR.flag, default=DEFAULT_FACTOR,
                   help="slowdown / memory growth ratio that counts (default %(default)s)")
    p.add_argument("--alpha", type=ALPHA.flag, default=DEFAULT_ALPHA,
                   help="false-alarm rate of the whole run: family-wise, Holm over its cases "
                        "(default %(default)s)")
    p.add_argument("--only-common", action="store_true",
                   help="compare the cases both runs have; head lacking base's cases is no failure")


def setup_arguments(sub) -> None:
    p = sub.add_parser(NAME, help=HELP,
                       description="Match the cases of two run directories by key and flag regressions.")
    p.add_argument("base", metavar="BASE_RUN")
    p.add_argument("head", metavar="HEAD_RUN")
    add_verdict_arguments(p)
    p.add_argument("--base-also", action="append", default=[], metavar="RUN",
                   help="another run of base's commit (repeatable): one sample per run and case")
    p.add_argument("--head-also", action="append", default=[], metavar="RUN",
                   help="another run of head's commit (repeatable)")
    p.add_argument("--report", action="store_true", help="also write HEAD_RUN/compare.html")
    p.set_defaults(func=run)


# Worst first: a failure, then lost accuracy, a slowdown, more memory; then refused and missing
# cases; then the rest, slowest ratio first (the report links compare.html from the index).
SEVERITY = ("failure", "accuracy", "speed", "memory")


def severity(case) -> tuple:
    worst = min((SEVERITY.index(v) for v in case.verdicts if v in SEVERITY), default=len(SEVERITY))
    missing = case.base is None or case.head is None
    ratio = case.speed_ratio if case.speed_ratio is not None else float("inf")
    return (worst, not case.refused, not missing, ratio, case.key)


def run(args) -> int:
    from lsbench.compare.verdicts import compare_runs, format_table, write_compare_html

    try:
        res = compare_runs([args.base, *args.base_also], [args.head, *args.head_also],
                           factor=args.factor, alpha=args.alpha,
                           only_common=args.only_common)
    except FileNotFoundError as exc:
        print(f"lsbench compare: error: {exc}", file=sys.stderr)
        return 2
    res.cases.sort(key=severity)
    print(format_table(res))
    if args.report:
        print(f"wrote {write_compare_html(res, Path(res.folder) / 'compare.html')}")
    return res.exit_code
