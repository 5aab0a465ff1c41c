"""`lsbench run SCENARIO`: every case of a scenario, each in its own worker; resumes --out.
Exit status: 0 when every case is ok, 1 when one failed (0 with --allow-failed), 2 for bad input
or a run folder that cannot be written or is in use."""
from __future__ import annotations

import dataclasses
import datetime as _dt
import sys
from pathlib import Path

from lsbench.commands.common import UsageError, add_scenario_arguments, say
from lsbench.inputs.checks import writable_folder

NAME = "run"
HELP = "run every case of a scenario"


def setup_arguments(sub) -> None:
    p = sub.add_parser(NAME, help=HELP)
    add_scenario_arguments(p)
    p.add_argument("--allow-failed", action="store_true",
                   help="exit 0 even when cases fail (sweeps that expect named driver limits)")
    p.add_argument("--history", type=writable_folder, metavar="DIR",
                   help="when the run ends, append its records to the history database DIR "
                        "(docs/history.md; the nightly does)")
    p.set_defaults(func=run)


def default_out_dir(name: str) -> Path:
    from lsbench.paths import reports_dir
    from lsbench.running.environment import code_state

    commit, dirty = code_state()
    stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    return reports_dir() / f"{name}-{stamp}-{commit[:7]}{'-dirty' if dirty else ''}"


def write_run_json(out: Path, scenario, devices: dict, argv, extra: dict | None = None) -> None:
    from lsbench.results.store import write_run_info
    from lsbench.running.environment import code_state, environment_info

    commit, dirty = code_state()
    info = environment_info()
    info.update({"commit": commit, "dirty": dirty, "devices": devices, "scenario": scenario.path,
                 "settings": dataclasses.asdict(scenario.settings),
                 "scenario_name": scenario.name, "command": " ".join(argv), **(extra or {})})
    write_run_info(out, info)


def prepare_out_dir(path: Path) -> Path:
    """The run folder, created if need be; a one-line error when it cannot be one."""
    if path.exists() and not path.is_dir():
        raise UsageError(f"--out {path}: not a folder")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UsageError(f"--out {path}: cannot create it ({exc.strerror or exc})") from None
    return path


def load_run_scenario(args, gpu: bool = False):
    """The scenario the arguments name, at its GPU image size when `gpu`, with --memory-budget and --budget."""
    from lsbench.inputs.scenario import load_scenario

    scenario = load_scenario(args.scenario, gpu=gpu)
    if args.memory_budget:
        scenario.settings = dataclasses.replace(scenario.settings, memory_budget_mb=args.memory_budget)
    if args.budget:
        scenario.settings = dataclasses.replace(scenario.settings, budget_mib=args.budget)
    return scenario


def run_scenario_file(args):
    """Load and run the scenario the arguments name, holding the lock on its run folder:
    (scenario, records). `gate` runs the same and then judges the records. With --cluster the
    cases run on a Ray cluster (lsbench/running/cluster.py) into the same folder and store."""
    from lsbench.results.store import ResultsError, RunLock, check_writable
    from lsbench.running.environment import device_info, record_env, uses_gpu
    from lsbench.running.runner import plan_cases, summary_table

    scenario = load_run_scenario(args)
    backends = {c.backend for c in scenario.cases}
    if scenario.settings.gpu_width and not args.cluster:
        scenario = load_run_scenario(args, gpu=uses_gpu(backends))
    out = prepare_out_dir(Path(args.out) if args.out else default_out_dir(scenario.name))
    args.run_dir = out  # where it went, for `run --history`
    try:
        with RunLock(out, " ".join(["lsbench", *sys.argv[1:]])):
            check_writable(out, args.fresh)
            env = record_env()
            if args.cluster:
                from lsbench.running.cluster import Cluster, ClusterError

                try:
                    with Cluster(args.cluster, dict(args.cluster_resource), args.cluster_retries, log=say) as cluster:
                        if scenario.settings.gpu_width:
                            scenario = load_run_scenario(args, gpu=cluster.uses_gpu(backends))
                        plans = cluster.plan(scenario, env)  # bad scene or ray files: exit 2 here
                        records = _run_into(out, args, scenario, cluster.devices(backends), plans, env,
                                            cluster.run_cases, {"cluster": cluster.describe()})
                except ClusterError as exc:
                    raise UsageError(str(exc)) from None
            else:
                devices = device_info(backends)
                plans = plan_cases(scenario, env, devices)  # bad scene or ray files: exit 2 here
                records = _run_into(out, args, scenario, devices, plans, env)
    except ResultsError as exc:
        raise UsageError(str(exc)) from None
    say()
    say(summary_table(records))
    say(f"\nresults: {out / 'results.jsonl'}")
    return scenario, records


def _run_into(out: Path, args, scenario, devices: dict, plans, env: dict, cases=None, info: dict | None = None):
    """Run the planned cases into `out` (locked), writing run.json (with `info` added, and the
    history database it will go to: the report links that history's page)."""
    if getattr(args, "history", None):
        info = dict(info or {}, history_dir=str(Path(args.history).resolve()))
    from lsbench.running.runner import run_locally, run_scenario

    if not args.fresh:  # a --fresh run replaces run.json with results.jsonl, once done
        write_run_json(out, scenario, devices, sys.argv, info)
    say(f"lsbench run {scenario.name}: {len(scenario.cases)} cases -> {out}")
    records = run_scenario(scenario, plans, out, env, fresh=args.fresh, heatmaps=True if args.heatmaps else None,
                           keep_failed=args.keep_failed, log=say, cases=cases or run_locally)
    if args.fresh:
        write_run_json(out, scenario, devices, sys.argv, info)
    return records


def run(args) -> int:
    _, records = run_scenario_file(args)
    if args.history:
        from lsbench.paths import source_checkout
        from lsbench.results.history import HistoryError, append_run

        try:
            say(f"history: stored as {append_run(args.history, args.run_dir, source_checkout() or '.')}")
        except HistoryError as exc:
            raise UsageError(f"--history {args.history}: {exc}") from None
        from lsbench.commands.history import write_page
        say(f"history page: {write_page(args.history)}")
    failed = [r for r in records if r.get("status") != "ok"]
    if failed and not args.allow_failed:
        say(f"\n{len(failed)} of {len(records)} cases failed (exit 1; --allow-failed exits 0)")
        return 1
    return 0
