"""Arguments and parsers that several commands share, defined once (asv's common_args)."""
from __future__ import annotations

import argparse


class UsageError(ValueError):
    """A bad command-line value: `lsbench` prints the one-line message and exits 2."""


def say(*a, **k) -> None:
    print(*a, **k, flush=True)


def add_scenario_arguments(p: argparse.ArgumentParser) -> None:
    """SCENARIO and the run-folder flags of `run` and `gate`."""
    p.add_argument("scenario", help="scenario TOML file, e.g. scenarios/default.toml")
    p.add_argument("--out", help="run folder (default reports/<name>-<date>-<commit>); an existing one resumes")
    p.add_argument("--fresh", action="store_true", help="redo cases already in --out")
    p.add_argument("--heatmaps", action="store_true", help="write heatmaps for every case")
    p.add_argument("--memory-budget", type=float, metavar="MiB", help="host memory limit per case worker")


def add_case_arguments(p: argparse.ArgumentParser, size: str = "256x256") -> None:
    """One case named on the command line (`trace`, `stability`)."""
    from lsbench import backends

    p.add_argument("--scene", required=True, help="built-in name or mesh file")
    p.add_argument("--structure", required=True, choices=backends.structure_names())
    p.add_argument("--backend", required=True, choices=list(backends.BACKENDS))
    p.add_argument("--resolution", default="64", help="64 (cubic) or RxRyRz")
    p.add_argument("--ls-n", type=int, default=0, help="Line Space patches per face edge")
    p.add_argument("--ls-min-candidates", type=int, default=0,
                   help="only cells with more candidates get a Line Space")
    p.add_argument("--size", default=size, help="image size WxH for camera rays")
    p.add_argument("--rays", default="primary", help="ray set name or .npz file with origins/directions")
    p.add_argument("--repeats", type=int, default=5, help="timed launches")
    p.add_argument("--warmup", type=int, default=1, help="untimed launches before them")


def parse_size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
        if w < 1 or h < 1:
            raise ValueError
        return w, h
    except ValueError:
        raise UsageError(f"--size must look like 512x512, got {text!r}") from None


def parse_camera(text: str):
    """"ex,ey,ez:tx,ty,tz[:fov]" -> ((eye), (target), (up), fov)."""
    try:
        parts = text.split(":")
        eye = tuple(float(v) for v in parts[0].split(","))
        target = tuple(float(v) for v in parts[1].split(","))
        fov = float(parts[2]) if len(parts) > 2 else 60.0
        if len(eye) != 3 or len(target) != 3:
            raise ValueError
    except (ValueError, IndexError):
        raise UsageError(f"--camera must look like 'ex,ey,ez:tx,ty,tz[:fov]', got {text!r}") from None
    return (eye, target, (0.0, 1.0, 0.0), fov)


def case_from_args(args, camera=None):
    """The Case that `trace` / `stability` arguments name."""
    from lsbench.inputs.scenario import Case

    width, height = parse_size(args.size)
    return Case(args.scene, args.structure, args.backend, str(args.resolution), args.ls_n,
                args.ls_min_candidates, args.rays, width, height, camera)
