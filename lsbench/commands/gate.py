"""`lsbench gate SCENARIO`: run a scenario; exit 1 if any case fails or has a disagreement with
Embree that lsbench.oracle.classifier cannot explain (more than the scenario's max_unexplained,
default 0), or, where the scenario states min_agreement, agrees on fewer rays than that."""
from __future__ import annotations

from lsbench.commands.common import add_scenario_arguments, say
from lsbench.commands.run import run_scenario_file

NAME = "gate"
HELP = "run a scenario; exit 1 if any case fails or has an unexplained disagreement with Embree"


def setup_arguments(sub) -> None:
    p = sub.add_parser(NAME, help=HELP)
    add_scenario_arguments(p)
    p.set_defaults(func=run)


def _counts(r) -> str:
    classes = r.get("classes") or {}
    explained = ", ".join(f"{name} {n}" for name, n in classes.items() if n and name not in ("agree", "unexplained"))
    return (f"missed {r.get('missed')}, extra {r.get('extra')}, wrong {r.get('wrong')}, "
            f"distance {r.get('distance')}, of {r.get('ray_count')} rays; max |dt| {r.get('max_abs_dt', 0):.3g}"
            + (f"; explained: {explained}" if explained else "")
            + ("; classifier capped" if r.get("classify_capped") else ""))


def gate_failures(records, settings) -> list[str]:
    out = []
    for r in records:
        if r.get("status") != "ok":
            out.append(f"{r.get('key')}: FAILED: {r.get('reason')}")
            continue
        unexplained = r.get("unexplained")
        if unexplained is None or unexplained > settings.max_unexplained:
            rays = r.get("unexplained_rays") or []
            out.append(f"{r.get('key')}: {unexplained} unexplained disagreements > {settings.max_unexplained} "
                       f"(rays {rays[:5]}{' ...' if len(rays) > 5 else ''}; {_counts(r)})")
        if settings.min_agreement is not None and r["agreement"] < settings.min_agreement:
            out.append(f"{r.get('key')}: agreement {r['agreement']:.6f} < {settings.min_agreement} ({_counts(r)})")
    return out


def _criterion(settings) -> str:
    text = f"at most {settings.max_unexplained} unexplained disagreements"
    if settings.min_agreement is not None:
        text += f", agreement >= {settings.min_agreement}"
    return text


def run(args) -> int:
    scenario, records = run_scenario_file(args)
    settings = scenario.settings
    failures = gate_failures(records, settings)
    if failures:
        say(f"\nGATE FAILED: {len(failures)} findings in {len(records)} cases ({_criterion(settings)}):")
        for f in failures:
            say("  " + f)
        return 1
    unexplained = sum(r.get("unexplained", 0) for r in records)
    explained = sum(sum(n for k, n in (r.get("classes") or {}).items() if k not in ("agree", "unexplained",
                                                                                    "unclassified"))
                    for r in records)
    say(f"\ngate passed: {len(records)} cases, {unexplained} unexplained disagreements, "
        f"{explained} ties and explained ({_criterion(settings)})")
    return 0
