"""Adversarial rays: the cases where traversals and ray/triangle tests fail, and the rules that
decide which disagreements with Embree are legitimate ties.

`adversarial_rays(scene)` (registered as the ray set "adversarial": `--rays adversarial`) builds
a deterministic set of a few thousand rays from the scene's triangles and its bounding box
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
                size carry absolute errors of ~1e-3 * diag; see the tolerance below).

Classification of disagreements (`classify`). A ray on which a backend and Embree differ
(verify's `missed`/`extra`/`wrong`; verify's `tie` already covers equal distances) is
re-evaluated in float64 against every triangle of the scene:

- pos_eps = 8 * 2^-24 * (M + t) is the position tolerance of a float32 decision at distance t,
  where M is the largest coordinate magnitude of the ray origin and the scene (both Embree and
  the backends compute v - o in float32: an error of a few ulps of M, plus direction rounding
  growing with t). With origins at 1e4 * diag (category `far`) or scenes at offset 1e6, pos_eps
  is correspondingly large: float32 (Embree included) cannot place those hits better.
- A triangle is *ambiguous* for a ray when the ray passes within pos_eps of its boundary (its
  three edges as 3D segments) or its origin lies within pos_eps of it. This covers grazing edges
  and vertices, rays inside the triangle's plane (they cross its boundary), zero-area triangles
  (all boundary) and self-hits at t ~ 0 of origins on a triangle (tmin = 0: whether the origin's
  own triangle counts at t = 0 or at t = -1e-9 is decided by rounding, in Embree as here).
- A triangle is *robustly hit* when the float64 ray meets its interior at t >= 0 and it is not
  ambiguous. t* is the nearest robust hit (inf if none).
- Watertightness is still enforced: where the ray crosses the interior of an edge shared by two
  ambiguous triangles whose third vertices lie on opposite sides of the edge seen along the ray
  (a surface the ray passes through, not a silhouette it grazes), that crossing counts as a
  robust hit at its distance (a leak through a shared edge is never a tie).
- An answer is *acceptable* when it is a miss and t* is inf; or a robust triangle at t* (within
  the tie tolerance abs_tol + rel_tol * t + pos_eps) reported at its float64 distance; or an
  ambiguous triangle reported no farther than t* (+ tolerance) at a point that lies within
  pos_eps of that triangle.
- A disagreement is a documented tie (`tie:self-hit`, `tie:in-plane`, `tie:degenerate`,
  `tie:graze`, named after the ambiguous triangle involved) when both answers are acceptable;
  `embree-imprecise` when only the backend's is; `unexplained` when the backend's answer is not
  acceptable (a bug: tests require none).
"""
from __future__ import annotations

import numpy as np

from lsbench.inputs.rays import RaySet
from lsbench.inputs.scene import Scene

RAY_CATEGORIES = ("axis", "vertex", "edge", "plane", "box", "voxel", "surface", "miss", "short", "far")
MAX_TRIANGLES = 96  # triangles sampled per category (deterministic): keeps the set ~4k rays
EPS32 = 2.0 ** -24


# ----------------------------------------------------------------------------------------------
# generator


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


def adversarial_rays(scene: Scene) -> tuple[RaySet, np.ndarray]:
    """(RaySet, category label per ray); deterministic for a given scene."""
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
    rays = RaySet(name="adversarial", origins=np.ascontiguousarray(O32[good]),
                  directions=np.ascontiguousarray(D32[good]), tmin=0.0)
    return rays, np.asarray(labels, dtype=object)[good]


def make_adversarial(scene: Scene, width: int = 0, height: int = 0, camera=None) -> RaySet:
    """RAY_SETS entry: image size and camera do not apply."""
    return adversarial_rays(scene)[0]


# ----------------------------------------------------------------------------------------------
# classification (float64 re-evaluation of disagreeing rays; see the module docstring)

POS_EPS_ULPS = 8.0


def _closest_seg_seg(p1, q1, p2, q2):
    """Ericson, Real-Time Collision Detection 5.1.9, vectorized over the leading axis:
    (s, t, c1, c2) with c1 = p1 + s (q1 - p1), c2 = p2 + t (q2 - p2) closest."""
    d1, d2, r = q1 - p1, q2 - p2, p1 - p2
    a = np.einsum("...i,...i", d1, d1)
    e = np.einsum("...i,...i", d2, d2)
    f = np.einsum("...i,...i", d2, r)
    c = np.einsum("...i,...i", d1, r)
    b = np.einsum("...i,...i", d1, d2)
    a_s = np.where(a > 0, a, 1.0)
    e_s = np.where(e > 0, e, 1.0)
    denom = a * e - b * b
    with np.errstate(invalid="ignore", divide="ignore"):
        s = np.where(denom > 1e-300 * np.maximum(a * e, 1e-300),
                     np.clip((b * f - c * e) / np.where(denom != 0, denom, 1.0), 0, 1), 0.0)
        t = (b * s + f) / e_s
        s = np.where(t < 0, np.clip(-c / a_s, 0, 1), np.where(t > 1, np.clip((b - c) / a_s, 0, 1), s))
        t = np.clip(t, 0, 1)
    s = np.where(a > 0, s, 0.0)
    t = np.where(e > 0, t, 0.0)
    c1 = p1 + s[..., None] * d1
    c2 = p2 + t[..., None] * d2
    return s, t, c1, c2


def _point_triangle_dist(p, tris):
    """Distance of point(s) p (F,3 or 3) to triangles (F,3,3): inside-projection or edges."""
    a, b, c = tris[:, 0], tris[:, 1], tris[:, 2]
    n = np.cross(b - a, c - a)
    nn = np.einsum("ij,ij->i", n, n)
    edge_d = np.full(len(tris), np.inf)
    for u, v in ((a, b), (b, c), (c, a)):
        uv = v - u
        L = np.einsum("ij,ij->i", uv, uv)
        s = np.clip(np.einsum("ij,ij->i", p - u, uv) / np.where(L > 0, L, 1.0), 0, 1)
        edge_d = np.minimum(edge_d, np.linalg.norm(p - (u + s[:, None] * uv), axis=1))
    with np.errstate(invalid="ignore", divide="ignore"):
        plane = np.abs(np.einsum("ij,ij->i", p - a, n)) / np.sqrt(nn)
        q = p - (np.einsum("ij,ij->i", p - a, n) / nn)[:, None] * n
        w0 = np.einsum("ij,ij->i", np.cross(b - q, c - q), n)
        w1 = np.einsum("ij,ij->i", np.cross(c - q, a - q), n)
        w2 = np.einsum("ij,ij->i", np.cross(a - q, b - q), n)
    inside = (nn > 0) & (w0 >= 0) & (w1 >= 0) & (w2 >= 0)
    return np.where(inside, np.minimum(plane, edge_d), edge_d)


class _RayEval:
    """Float64 facts about one ray against every triangle of the scene."""

    def __init__(self, tris, o, d, M, rel_tol, abs_tol):
        self.tris, self.o, self.d = tris, o, d
        F = len(tris)
        a, b, c = tris[:, 0], tris[:, 1], tris[:, 2]
        # ray as a long segment; the far end beyond anything in the scene
        L = 4.0 * (M + np.abs(o).max() + 1.0)
        far = o + d * L
        self.eps_of = lambda t: POS_EPS_ULPS * EPS32 * (M + np.abs(t))
        # boundary distance (3 edges) and the ray parameter of the closest approach
        self.bdist = np.full(F, np.inf)
        self.bt = np.zeros(F)
        self.edge_info = []
        for k, (u, v) in enumerate(((a, b), (b, c), (c, a))):
            s, t, c1, c2 = _closest_seg_seg(np.broadcast_to(o, u.shape), np.broadcast_to(far, u.shape), u, v)
            dist = np.linalg.norm(c1 - c2, axis=1)
            tt = s * L
            better = dist < self.bdist
            self.bdist = np.where(better, dist, self.bdist)
            self.bt = np.where(better, tt, self.bt)
            self.edge_info.append((dist, tt, t))
        self.odist = _point_triangle_dist(np.broadcast_to(o, a.shape), tris)
        n = np.cross(b - a, c - a)
        nlen = np.linalg.norm(n, axis=1)
        self.degenerate = nlen <= 1e-12 * np.maximum(np.einsum("ij,ij->i", b - a, b - a)
                                                      + np.einsum("ij,ij->i", c - a, c - a), 1e-300)
        with np.errstate(invalid="ignore", divide="ignore"):
            self.cos = np.abs(n @ d) / np.where(nlen > 0, nlen, 1.0)
        # Moeller-Trumbore in float64
        e1, e2 = b - a, c - a
        pv = np.cross(d, e2)
        det = np.einsum("ij,ij->i", e1, pv)
        with np.errstate(invalid="ignore", divide="ignore"):
            inv = 1.0 / det
            tv = o - a
            uu = np.einsum("ij,ij->i", tv, pv) * inv
            qv = np.cross(tv, e1)
            vv = (qv @ d) * inv
            t = np.einsum("ij,ij->i", e2, qv) * inv
        self.t = np.where(np.isfinite(t), t, np.inf)
        with np.errstate(invalid="ignore"):
            self.hit = (det != 0) & (uu >= 0) & (vv >= 0) & (uu + vv <= 1) & (t >= 0) & np.isfinite(t)
        self.amb = (self.bdist <= self.eps_of(self.bt)) | (self.odist <= self.eps_of(0.0))
        robust = self.hit & ~self.amb
        self.t_star = float(self.t[robust].min()) if robust.any() else np.inf
        self.t_star = min(self.t_star, self._shared_edge_crossing())
        self.rel_tol, self.abs_tol = rel_tol, abs_tol

    def _shared_edge_crossing(self) -> float:
        """Nearest crossing of an edge shared by two ambiguous triangles that face the ray from
        opposite sides of the edge (the ray goes through the surface there): inf if none."""
        best = np.inf
        cand = np.nonzero(self.amb & ~self.degenerate & (self.cos > 1e-4)
                          & (self.odist > self.eps_of(0.0)))[0]
        if len(cand) < 2:
            return best
        edges: dict = {}
        for f in cand:
            tri = self.tris[f]
            for k in range(3):
                dist, tt, s_edge = (x[f] for x in self.edge_info[k])
                eps = self.eps_of(tt)
                u, v, w = tri[k], tri[(k + 1) % 3], tri[(k + 2) % 3]
                elen = np.linalg.norm(v - u)
                if dist > eps or elen == 0 or not (eps < s_edge * elen < elen - eps):
                    continue  # not crossing this edge's interior (vertex hits are not checked)
                if any(self.edge_info[j][0][f] <= eps for j in range(3) if j != k):
                    continue  # near another edge too: no watertight promise there
                if u.tobytes() > v.tobytes():
                    u, v = v, u  # one orientation per edge, so the two sides compare
                key = (u.tobytes(), v.tobytes())
                side = float(np.dot(np.cross(v - u, w - u), self.d))
                edges.setdefault(key, []).append((side, tt))
        for hits in edges.values():
            sides = [s for s, _ in hits]
            if min(sides) < 0 < max(sides):
                best = min(best, min(t for _, t in hits))
        return best

    def tol(self, t) -> float:
        return self.abs_tol + self.rel_tol * abs(t) + self.eps_of(t)

    def acceptable(self, prim: int, t: float) -> bool:
        if prim < 0:
            return not np.isfinite(self.t_star)
        if not np.isfinite(t):
            return False
        if self.amb[prim]:
            on_tri = _point_triangle_dist((self.o + t * self.d)[None], self.tris[prim:prim + 1])[0]
            return t <= self.t_star + self.tol(self.t_star) and on_tri <= self.eps_of(t)
        return bool(self.hit[prim]) and abs(self.t[prim] - self.t_star) <= self.tol(self.t_star) \
            and abs(t - self.t[prim]) <= self.tol(t)

    def reason(self, prims) -> str:
        for p in prims:
            if p >= 0 and self.amb[p]:
                if self.odist[p] <= self.eps_of(0.0):
                    return "self-hit"
                if self.degenerate[p]:
                    return "degenerate"
                if self.cos[p] <= 1e-3:
                    return "in-plane"
                return "graze"
        # neither side's triangle is ambiguous: a nearer ambiguous one explains a miss
        near = np.nonzero(self.amb & (self.bt <= (self.t_star if np.isfinite(self.t_star) else np.inf)))[0]
        if len(near):
            return self.reason([int(near[np.argmin(self.bt[near])])])
        return "graze"


def classify(scene: Scene, rays: RaySet, prim_ids, distances, ref_prim_ids, ref_distances,
             rel_tol: float = 1e-4, abs_tol: float | None = None) -> dict:
    """Per-ray labels for a backend's answers against Embree's: 'agree', 'tie' (verify's equal
    distance), 'tie:<reason>', 'embree-imprecise' or 'unexplained' (module docstring).
    Returns {'labels': array, 'counts': {label: n}, 'unexplained': [ray ids]}."""
    from lsbench.oracle.verify import AGREE, TIE, classify as verify_classify, resolve_abs_tol

    lo, hi = scene.bounds
    extent = float(np.linalg.norm(hi.astype(np.float64) - lo))
    abs_tol = resolve_abs_tol(abs_tol, extent)
    cat = verify_classify(prim_ids, distances, ref_prim_ids, ref_distances, rel_tol=rel_tol, abs_tol=abs_tol)
    labels = np.where(cat == AGREE, "agree", np.where(cat == TIE, "tie", "")).astype(object)
    tris = scene.triangles.astype(np.float64)
    M = float(np.abs(scene.vertices).max())
    p = np.asarray(prim_ids).astype(np.int64)
    r = np.asarray(ref_prim_ids).astype(np.int64)
    t = np.asarray(distances, np.float64)
    tr = np.asarray(ref_distances, np.float64)
    for i in np.nonzero(labels == "")[0]:
        o = rays.origins[i].astype(np.float64)
        d = rays.directions[i].astype(np.float64)
        ev = _RayEval(tris, o, d, max(M, float(np.abs(o).max())), rel_tol, abs_tol)
        ok_b = ev.acceptable(int(p[i]), float(t[i]))
        ok_e = ev.acceptable(int(r[i]), float(tr[i]))
        if ok_b and ok_e:
            labels[i] = "tie:" + ev.reason([int(p[i]), int(r[i])])
        elif ok_b:
            labels[i] = "embree-imprecise"
        else:
            labels[i] = "unexplained"
    names, counts = np.unique(labels.astype(str), return_counts=True)
    return {"labels": labels, "counts": dict(zip(names.tolist(), counts.tolist())),
            "unexplained": np.nonzero(labels == "unexplained")[0].tolist()}


def check_structure(device, structure: str, scene: Scene, resolution, ls_n: int = 0, rays=None):
    """Build `structure` on `device`, trace the adversarial set, classify against Embree."""
    from lsbench import backends
    from lsbench.backends import BuildParams

    from lsbench.oracle.embree import embree_closest

    if rays is None:
        rays, cats = adversarial_rays(scene)
    else:
        cats = np.full(rays.count, "given", dtype=object)
    built = backends.build(device, structure, scene, BuildParams(resolution=tuple(resolution), ls_n=ls_n))
    try:
        hits = backends.trace(built, rays)
    finally:
        built.release()
    ref_p, ref_t = embree_closest(scene, rays)
    out = classify(scene, rays, hits.prim_ids, hits.distances, ref_p, ref_t)
    out.update({"rays": rays, "categories": cats, "hits": hits, "ref": (ref_p, ref_t)})
    return out


def structure_params(structure: str, cubic_res: int = 16, grid_res=(12, 16, 9)) -> dict:
    """Build parameters that every registered structure accepts in tests: octrees (cubic
    structures) a power-of-two cube, Line Space structures N = 2,
    others a non-cubic grid."""
    from lsbench import backends

    info = backends.structure_info(structure)
    ls_n = 2 if info.line_space else 0
    if info.cubic_power_of_two:
        return {"resolution": (cubic_res,) * 3, "ls_n": ls_n}
    return {"resolution": tuple(grid_res), "ls_n": ls_n}
