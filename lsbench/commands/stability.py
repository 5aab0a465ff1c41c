"""`lsbench stability ...`: one case repeated in this process and in separate processes; the
spread of its timings, printed and written as JSON."""
from __future__ import annotations

import datetime as _dt
import json
import sys
from pathlib import Path

from lsbench.commands.common import add_case_arguments, case_from_args
from lsbench.inputs.checks import integer
from lsbench.inputs.scenario import RUN_RULES

NAME = "stability"
HELP = "repeat one case in this process and in separate processes; print and write the spread of its timings"


def setup_arguments(sub) -> None:
    s = sub.add_parser(NAME, help=HELP)
    add_case_arguments(s, size="128x128")
    s.add_argument("--processes", type=integer(1).flag, default=3,
                   help="runs in this process and, as many again, each in its own process")
    s.add_argument("--timeout", type=RUN_RULES["timeout_seconds"].flag, default=600.0,
                   help="seconds per separate-process run")
    s.add_argument("--out", metavar="FILE.json", help="default reports/stability-<case>-<date>.json")
    s.set_defaults(func=run)


def run(args) -> int:
    from lsbench.inputs.scenario import RunSettings
    from lsbench.inputs.scenes import load_scene
    from lsbench.paths import reports_dir
    from lsbench.profile.heatmaps import case_slug
    from lsbench.profile.stability import stability_text, timing_stability
    from lsbench.running.environment import record_env

    case = case_from_args(args)
    load_scene(args.scene)  # bad input fails here, before any worker starts
    settings = RunSettings(width=case.width, height=case.height, rays=args.rays, repeats=args.repeats,
                           warmup=args.warmup, timeout_seconds=args.timeout, budget_mib=args.budget)
    env = record_env()
    result = timing_stability(case, settings, args.processes, env,
                              log=lambda m: print(m, file=sys.stderr, flush=True))
    result.update(env)
    result["date"] = _dt.datetime.now().isoformat(timespec="seconds")
    result["command"] = " ".join(sys.argv)
    if args.out:
        out = Path(args.out)
    else:
        stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
        out = reports_dir() / f"stability-{case_slug(case.key)}-{stamp}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2, default=str))
    print(stability_text(result))
    print(f"written: {out}")
    ok = result["in_process"].get("ok") and result["cross_process"].get("ok")
    return 0 if ok else 1
