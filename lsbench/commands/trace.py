"""`lsbench trace --scene S --structure X --backend B`: build and trace one case, print its record."""
from __future__ import annotations

import time

from lsbench.commands.common import add_case_arguments, case_from_args, checked_text, parse_camera, writable_file
from lsbench.inputs.checks import writable_folder
from lsbench.inputs.scenario import RUN_RULES

NAME = "trace"
HELP = "build and trace one case, print its record"


def setup_arguments(sub) -> None:
    t = sub.add_parser(NAME, help=HELP)
    add_case_arguments(t)
    t.add_argument("--camera", type=checked_text(parse_camera),
                   help="eye and target 'ex,ey,ez:tx,ty,tz[:fov]' (default: the scene's)")
    t.add_argument("--rel-tol", type=RUN_RULES["rel_tol"].flag, default=1e-4,
                   help="relative distance tolerance")
    t.add_argument("--json", action="store_true", help="print the record as one JSON object")
    t.add_argument("--dump-hits", type=writable_npz, metavar="FILE.npz",
                   help="write rays and hits (and Embree's) to FILE.npz")
    t.add_argument("--heatmaps", type=writable_folder, metavar="DIR",
                   help="write work/clock heatmaps (EXR + PNG) to DIR")
    t.set_defaults(func=run)


def writable_npz(text: str) -> str:
    """argparse `type=` for --dump-hits: the file must be writable before the case runs, or a
    failed write after tracing would turn a measured case into a failed record."""
    writable_file(text if text.endswith(".npz") else text + ".npz")  # np.savez adds .npz
    return text


def run(args) -> int:
    from lsbench.inputs.rays import make_rays
    from lsbench.inputs.scenario import RunSettings
    from lsbench.inputs.scenes import load_scene
    from lsbench.results.store import encode_record
    from lsbench.running.environment import record_env
    from lsbench.running.execute import execute
    from lsbench.running.runner import summary_table

    camera = parse_camera(args.camera) if args.camera else None
    case = case_from_args(args, camera)
    scene = load_scene(args.scene)  # bad input fails here, before anything looks like a result
    rays = make_rays(args.rays, scene, case.width, case.height, case.camera_object(), case.ray_params)
    settings = RunSettings(width=case.width, height=case.height, rays=args.rays,
                           ray_params=dict(case.ray_params), repeats=args.repeats,
                           warmup=args.warmup, rel_tol=args.rel_tol, budget_mib=args.budget)
    t0 = time.perf_counter()
    rec = execute(case, settings, record_env(), dump_hits=args.dump_hits, heatmap_dir=args.heatmaps,
                  scene=scene, rays=rays)
    rec["wall_seconds"] = time.perf_counter() - t0
    if args.json:
        print(encode_record(rec), end="")
    else:
        print(summary_table([rec]))
    return 0 if rec["status"] == "ok" else 1
