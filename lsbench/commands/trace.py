"""`lsbench trace --scene S --structure X --backend B`: build and trace one case, print its record."""
from __future__ import annotations

import json

from lsbench.commands.common import add_case_arguments, case_from_args, checked_text, parse_camera
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
    t.add_argument("--dump-hits", metavar="FILE.npz", help="write rays and hits (and Embree's) to FILE.npz")
    t.add_argument("--heatmaps", type=writable_folder, metavar="DIR",
                   help="write work/clock heatmaps (EXR + PNG) to DIR")
    t.set_defaults(func=run)


def run(args) -> int:
    from lsbench.inputs.rays import make_rays
    from lsbench.inputs.scenario import RunSettings
    from lsbench.inputs.scenes import load_scene
    from lsbench.running.environment import record_env
    from lsbench.running.execute import execute
    from lsbench.running.runner import summary_table

    camera = parse_camera(args.camera) if args.camera else None
    case = case_from_args(args, camera)
    scene = load_scene(args.scene)  # bad input fails here, before anything looks like a result
    rays = make_rays(args.rays, scene, case.width, case.height, case.camera_object())
    settings = RunSettings(width=case.width, height=case.height, rays=args.rays, repeats=args.repeats,
                           warmup=args.warmup, rel_tol=args.rel_tol)
    rec = execute(case, settings, record_env(), dump_hits=args.dump_hits, heatmap_dir=args.heatmaps,
                  scene=scene, rays=rays)
    if args.json:
        print(json.dumps(rec, default=str))
    else:
        print(summary_table([rec]))
    return 0 if rec["status"] == "ok" else 1
