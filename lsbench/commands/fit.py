"""`lsbench fit`: measure the cost model's constants on this machine's devices (model/cost.py:
seconds per ray = launch / rays + ray + step[structure] x iterations + test x candidate tests +
lookup x Line Space lookups) from a short calibration sweep, and store them per device
(model/constants.py), where every "auto" case on that device then finds them.

The sweep: every structure at a few settings on small built-in scenes (the same cases as `lsbench
trace`, in this process), each with its work counters (iterations, tests, lookups per ray) and its
device time per ray; the iterations and tests are taken as the device's SIMD groups issue them
(the record's mean over its SIMD efficiency at the device's width: what the model predicts); a
non-negative least-squares fit weighted by relative error gives the constants, and the stored file
keeps each case's measured time beside the fitted one."""
from __future__ import annotations

import datetime as _dt
import itertools
import json

from lsbench.commands.common import UsageError, checked_text, parse_size, say
from lsbench.inputs.checks import writable_folder
from lsbench.inputs.scenario import RUN_RULES

NAME = "fit"
HELP = "measure the cost model's constants per device (for \"auto\" settings) and store them"
DEFAULT_SCENES = ("atrium", "spheres")
# The calibration's image per backend (--size overrides it). Each case's device time per ray must
# stand for the same case at the sizes auto cases trace (512x512 in fit-thesis.toml). On PoCL it
# did not at 128x128: on the 2-core machine (2026-12-04) a case took 1.5-3 times its time per ray at
# 512x512 (atrium grid 128^3: 1729 against 601 ns), K = 0 against K = 16 of one Line Space came out
# either way by up to 30 % from one round to the next, and the fit put the grid-ls step at the plain
# grid's 2.37 ns, where the atrium's own settings at 512x512 gave 3.0-4.0 ns; auto then took
# 98 x 43 x 49 N=3 on the atrium, where 61 x 27 x 31 traces in 0.82 of its time. At 512x512 the fit's
# residual fell from 18 to 10 % and that choice, with six others, traced as fast or faster (docs/fit.md).
# llvmpipe's cases at 128x128 already take 60-250 ms (4-15 us a ray) and fit within 10 %; at 512x512
# its four rounds would take half an hour.
DEFAULT_SIZES = {"glsl": "128x128", "opencl": "512x512"}
# (structure, resolution, N, K): steps, tests and lookups in different proportions, so the fit can
# tell the constants apart, in the range where the auto choice decides (5-250 candidate tests per
# ray on the two scenes, not the 500-1000 of a 4^3 or 16^3 grid, whose long lists cost less per
# test and pulled the test constant down: docs/fit.md, "The constants"); each Line Space structure
# at K = 0 (a lookup in every non-empty cell) and K = 16 (fewer lookups, more list tests on the
# same walk), and at 128^3 N=1 K=0 (two to four times the steps of its other cases, a lookup in every
# non-empty cell), so its own step constant and the lookup's come apart (without the 128^3 cases the
# PoCL fit put every Line Space step at its plain walk's: docs/fit.md).
CALIBRATION = (
    ("grid", "32", 0, 0), ("grid", "64", 0, 0), ("grid", "128", 0, 0),
    ("svo", "64", 0, 0), ("svo", "128", 0, 0), ("esvo", "64", 0, 0), ("esvo", "128", 0, 0),
    ("grid-ls", "32", 2, 0), ("grid-ls", "32", 2, 16), ("grid-ls", "64", 2, 0),
    ("svo-ls", "64", 2, 0), ("svo-ls", "64", 2, 16), ("esvo-ls", "64", 2, 0), ("esvo-ls", "64", 2, 16),
    ("grid-ls", "128", 1, 0), ("svo-ls", "128", 1, 0), ("esvo-ls", "128", 1, 0),
)
# Run again with LAUNCH_SCALE^2 times the rays, so the launch's fixed cost (shared by its rays)
# comes apart from a ray's: at one size the two are one column. On the development machine a
# launch cost 4-12 ms (two runs on each backend, 2026-12-02), 250-750 ns of each of 16,384 rays.
LAUNCH_CALIBRATION = (("grid", "64", 0, 0), ("esvo", "128", 0, 0))
LAUNCH_SCALE = 2
# Rounds of the calibration fitted together by default. One round's constants moved by tens of
# percent between runs (the lookup on PoCL from 1.8 ns to 0), and the auto choices with them: on the
# 2-core machine (2026-12-04) four rounds changed 17 of the 24 Line Space cells' choices of
# fit-thesis.toml against one round, and every changed choice traced as fast or faster (0.75-1.03 of
# the time, paired), with no plain cell changed (docs/fit.md). With DEFAULT_SIZES and the 128^3 N=1
# cases, 14 min 46 s for both backends there (llvmpipe about 10, PoCL about 5).
DEFAULT_ROUNDS = 4


def setup_arguments(sub) -> None:
    from lsbench import backends

    p = sub.add_parser(NAME, help=HELP, description=__doc__)
    p.add_argument("--backends", nargs="+", choices=list(backends.BACKENDS), default=list(backends.BACKENDS),
                   metavar="BACKEND", help=f"devices to calibrate (default: {', '.join(backends.BACKENDS)})")
    p.add_argument("--scenes", nargs="+", default=list(DEFAULT_SCENES), metavar="SCENE",
                   help=f"calibration scenes (default: {', '.join(DEFAULT_SCENES)})")
    p.add_argument("--size", type=checked_text(parse_size),
                   help="image size WxH (camera rays; default per backend: "
                        + ", ".join(f"{b} {s}" for b, s in DEFAULT_SIZES.items()) + ")")
    p.add_argument("--repeats", type=RUN_RULES["repeats"].flag, default=3, help="timed launches per case")
    p.add_argument("--rounds", type=RUN_RULES["repeats"].flag, default=DEFAULT_ROUNDS, metavar="R",
                   help="run the calibration cases R times over, one round after the other, and fit on all "
                        "of them (one round's constants moved by tens of percent between runs on a 2-core "
                        f"machine, and the choices with them: docs/fit.md; default {DEFAULT_ROUNDS})")
    p.add_argument("--out-dir", type=writable_folder, metavar="DIR",
                   help="where the constants go (default $LSBENCH_FIT_DIR or ~/.cache/lsbench/fit)")
    p.add_argument("--json", action="store_true", help="print the stored constants as JSON")
    p.add_argument("--check", metavar="RUN_DIR",
                   help="calibrate nothing: print the fit check of a run of scenarios/fit-check.toml or "
                        "fit-thesis.toml (each auto case beside the best swept setting under the same budget, "
                        "lsbench/model/check.py)")
    p.add_argument("--pairs", type=RUN_RULES["repeats"].flag, metavar="K",
                   help="with --check: rebuild each cell's auto setting and best swept setting (where they "
                        "differ) on this machine and trace them alternately K times, and add the median "
                        "auto/best ratio of the pairs with its quartiles")
    p.set_defaults(func=run)


def calibrate(backend: str, scenes, width: int, height: int, repeats: int, log=say, rounds: int = 1) -> dict:
    """Run the calibration cases on `backend`, all of them `rounds` times over, one round after the
    other, and fit the constants on every round's cases together; returns the file's contents
    (model/constants.py) with the fitted constants, each case, the fit's relative rms residual and
    the image size."""
    from lsbench.inputs.rays import make_rays
    from lsbench.inputs.scenario import Case, RunSettings
    from lsbench.inputs.scenes import load_scene
    from lsbench.model.constants import COLUMNS, design_row, fit_constants, steps_from_fit
    from lsbench.running.environment import record_env
    from lsbench.running.execute import execute

    env = record_env()
    rows, seconds, cases, device, simd_width = [], [], [], None, 1
    big = (width * LAUNCH_SCALE, height * LAUNCH_SCALE)
    runs = [(s, (width, height), c) for s in scenes for c in CALIBRATION] + [(s, big, c) for s in scenes
                                                                              for c in LAUNCH_CALIBRATION]
    loaded = (None, None)
    for round_, (scene_name, (w, h), (structure, resolution, n, k)) in itertools.product(range(1, rounds + 1), runs):
        if loaded != (scene_name, (w, h)):
            scene, loaded = load_scene(scene_name), (scene_name, (w, h))
            rays = make_rays("primary", scene, w, h)
        settings = RunSettings(width=w, height=h, repeats=repeats, warmup=1, embree_timing=False)
        case = Case(scene_name, structure, backend, resolution, n, k, "primary", w, h)
        rec = execute(case, settings, env, scene=scene, rays=rays)
        if rec["status"] != "ok" or rec.get("iterations_per_ray") is None:
            log(f"  {case.key}: left out ({rec['reason'] or rec.get('work_counters_error')})")
            continue
        device, simd_width = rec["device"], rec.get("simd_width_device") or 1
        per_ray = rec["trace_seconds"] / rec["ray_count"]
        work = (rec["iterations_per_ray"], rec["candidate_tests_per_ray"], rec["linespace_lookups_per_ray"])
        issued = (_issued(work[0], rec.get("simd_efficiency_steps_device")),
                  _issued(work[1], rec.get("simd_efficiency_tests_device")))
        rows.append(design_row(structure, rec["ray_count"], *issued, work[2]))
        seconds.append(per_ray)
        cases.append({"round": round_, "scene": scene_name, "structure": structure, "resolution": resolution, "ls_n": n,
                      "ls_min_candidates": k, "rays": rec["ray_count"],
                      "iterations_per_ray": work[0], "candidate_tests_per_ray": work[1],
                      "linespace_lookups_per_ray": work[2], "issued_iterations_per_ray": issued[0],
                      "issued_tests_per_ray": issued[1], "seconds_per_ray": per_ray})
        log(f"  {case.key}: {per_ray * 1e9:.1f} ns/ray, {work[0]:.1f} steps, {work[1]:.1f} tests "
            f"({issued[0]:.1f}, {issued[1]:.1f} issued by groups of {simd_width}), {work[2]:.1f} lookups")
    if len(rows) < len(COLUMNS):
        raise RuntimeError(f"{backend}: only {len(rows)} calibration cases ran, fewer than the "
                           f"{len(COLUMNS)} constants")
    coef, residual = fit_constants(rows, seconds)
    for case, row in zip(cases, rows):
        case["fitted_seconds_per_ray"] = float(sum(c * v for c, v in zip(coef, row)))
    c = dict(zip(COLUMNS, (float(v) for v in coef)))
    return {"device": device, "backend": backend, "driver": rec.get("driver"), "commit": env.get("commit"),
            "made": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            "launch": c["launch"], "ray": c["ray"], "step": steps_from_fit(c),
            "test": c["test"], "lookup": c["lookup"], "simd_width": simd_width, "residual": residual,
            "size": f"{width}x{height}", "cases": cases}


def _issued(mean: float, efficiency: float | None) -> float:
    """Lane-slots per ray that the device's SIMD groups issued for a counter: its mean over the
    record's SIMD efficiency at the device's width (profile/simd.py; the mean where there is none:
    width 1, unknown, or nothing counted)."""
    return mean / efficiency if efficiency else mean


def run(args) -> int:
    from pathlib import Path

    from lsbench.model.constants import STEPS, save_constants

    if args.check:
        return print_check(args.check, args.pairs or 0)
    if args.pairs:
        raise UsageError("--pairs: only with --check RUN_DIR")
    out = []
    for backend in args.backends:
        width, height = parse_size(args.size or DEFAULT_SIZES[backend])
        say(f"lsbench fit: {backend}, {(len(CALIBRATION) + len(LAUNCH_CALIBRATION)) * len(args.scenes)} "
            f"calibration cases at {width}x{height}" + (f", {args.rounds} rounds" if args.rounds > 1 else ""))
        data = calibrate(backend, args.scenes, width, height, args.repeats, rounds=args.rounds)
        path = save_constants(data, backend, data["device"], Path(args.out_dir) if args.out_dir else None)
        say(f"{backend} ({data['device']}): launch {data['launch'] * 1e3:.2f} ms, ray {data['ray'] * 1e9:.1f} ns, "
            f"step {'/'.join(STEPS)} " + "/".join(f"{data['step'][f] * 1e9:.2f}" for f in STEPS)
            + f" ns, test {data['test'] * 1e9:.2f} ns, lookup {data['lookup'] * 1e9:.2f} ns; "
            f"fit residual {100 * data['residual']:.0f} % rms; written {path}")
        out.append(data)
    if args.json:
        print(json.dumps(out, indent=1))
    return 0


def print_check(run_dir: str, pairs: int = 0) -> int:
    """The fit-check table of a run folder (with `pairs`: each cell's two settings rerun
    alternated, model/check.py pair_rows); exit 1 when it holds no auto case."""
    from lsbench.model.check import check_rows, check_table, pair_rows
    from lsbench.results.store import read_run

    try:
        _, records = read_run(run_dir)
    except FileNotFoundError as exc:
        raise UsageError(f"--check: {exc}") from None
    rows = check_rows(records)
    if not rows:
        say(f"{run_dir}: no auto case (run scenarios/fit-check.toml or fit-thesis.toml into it)")
        return 1
    if pairs:
        pair_rows(rows, pairs, log=say)
    for line in check_table(rows):
        say(line)
    return 0
