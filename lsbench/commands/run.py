"""`lsbench run SCENARIO`: every case of a scenario, each in its own worker; resumes --out."""
from __future__ import annotations

import dataclasses
import datetime as _dt
import sys
from pathlib import Path

from lsbench.commands.common import add_scenario_arguments, say

NAME = "run"
HELP = "run every case of a scenario"


def setup_arguments(sub) -> None:
    p = sub.add_parser(NAME, help=HELP)
    add_scenario_arguments(p)
    p.set_defaults(func=run)


def default_out_dir(name: str) -> Path:
    from lsbench.paths import reports_dir
    from lsbench.running.environment import code_state

    commit, dirty = code_state()
    stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    return reports_dir() / f"{name}-{stamp}-{commit[:7]}{'-dirty' if dirty else ''}"


def write_run_json(out: Path, scenario, argv) -> None:
    from lsbench import backends
    from lsbench.results.store import write_run_info
    from lsbench.running.environment import code_state, environment_info

    commit, dirty = code_state()
    info = environment_info()
    devices = {}
    for name in sorted({c.backend for c in scenario.cases}):
        try:
            d = backends.get_device(name).info()
            devices[name] = {"device": d["device"], "driver": d["driver"]}
        except Exception as exc:  # the cases will fail with the reason; run.json says it too
            devices[name] = {"device": None, "error": str(exc).splitlines()[0]}
    info.update({"commit": commit, "dirty": dirty, "devices": devices, "scenario": scenario.path,
                 "settings": dataclasses.asdict(scenario.settings),
                 "scenario_name": scenario.name, "command": " ".join(argv)})
    write_run_info(out, info)


def check_inputs(scenario) -> None:
    """Load every scene file and .npz ray file of the scenario once, before any case runs: a
    missing or corrupt file is a one-line error (exit 2), not a run of failed cases."""
    from lsbench.inputs.rays import load_rays_file
    from lsbench.inputs.scenes import builtin_names, load_scene

    for spec in dict.fromkeys(c.scene for c in scenario.cases):
        if spec not in builtin_names():
            load_scene(spec)
    for spec in dict.fromkeys(c.rays for c in scenario.cases):
        if spec.lower().endswith(".npz"):
            load_rays_file(spec)


def run_scenario_file(args):
    """Load, check and run the scenario the arguments name: (scenario, records). `gate` runs
    the same and then judges the records."""
    from lsbench.inputs.scenario import load_scenario
    from lsbench.running.environment import record_env, uses_gpu
    from lsbench.running.runner import run_scenario, summary_table

    scenario = load_scenario(args.scenario)
    if scenario.settings.gpu_width:
        scenario = load_scenario(args.scenario, gpu=uses_gpu({c.backend for c in scenario.cases}))
    if args.memory_budget:
        scenario.settings = dataclasses.replace(scenario.settings, memory_budget_mb=args.memory_budget)
    check_inputs(scenario)
    out = Path(args.out) if args.out else default_out_dir(scenario.name)
    out.mkdir(parents=True, exist_ok=True)
    write_run_json(out, scenario, sys.argv)
    say(f"lsbench run {scenario.name}: {len(scenario.cases)} cases -> {out}")
    records = run_scenario(scenario, out, record_env(), fresh=args.fresh,
                           heatmaps=True if args.heatmaps else None, log=say)
    say()
    say(summary_table(records))
    say(f"\nresults: {out / 'results.jsonl'}")
    return scenario, records


def run(args) -> int:
    run_scenario_file(args)
    return 0
