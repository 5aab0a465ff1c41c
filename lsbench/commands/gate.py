"""`lsbench gate SCENARIO`: run a scenario; exit 1 if any case fails or is below its tolerance."""
from __future__ import annotations

from lsbench.commands.common import add_scenario_arguments, say
from lsbench.commands.run import run_scenario_file

NAME = "gate"
HELP = "run a scenario; exit 1 if any case is below its accuracy tolerance"


def setup_arguments(sub) -> None:
    p = sub.add_parser(NAME, help=HELP)
    add_scenario_arguments(p)
    p.set_defaults(func=run)


def gate_failures(records, settings) -> list[str]:
    out = []
    for r in records:
        if r.get("status") != "ok":
            out.append(f"{r.get('key')}: FAILED: {r.get('reason')}")
        elif r["agreement"] < settings.min_agreement:
            out.append(f"{r.get('key')}: agreement {r['agreement']:.6f} < {settings.min_agreement} "
                       f"(missed {r.get('missed')}, extra {r.get('extra')}, wrong {r.get('wrong')}, "
                       f"ties {r.get('ties')}, of {r.get('ray_count')} rays)")
    return out


def run(args) -> int:
    scenario, records = run_scenario_file(args)
    settings = scenario.settings
    failures = gate_failures(records, settings)
    if failures:
        say(f"\nGATE FAILED: {len(failures)} of {len(records)} cases below tolerance "
            f"(min agreement {settings.min_agreement}):")
        for f in failures:
            say("  " + f)
        return 1
    say(f"\ngate passed: {len(records)} cases at agreement >= {settings.min_agreement}")
    return 0
