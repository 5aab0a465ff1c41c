"""Scenarios: declarative runs in TOML (scenes x structures x backends x resolutions x N).

    name = "ci"
    [run]                    # settings shared by every case (all optional)
    width = 64               # primary-ray image size
    height = 64
    gpu_width = 1920         # image size used instead when the devices are GPUs
    gpu_height = 1080
    rays = "primary"         # ray set name or .npz path
    repeats = 5              # timed launches after `warmup` untimed ones
    warmup = 1
    rel_tol = 1e-4           # tie tolerance for distances (relative)
    min_agreement = 0.9999   # the gate's threshold per case
    timeout_seconds = 600    # per case, in its worker process
    heatmaps = false         # write per-case heatmaps (profiling kernels)
    embree_timing = true     # record Embree's rays/s on the same rays (the CPU reference)
    [[cases]]                # each block is a cross product
    scenes = ["atrium", "$SCENES/sponza.ply"]
    structures = ["grid"]
    backends = ["glsl", "opencl"]
    resolutions = [64, "64x32x16"]
    ls_n = [0]               # Line Space N (0 = none)
    ls_min_candidates = 0    # or a list: only cells with more candidates get a Line Space
    camera = { eye = [1100, 180, -40], target = [-900, 420, 40], up = [0, 1, 0], fov = 65 }
                             # optional; default: the scene's own camera or one from its bounds

`$SCENES` is the real-scene folder: env LSBENCH_SCENES, else ../shared/scenes beside the repo.
"""
from __future__ import annotations

import dataclasses
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

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
    repeats: int = 5
    warmup: int = 1
    rel_tol: float = 1e-4
    min_agreement: float = 0.9999
    timeout_seconds: float = 600.0
    heatmaps: bool = False
    memory_budget_mb: float | None = None
    embree_timing: bool = True  # also time Embree (CPU, all cores) on the same rays


@dataclass(frozen=True)
class Case:
    scene: str  # built-in name or path
    structure: str
    backend: str
    resolution: str  # "64" or "64x32x16"
    ls_n: int = 0
    ls_min_candidates: int = 0
    rays: str = "primary"
    width: int = 64
    height: int = 64
    camera: tuple | None = None  # ((eye), (target), (up), fov_deg) or None for the scene default

    @property
    def key(self) -> str:
        """Stable identity of a case across runs and commits (what resume and compare match on)."""
        scene = Path(self.scene).name if ("/" in self.scene or "\\" in self.scene) else self.scene
        rays = f"{self.rays}@{self.width}x{self.height}"
        if self.camera is not None:
            eye, target, up, fov = self.camera
            rays += "@cam(" + ",".join(f"{v:g}" for v in (*eye, *target, *up, fov)) + ")"
        return (f"{scene}|{rays}|{self.structure}|{self.backend}|"
                f"r{self.resolution}|n{self.ls_n}|k{self.ls_min_candidates}")

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


def _as_list(value, what: str) -> list:
    if value is None:
        return []
    return list(value) if isinstance(value, (list, tuple)) else [value]


def _camera(table, where: str):
    if table is None:
        return None
    try:
        eye = tuple(float(v) for v in table["eye"])
        target = tuple(float(v) for v in table["target"])
        up = tuple(float(v) for v in table.get("up", (0.0, 1.0, 0.0)))
        fov = float(table.get("fov", 60.0))
    except (KeyError, TypeError, ValueError) as exc:
        raise ScenarioError(f"{where}: camera needs eye = [x,y,z], target = [x,y,z] (optional up, fov): {exc}") from None
    if len(eye) != 3 or len(target) != 3 or len(up) != 3:
        raise ScenarioError(f"{where}: camera eye/target/up need 3 numbers each")
    return (eye, target, up, fov)


def load_scenario(path: str, gpu: bool = False) -> Scenario:
    from lsbench.backends import BACKENDS, structure_info, structure_names

    p = Path(path)
    if not p.is_file() and shipped_scenario(str(path)) is not None:
        p = shipped_scenario(str(path))  # a shipped scenario by name: `lsbench gate ci`
    if not p.is_file():
        raise ScenarioError(f"scenario file not found: {path}")
    try:
        data = tomllib.loads(p.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ScenarioError(f"{path}: not valid TOML ({exc})") from None
    run = dict(data.get("run", {}))
    known = {f.name for f in dataclasses.fields(RunSettings)}
    unknown = set(run) - known
    if unknown:
        raise ScenarioError(f"{path}: unknown [run] settings {sorted(unknown)}; known: {sorted(known)}")
    try:
        settings = RunSettings(**run)
    except TypeError as exc:
        raise ScenarioError(f"{path}: {exc}") from None
    width, height = settings.width, settings.height
    if gpu and settings.gpu_width and settings.gpu_height:
        width, height = settings.gpu_width, settings.gpu_height
    blocks = data.get("cases")
    if not blocks:
        raise ScenarioError(f"{path}: no [[cases]] blocks")
    cases: list[Case] = []
    structures = set(structure_names())
    for i, block in enumerate(blocks):
        where = f"{path}: [[cases]] #{i + 1}"
        scenes = [expand_scene(str(s)) for s in _as_list(block.get("scenes"), "scenes")]
        names = _as_list(block.get("structures"), "structures")
        backs = _as_list(block.get("backends", list(BACKENDS)), "backends")
        resolutions = _as_list(block.get("resolutions"), "resolutions")
        try:
            ns = [int(n) for n in _as_list(block.get("ls_n", [2]), "ls_n")]  # N for Line Space structures
            ks = [int(k) for k in _as_list(block.get("ls_min_candidates", 0), "ls_min_candidates")]
        except (TypeError, ValueError) as exc:
            raise ScenarioError(f"{where}: ls_n and ls_min_candidates take integers ({exc})") from None
        camera = _camera(block.get("camera"), where)
        if not scenes or not names or not resolutions:
            raise ScenarioError(f"{where}: needs scenes, structures and resolutions")
        for s in names:
            if s not in structures:
                raise ScenarioError(f"{where}: unknown structure {s!r}; known: {sorted(structures)}")
        for b in backs:
            if b not in BACKENDS:
                raise ScenarioError(f"{where}: unknown backend {b!r}; known: {list(BACKENDS)}")
        for scene in scenes:
            for s in names:
                for b in backs:
                    for r in resolutions:
                        # A Line Space N only means something for Line Space structures.
                        line_space = structure_info(s).line_space
                        for n in (ns if line_space else [0]):
                            for k in (ks if line_space else [0]):
                                cases.append(Case(scene, s, b, str(r), n, k, settings.rays, width, height,
                                                  camera))
    seen, unique = set(), []
    for c in cases:
        if c.key not in seen:
            seen.add(c.key)
            unique.append(c)
    return Scenario(str(data.get("name", p.stem)), str(p), settings, unique)
