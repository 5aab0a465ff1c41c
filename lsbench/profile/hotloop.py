"""One case's trace kernel in a loop, for profilers and for A/B runs on a loaded machine
(docs/profiles.md):

    python -m lsbench.profile.hotloop SCENE STRUCTURE BACKEND RES [--ls-n N] [--rays SET]
        [--size WxH] [--camera ex,ey,ez:tx,ty,tz[:fov]] (--seconds S | --cpu-repeats K)

--seconds S: build, then backends.trace() for S seconds (run it under `perf record -g`; the build
is in the profile too, so profile long enough). --cpu-repeats K: CPU seconds of this process per
trace launch (all its threads: `time.process_time()` around one backends.time_trace launch) and
Embree's on the same rays, medians of K, printed as one JSON line. CPU seconds barely move with
other load on the machine, where wall-clock ratios swing by 2x; compare them between two trees
run alternately (PYTHONPATH=TREE), not with wall-clock figures.
"""
from __future__ import annotations

import argparse
import json
import statistics
import time


def case_arguments(prog: str, doc: str, size: str = "256x256") -> argparse.ArgumentParser:
    """The arguments naming one case, shared by this tool and lsbench.profile.ab."""
    p = argparse.ArgumentParser(prog=prog, description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scene")
    p.add_argument("structure")
    p.add_argument("backend")
    p.add_argument("resolution", type=int)
    p.add_argument("--ls-n", type=int, default=0)
    p.add_argument("--rays", default="primary")
    p.add_argument("--size", default=size)
    p.add_argument("--camera", help="default: the scene's own")
    return p


def load_case(args):
    """(scene, rays, device, build) of the parsed case arguments; build(leaf_size=0) builds it."""
    from lsbench import backends
    from lsbench.backends import BuildParams
    from lsbench.commands.common import parse_camera, parse_size
    from lsbench.inputs.rays import make_rays
    from lsbench.inputs.scene import Camera
    from lsbench.inputs.scenes import load_scene

    scene = load_scene(args.scene)
    width, height = parse_size(args.size)
    camera = Camera(*parse_camera(args.camera)) if args.camera else None
    rays = make_rays(args.rays, scene, width, height, camera, ())
    device = backends.get_device(args.backend)

    def build(leaf_size: int = 0):
        return backends.build(device, args.structure, scene, BuildParams(
            resolution=(args.resolution,) * 3, ls_n=args.ls_n, leaf_size=leaf_size))
    return scene, rays, device, build


def main(argv=None) -> None:
    from lsbench import backends
    from lsbench.oracle.embree import embree_timer

    p = case_arguments("python -m lsbench.profile.hotloop", __doc__)
    what = p.add_mutually_exclusive_group(required=True)
    what.add_argument("--seconds", type=float)
    what.add_argument("--cpu-repeats", type=int)
    args = p.parse_args(argv)
    scene, rays, _, build = load_case(args)
    built = build()
    label = f"{args.structure} {args.backend} r{args.resolution}" + (f" N{args.ls_n}" if args.ls_n else "")
    if args.seconds is not None:
        backends.trace(built, rays)
        t0, launches = time.perf_counter(), 0
        while time.perf_counter() - t0 < args.seconds:
            backends.trace(built, rays)
            launches += 1
        wall = time.perf_counter() - t0
        print(f"{label} {args.rays}: {launches} traces, {launches * rays.count / wall / 1e6:.3f} Mrays/s wall")
    else:
        backends.time_trace(built, rays, 1, 1)
        timer = embree_timer(scene, rays)
        ours, embree = [], []
        for _ in range(max(args.cpu_repeats, 1)):
            c0 = time.process_time()
            backends.time_trace(built, rays, 0, 1)
            ours.append(time.process_time() - c0)
            c0 = time.process_time()
            timer()
            embree.append(time.process_time() - c0)
        o, e = statistics.median(ours), statistics.median(embree)
        print(json.dumps({"case": f"{label} {args.rays}", "cpu_seconds": o, "embree_cpu_seconds": e,
                          "x_embree_cpu": e / o if o > 0 else None,
                          "mrays_per_cpu_second": rays.count / o / 1e6 if o > 0 else None}))
    built.release()


if __name__ == "__main__":
    main()
