"""Adversarial rays: the cases where traversals and ray/triangle tests fail.

`adversarial_arrays(scene)` (the ray set "adversarial": `--rays adversarial`, made a RaySet by
lsbench/inputs/rays.py's `adversarial_rays`, so this module imports no ray module) builds a
deterministic set of a few thousand rays from the scene's triangles and its bounding box
(`scene.bounds`, independent of any grid resolution). Every ray has a unit float32 direction and
the set's tmin is 0 (RaySet has one tmin per set). Categories (`RAY_CATEGORIES`, the second
return value labels each ray):

- `axis`      : axis-parallel directions (+-x, +-y, +-z) whose zero components are +0.0, in a
                second copy -0.0 (safe_rcp turns them into +-inf by sign bit), in a third
                +-1.4e-45 (denormal: 1/d overflows), aimed at triangle centroids from outside.
- `vertex`    : aimed exactly at triangle vertices, from random directions and along an axis
                (origin = vertex - axis * diag: two coordinates equal the vertex's exactly).
- `edge`      : aimed at edge midpoints (a shared edge: the watertight test must hit one side).
- `plane`     : in the triangle's plane: along an edge line (through two vertices) and towards
                the centroid.
- `box`       : origins exactly on the bounding box's corners, edge midpoints and face centres;
                directions tangent to the faces/edges, inward along axes and diagonals.
- `voxel`     : origins inside the bounds at lo + extent * m / 2^k (k = 1..6), i.e. on typical
                voxel and octree-cell boundaries on all three axes; random and axis directions;
                origins on the centre planes moving off them by a denormal component.
- `surface`   : origins on triangles (vertices, centroids) with tmin = 0, directions to both
                sides and along +-normal.
- `miss`      : origins outside the bounds pointing away from them, or passing beside them.
- `short`     : origins a hair (1e-6 * diag) in front of a triangle centroid, pointing at it.
- `far`       : origins 1e4 * diag away, aimed at centroids and vertices (float32 origins of that
                size carry absolute errors of ~1e-3 * diag; see pos_eps in lsbench/oracle/classifier.py).

The disagreements these rays provoke are explained (or not) by lsbench.oracle.classifier:
float64 re-evaluation, ties by rule (grazing, origin on a surface, float32 limit).
"""
from __future__ import annotations

import numpy as np

from lsbench.inputs.scene import Scene

RAY_CATEGORIES = ("axis", "vertex", "edge", "plane", "box", "voxel", "surface", "miss", "short", "far")
MAX_TRIANGLES = 96  # triangles sampled per category (deterministic): keeps the set ~4k rays


def _unit(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, np.float64)
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    n[n == 0] = 1.0
    return v / n


def _random_dirs(rng, n: int) -> np.ndarray:
    return _unit(rng.normal(size=(n, 3)))


def _sample_triangles(scene: Scene, rng, n: int) -> np.ndarray:
    """Ids of up to n triangles with non-zero area (zero-area ones are aimed at separately)."""
    count = scene.triangle_count
    ids = np.arange(count) if count <= n else np.sort(rng.choice(count, n, replace=False))
    return ids


def adversarial_arrays(scene: Scene) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(origins, unit directions, category label per ray): float32 (N, 3) arrays and an object
    array; deterministic for a given scene. tmin is 0."""
    rng = np.random.default_rng(0x5EED)
    lo, hi = (b.astype(np.float64) for b in scene.bounds)
    ext = hi - lo
    diag = float(np.linalg.norm(ext)) or 1.0
    centre = (lo + hi) / 2
    tris = scene.triangles.astype(np.float64)  # (F, 3, 3)
    ids = _sample_triangles(scene, rng, MAX_TRIANGLES)
    T = tris[ids]
    cent = T.mean(axis=1)
    origins: list[np.ndarray] = []
    dirs: list[np.ndarray] = []
    labels: list[str] = []

    def add(label: str, o, d, keep_signed_zero: bool = False):
        o = np.atleast_2d(np.asarray(o, np.float64))
        d = np.atleast_2d(np.asarray(d, np.float64))
        o, d = np.broadcast_arrays(o, d)
        if not keep_signed_zero:
            d = _unit(d)
        ok = np.linalg.norm(d, axis=1) > 0
        origins.append(o[ok])
        dirs.append(d[ok])
        labels.extend([label] * int(ok.sum()))

    axes = np.concatenate([np.eye(3), -np.eye(3)])
    # axis: centroids seen along +-x/y/z from outside the bounds; a second copy with -0.0 zeros
    for a in axes:
        o = cent - a * diag
        add("axis", o, a, keep_signed_zero=True)
        neg_zero = np.where(a == 0, -0.0, a)
        add("axis", o, np.broadcast_to(neg_zero, o.shape).copy(), keep_signed_zero=True)
        # denormal "zeros" (+-1.4e-45 in float32): 1/d overflows to inf (see safe_rcp)
        tiny = np.where(a == 0, np.where(np.arange(3) % 2 == 0, 1e-45, -1e-45), a)
        add("axis", o[: max(1, len(o) // 3)], tiny, keep_signed_zero=True)
    # vertex: exactly at corners, from random directions and along axes
    verts = T.reshape(-1, 3)
    vsel = verts[rng.choice(len(verts), min(len(verts), 2 * MAX_TRIANGLES), replace=False)]
    rd = _random_dirs(rng, len(vsel))
    o = vsel - rd * 0.7 * diag
    add("vertex", o, vsel - o)
    ax = axes[rng.integers(0, 6, len(vsel))]
    add("vertex", vsel - ax * diag, ax, keep_signed_zero=True)
    # edge midpoints
    mids = np.concatenate([(T[:, 0] + T[:, 1]) / 2, (T[:, 1] + T[:, 2]) / 2, (T[:, 2] + T[:, 0]) / 2])
    mids = mids.astype(np.float32).astype(np.float64)
    rd = _random_dirs(rng, len(mids))
    o = mids - rd * 0.6 * diag
    add("edge", o, mids - o)
    ax = axes[rng.integers(0, 6, len(mids) // 3)]
    add("edge", mids[: len(ax)] - ax * diag, ax, keep_signed_zero=True)
    # plane: along an edge line (through both of its vertices) and towards the centroid
    e = T[:, 1] - T[:, 0]
    add("plane", T[:, 0] - e * 0.5, e)
    add("plane", T[:, 1] + (T[:, 1] - cent) * 1.5, cent - T[:, 1])
    # box: corners, edge midpoints, face centres exactly on the boundary (float32-representable)
    lo32, hi32 = scene.bounds
    lo32, hi32 = lo32.astype(np.float64), hi32.astype(np.float64)
    mid32 = ((lo32 + hi32) / 2).astype(np.float32).astype(np.float64)
    pick = np.stack([lo32, mid32, hi32])  # per axis: 0 = lo, 1 = mid, 2 = hi
    box_pts = []
    for ix in range(3):
        for iy in range(3):
            for iz in range(3):
                if (ix, iy, iz) != (1, 1, 1):
                    box_pts.append([pick[ix, 0], pick[iy, 1], pick[iz, 2]])
    box_pts = np.array(box_pts)
    diag_dirs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], np.float64)
    box_dirs = np.concatenate([axes, diag_dirs, _unit(np.array([[1, 1, 0], [1, 0, 1], [0, 1, 1],
                                                                [1, -1, 0], [-1, 0, 1], [0, -1, 1]], float))])
    for p in box_pts:
        add("box", np.broadcast_to(p, box_dirs.shape), box_dirs, keep_signed_zero=True)
    # voxel: origins on lo + ext * m / 2^k, k = 1..6, inside the bounds
    for k in range(1, 7):
        m = rng.integers(0, 2 ** k + 1, size=(48, 3))
        o = (lo32 + ext * m / 2 ** k).astype(np.float32).astype(np.float64)
        add("voxel", o[:32], _random_dirs(rng, 32))
        add("voxel", o[32:], axes[rng.integers(0, 6, 16)], keep_signed_zero=True)
    # on the centre planes (a cell boundary at every octree level), moving off them by a
    # denormal component (+-1.4e-45): 0 * (1/d = inf) = NaN if the reciprocal overflows
    for a in range(3):
        o = lo32 + ext * rng.uniform(0.05, 0.95, size=(16, 3))
        o[:, a] = mid32[a]
        d = _random_dirs(rng, 16)
        d[:, a] = np.where(np.arange(16) % 2 == 0, 1e-45, -1e-45)
        add("voxel", o, d, keep_signed_zero=True)
    # surface: origins on triangles (vertices, centroids), both sides and along the normals
    nrm = _unit(np.cross(T[:, 1] - T[:, 0], T[:, 2] - T[:, 0]))
    c32 = cent.astype(np.float32).astype(np.float64)
    add("surface", c32, nrm)
    add("surface", c32, -nrm)
    rd = _random_dirs(rng, len(T))
    add("surface", T[:, 0], rd)
    add("surface", c32, -rd)
    # miss: outside, pointing away or beside the box
    out_dirs = _random_dirs(rng, 96)
    o = centre + out_dirs * diag * 1.5
    add("miss", o, out_dirs)
    side = _unit(np.cross(out_dirs, _random_dirs(rng, 96)))
    add("miss", o + out_dirs * diag * 0.5, side)
    # short: a hair in front of a centroid, pointing at it
    rd = _random_dirs(rng, len(T))
    add("short", c32 - rd * 1e-6 * diag, rd)
    # far: 1e4 * diag away, aimed at centroids and vertices
    rd = _random_dirs(rng, len(T))
    o = (c32 - rd * 1e4 * diag).astype(np.float32).astype(np.float64)
    add("far", o, c32 - o)
    o = (T[:, 2] - rd * 1e4 * diag).astype(np.float32).astype(np.float64)
    add("far", o, T[:, 2] - o)

    O = np.concatenate(origins)
    D = np.concatenate(dirs)
    # unit length in float32, keeping exact axis directions and their signed zeros
    D32 = np.where(D == 0, D, D / np.linalg.norm(D, axis=1, keepdims=True)).astype(np.float32)
    O32 = O.astype(np.float32)
    good = np.isfinite(O32).all(axis=1) & np.isfinite(D32).all(axis=1) & (np.abs(D32).sum(axis=1) > 0)
    return (np.ascontiguousarray(O32[good]), np.ascontiguousarray(D32[good]),
            np.asarray(labels, dtype=object)[good])
