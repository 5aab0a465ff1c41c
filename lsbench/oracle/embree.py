"""Embree ground truth: the closest hit of every ray, cached on disk.

`embree_closest(scene, rays)` returns `(prim_ids, t)`: int32 primitive ids (-1 = miss) and
float32 distances (np.inf for a miss). Every backend result is checked against these arrays
(see `lsbench.oracle.verify`).

Facts about embreex 4.4 this module relies on (checked on this machine; check again when the
version changes):

- `EmbreeScene.run(origins, dirs, output=1)` takes float32 (N, 3) arrays only and returns a dict
  with `primID` (-1 = miss) and `tfar` (1e37 for a miss, otherwise in units of |dir|; our
  directions are unit length, so tfar is a distance).
- `tnear` is hard-wired to 0 and the hit test is inclusive (an origin lying on a triangle hits it
  at t = 0). `rays.tmin` therefore cannot be passed through; for tmin != 0 the origins are moved
  to `o + tmin * d` and tmin is added back to the distance. That equals "ignore hits with
  t < tmin" up to float32 rounding of the moved origin (|error| ~ 1 ulp of the coordinates).
- A ray set's per-ray tmax is not passed to the ground truth: every ray is traced to infinity,
  and lsbench.oracle.verify reads a hit at t >= tmax as none. An any-hit query (shadow, AO rays)
  is answered from the closest hit too (occluded iff t < tmax, verify.embree_occluded), so the
  cache holds closest hits only and one file serves a ray set under either query.
- `query='OCCLUDED'` with `dists=` (tfar) returns 0 for an occluded ray and -1 otherwise (a flag,
  not a hit id; the tfar test is inclusive). It is what Embree's any-hit speed is timed with
  (embree_timer for a ray set whose query is "any"), with tfar one float below tmax - tmin so its
  range is our [tmin, tmax); `embree_any_hit` returns its flags (tests check them against the
  closest-hit answer). OCCLUDED leaves `dists` as it was (checked), so one tfar array serves every
  timed repeat; with `query='INTERSECT'`, `dists=` is written in place, and we never pass it there.
- Zero-area triangles (a repeated index, or collinear corners) are accepted by the build and are
  never hit (Embree's determinant is zero), which is the right answer for a closest-hit query.
- `run()` is a plain loop over `rtcIntersect1` that releases the GIL, and Embree allows
  concurrent queries on a committed scene. embreex commits lazily inside the first `run()` and
  the flag it sets is not thread-safe, so the scene is committed by one serial warm-up call
  before rays are split over threads. Threaded and serial results are bit-identical (tested).
  On the 2-core development machine (Sponza, 279k triangles, 262k rays) tracing takes 0.071 s
  serial and 0.038 s on 2 threads (4 threads: 0.042 s); the build takes ~0.2 s either way.
- The scene is built with `robust=True` (RTC_SCENE_FLAG_ROBUST: "avoids artifacts caused by rays
  shooting through edges of neighboring primitives"); it costs ~5 % trace time and makes a
  leak through a shared edge less likely to be blamed on a backend.
"""
from __future__ import annotations

import functools
import os
import tempfile
from concurrent.futures import ThreadPoolExecutor
from importlib import metadata
from pathlib import Path
from typing import Protocol

import numpy as np

from lsbench.inputs.scene import Scene


class RaySet(Protocol):
    """What Embree reads of a ray set (lsbench.inputs.rays.RaySet). Not imported from there: the
    secondary ray sets start at Embree's hits (inputs/secondary.py), so inputs.rays needs this
    module, and an import back would be a cycle."""
    origins: np.ndarray
    directions: np.ndarray
    tmin: float
    query: str

    @property
    def tmax_array(self) -> np.ndarray: ...

    @property
    def count(self) -> int: ...

    @property
    def content_hash(self) -> str: ...

# Bump when the meaning of cached arrays changes (build flags, tmin handling, ...).
CACHE_FORMAT = 1
# Below this many rays per thread, threading costs more than it saves.
MIN_RAYS_PER_CHUNK = 16384
# Directions further than this from unit length make Embree's tfar not a distance.
UNIT_LENGTH_TOL = 1e-3


@functools.lru_cache(maxsize=1)
def embree_version() -> str:
    """'embree 4.4.0' from the library itself, else 'embreex <package version>'."""
    try:
        from embreex import rtcore as rtc

        text = str(rtc.EmbreeDevice())  # "Embree version:  4.4.0"
        version = text.split(":", 1)[1].strip()
        if version:
            return f"embree {version}"
    except Exception:  # pragma: no cover - depends on the installed binding
        pass
    try:
        return f"embreex {metadata.version('embreex')}"
    except metadata.PackageNotFoundError:  # pragma: no cover
        return "embreex unknown"


def default_cache_dir() -> Path:
    """`$LSBENCH_CACHE` if set, else `~/.cache/lsbench/embree`."""
    env = os.environ.get("LSBENCH_CACHE")
    return Path(env) if env else Path.home() / ".cache" / "lsbench" / "embree"


def cache_path(scene: Scene, rays: RaySet, cache_dir: str | os.PathLike | None = None) -> Path:
    """Cache file for (scene, rays). RaySet.content_hash does not cover tmin, so a non-zero
    tmin is part of the name."""
    folder = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    name = f"{scene.content_hash}_{rays.content_hash}"
    if rays.tmin != 0.0:
        name += f"_tmin{float(rays.tmin)!r}"
    return folder / f"{name}.npz"


def embree_closest(
    scene: Scene,
    rays: RaySet,
    cache_dir: str | os.PathLike | None = None,
    *,
    use_cache: bool = True,
    threads: int | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Closest hit for every ray: (prim_ids int32, -1 = miss; t float32, inf = miss).

    Results are cached in `cache_dir` (default: `default_cache_dir()`) keyed by the scene and
    ray-set content hashes; a cached file is used only if its Embree version and format match.
    `threads`: worker threads (default: the usable CPUs; 1 = serial).
    """
    path = cache_path(scene, rays, cache_dir) if use_cache else None
    if path is not None:
        cached = _load(path, rays.count)
        if cached is not None:
            return cached
    prim_ids, t = _trace(scene, rays, threads)
    if path is not None:
        _store(path, prim_ids, t)
    return prim_ids, t


# --- tracing ---------------------------------------------------------------------------------


def _build(scene: Scene):
    """A committed robust Embree scene (the geometry object is kept alive next to it)."""
    from embreex import rtcore_scene as rtcs
    from embreex.mesh_construction import TriangleMesh

    faces = np.asarray(scene.faces)
    if faces.size and int(faces.max()) >= 2**31:
        raise ValueError("vertex index does not fit embreex's int32 indices")
    vertices = np.ascontiguousarray(scene.vertices, dtype=np.float32)
    faces = np.ascontiguousarray(faces, dtype=np.int32)
    escene = rtcs.EmbreeScene(robust=True)
    mesh = TriangleMesh(escene, vertices, faces)
    # Commit now, from one thread: embreex commits lazily in run() behind an unguarded flag.
    escene.run(np.zeros((1, 3), np.float32), np.array([[1.0, 0.0, 0.0]], np.float32))
    return escene, mesh


def _ray_arrays(rays: RaySet) -> tuple[np.ndarray, np.ndarray]:
    """float32 C-contiguous (N,3) origins and directions, origins moved by tmin (see module doc)."""
    origins = np.asarray(rays.origins)
    directions = np.asarray(rays.directions)
    if origins.shape != directions.shape or origins.ndim != 2 or origins.shape[1] != 3:
        raise ValueError(f"rays must be (N,3): origins {origins.shape}, directions {directions.shape}")
    if origins.shape[0]:
        lengths = np.linalg.norm(directions.astype(np.float64), axis=1)
        finite = np.isfinite(lengths)
        if np.any(np.abs(lengths[finite] - 1.0) > UNIT_LENGTH_TOL):
            raise ValueError("ray directions must be unit length (Embree's tfar is in units of |dir|)")
    if rays.tmin != 0.0:
        origins = origins.astype(np.float64) + float(rays.tmin) * directions.astype(np.float64)
    return (
        np.ascontiguousarray(origins, dtype=np.float32),
        np.ascontiguousarray(directions, dtype=np.float32),
    )


def _usable_cpus() -> int:
    """CPUs this process may run on (the affinity mask can be smaller than os.cpu_count())."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return os.cpu_count() or 1


def _trace(scene: Scene, rays: RaySet, threads: int | None) -> tuple[np.ndarray, np.ndarray]:
    n = rays.count
    prim_ids = np.full(n, -1, dtype=np.int32)
    t = np.full(n, np.inf, dtype=np.float32)
    if n == 0 or scene.triangle_count == 0:
        return prim_ids, t
    origins, directions = _ray_arrays(rays)
    escene, _mesh = _build(scene)
    _run_threads(escene, origins, directions, prim_ids, t, threads)
    miss = prim_ids < 0
    prim_ids[miss] = -1
    t[miss] = np.inf
    if rays.tmin != 0.0:
        t[~miss] += np.float32(rays.tmin)
    return prim_ids, t


def _run_threads(escene, origins, directions, prim_ids, t, threads: int | None) -> None:
    n = origins.shape[0]

    def run_chunk(bounds: tuple[int, int]) -> None:
        lo, hi = bounds
        out = escene.run(origins[lo:hi], directions[lo:hi], output=1)
        prim_ids[lo:hi] = out["primID"]
        t[lo:hi] = out["tfar"]

    _map_chunks(n, run_chunk, threads)


def _map_chunks(n: int, run_chunk, threads: int | None) -> None:
    """Run run_chunk((lo, hi)) over [0, n) in chunks on `threads` threads (all usable CPUs by
    default); Embree releases the GIL inside run()."""
    threads = threads or _usable_cpus()
    chunk_count = min(threads * 4, max(1, n // MIN_RAYS_PER_CHUNK))  # x4: load balance
    edges = np.linspace(0, n, chunk_count + 1).astype(np.int64)
    chunks = list(zip(edges[:-1].tolist(), edges[1:].tolist()))
    if threads == 1 or chunk_count == 1:
        for chunk in chunks:
            run_chunk(chunk)
    else:
        with ThreadPoolExecutor(max_workers=threads) as pool:
            list(pool.map(run_chunk, chunks))  # list(): re-raise worker exceptions


def _occlusion_tfar(rays: RaySet) -> np.ndarray:
    """Embree's inclusive tfar for our [tmin, tmax): one float32 below tmax - tmin (the origins
    are moved by tmin, _ray_arrays)."""
    tmax = np.asarray(rays.tmax_array, np.float64) - float(rays.tmin)
    return np.nextafter(tmax.astype(np.float32), np.float32(-np.inf)).clip(min=0.0).astype(np.float32)


def _run_occluded(escene, origins, directions, tfar, occluded, threads: int | None) -> None:
    """Embree's any-hit query of every ray, split over threads like _run_threads."""
    def run_chunk(bounds: tuple[int, int]) -> None:
        lo, hi = bounds
        occluded[lo:hi] = escene.run(origins[lo:hi], directions[lo:hi], dists=tfar[lo:hi],
                                     query="OCCLUDED") != -1

    _map_chunks(origins.shape[0], run_chunk, threads)


def embree_any_hit(scene: Scene, rays: RaySet, threads: int | None = None) -> np.ndarray:
    """Embree's own any-hit answer: a bool per ray, occluded in [tmin, tmax). The ground truth
    derives occlusion from the cached closest hits instead (verify.embree_occluded); this is the
    query embree_timer times for any-hit ray sets, and tests check that the two agree."""
    occluded = np.zeros(rays.count, bool)
    if rays.count == 0 or scene.triangle_count == 0:
        return occluded
    origins, directions = _ray_arrays(rays)
    escene, _mesh = _build(scene)
    _run_occluded(escene, origins, directions, _occlusion_tfar(rays), occluded, threads)
    return occluded


def embree_timer(scene: Scene, rays: RaySet, threads: int | None = None):
    """A function that traces the whole ray set with Embree once on this CPU (all usable cores;
    the scene is built and one untimed trace run here, not in the timing) and returns its wall
    time in seconds: the CPU reference speed, under the ray set's own query (closest hit, or
    Embree's occlusion query for "any"). lsbench/running/execute.py calls it between the
    device's timed launches, so both figures of a case's ratio are taken under the same load."""
    import time

    if rays.count == 0 or scene.triangle_count == 0:
        return lambda: 0.0
    origins, directions = _ray_arrays(rays)
    escene, mesh = _build(scene)
    prim_ids = np.empty(rays.count, np.int32)
    t = np.empty(rays.count, np.float32)
    any_hit = getattr(rays, "query", "closest") == "any"
    tfar = _occlusion_tfar(rays) if any_hit else None
    occluded = np.empty(rays.count, bool)

    def trace_seconds() -> float:
        _ = mesh  # the geometry object lives as long as its scene
        t0 = time.perf_counter()
        if any_hit:
            _run_occluded(escene, origins, directions, tfar, occluded, threads)
        else:
            _run_threads(escene, origins, directions, prim_ids, t, threads)
        return time.perf_counter() - t0

    trace_seconds()  # warm-up: first-touch page faults, thread start
    return trace_seconds


def embree_trace_seconds(scene: Scene, rays: RaySet, repeats: int = 3, threads: int | None = None) -> list[float]:
    """Wall time of Embree's closest-hit trace of the whole ray set, one entry per repeat
    (embree_timer's traces one after another)."""
    timer = embree_timer(scene, rays, threads)
    return [timer() for _ in range(repeats)]


# --- cache -----------------------------------------------------------------------------------


def _load(path: Path, count: int) -> tuple[np.ndarray, np.ndarray] | None:
    """Cached arrays, or None if absent, unreadable, stale or of the wrong length."""
    try:
        with np.load(path, allow_pickle=False) as data:
            if int(data["format"]) != CACHE_FORMAT or str(data["embree"]) != embree_version():
                return None
            prim_ids = np.ascontiguousarray(data["prim_ids"], dtype=np.int32)
            t = np.ascontiguousarray(data["t"], dtype=np.float32)
    except (OSError, KeyError, ValueError, EOFError):
        return None
    if prim_ids.shape != (count,) or t.shape != (count,):
        return None
    return prim_ids, t


def _store(path: Path, prim_ids: np.ndarray, t: np.ndarray) -> None:
    """Write atomically (temp file in the same folder + os.replace): readers never see half a file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=path.stem + ".", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            np.savez(f, prim_ids=prim_ids, t=t, format=CACHE_FORMAT, embree=embree_version())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
