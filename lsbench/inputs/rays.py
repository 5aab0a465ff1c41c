"""RaySet: origins + normalized directions, a per-ray tmax and the query they ask (plain data);
the registry of named generators lives below.

Ray sets by name (`--rays NAME`, a scenario's `rays = "NAME"`; their parameters, checked by
inputs/checks.py RAY_PARAMS, in `ray_params = { ... }` or `--ray-param KEY=VALUE`):

- `primary`     one camera ray through each pixel centre (closest hit).
- `adversarial` grazing, axis-parallel, boundary and degenerate rays (inputs/adversarial.py).
- `shadow`      from each primary hit to a light, tmax = the distance to the light point; any hit.
                light = [x, y, z] (default: above the scene's centre, inputs/secondary.py
                default_light), light_size = edge of a square quad light (0: a point light),
                samples = points on it per hit (1), seed (0).
- `ao`          samples = K cosine-weighted directions per primary hit (4), tmax = distance x the
                scene diagonal (0.1); any hit. seed (0).
- `diffuse`     one cosine-weighted bounce per primary hit; closest hit. seed (0).
- `incoherent`  count rays (default: width x height) with origins uniform in the scene bounds and
                directions uniform on the sphere; closest hit. seed (0).

The secondary sets (shadow, ao, diffuse) start at Embree's hits of the primary rays of the case's
image size and camera, offset from the surface (inputs/secondary.py); a primary miss spawns none.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lsbench.inputs.adversarial import adversarial_arrays
from lsbench.inputs.checks import MAX_IMAGE_RAYS, BadValue, check_camera, check_image_size
from lsbench.inputs.scene import Camera, Scene, arrays_hash
from lsbench.inputs import secondary

# The query each ray set asks: shadow and AO rays only need "is anything in [tmin, tmax)".
ANY_HIT_SETS = frozenset({"shadow", "ao"})


def query_of(name: str) -> str:
    """"any" for the any-hit ray sets, else "closest" (ray files and every other set)."""
    return "any" if name in ANY_HIT_SETS else "closest"


@dataclass
class RaySet:
    name: str
    origins: np.ndarray  # (N, 3) float32
    directions: np.ndarray  # (N, 3) float32, unit length (distances compare with Embree's)
    width: int = 0  # image size for camera ray sets (0 = not an image)
    height: int = 0
    tmin: float = 0.0
    tmax: np.ndarray | None = None  # (N,) float32 per-ray end of the query; None: inf for every ray
    query: str = "closest"  # "closest" hit, or "any" hit in [tmin, tmax) (shadow, AO)
    params: dict = field(default_factory=dict)  # the generator's parameters, defaults filled in
    _hash: str | None = field(default=None, repr=False)

    @property
    def count(self) -> int:
        return int(self.origins.shape[0])

    @property
    def tmax_array(self) -> np.ndarray:
        """(N,) float32 tmax of every ray (inf where the set has none)."""
        if self.tmax is None:
            return np.full(self.count, np.inf, np.float32)
        return np.asarray(self.tmax, np.float32)

    def part(self, start: int, stop: int) -> "RaySet":
        """Rays [start, stop) as a set of their own: the same name, query, tmin and parameters. A
        part of an image that is whole rows stays an image of those rows; any other part is not
        an image (width = height = 0)."""
        start, stop = max(0, int(start)), min(self.count, int(stop))
        if not start < stop:
            raise ValueError(f"a part of a ray set needs start < stop within its {self.count} rays, "
                             f"got [{start}, {stop})")
        image = (self.width > 0 and self.width * self.height == self.count
                 and start % self.width == 0 and stop % self.width == 0)
        return RaySet(name=self.name, origins=self.origins[start:stop], directions=self.directions[start:stop],
                      width=self.width if image else 0, height=(stop - start) // self.width if image else 0,
                      tmin=self.tmin, tmax=None if self.tmax is None else self.tmax[start:stop],
                      query=self.query, params=dict(self.params))

    @property
    def content_hash(self) -> str:
        """Hash of the float32 origins and directions, and of tmax when the set has one (sets
        without keep the hash they had before tmax existed)."""
        if self._hash is None:
            arrays = [np.asarray(self.origins, np.float32), np.asarray(self.directions, np.float32)]
            if self.tmax is not None:
                arrays.append(np.asarray(self.tmax, np.float32))
            self._hash = arrays_hash(*arrays)
        return self._hash


# ----------------------------------------------------------------------------------------------
# generators


class RayError(ValueError):
    """Bad ray input (unknown ray set name, missing/invalid .npz): one-line message."""


def primary_rays(scene: Scene, width: int, height: int, camera: Camera | None = None) -> RaySet:
    """Pinhole camera rays, one through each pixel centre.

    Row-major with row 0 at the TOP of the image: pixel (x, y) is ray y * width + x.
    Origins are the eye; directions are unit length (float32).
    """
    from lsbench.inputs.scenes import default_camera  # scenes imports trimesh lazily; keep it lazy

    if width <= 0 or height <= 0:
        raise RayError(f"image size must be positive, got {width}x{height}")
    cam = camera if camera is not None else default_camera(scene)
    try:  # the inputs are checked where they are read; this holds for cameras built in code too
        check_image_size(width, height)
        check_camera("camera ", cam.eye, cam.target, cam.up, cam.fov_deg)
    except BadValue as exc:
        raise RayError(str(exc)) from None
    forward, right, up = _camera_basis(cam)
    half_h = np.tan(np.radians(cam.fov_deg) / 2)
    half_w = half_h * width / height
    # pixel centres in [-1, 1]; the centre pixel of an odd size lands exactly on 0
    sx = ((np.arange(width) + 0.5) / width) * 2 - 1
    sy = 1 - ((np.arange(height) + 0.5) / height) * 2  # +1 at the top row
    px, py = np.meshgrid(sx * half_w, sy * half_h, indexing="xy")
    dirs = forward + px[..., None] * right + py[..., None] * up
    dirs = (dirs / np.linalg.norm(dirs, axis=-1, keepdims=True)).reshape(-1, 3)
    origins = np.broadcast_to(np.asarray(cam.eye, dtype=np.float32), dirs.shape)
    return RaySet(name="primary", origins=np.ascontiguousarray(origins),
                  directions=dirs.astype(np.float32), width=width, height=height)


def _camera_basis(cam: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Orthonormal forward/right/up (float64) of a camera."""
    forward = np.subtract(cam.target, cam.eye, dtype=np.float64)
    length = np.linalg.norm(forward)
    if not np.isfinite(length) or length == 0:
        raise RayError(f"camera eye {cam.eye} and target {cam.target} must differ")
    forward /= length
    right = np.cross(forward, np.asarray(cam.up, dtype=np.float64))
    if np.linalg.norm(right) < 1e-9:
        # looking along `up`: any perpendicular will do, pick one deterministically
        helper = np.array([0.0, 0.0, 1.0]) if abs(forward[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
        right = np.cross(forward, helper)
    right /= np.linalg.norm(right)
    return forward, right, np.cross(right, forward)


def load_rays_file(path: str) -> RaySet:
    """Rays from a `.npz` with (N, 3) arrays `origins` and `directions`.

    Directions are normalized on load, so hit distances are in scene units of length (as for
    every RaySet), whatever the lengths stored in the file were.
    """
    p = Path(path)
    if not p.is_file():
        raise RayError(f"ray file not found: {path}")
    try:
        with np.load(p, allow_pickle=False) as data:
            missing = [k for k in ("origins", "directions") if k not in data.files]
            if missing:
                raise RayError(f"{path}: missing array(s) {', '.join(missing)} "
                               f"(found: {', '.join(data.files) or 'none'})")
            origins, directions = data["origins"], data["directions"]
    except RayError:
        raise
    except Exception as err:  # not a zip, truncated, pickled objects, ...
        raise RayError(f"cannot read {path} as .npz: {' '.join(str(err).split())}") from None
    for key, arr in (("origins", origins), ("directions", directions)):
        if arr.dtype.kind not in "fiu" or arr.ndim != 2 or arr.shape[1] != 3:
            raise RayError(f"{path}: {key} must be a numeric (N, 3) array, "
                           f"got {arr.dtype} {arr.shape}")
    if origins.shape != directions.shape:
        raise RayError(f"{path}: origins {origins.shape} and directions {directions.shape} differ")
    if origins.shape[0] == 0:
        raise RayError(f"{path}: no rays")
    # checked in float32, the precision backends and Embree see
    with np.errstate(over="ignore"):  # values beyond float32 range become Inf, caught below
        origins = origins.astype(np.float32)
        directions = directions.astype(np.float32)
    if not (np.isfinite(origins).all() and np.isfinite(directions).all()):
        raise RayError(f"{path}: origins or directions contain NaN/Inf")
    length = np.linalg.norm(directions.astype(np.float64), axis=1, keepdims=True)
    if (length == 0).any():
        raise RayError(f"{path}: {int((length == 0).sum())} directions have zero length "
                       f"(first: ray {int(np.argmax(length == 0))})")
    return RaySet(name=p.stem, origins=np.ascontiguousarray(origins),
                  directions=(directions / length).astype(np.float32))


# name -> generator(scene, width, height, camera, **params); other ray sets register here
RAY_SETS: dict[str, Callable[..., RaySet]] = {"primary": primary_rays}


def adversarial_rays(scene: Scene) -> tuple[RaySet, np.ndarray]:
    """The adversarial ray set (lsbench/inputs/adversarial.py) and its category label per ray."""
    origins, directions, labels = adversarial_arrays(scene)
    return RaySet(name="adversarial", origins=origins, directions=directions, tmin=0.0), labels


def _adversarial(scene: Scene, width: int, height: int, camera: Camera | None = None) -> RaySet:
    return adversarial_rays(scene)[0]  # image size and camera do not apply


RAY_SETS["adversarial"] = _adversarial


def _generated(name: str, arrays, params: dict) -> RaySet:
    origins, directions, tmax = arrays
    return RaySet(name=name, origins=np.ascontiguousarray(origins, np.float32),
                  directions=np.ascontiguousarray(directions, np.float32),
                  tmax=None if tmax is None else np.ascontiguousarray(tmax, np.float32),
                  query=query_of(name), params=dict(params))


def _secondary(name: str, make_arrays):
    """A generator of rays that start at the primary rays' hits (inputs/secondary.py)."""
    def generate(scene: Scene, width: int, height: int, camera: Camera | None = None, **params) -> RaySet:
        most = width * height * params.get("samples", 1)  # every pixel hits: the most rays it makes
        if most > MAX_IMAGE_RAYS:
            raise RayError(f"{name} rays: {width}x{height} pixels x {params.get('samples', 1)} samples may make "
                           f"{most} rays, over the limit of {MAX_IMAGE_RAYS}")
        primary = primary_rays(scene, width, height, camera)
        try:
            return _generated(name, make_arrays(scene, primary, **params), params)
        except secondary.SecondaryError as exc:
            raise RayError(f"{name} rays: {exc}") from None
    generate.__doc__ = make_arrays.__doc__
    return generate


def _incoherent(scene: Scene, width: int, height: int, camera: Camera | None = None, **params) -> RaySet:
    count = params.get("count", width * height)  # the camera is not used
    if count > MAX_IMAGE_RAYS:
        raise RayError(f"incoherent rays: count = {count} is over the limit of {MAX_IMAGE_RAYS} rays")
    if count < 1:
        raise RayError(f"incoherent rays: count = {count} must be at least 1")
    return _generated("incoherent", secondary.incoherent_arrays(scene, count=count, seed=params.get("seed", 0)),
                      dict(params, count=count))


RAY_SETS.update({"shadow": _secondary("shadow", secondary.shadow_arrays),
                 "ao": _secondary("ao", secondary.ao_arrays),
                 "diffuse": _secondary("diffuse", secondary.diffuse_arrays),
                 "incoherent": _incoherent})


def make_rays(name_or_path: str, scene: Scene, width: int, height: int,
              camera: Camera | None = None, params=()) -> RaySet:
    """A registered ray set by name with its parameters (a dict or a case's (key, value) pairs,
    checked by inputs/checks.py resolve_ray_params), or a `.npz` ray file."""
    params = {k: (list(v) if isinstance(v, tuple) else v) for k, v in dict(params).items()}
    generator = RAY_SETS.get(name_or_path)
    if generator is not None:
        if name_or_path in ("primary", "adversarial"):
            if params:
                raise RayError(f"the ray set {name_or_path!r} takes no parameters, got {params}")
            return generator(scene, width, height, camera)
        return generator(scene, width, height, camera, **params)
    if params:
        raise RayError(f"a ray file takes no parameters, got {params}")
    if name_or_path.lower().endswith(".npz"):
        return load_rays_file(name_or_path)
    raise RayError(f"unknown ray set {name_or_path!r}: use one of "
                   f"{', '.join(sorted(RAY_SETS))} or a path to a .npz file")
