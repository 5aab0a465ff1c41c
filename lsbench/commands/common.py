"""Arguments and parsers that several commands share, defined once (asv's common_args).

Every flag's value is checked by its `type=` while parsing (the rules of inputs/checks.py, the
same ones a scenario's [run] keys use), so a bad value is one line naming the flag, the value and
what is allowed, exit 2, before anything runs."""
from __future__ import annotations

import argparse
from pathlib import Path

from lsbench.inputs.checks import (FOV, MAX_IMAGE_RAYS, RESOLUTION_OR_AUTO, BadValue, check_camera,
                                   check_image_size, integer, number, ray_param_text, resolve_ray_params,
                                   writable_folder)
from lsbench.inputs.scenario import LEAF_SIZE, LS_MIN_CANDIDATES_OR_AUTO, LS_N_OR_AUTO, RUN_RULES


class UsageError(BadValue):
    """A bad command-line value: `lsbench` prints the one-line message and exits 2."""


class Parser(argparse.ArgumentParser):
    """argparse whose errors are one line and exit 2, like every other bad input (argparse's own
    print the usage first)."""

    def error(self, message: str):
        self.exit(2, f"lsbench: error: {message} (see `{self.prog} --help`)\n")


def say(*a, **k) -> None:
    print(*a, **k, flush=True)


# compare / compare-commits: a slowdown or growth ratio (1.1 = 10 %; below 1 every case would
# regress) and the significance level of a one-sided test.
FACTOR = number(1)
ALPHA = number(0, 1, low_open=True, high_open=True)


def checked_text(parse):
    """argparse `type=` for a flag whose command parses the text itself (--size, --camera):
    `parse` checks it now, the text is kept as given."""
    def check(text: str) -> str:
        try:
            parse(text)
        except BadValue as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None
        return text
    return check


def writable_file(text: str) -> str:
    """argparse `type=` for an output file that is written after cases ran (--dump-hits, a
    speedtest's --out): checked by opening it for appending now, so a measured case is not lost to
    a failed write; a file that did not exist is removed again."""
    target = Path(text)
    try:
        existed = target.exists()
        with open(target, "ab"):
            pass
        if not existed:
            target.unlink()
    except OSError as exc:
        raise argparse.ArgumentTypeError(f"cannot write {target} ({exc.strerror or exc})") from None
    return text


def add_scenario_arguments(p: argparse.ArgumentParser) -> None:
    """SCENARIO and the run-folder flags of `run` and `gate`."""
    p.add_argument("scenario", help="scenario TOML file, e.g. scenarios/default.toml")
    p.add_argument("--out", type=writable_folder,
                   help="run folder (default reports/<name>-<date>-<commit>); an existing one resumes")
    p.add_argument("--fresh", action="store_true",
                   help="redo every case; the new records replace those in --out when the run finishes")
    p.add_argument("--keep-failed", action="store_true",
                   help="reuse failed records of --out instead of retrying those cases")
    p.add_argument("--heatmaps", action="store_true", help="write heatmaps for every case")
    p.add_argument("--memory-budget", type=RUN_RULES["memory_budget_mb"].flag, metavar="MiB",
                   help="host memory limit per case worker")
    add_budget_argument(p)
    cluster = p.add_argument_group("sweeps on a Ray cluster (pip install 'lsbench[cluster]'; docs/cluster.md)")
    cluster.add_argument("--cluster", type=cluster_address, metavar="ADDRESS",
                         help="run each case as a Ray task on the cluster at ADDRESS: auto, HOST:PORT, "
                              "ray://HOST:PORT, or local (a throw-away Ray on this machine)")
    cluster.add_argument("--cluster-resource", type=cluster_resource, action="append", default=[],
                         metavar="NAME[=N]", help="every case asks for N (default 1) of a custom resource "
                                                  "(ray start --resources): pins cases to the nodes that carry it")
    cluster.add_argument("--cluster-retries", type=CLUSTER_RETRIES.flag, default=2, metavar="N",
                         help="run a case again on another node this many times when its node dies (default 2)")


def add_budget_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument("--budget", type=RUN_RULES["budget_mib"].flag, metavar="MiB",
                   help="device-memory budget of each structure: a case whose structure needs more fails; "
                        "\"auto\" settings are chosen under it (docs/fit.md). Not the host --memory-budget")


CLUSTER_RETRIES = integer(0)


def cluster_address(text: str) -> str:
    """argparse `type=` for --cluster: the address as ray.init takes it."""
    host, _, port = text.removeprefix("ray://").rpartition(":")
    if text in ("auto", "local") or (host and port.isdigit() and 0 < int(port) < 65536):
        return text
    raise argparse.ArgumentTypeError(f"{text} is not a Ray address: auto, local, HOST:PORT or ray://HOST:PORT")


def cluster_resource(text: str) -> tuple[str, float]:
    """argparse `type=` for --cluster-resource: NAME or NAME=N, N a number > 0."""
    name, eq, amount = text.partition("=")
    try:
        value = float(amount) if eq else 1.0
    except ValueError:
        value = 0.0
    if not name or name in ("CPU", "GPU", "memory") or not (value > 0 and value < float("inf")):
        raise argparse.ArgumentTypeError(f"{text} is not NAME[=N]: a custom resource of the nodes "
                                         "(not CPU, GPU or memory) and an amount > 0")
    return name, value


def add_case_arguments(p: argparse.ArgumentParser, size: str = "256x256") -> None:
    """One case named on the command line (`trace`, `stability`)."""
    from lsbench import backends

    p.add_argument("--scene", required=True, help="built-in name or mesh file")
    p.add_argument("--structure", required=True, choices=backends.structure_names())
    p.add_argument("--backend", required=True, choices=list(backends.BACKENDS))
    p.add_argument("--resolution", type=RESOLUTION_OR_AUTO.flag, default="64",
                   help="64 (cubic), RxRyRz, or auto (the cost model's choice under --budget)")
    p.add_argument("--ls-n", type=LS_N_OR_AUTO.flag, default=0, help="Line Space patches per face edge, or auto")
    p.add_argument("--ls-min-candidates", type=LS_MIN_CANDIDATES_OR_AUTO.flag, default=0,
                   help="only cells with more candidates get a Line Space; or auto")
    p.add_argument("--leaf-size", type=LEAF_SIZE.flag, default=0,
                   help="bvh, bvh-ls: most triangles per leaf (0: the structure's default)")
    add_budget_argument(p)
    p.add_argument("--size", type=checked_text(parse_size), default=size,
                   help=f"image size WxH for camera rays (W*H <= {MAX_IMAGE_RAYS})")
    p.add_argument("--rays", default="primary",
                   help="ray set (primary, adversarial, shadow, ao, diffuse, incoherent) or .npz file "
                        "with origins/directions")
    p.add_argument("--ray-param", type=ray_param_text, action="append", default=[], metavar="KEY=VALUE",
                   help="a parameter of the ray set, VALUE as in TOML (samples=4, light=[0,5,0]); repeatable")
    p.add_argument("--repeats", type=RUN_RULES["repeats"].flag, default=5, help="timed launches")
    p.add_argument("--warmup", type=RUN_RULES["warmup"].flag, default=1, help="untimed launches before them")


def parse_size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
        if w < 1 or h < 1:
            raise ValueError
    except ValueError:
        raise UsageError(f"{text} is not WxH with W, H >= 1, e.g. 512x512") from None
    try:
        check_image_size(w, h)
    except BadValue as exc:
        raise UsageError(str(exc)) from None
    return w, h


def parse_camera(text: str):
    """"ex,ey,ez:tx,ty,tz[:fov]" -> ((eye), (target), (up), fov)."""
    try:
        parts = text.split(":")
        eye = tuple(float(v) for v in parts[0].split(","))
        target = tuple(float(v) for v in parts[1].split(","))
        fov = float(parts[2]) if len(parts) > 2 else 60.0
        if len(eye) != 3 or len(target) != 3 or len(parts) > 3:
            raise ValueError
    except (ValueError, IndexError):
        raise UsageError(f"{text} is not 'ex,ey,ez:tx,ty,tz[:fov]' (eye and target, "
                         f"fov {FOV.allowed})") from None
    up = (0.0, 1.0, 0.0)
    try:
        check_camera("", eye, target, up, fov)
    except BadValue as exc:
        raise UsageError(f"{text}: {exc}") from None
    return (eye, target, up, fov)


def case_from_args(args, camera=None):
    """The Case that `trace` / `stability` arguments name."""
    from lsbench.inputs.scenario import Case

    width, height = parse_size(args.size)
    return Case(args.scene, args.structure, args.backend, str(args.resolution), args.ls_n,
                args.ls_min_candidates, args.rays, width, height, camera, ray_params_from_args(args),
                args.leaf_size)


def ray_params_from_args(args) -> tuple:
    """The --ray-param values checked by the ray set's rules (one line, exit 2, when one is bad)."""
    try:
        return resolve_ray_params("--ray-param: ", args.rays, dict(args.ray_param))
    except BadValue as exc:
        raise UsageError(str(exc)) from None
