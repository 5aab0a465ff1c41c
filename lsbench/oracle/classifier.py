"""Float64 explanation of every disagreement between a backend and Embree.

verify.py sorts each ray into agree / tie / missed / extra / wrong / distance with float32-sized
tolerances. A disagreement (the last four) is then re-evaluated here in float64 against the
triangles near the ray, and gets one class (CLASSES):

- `agree`, `tie`         : verify's categories, not re-evaluated.
- `grazing`              : both answers are acceptable (below) and a triangle involved is
                           ambiguous because the ray passes within pos_eps of its boundary: it
                           grazes an edge or vertex, lies in the triangle's plane, or the
                           triangle has zero area (all boundary).
- `origin-on-surface`    : as `grazing`, but the ambiguous triangle holds the ray's origin (a
                           self-hit at t ~ 0 with tmin = 0 is decided by rounding, in Embree too).
- `float32-limit`        : both answers acceptable and both robust: they differ only within the
                           float32 position tolerance pos_eps (far origins, scenes far from the
                           origin, where float32 cannot place a hit better).
- `embree-imprecise`     : only the backend's answer is acceptable.
- `unexplained`          : the backend's answer is not acceptable: a bug. The gate fails on it.
- `unclassified`         : a disagreement past the per-case cap (MAX_CLASSIFIED_RAYS); it counts
                           as unexplained, and the record says the case was capped.

The rules (they were written for the adversarial rays, lsbench/inputs/adversarial.py):

- pos_eps = 8 * 2^-24 * (M + t) is the position tolerance of a float32 decision at distance t,
  where M is the largest coordinate magnitude of the ray origin and the scene (both Embree and
  the backends compute v - o in float32: an error of a few ulps of M, plus direction rounding
  growing with t).
- A triangle is *ambiguous* for a ray when the ray passes within pos_eps of its boundary (its
  three edges as 3D segments) or its origin lies within pos_eps of it.
- A triangle is *robustly hit* when the float64 ray meets its interior at t >= 0 and it is not
  ambiguous. t* is the nearest robust hit (inf if none).
- Watertightness is still enforced: where the ray crosses the interior of an edge shared by two
  ambiguous triangles whose third vertices lie on opposite sides of the edge seen along the ray
  (a surface the ray passes through, not a silhouette it grazes), that crossing counts as a
  robust hit at its distance (a leak through a shared edge is never explained).
- An answer is *acceptable* when it is a miss and t* is inf; or a robust triangle at t* (within
  abs_tol + rel_tol * t + pos_eps) reported at its float64 distance (same tolerance); or an
  ambiguous triangle reported no farther than t* (+ tolerance) at a point that lies within
  pos_eps of that triangle, or at its float64 distance (same tolerance) where the ray meets it,
  or (same tolerance) where the ray passes within pos_eps of one of its edges or vertices (a
  float32 test's distance errs by more than pos_eps when the ray is nearly parallel to the
  triangle: its rounding is divided by the determinant).
- Any-hit query (rays.query "any", verify.py): the backend's answer is acceptable when it says
  "not occluded" and t* is not before tmax (- tolerance), or names a triangle that the ray meets
  at the reported distance before tmax (+ tolerance): robustly hit there, or ambiguous with the
  reported point within pos_eps of it or met at that distance; it need not be the nearest.
  Embree's answer is its closest hit, judged as above (its occluded flag follows from it).

Cost: only disagreeing rays are re-evaluated, each against the triangles whose bounding boxes
come within pos_eps of it (one vectorized slab test over the scene), at most
MAX_CLASSIFIED_RAYS per case.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from lsbench.oracle.verify import AGREE, TIE, Accuracy, classify as verify_categories, compare, resolve_abs_tol

CLASSES = ("agree", "tie", "grazing", "origin-on-surface", "float32-limit", "embree-imprecise",
           "unexplained", "unclassified")
EXPLAINED = ("agree", "tie", "grazing", "origin-on-surface", "float32-limit", "embree-imprecise")
MAX_CLASSIFIED_RAYS = 2000  # per case; ~35 ms a ray on Sponza (262k triangles), 1 ms on Cornell
POS_EPS_ULPS = 8.0
EPS32 = 2.0 ** -24



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


def _segment_length(m: float, o) -> float:
    """The length of the segment that stands for the ray: beyond anything in a scene whose vertices
    lie within m of the origin (4 (m + |o|) > 2 (m + |o|) >= the distance from o to any of them).
    Relative to the scene's own scale, so that the pads and tolerances derived from it are too: an
    absolute term here (it was + 1.0) made a scene of size 1e-14 look near every ray, and the
    classification of one disagreement then took minutes."""
    return 4.0 * max(m + float(np.abs(o).max()), float(np.finfo(np.float32).tiny))


class _RayEval:
    """Float64 facts about one ray against the triangles `tris` (those near it)."""

    def __init__(self, tris, o, d, M, rel_tol, abs_tol):
        self.tris, self.o, self.d = tris, o, d
        F = len(tris)
        a, b, c = tris[:, 0], tris[:, 1], tris[:, 2]
        # ray as a long segment; the far end beyond anything in the scene
        L = _segment_length(M, o)
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
            return t <= self.t_star + self.tol(self.t_star) and self._on_ambiguous(prim, t)
        return bool(self.hit[prim]) and abs(self.t[prim] - self.t_star) <= self.tol(self.t_star) \
            and abs(t - self.t[prim]) <= self.tol(t)

    def _on_ambiguous(self, prim: int, t: float) -> bool:
        """Whether an ambiguous triangle is met at the reported distance: the reported point lies
        within pos_eps of it, or the float64 ray meets it and t is within tolerance of that
        distance, as for a robust hit. (A ray grazing a surface moves along it as t changes: in a
        soup of 2,000 triangles 2 units across, a ray at 3 degrees to one, 7e-7 inside its edge,
        was reported at t 2e-6 relative too far, 4e-6 past the edge and over pos_eps.)"""
        if bool(self.hit[prim]) and abs(t - self.t[prim]) <= self.tol(t):
            return True
        # The mirror case: the float64 ray passes just outside the triangle, within pos_eps of an
        # edge or vertex at tt, and a float32 test met it there. Its distance is off by the test's
        # rounding over the determinant, which shrinks as the ray turns parallel to the triangle:
        # in a fan of 3,000 slivers sharing a vertex, a ray through that vertex at a cosine of
        # 7e-3 to one of them was reported 2e-5 (4e-6 relative) before the vertex, past pos_eps.
        # Judged as a robust hit at tt would be.
        for dist, tt, _ in self.edge_info:
            if dist[prim] <= self.eps_of(tt[prim]) and abs(t - tt[prim]) <= self.tol(t):
                return True
        return _point_triangle_dist((self.o + t * self.d)[None], self.tris[prim:prim + 1])[0] <= self.eps_of(t)

    def acceptable_any(self, prim: int, t: float, tmax: float) -> bool:
        """An any-hit answer (module docstring): a hit the ray really makes before tmax, or no
        hit where no robust one lies before tmax."""
        if prim < 0:
            return self.t_star >= tmax - self.tol(tmax)
        if not np.isfinite(t) or t > tmax + self.tol(tmax):
            return False
        if self.amb[prim]:
            return self._on_ambiguous(prim, t)
        return bool(self.hit[prim]) and abs(t - self.t[prim]) <= self.tol(t)

    def reason(self, prims) -> str:
        """Class of a disagreement both of whose answers are acceptable (module docstring)."""
        for p in prims:
            if p >= 0 and self.amb[p]:
                return "origin-on-surface" if self.odist[p] <= self.eps_of(0.0) else "grazing"
        # neither side's triangle is ambiguous: a nearer ambiguous one explains a miss
        near = np.nonzero(self.amb & (self.bt <= self.t_star))[0]
        if len(near):
            return self.reason([int(near[np.argmin(self.bt[near])])])
        return "float32-limit"  # two robust answers that differ only within pos_eps


def _near_ray(lo, hi, o, d, pad: float, length: float) -> np.ndarray:
    """Triangles whose bounding boxes, grown by pad, meet the segment o + [0, length] d."""
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        ta = (lo - pad - o) * inv
        tb = (hi + pad - o) * inv
    flat = d == 0  # an axis the ray does not move along: inside the slab or never
    inside = (lo - pad <= o) & (o <= hi + pad)
    t_near = np.where(flat, np.where(inside, -np.inf, np.inf), np.minimum(ta, tb)).max(axis=1)
    t_far = np.where(flat, np.where(inside, np.inf, -np.inf), np.maximum(ta, tb)).min(axis=1)
    return np.flatnonzero((t_near <= t_far) & (t_far >= 0) & (t_near <= length))


def _triangles_near_ray(tri_lo, tri_hi, o, d, m: float) -> np.ndarray:
    """The triangles (by their float64 boxes) within the position tolerance of the ray's segment
    (_RayEval's: beyond the whole scene), m the scene's and the origin's largest coordinate."""
    length = _segment_length(m, o)
    return _near_ray(tri_lo, tri_hi, o, d, 2 * POS_EPS_ULPS * EPS32 * (m + length), length)


def classify_disagreements(scene, rays, prim_ids, distances, ref_prim_ids, ref_distances,
                           rel_tol: float = 1e-4, abs_tol: float | None = None,
                           max_rays: int = MAX_CLASSIFIED_RAYS) -> dict:
    """One class per ray (module docstring) for a backend's answers against Embree's, for the
    ray set's query (rays.query, rays.tmax).
    Returns {'labels': object array, 'counts': {class: n} (non-zero only), 'unexplained': ray ids
    (unclassified included), 'capped': whether some disagreements were left unclassified}."""
    lo, hi = scene.bounds
    extent = float(np.linalg.norm(hi.astype(np.float64) - lo))
    abs_tol = resolve_abs_tol(abs_tol, extent)
    any_hit = rays.query == "any"
    tmax = rays.tmax_array
    cat = verify_categories(prim_ids, distances, ref_prim_ids, ref_distances, rel_tol=rel_tol, abs_tol=abs_tol,
                            query=rays.query, tmax=tmax, tmin=rays.tmin)
    labels = np.where(cat == AGREE, "agree", np.where(cat == TIE, "tie", "")).astype(object)
    todo = np.flatnonzero(labels == "")
    labels[todo[max_rays:]] = "unclassified"
    classified = todo[:max_rays]
    if classified.size:  # the scene in float64 only where some ray disagrees (most cases: none)
        tris = scene.triangles.astype(np.float64)
        tri_lo, tri_hi = tris.min(axis=1), tris.max(axis=1)
        M = float(np.abs(scene.vertices).max())
        p = np.asarray(prim_ids).astype(np.int64)
        r = np.asarray(ref_prim_ids).astype(np.int64)
        t = np.asarray(distances, np.float64)
        tr = np.asarray(ref_distances, np.float64)
    for i in classified:
        o = rays.origins[i].astype(np.float64)
        d = rays.directions[i].astype(np.float64)
        m = max(M, float(np.abs(o).max()))
        near = _triangles_near_ray(tri_lo, tri_hi, o, d, m)
        local = {int(f): k for k, f in enumerate(near)}
        ev = _RayEval(tris[near], o, d, m, rel_tol, abs_tol)

        def acceptable(prim: int, dist: float) -> bool:
            if prim >= 0 and prim not in local:
                return False  # a triangle nowhere near the ray
            return ev.acceptable(local.get(prim, -1), dist)

        if any_hit:
            ok_b = (int(p[i]) < 0 or int(p[i]) in local) and ev.acceptable_any(local.get(int(p[i]), -1), float(t[i]),
                                                                                float(tmax[i]))
        else:
            ok_b = acceptable(int(p[i]), float(t[i]))
        ok_e = acceptable(int(r[i]), float(tr[i]))
        if ok_b and ok_e:
            labels[i] = ev.reason([local.get(int(x), -1) for x in (p[i], r[i])])
        elif ok_b:
            labels[i] = "embree-imprecise"
        else:
            labels[i] = "unexplained"
    names, counts = np.unique(labels.astype(str), return_counts=True)
    bad = np.flatnonzero((labels == "unexplained") | (labels == "unclassified"))
    return {"labels": labels, "counts": dict(zip(names.tolist(), counts.tolist())),
            "unexplained": bad.tolist(), "capped": bool(len(todo) > max_rays)}


@dataclass
class Classification:
    """The float64 classes of one case's disagreements (what the gate judges): record columns."""
    classes: dict  # count per class of CLASSES (every class present)
    unexplained: int  # unexplained + unclassified rays: what the gate counts
    unexplained_rays: list  # the first 20 such ray ids, for a look with --dump-hits
    classify_capped: bool  # more disagreements than MAX_CLASSIFIED_RAYS: the rest are unclassified
    classify_seconds: float  # host time the classification took


def judge_hits(scene, rays, prim_ids, distances, ref_prim_ids, ref_distances,
               rel_tol: float = 1e-4, max_rays: int = MAX_CLASSIFIED_RAYS) -> tuple[Accuracy, Classification]:
    """What a result record says about accuracy: verify's counts and distance statistics, and
    the float64 classes of its disagreements."""
    lo, hi = scene.bounds
    extent = float(np.linalg.norm(hi.astype(np.float64) - lo))
    acc = compare(prim_ids, distances, ref_prim_ids, ref_distances, rel_tol=rel_tol, scene_extent=extent,
                  query=rays.query, tmax=rays.tmax_array, tmin=rays.tmin)
    t0 = time.perf_counter()
    out = classify_disagreements(scene, rays, prim_ids, distances, ref_prim_ids, ref_distances,
                                 rel_tol=rel_tol, abs_tol=acc.abs_tol, max_rays=max_rays)
    return acc, Classification(
        classes={name: int(out["counts"].get(name, 0)) for name in CLASSES},
        unexplained=len(out["unexplained"]),
        unexplained_rays=[int(i) for i in out["unexplained"][:20]],
        classify_capped=bool(out["capped"]),
        classify_seconds=time.perf_counter() - t0)
