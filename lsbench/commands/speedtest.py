"""`lsbench speedtest [SCENE ...]`: every structure on both backends at its best known setting,
against Embree on the same rays, in one table (the spirit of tinybvh's tiny_bvh_speedtest.cpp:
one line per layout, same rays).

The settings are the cases of a scenario, by default the shipped scenarios/speedtest.toml (the one
table of best settings; `lsbench run scenarios/speedtest.toml` runs the same set for the nightly).
SCENE arguments replace its scenes, and --rays/--size/--camera/--structures/--backends and the
per-structure --resolution/--ls-n/--ls-min-candidates override it. Each case runs in its own worker
process as `run` does (runner.run_case_isolated), so a driver crash or limit is a failed row.
Embree is timed inside that worker on the same rays (RunSettings.embree_timing), so `× Embree`
(lsbench rays/s ÷ Embree rays/s) is a ratio of two figures taken side by side: the figure that
counts on a machine shared with other work. Exit status: 0 when every case is ok with no more
unexplained disagreements than the scenario's max_unexplained, 1 otherwise, 2 for bad input."""
from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import sys
import time
from pathlib import Path

from lsbench.commands.common import (UsageError, checked_text, parse_camera, parse_size, say,
                                     writable_file)
from lsbench.inputs.checks import BadValue, ray_param_text, resolve_ray_params
from lsbench.inputs.scenario import LS_MIN_CANDIDATES, LS_N, RUN_RULES, Case, Scenario

NAME = "speedtest"
HELP = "every structure on both backends at its best setting against Embree, in one table"
DEFAULT_SETTINGS = "speedtest"  # the shipped scenario that holds the best setting per structure
OUT_SUFFIXES = (".json", ".csv")


def per_structure(rule):
    """argparse `type=` for "[STRUCTURE=]VALUE": VALUE checked by `rule`, for one structure or,
    without a prefix, for all. Returns (structure or None, value)."""
    from lsbench import backends

    def parse(text: str):
        name, sep, value = text.rpartition("=")
        if sep and name not in backends.structure_names():
            raise argparse.ArgumentTypeError(
                f"{text}: {name!r} is not a structure ({', '.join(backends.structure_names())})")
        return (name if sep else None), rule.flag(value)
    return parse


def table_file(text: str) -> str:
    """argparse `type=` for --out: a .json or .csv file that can be written before any case runs."""
    if Path(text).suffix.lower() not in OUT_SUFFIXES:
        raise argparse.ArgumentTypeError(f"{text} does not end in {' or '.join(OUT_SUFFIXES)}")
    return writable_file(text)


def setup_arguments(sub) -> None:
    from lsbench import backends
    from lsbench.inputs.checks import RESOLUTION

    p = sub.add_parser(NAME, help=HELP, description=__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scenes", nargs="*", metavar="SCENE",
                   help="built-in name or mesh file (default: the settings' scenes and camera)")
    p.add_argument("--settings", default=DEFAULT_SETTINGS, metavar="SCENARIO",
                   help="scenario whose cases are the best setting per structure and backend "
                        "(default: the shipped speedtest.toml)")
    p.add_argument("--rays", type=RUN_RULES["rays"].flag, help="ray set name or .npz file (default the settings')")
    p.add_argument("--ray-param", type=ray_param_text, action="append", default=[], metavar="KEY=VALUE",
                   help="a parameter of the ray set, VALUE as in TOML (samples=4); repeatable")
    p.add_argument("--size", type=checked_text(parse_size), help="image size WxH (default the settings')")
    p.add_argument("--camera", type=checked_text(parse_camera),
                   help="eye and target 'ex,ey,ez:tx,ty,tz[:fov]' (default: the settings' camera for "
                        "their scenes, the scene's own for a SCENE)")
    p.add_argument("--structures", nargs="+", choices=backends.structure_names(), metavar="STRUCTURE",
                   help=f"only these ({', '.join(backends.structure_names())})")
    p.add_argument("--backends", nargs="+", choices=list(backends.BACKENDS), metavar="BACKEND",
                   help=f"only these ({', '.join(backends.BACKENDS)})")
    p.add_argument("--resolution", type=per_structure(RESOLUTION), action="append", default=[],
                   metavar="[STRUCTURE=]R", help="resolution for every structure or one (repeatable)")
    p.add_argument("--ls-n", type=per_structure(LS_N), action="append", default=[],
                   metavar="[STRUCTURE=]N", help="Line Space N for every Line Space structure or one")
    p.add_argument("--ls-min-candidates", type=per_structure(LS_MIN_CANDIDATES), action="append",
                   default=[], metavar="[STRUCTURE=]K", help="only cells with more candidates get a Line Space")
    p.add_argument("--repeats", type=RUN_RULES["repeats"].flag, help="timed launches (default the settings')")
    p.add_argument("--warmup", type=RUN_RULES["warmup"].flag, help="untimed launches before them")
    p.add_argument("--timeout", type=RUN_RULES["timeout_seconds"].flag, help="seconds per case worker")
    p.add_argument("--work", action="store_true",
                   help="also where the time goes: steps and candidate tests per ray, their SIMD "
                        "efficiency (32-ray groups and the device's own width), device time per build "
                        "kernel (OpenCL event profiling)")
    p.add_argument("--out", type=table_file, metavar="FILE.json|FILE.csv",
                   help="also write the table's rows (JSON with the full records, or CSV)")
    p.set_defaults(func=run)


# --- the cases ------------------------------------------------------------------------------------

def override(values: list[tuple[str | None, object]], structure: str, default):
    """The last --flag value given for `structure` or for all structures, else `default`."""
    for name, value in reversed(values):
        if name in (None, structure):
            return value
    return default


def speedtest_cases(args, settings_scenario: Scenario, width: int, height: int) -> list[Case]:
    """One case per scene x (structure, backend) setting of the settings scenario, overridden by
    the arguments, in display order. A structure chosen with --structures that the settings lack
    needs its --resolution."""
    from lsbench import backends
    from lsbench.inputs.scenario import expand_scene

    wanted = args.structures or backends.structure_names()
    chosen_backends = args.backends or list(backends.BACKENDS)
    settings: dict[tuple[str, str], list[tuple]] = {}
    for c in settings_scenario.cases:
        settings.setdefault((c.structure, c.backend), [])
        if (c.resolution, c.ls_n, c.ls_min_candidates) not in settings[(c.structure, c.backend)]:
            settings[(c.structure, c.backend)].append((c.resolution, c.ls_n, c.ls_min_candidates))
    camera = parse_camera(args.camera) if args.camera else None

    def ray_set(rays: str, params: tuple) -> tuple[str, tuple]:
        """--rays / --ray-param over a case's ray set and parameters."""
        if not (args.rays or args.ray_param):
            return rays, params
        rays = args.rays or rays
        try:
            return rays, resolve_ray_params("--ray-param: ", rays, dict(args.ray_param))
        except BadValue as exc:
            raise UsageError(str(exc)) from None

    if args.scenes:
        given = ray_set(settings_scenario.settings.rays, ())
        if not args.rays and not args.ray_param:
            given = ray_set(*next(iter((c.rays, c.ray_params) for c in settings_scenario.cases)))
        scenes = [(expand_scene(s), camera, *given) for s in args.scenes]
    else:
        scenes = list(dict.fromkeys((c.scene, camera or c.camera, *ray_set(c.rays, c.ray_params))
                                    for c in settings_scenario.cases))
    cases = []
    for scene, cam, rays, ray_params in scenes:
        for structure in sorted(wanted, key=backends.display_order):
            line_space = backends.structure_info(structure).line_space
            for backend in chosen_backends:
                known = settings.get((structure, backend))
                if not known:
                    given = override(args.resolution, structure, None)
                    if given is None:
                        if args.structures:
                            raise UsageError(f"{settings_scenario.path} has no setting for {structure} on "
                                             f"{backend}: give --resolution {structure}=R")
                        continue
                    known = [(str(given), 0, 0)]
                for res, n, k in known:
                    n = override(args.ls_n, structure, n) if line_space else 0
                    k = override(args.ls_min_candidates, structure, k) if line_space else 0
                    cases.append(Case(scene, structure, backend, str(override(args.resolution, structure, res)),
                                      n, k, rays, width, height, cam, ray_params))
    unique = list({c.key: c for c in cases}.values())
    if not unique:
        raise UsageError("no case to run: the settings have none for these structures and backends")
    return unique


# --- one row per case ----------------------------------------------------------------------------

ROW_FIELDS = ("scene", "rays", "width", "height", "structure", "backend", "resolution", "ls_n",
              "ls_min_candidates", "leaf_size", "status", "reason", "rays_per_second", "embree_rays_per_second",
              "x_embree", "memory_bytes", "build_seconds", "agreement", "unexplained",
              "iterations_per_ray", "candidate_tests_per_ray", "linespace_lookups_per_ray",
              "simd_efficiency_steps_w32", "simd_efficiency_tests_w32", "simd_width_device",
              "simd_efficiency_steps_device", "simd_efficiency_tests_device",
              "build_kernel_seconds", "wall_seconds", "key")


def speed_row(rec: dict) -> dict:
    """The speedtest's figures of one record; x_embree = rays/s ÷ Embree's rays/s in the same
    worker process (None where either is missing)."""
    row = {f: rec.get(f) for f in ROW_FIELDS if f in rec}
    ours, embree = rec.get("rays_per_second"), rec.get("embree_rays_per_second")
    row["x_embree"] = ours / embree if rec.get("status") == "ok" and ours and embree else None
    row["build_kernel_seconds"] = (rec.get("stats") or {}).get("build_kernel_seconds")
    return {f: row.get(f) for f in ROW_FIELDS}


def _num(v, fmt: str) -> str:
    return "-" if v is None else format(v, fmt)


def speed_table(rows: list[dict], work: bool = False) -> list[str]:
    """The plain-text table: one line per case; a failed case's reason in its last column."""
    from lsbench.report.format import fmt_mib, text_table

    head = ["scene", "structure", "backend", "res", "N", "Mrays/s", "Embree Mrays/s", "× Embree", "MiB",
            "build s", "agreement", "unexpl."]
    if work:  # SIMD efficiency: lsbench/profile/simd.py (32-ray groups, and the device's own width)
        head += ["steps/ray", "tests/ray", "SIMD steps w32", "SIMD tests w32", "lanes", "SIMD steps dev", "SIMD tests dev"]
    head.append("status")
    lines = []
    for r in rows:
        ok = r["status"] == "ok"
        res = f"leaf={r['leaf_size']}" if r.get("leaf_size") else r["resolution"]  # a BVH has no grid
        line = [r["scene"], r["structure"], r["backend"], res, str(r["ls_n"] or "-"),
                _num(r["rays_per_second"] and r["rays_per_second"] / 1e6, ".3f") if ok else "-",
                _num(r["embree_rays_per_second"] and r["embree_rays_per_second"] / 1e6, ".3f"),
                _num(r["x_embree"], ".3f"), fmt_mib(r["memory_bytes"]) if ok else "-",
                _num(r["build_seconds"], ".2f") if ok else "-",
                _num(r["agreement"], ".6f") if ok else "-", _num(r["unexplained"], "d") if ok else "-"]
        if work:
            line += [_num(r[f], fmt) if ok else "-" for f, fmt in (
                ("iterations_per_ray", ".1f"), ("candidate_tests_per_ray", ".1f"),
                ("simd_efficiency_steps_w32", ".2f"), ("simd_efficiency_tests_w32", ".2f"),
                ("simd_width_device", "d"), ("simd_efficiency_steps_device", ".2f"),
                ("simd_efficiency_tests_device", ".2f"))]
        line.append("ok" if ok else f"FAILED: {r['reason']}")
        lines.append(line)
    numbers = set(range(3, len(head) - 1))
    return text_table(head, lines, right=numbers, max_width={len(head) - 1: 160})


def kernel_table(rows: list[dict]) -> list[str]:
    """Device time of each build kernel (OpenCL event profiling), the largest first, per case;
    "other" is the build's wall time the kernels do not cover (prefix sums, copies, host work)."""
    from lsbench.report.format import fmt_seconds, text_table

    lines = []
    for r in rows:
        kernels = r["build_kernel_seconds"]
        if r["status"] != "ok" or not kernels:
            continue
        label = f"{r['structure']} {r['backend']} r{r['resolution']}" + (f" N{r['ls_n']}" if r["ls_n"] else "")
        total = r["build_seconds"] or 0.0
        other = max(total - sum(kernels.values()), 0.0)
        for name, seconds in [*sorted(kernels.items(), key=lambda kv: -kv[1]), ("other", other)]:
            share = f"{100 * seconds / total:.0f}%" if total > 0 else "-"
            lines.append([label, name, fmt_seconds(seconds), share])
            label = ""
    if not lines:
        return []
    return text_table(["case", "build kernel", "device time", "of build"], lines, right={2, 3})


def write_rows(path: Path, rows: list[dict], records: list[dict], info: dict) -> None:
    from lsbench.results.store import encode_record

    if path.suffix.lower() == ".csv":
        with open(path, "w", newline="") as f:
            out = csv.DictWriter(f, fieldnames=ROW_FIELDS)
            out.writeheader()
            for r in rows:
                out.writerow({k: json.dumps(v) if isinstance(v, dict) else v for k, v in r.items()})
    else:
        path.write_text(json.dumps({**info, "rows": rows,
                                    "records": [json.loads(encode_record(r)) for r in records]},
                                   indent=1, default=str) + "\n")


# --- the command ---------------------------------------------------------------------------------

def progress_line(i: int, total: int, case: Case, rec: dict, walls: list[float]) -> str:
    """`[i/total] case: ok 3.1 s: 1.23 Mrays/s = 0.45× Embree, ...; ETA 2 min` (the mean wall
    time of the cases so far times the cases left)."""
    from lsbench.report.format import eta_text

    row = speed_row(rec)
    label = f"{case.structure} {case.backend} r{case.resolution}" + (f" N{case.ls_n}" if row["ls_n"] else "")
    if rec.get("status") == "ok":
        what = (f"ok ({rec['wall_seconds']:.1f} s): {rec['rays_per_second'] / 1e6:.3f} Mrays/s = "
                f"{_num(row['x_embree'], '.3f')}× Embree, agreement {rec['agreement']:.6f} "
                f"({rec.get('unexplained')} unexplained), build {rec['build_seconds']:.2f} s")
    else:
        what = f"FAILED ({rec['wall_seconds']:.1f} s): {rec.get('reason')}"
    return f"[{i}/{total}] {Path(case.scene).stem} {label}: {what}{eta_text(walls, total - i)}"


def run(args) -> int:
    from lsbench.inputs.scenario import load_scenario
    from lsbench.oracle.embree import embree_version
    from lsbench.running.environment import device_info, record_env, uses_gpu
    from lsbench.running.runner import plan_cases, run_case_isolated

    base = load_scenario(args.settings)
    s = base.settings
    if args.size:
        width, height = parse_size(args.size)
    else:
        gpu = s.gpu_width is not None and uses_gpu(args.backends or {c.backend for c in base.cases})
        width, height = (s.gpu_width, s.gpu_height) if gpu else (s.width, s.height)
    settings = dataclasses.replace(
        s, width=width, height=height, embree_timing=True,
        repeats=args.repeats or s.repeats, warmup=s.warmup if args.warmup is None else args.warmup,
        timeout_seconds=args.timeout or s.timeout_seconds)
    cases = speedtest_cases(args, base, width, height)
    scenario = Scenario(f"speedtest-{base.name}", base.path, settings, cases)
    env = record_env()
    devices = device_info(c.backend for c in cases)
    plans = plan_cases(scenario, env, devices)  # bad scene or ray files: exit 2 here
    ray_sets = ", ".join(dict.fromkeys(c.key.split("|")[1] for c in cases))
    say(f"lsbench speedtest: {len(cases)} cases, rays {ray_sets}, "
        f"settings from {base.path}; {embree_version()} on all usable cores in each case's worker")
    for name, d in devices.items():
        say(f"  {name}: {d.get('device') or 'unavailable: ' + str(d.get('error'))}")
    records, walls = [], []
    for i, plan in enumerate(plans, 1):
        t0 = time.perf_counter()
        rec = run_case_isolated(plan.case, settings, env, None, plan.expected)
        rec["wall_seconds"] = time.perf_counter() - t0
        walls.append(rec["wall_seconds"])
        records.append(rec)
        say(progress_line(i, len(plans), plan.case, rec, walls))
    rows = [speed_row(r) for r in records]
    say()
    say("\n".join(speed_table(rows, args.work)))
    if args.work:
        kernels = kernel_table(rows)
        say("\n" + ("\n".join(kernels) if kernels else
                    "device time per build kernel: none measured (OpenCL event profiling only)"))
    if args.out:
        info = {"command": " ".join(["lsbench", *sys.argv[1:]]), "settings_file": base.path,
                "settings": dataclasses.asdict(settings), "devices": devices, **env}
        write_rows(Path(args.out), rows, records, info)
        say(f"\nwritten: {args.out}")
    bad = [r for r in rows if r["status"] != "ok" or (r["unexplained"] or 0) > settings.max_unexplained]
    if bad:
        say(f"\n{len(bad)} of {len(rows)} cases failed or have unexplained disagreements (exit 1)")
        return 1
    return 0
