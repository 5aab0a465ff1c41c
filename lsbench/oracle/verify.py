"""Compare a backend's closest hits with the Embree reference (lsbench.oracle.embree).

Every ray falls in exactly one category:

- `agree`    : same primitive at the same distance within tolerance, or both miss.
- `tie`      : both hit different primitives at the same distance within tolerance (shared
               edges, coplanar or duplicated faces: either answer is a correct closest hit).
- `missed`   : Embree hits, the backend misses.
- `extra`    : the backend hits, Embree misses.
- `wrong`    : both hit different primitives and the distances differ beyond tolerance.
- `distance` : same primitive, but the distances differ beyond tolerance (a traversal that
               finds the right triangle and reports the wrong t, say measured from a cell's entry).

A miss is prim id -1 (any negative id, or 0xFFFFFFFF from an unsigned buffer). The distance of a
miss is not looked at. A backend *hit* whose distance is NaN is never agreement: it is `wrong`
when Embree hits (even with the same primitive) and `extra` when Embree misses. An infinite
distance never ties (the relative tolerance would otherwise be infinite too).

Distance tolerance (agree and tie): |t - t_ref| <= abs_tol + rel_tol * max(t_ref, t). abs_tol
defaults to 1e-5 * scene_extent (the scene bounding-box diagonal) when that is given, else 1e-6.
`missed`, `extra`, `wrong` and `distance` are the disagreements; lsbench.oracle.classifier
re-evaluates each in float64 and says which of them float32 or Embree explain.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

AGREE, TIE, MISSED, EXTRA, WRONG, DISTANCE = 0, 1, 2, 3, 4, 5
CATEGORY_NAMES = ("agree", "tie", "missed", "extra", "wrong", "distance")


@dataclass
class Accuracy:
    ray_count: int
    agree: int
    ties: int
    missed: int
    extra: int
    wrong: int
    distance: int  # same primitive, |dt| beyond the tolerance
    agreement: float  # (agree + ties) / ray_count; 1.0 for an empty ray set
    max_abs_dt: float  # over rays where both hit (NaN distances left out); 0.0 if none
    median_abs_dt: float
    rel_tol: float
    abs_tol: float

    @property
    def disagreements(self) -> int:
        return self.missed + self.extra + self.wrong + self.distance

    def to_dict(self) -> dict:
        return asdict(self)


def resolve_abs_tol(abs_tol: float | None, scene_extent: float | None) -> float:
    """abs_tol as given, else 1e-5 * scene_extent, else 1e-6."""
    if abs_tol is not None:
        return float(abs_tol)
    if scene_extent is not None:
        return 1e-5 * float(scene_extent)
    return 1e-6


def _prim_array(prim_ids) -> np.ndarray:
    """int64 ids with every miss encoding (negative, or 0xFFFFFFFF as unsigned) turned into -1."""
    a = np.asarray(prim_ids)
    if a.dtype.kind == "u":
        wide = a.astype(np.uint64)
        out = wide.astype(np.int64)
        out[(wide == 0xFFFFFFFF) | (wide == np.iinfo(np.uint64).max)] = -1
        return out
    out = a.astype(np.int64)
    out[out < 0] = -1
    return out


def _inputs(prim_ids, distances, ref_prim_ids, ref_distances):
    p = _prim_array(prim_ids)
    r = _prim_array(ref_prim_ids)
    t = np.asarray(distances, dtype=np.float64)
    tr = np.asarray(ref_distances, dtype=np.float64)
    shapes = {p.shape, r.shape, t.shape, tr.shape}
    if len(shapes) != 1 or p.ndim != 1:
        raise ValueError(f"expected four 1-D arrays of one length, got shapes {sorted(shapes)}")
    return p, t, r, tr


def _categories(p, t, r, tr, rel_tol: float, abs_tol: float) -> tuple[np.ndarray, np.ndarray]:
    """Category code per ray, and |dt| (NaN where not both hit)."""
    hit, ref_hit = p >= 0, r >= 0
    both = hit & ref_hit
    with np.errstate(invalid="ignore"):
        dt = np.where(both, np.abs(t - tr), np.nan)
        tol = abs_tol + rel_tol * np.maximum(t, tr)
        close = np.isfinite(dt) & (dt <= tol)  # an inf or NaN distance never ties
    nan_hit = hit & np.isnan(t)

    cat = np.full(p.shape, WRONG, dtype=np.int8)
    cat[~hit & ~ref_hit] = AGREE
    cat[both & (p == r) & ~nan_hit] = DISTANCE
    cat[both & (p == r) & ~nan_hit & close] = AGREE
    cat[both & (p != r) & close] = TIE  # nan_hit gives close == False
    cat[~hit & ref_hit] = MISSED
    cat[hit & ~ref_hit] = EXTRA
    return cat, dt


def classify(
    prim_ids, distances, ref_prim_ids, ref_distances, rel_tol=1e-4, abs_tol=None, scene_extent=None
) -> np.ndarray:
    """int8 category per ray: AGREE, TIE, MISSED, EXTRA, WRONG, DISTANCE (module docstring)."""
    p, t, r, tr = _inputs(prim_ids, distances, ref_prim_ids, ref_distances)
    return _categories(p, t, r, tr, float(rel_tol), resolve_abs_tol(abs_tol, scene_extent))[0]


def compare(
    prim_ids, distances, ref_prim_ids, ref_distances, rel_tol=1e-4, abs_tol=None, scene_extent=None
) -> Accuracy:
    """Accuracy of (prim_ids, distances) against the reference (Embree) arrays."""
    p, t, r, tr = _inputs(prim_ids, distances, ref_prim_ids, ref_distances)
    abs_tol = resolve_abs_tol(abs_tol, scene_extent)
    cat, dt = _categories(p, t, r, tr, float(rel_tol), abs_tol)
    counts = np.bincount(cat, minlength=len(CATEGORY_NAMES))
    n = int(p.shape[0])

    measured = dt[~np.isnan(dt)]
    max_dt = float(measured.max()) if measured.size else 0.0
    median_dt = float(np.median(measured)) if measured.size else 0.0
    return Accuracy(
        ray_count=n,
        agree=int(counts[AGREE]),
        ties=int(counts[TIE]),
        missed=int(counts[MISSED]),
        extra=int(counts[EXTRA]),
        wrong=int(counts[WRONG]),
        distance=int(counts[DISTANCE]),
        agreement=float(counts[AGREE] + counts[TIE]) / n if n else 1.0,
        max_abs_dt=max_dt,
        median_abs_dt=median_dt,
        rel_tol=float(rel_tol),
        abs_tol=abs_tol,
    )


def disagreement_indices(
    prim_ids, distances, ref_prim_ids, ref_distances, rel_tol=1e-4, abs_tol=None, scene_extent=None
) -> np.ndarray:
    """Sorted int64 indices of the disagreeing rays (missed, extra, wrong, distance);
    `classify()` tells which category each one is."""
    cat = classify(prim_ids, distances, ref_prim_ids, ref_distances, rel_tol, abs_tol, scene_extent)
    return np.flatnonzero(cat >= MISSED).astype(np.int64)
