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

Any-hit query (query="any": shadow and ambient-occlusion rays, per-ray `tmax`): the answer is
only whether something lies in [tmin, tmax). Embree's answer is derived from its cached closest
hit: occluded iff it hits at t < tmax (its t is already >= tmin, oracle/embree.py), so one cache
file serves either query; Embree's own occlusion query (embree_any_hit, the one its any-hit speed
is timed with) gives the same flags (tests/test_workloads.py). A ray whose occluded flag is the same agrees
(`agree`), whichever primitive either side names; the backend occluded and Embree not is `extra`,
the reverse `missed`; such a disagreement is a `tie` when the hit it hangs on (the backend's for
`extra`, Embree's for `missed`) lies within the distance tolerance of tmin or tmax, where either
answer is right up to rounding. There is no `wrong` or `distance`, and no |dt| (0.0).
A closest-hit query with a finite tmax takes Embree's hits at t >= tmax as misses.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

AGREE, TIE, MISSED, EXTRA, WRONG, DISTANCE = 0, 1, 2, 3, 4, 5
CATEGORY_NAMES = ("agree", "tie", "missed", "extra", "wrong", "distance")
QUERIES = ("closest", "any")


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


def _tmax_array(tmax, n: int) -> np.ndarray:
    """Per-ray tmax as float64 (None: inf)."""
    if tmax is None:
        return np.full(n, np.inf)
    out = np.broadcast_to(np.asarray(tmax, np.float64), (n,))
    return np.array(out)


def _categories(p, t, r, tr, rel_tol: float, abs_tol: float, query: str = "closest", tmax=None,
                tmin: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Category code per ray, and |dt| (NaN where not both hit, and for an any-hit query)."""
    if query not in QUERIES:
        raise ValueError(f"unknown query {query!r}; choose one of {', '.join(QUERIES)}")
    tmax = _tmax_array(tmax, p.shape[0])
    if query == "any":
        return _any_categories(p, t, r, tr, rel_tol, abs_tol, tmax, tmin), np.full(p.shape, np.nan)
    r = np.where(tr < tmax, r, -1)  # Embree traces to infinity; past tmax is no hit of this query
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


def embree_occluded(ref_prim_ids, ref_distances, tmax) -> np.ndarray:
    """Embree's any-hit answer from its cached closest hit (oracle/embree.py): a hit
    before tmax. Its closest hit already lies at or past tmin (oracle/embree.py)."""
    r = _prim_array(ref_prim_ids)
    return (r >= 0) & (np.asarray(ref_distances, np.float64) < _tmax_array(tmax, r.shape[0]))


def _any_categories(p, t, r, tr, rel_tol: float, abs_tol: float, tmax: np.ndarray, tmin: float) -> np.ndarray:
    """AGREE (same occluded flag), MISSED, EXTRA or TIE (the disagreement's hit within the
    tolerance of tmin or tmax) per ray of an any-hit query."""
    occluded, ref_occluded = p >= 0, embree_occluded(r, tr, tmax)
    cat = np.full(p.shape, AGREE, dtype=np.int8)
    cat[ref_occluded & ~occluded] = MISSED
    cat[occluded & ~ref_occluded] = EXTRA
    t_hit = np.where(occluded, t, tr)  # the hit the disagreement hangs on
    with np.errstate(invalid="ignore"):
        near_end = ((np.abs(t_hit - tmax) <= abs_tol + rel_tol * np.abs(tmax))
                    | (np.abs(t_hit - tmin) <= abs_tol + rel_tol * abs(tmin)))
    cat[(cat != AGREE) & near_end] = TIE  # NaN or inf distances are never near a finite end
    return cat


def classify(
    prim_ids, distances, ref_prim_ids, ref_distances, rel_tol=1e-4, abs_tol=None, scene_extent=None,
    query: str = "closest", tmax=None, tmin: float = 0.0,
) -> np.ndarray:
    """int8 category per ray: AGREE, TIE, MISSED, EXTRA, WRONG, DISTANCE (module docstring).
    query "any": the any-hit categories against Embree's closest hits and per-ray tmax."""
    p, t, r, tr = _inputs(prim_ids, distances, ref_prim_ids, ref_distances)
    return _categories(p, t, r, tr, float(rel_tol), resolve_abs_tol(abs_tol, scene_extent), query, tmax, tmin)[0]


def compare(
    prim_ids, distances, ref_prim_ids, ref_distances, rel_tol=1e-4, abs_tol=None, scene_extent=None,
    query: str = "closest", tmax=None, tmin: float = 0.0,
) -> Accuracy:
    """Accuracy of (prim_ids, distances) against the reference (Embree) arrays, for the query."""
    p, t, r, tr = _inputs(prim_ids, distances, ref_prim_ids, ref_distances)
    abs_tol = resolve_abs_tol(abs_tol, scene_extent)
    cat, dt = _categories(p, t, r, tr, float(rel_tol), abs_tol, query, tmax, tmin)
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
    prim_ids, distances, ref_prim_ids, ref_distances, rel_tol=1e-4, abs_tol=None, scene_extent=None,
    query: str = "closest", tmax=None, tmin: float = 0.0,
) -> np.ndarray:
    """Sorted int64 indices of the disagreeing rays (missed, extra, wrong, distance);
    `classify()` tells which category each one is."""
    cat = classify(prim_ids, distances, ref_prim_ids, ref_distances, rel_tol, abs_tol, scene_extent,
                   query, tmax, tmin)
    return np.flatnonzero(cat >= MISSED).astype(np.int64)
