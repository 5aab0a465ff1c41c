"""Scenarios: declarative runs in TOML (scenes x structures x backends x resolutions x N).

    name = "ci"
    [run]                    # settings shared by every case (all optional)
    width = 64               # primary-ray image size
    height = 64
    gpu_width = 1920         # image size used instead when the devices are GPUs
    gpu_height = 1080
    rays = "primary"         # ray set name or .npz path (inputs/rays.py lists the sets)
    ray_params = { seed = 1 } # the ray set's parameters (inputs/checks.py RAY_PARAMS)
    repeats = 5              # timed launches after `warmup` untimed ones
    warmup = 1
    rel_tol = 1e-4           # distance tolerance of agree and tie (relative)
    max_unexplained = 0      # the gate: most unexplained disagreements a case may have
    min_agreement = 0.9999   # optional extra gate check: (agree + tie) / rays per case
    timeout_seconds = 600    # per case, in its worker process
    budget_mib = 256         # device-memory budget of each case's structure (MiB): a built
                             # structure over it fails its case; "auto" settings are chosen under it
    heatmaps = false         # write per-case heatmaps (profiling kernels)
    embree_timing = true     # record Embree's rays/s on the same rays (the CPU reference)
    [[cases]]                # each block is a cross product
    scenes = ["atrium", "$SCENES/sponza.ply"]
    structures = ["grid"]
    backends = ["glsl", "opencl"]
    resolutions = [64, "64x32x16"]
    ls_n = [0]               # Line Space N (0 = none)
    ls_min_candidates = 0    # or a list: only cells with more candidates get a Line Space
    leaf_size = [4, 8]       # bvh, bvh-ls: most triangles per leaf (0 = the structure's default)
                             # resolutions, ls_n, ls_min_candidates may be (or list) "auto": the
                             # cost model picks the cheapest under the budget (docs/fit.md)
    budget_mib = [64, 256]   # optional: this block's budget(s) instead of [run]'s
    rays = ["shadow", "ao"]  # optional: this block's ray sets instead of [run]'s
    ray_params = { samples = 2 }  # optional: their parameters (default: [run]'s when the block
                             # names no rays, else none); every listed set must take each key
    camera = { eye = [1100, 180, -40], target = [-900, 420, 40], up = [0, 1, 0], fov = 65 }
                             # optional; default: the scene's own camera or one from its bounds

`$SCENES` is the real-scene folder: env LSBENCH_SCENES, else ../shared/scenes beside the repo.

Every key and value is checked when the file is read, before any case runs (RUN_RULES and the
[[cases]] rules below, in words from inputs/checks.py): an unknown key (`backend =`, a `[Run]`
table) is an error with a did-you-mean, as is a value of the wrong TOML type (`repeats = "3"`,
`width = 32.5`, `heatmaps = 1`) or out of range (`repeats = 0`, `min_agreement = 1.5`,
`backends = []`, a camera fov of 180). Key by key: width/height/gpu_* integers >= 1 with
width*height <= 2^26 rays; repeats >= 1, warmup >= 0; rel_tol finite >= 0; max_unexplained an
integer >= 0; min_agreement in [0, 1]; timeout_seconds, memory_budget_mb and budget_mib > 0; heatmaps, embree_timing true/false; scenes,
structures, backends, resolutions, ls_n, ls_min_candidates, leaf_size, budget_mib, rays one value or a
non-empty list (resolutions, ls_n, ls_min_candidates also "auto"; leaf_size 0 or one of 1, 2, 4, ...,
128, 255; bvh and bvh-ls ignore resolutions: a block of them only needs none, and a mixed block gives
them one case, at its first resolution);
camera eye/target/up 3 finite numbers each, fov in (0, 180) degrees; ray_params a table whose keys
the ray set takes, each value by its rule (e.g. samples an integer >= 1, light 3 finite numbers).
"""
from __future__ import annotations

import dataclasses
import os
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from lsbench.inputs.checks import (AUTO, BUDGET, FLAG, RESOLUTION_OR_AUTO, TEXT, BadValue, Rule, check_camera,
                                   check_image_size, check_keys, check_list, integer, leaf_size_rule, number,
                                   one_of, or_auto,
                                   resolve_ray_params, show_typed)
from lsbench.inputs.rays import RAY_SETS
from lsbench.paths import scenes_dir, shipped_scenario



class ScenarioError(ValueError):
    """A scenario file that cannot be run: one-line message."""


def expand_scene(spec: str) -> str:
    return spec.replace("$SCENES", str(scenes_dir()))


@dataclass(frozen=True)
class RunSettings:
    width: int = 64
    height: int = 64
    gpu_width: int | None = None
    gpu_height: int | None = None
    rays: str = "primary"
    ray_params: dict | None = None  # the ray set's parameters (checks.RAY_PARAMS); None: the defaults
    repeats: int = 5
    warmup: int = 1
    rel_tol: float = 1e-4
    max_unexplained: int = 0  # lsbench.oracle.classifier: a rate would hide real misses
    min_agreement: float | None = None  # checked only where a scenario states one
    timeout_seconds: float = 600.0
    heatmaps: bool = False
    memory_budget_mb: float | None = None  # host RLIMIT_AS of each case worker (runner.py)
    budget_mib: float | None = None  # device-memory budget of each case's structure (execute.py)
    embree_timing: bool = True  # also time Embree (CPU, all cores) on the same rays


def input_label(spec: str) -> str:
    """How a scene or ray file is named in a case key: a name without a folder or suffix (a
    built-in scene, a ray set) as it is; a file by its path: "$SCENES/..." under the real-scene
    folder, relative to the working folder inside it, else absolute."""
    if "/" not in spec and "\\" not in spec and not Path(spec).suffix:
        return spec
    path = Path(os.path.abspath(spec))
    for base, prefix in ((Path(os.path.abspath(scenes_dir())), "$SCENES/"), (Path(os.path.abspath(".")), "")):
        if path.is_relative_to(base):
            return prefix + path.relative_to(base).as_posix()
    return path.as_posix()


def _exact(value) -> str:
    """A number as its shortest exact text (1100, 0.1, 1e-07): two cameras that differ in the
    last digit are two cases."""
    text = repr(float(value))
    return text[:-2] if text.endswith(".0") else text


def _param_text(value) -> str:
    if isinstance(value, (tuple, list)):
        return "[" + ",".join(_exact(v) for v in value) + "]"
    return str(value) if isinstance(value, int) else _exact(value)


@dataclass(frozen=True)
class Case:
    scene: str  # built-in name or path
    structure: str
    backend: str
    resolution: str  # "64" or "64x32x16"
    ls_n: int | str = 0  # or "auto" (as resolution and ls_min_candidates)
    ls_min_candidates: int | str = 0
    rays: str = "primary"
    width: int = 64
    height: int = 64
    camera: tuple | None = None  # ((eye), (target), (up), fov_deg) or None for the scene default
    ray_params: tuple = ()  # sorted (key, value) pairs, defaults filled in (checks.resolve_ray_params)
    leaf_size: int = 0  # bvh, bvh-ls: most triangles per leaf (0: the structure's default)
    budget_mib: float | None = None  # the block's device-memory budget; None: the run's (RunSettings)

    @property
    def auto(self) -> tuple[str, ...]:
        """The parameters the cost model picks for this case (those that are "auto" and that the
        structure takes), in BuildParams order; () for a case built as given."""
        from lsbench.backends import structure_info

        try:
            info = structure_info(self.structure)
        except ValueError:
            return ()
        # a BVH has no grid resolution, and the cost model knows the grid and octree families only
        named = (() if info.leaf_size else (("resolution", self.resolution),)) + (
            (("ls_n", self.ls_n), ("ls_min_candidates", self.ls_min_candidates)) if info.line_space else ())
        return tuple(name for name, value in named if value == AUTO)

    @property
    def query(self) -> str:
        """What its rays ask: "any" hit (shadow, ao) or the "closest" one (inputs/rays.py)."""
        from lsbench.inputs.rays import query_of

        return query_of(self.rays)

    def build_params(self):
        """The BuildParams this case builds with, as the recipes take them: a Line Space
        structure always has one (N = 0 builds N = 1, backends/structures/grid_ls.py and
        octree_ls.py), the others ignore N and the candidate threshold."""
        from lsbench.backends import BuildParams, structure_info
        from lsbench.backends.structures.base import parse_resolution

        if self.auto:
            raise ValueError(f"{', '.join(self.auto)} = \"auto\": chosen when the case runs (model/cost.py)")
        info = structure_info(self.structure)
        line_space = info.line_space
        return BuildParams(resolution=parse_resolution(self.resolution),
                           ls_n=(self.ls_n or 1) if line_space else 0,
                           ls_min_candidates=self.ls_min_candidates if line_space else 0,
                           leaf_size=(self.leaf_size or info.leaf_size) if info.leaf_size else 0)

    @property
    def key(self) -> str:
        """Identity of a case across runs and commits (what resume and compare match on): the
        scene and ray file by path (never only the file name), the ray set, image size and
        camera, structure, backend and every build parameter as built (resolution "64" and
        "64x64x64" are one case), and a generated ray set's parameters with their defaults filled
        in ("shadow(samples=1,seed=0)"). The files' contents are the records' scene_hash / rays_hash."""
        from lsbench.backends.structures.base import format_resolution

        try:
            # "auto" stays "auto" (the chosen setting is in the record); the rest as built
            params = dataclasses.replace(self, **{name: 1 for name in self.auto}).build_params()
            res, n, k = format_resolution(params.resolution), params.ls_n, params.ls_min_candidates
            res, n, k = (AUTO if name in self.auto else value
                         for name, value in zip(("resolution", "ls_n", "ls_min_candidates"), (res, n, k)))
            leaf = params.leaf_size
        except ValueError:  # a resolution or structure that does not parse: the case fails when run
            res, n, k = self.resolution, self.ls_n, self.ls_min_candidates
            leaf = self.leaf_size
        rays = input_label(self.rays)
        if self.ray_params:
            rays += "(" + ",".join(f"{k}={_param_text(v)}" for k, v in self.ray_params) + ")"
        rays += f"@{self.width}x{self.height}"
        if self.camera is not None:
            eye, target, up, fov = self.camera
            rays += "@cam(" + ",".join(_exact(v) for v in (*eye, *target, *up, fov)) + ")"
        # The leaf size only for the structures that have one, so the other cases keep their keys.
        leaves = f"|l{leaf}" if leaf else ""
        budget = f"|b{_exact(self.budget_mib)}" if self.budget_mib is not None else ""
        return (f"{input_label(self.scene)}|{rays}|{self.structure}|{self.backend}|r{res}|n{n}|k{k}"
                f"{leaves}{budget}")

    def camera_object(self):
        from lsbench.inputs.scene import Camera

        if self.camera is None:
            return None
        eye, target, up, fov = self.camera
        return Camera(eye=tuple(eye), target=tuple(target), up=tuple(up), fov_deg=float(fov))


@dataclass
class Scenario:
    name: str
    path: str
    settings: RunSettings
    cases: list[Case] = field(default_factory=list)


# What each [run] setting allows (inputs/checks.py); the flags that set the same values
# (--repeats, --rel-tol, --memory-budget, ...) use these rules too. Every RunSettings field has
# one (tests/test_input_checks.py holds them together).
RUN_RULES: dict[str, Rule] = {
    "width": integer(1), "height": integer(1), "gpu_width": integer(1), "gpu_height": integer(1),
    "rays": Rule(f"a ray set ({', '.join(sorted(RAY_SETS))}) or a path to a .npz file",
                 lambda v: isinstance(v, str) and (v in RAY_SETS or v.lower().endswith(".npz")),
                 names=tuple(sorted(RAY_SETS)), noun="ray set"),
    # the table's keys and values are checked against the ray set's own rules (checks.RAY_PARAMS)
    "ray_params": Rule("a table { key = value, ... }", lambda v: isinstance(v, dict)),
    "repeats": integer(1), "warmup": integer(0),
    "rel_tol": number(0), "max_unexplained": integer(0), "min_agreement": number(0, 1),
    "timeout_seconds": number(0, low_open=True), "memory_budget_mb": number(0, low_open=True),
    "budget_mib": BUDGET,
    "heatmaps": FLAG, "embree_timing": FLAG,
}

# What each key of a [[cases]] block allows: one value or a non-empty list of them (camera
# aside). Structures and backends come from their catalogues, so these are built on use.
REQUIRED_CASE_KEYS = ("scenes", "structures", "resolutions")
CASE_KEYS = (*REQUIRED_CASE_KEYS, "backends", "ls_n", "ls_min_candidates", "leaf_size", "budget_mib", "camera",
             "rays", "ray_params")
LS_N = integer(0)  # 0 = the structure's own default (a Line Space structure builds N = 1)
LS_MIN_CANDIDATES = integer(0)
LS_N_OR_AUTO = or_auto(LS_N)
LS_MIN_CANDIDATES_OR_AUTO = or_auto(LS_MIN_CANDIDATES)
LEAF_SIZE = leaf_size_rule()
CAMERA_KEYS = ("eye", "target", "up", "fov")
TOP_KEYS = ("name", "run", "cases")


def _camera(table, where: str):
    if not isinstance(table, dict):
        raise BadValue(f"{where}camera = {show_typed(table)} is not a table "
                       "{ eye = [x, y, z], target = [x, y, z], up = [x, y, z], fov = degrees }")
    check_keys(f"{where}camera: ", table, CAMERA_KEYS)
    for key in ("eye", "target"):
        if key not in table:
            raise BadValue(f"{where}camera has no {key}; it needs eye = [x, y, z] and "
                           "target = [x, y, z] (up and fov are optional)")
    eye, target = table["eye"], table["target"]
    up, fov = table.get("up", [0.0, 1.0, 0.0]), table.get("fov", 60.0)
    check_camera(f"{where}camera.", eye, target, up, fov)
    return (tuple(map(float, eye)), tuple(map(float, target)), tuple(map(float, up)), float(fov))


def _settings(run, where: str) -> RunSettings:
    if not isinstance(run, dict):
        raise BadValue(f"run = {show_typed(run)} is not a table: write the settings under [run]")
    check_keys(where, run, [f.name for f in dataclasses.fields(RunSettings)])
    for key, value in run.items():
        if key in RUN_RULES:
            RUN_RULES[key].check(f"{where}{key}", value)
    resolve_ray_params(where, run.get("rays", "primary"), run.get("ray_params", {}))
    settings = RunSettings(**run)
    if (settings.gpu_width is None) != (settings.gpu_height is None):
        raise BadValue(f"{where}gpu_width and gpu_height go together: give both or neither")
    for w, h in (("width", "height"), ("gpu_width", "gpu_height")):
        if getattr(settings, w) is not None:
            try:
                check_image_size(getattr(settings, w), getattr(settings, h))
            except BadValue as exc:
                raise BadValue(f"{where}{w} x {h} = {exc}") from None
    return settings


def _takes_no_resolution(name) -> bool:
    """Structures with a leaf size (the BVHs) build no grid, so a resolution means nothing to them."""
    from lsbench.backends import STRUCTURES

    return name in STRUCTURES and bool(STRUCTURES[name].leaf_size)


def _block_cases(block, where: str, settings: RunSettings, width: int, height: int) -> list[Case]:
    """The cases of one [[cases]] block: the cross product of its lists."""
    from lsbench.backends import BACKENDS, structure_info, structure_names

    if not isinstance(block, dict):
        raise BadValue(f"{where}{show_typed(block)} is not a table: write each block under [[cases]]")
    check_keys(where, block, CASE_KEYS)
    missing = [k for k in REQUIRED_CASE_KEYS if k not in block]
    if missing == ["resolutions"] and isinstance(block.get("structures"), (list, str)) and all(
            _takes_no_resolution(s) for s in ([block["structures"]] if isinstance(block["structures"], str)
                                              else block["structures"])):
        missing = []  # a block of BVHs only: they have no grid resolution
    if missing:
        raise BadValue(f"{where}missing {', '.join(missing)} (needed: {', '.join(REQUIRED_CASE_KEYS)})")
    scenes = [expand_scene(s) for s in check_list(f"{where}scenes", block["scenes"], TEXT)]
    names = check_list(f"{where}structures", block["structures"], one_of(structure_names(), "structure"))
    backs = check_list(f"{where}backends", block.get("backends", list(BACKENDS)), one_of(BACKENDS, "backend"))
    resolutions = check_list(f"{where}resolutions", block.get("resolutions", ["1"]), RESOLUTION_OR_AUTO)
    ns = check_list(f"{where}ls_n", block.get("ls_n", [2]), LS_N_OR_AUTO)  # N for Line Space structures
    ks = check_list(f"{where}ls_min_candidates", block.get("ls_min_candidates", 0), LS_MIN_CANDIDATES_OR_AUTO)
    leaf_sizes = check_list(f"{where}leaf_size", block.get("leaf_size", 0), LEAF_SIZE)  # BVHs only
    budgets = check_list(f"{where}budget_mib", block["budget_mib"], BUDGET) if "budget_mib" in block else [None]
    camera = _camera(block["camera"], where) if "camera" in block else None
    if "rays" in block:
        ray_sets = check_list(f"{where}rays", block["rays"], RUN_RULES["rays"])
        params = block.get("ray_params", {})
    else:
        ray_sets, params = [settings.rays], block.get("ray_params", settings.ray_params or {})
    ray_params = {name: resolve_ray_params(where, name, params) for name in ray_sets}
    cases = []
    for scene in scenes:
        for rays in ray_sets:
            for s in names:
                for b in backs:
                    # A BVH ignores the resolution: one case, not one per resolution of the block.
                    for r in (resolutions[:1] if _takes_no_resolution(s) else resolutions):
                        # A Line Space N only means something for Line Space structures.
                        line_space = structure_info(s).line_space
                        for n in (ns if line_space else [0]):
                            for k in (ks if line_space else [0]):
                                for leaf in (leaf_sizes if structure_info(s).leaf_size else [0]):
                                    for budget in budgets:
                                        cases.append(Case(scene, s, b, str(r), n, k, rays, width, height,
                                                          camera, ray_params[rays], leaf_size=leaf,
                                                          budget_mib=None if budget is None else float(budget)))
    return cases


def load_scenario(path: str, gpu: bool = False) -> Scenario:
    """Read and check a scenario: an unknown key, a value of the wrong type or out of range is a
    ScenarioError naming the file, the key, the value and what is allowed, before any case runs."""
    p = Path(path)
    if not p.is_file() and shipped_scenario(str(path)) is not None:
        p = shipped_scenario(str(path))  # a shipped scenario by name: `lsbench gate ci`
    if not p.is_file():
        raise ScenarioError(f"scenario file not found: {path}")
    try:
        data = tomllib.loads(p.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ScenarioError(f"{path}: not valid TOML ({exc})") from None
    try:
        check_keys("top level: ", data, TOP_KEYS)
        name = TEXT.check("name", data.get("name", p.stem))
        settings = _settings(data.get("run", {}), "[run] ")
        width, height = settings.width, settings.height
        if gpu and settings.gpu_width:
            width, height = settings.gpu_width, settings.gpu_height
        blocks = data.get("cases")
        if blocks is None:
            raise BadValue("no [[cases]] blocks")
        if not isinstance(blocks, list) or not blocks:
            raise BadValue(f"cases = {show_typed(blocks)} is not a non-empty array of tables: "
                           "write each block under [[cases]]")
        cases: list[Case] = []
        for i, block in enumerate(blocks):
            cases += _block_cases(block, f"[[cases]] #{i + 1}: ", settings, width, height)
    except BadValue as exc:
        raise ScenarioError(f"{path}: {exc}") from None
    seen, unique = set(), []
    for c in cases:
        if c.key not in seen:
            seen.add(c.key)
            unique.append(c)
    return Scenario(name, str(p), settings, unique)
