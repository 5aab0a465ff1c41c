"""Reference conservative voxelizer (numpy, float64). The GPU voxelizers are tested against it.

Grid convention (shared with the GPU kernels)
---------------------------------------------
A grid is `origin` (3,) float, `voxel_size` (3,) float (> 0; non-cubic voxels allowed) and
`resolution` (rx, ry, rz) ints (non-cubic grids allowed).

- Voxel (i, j, k) covers origin + [i, i+1] x [j, j+1] x [k, k+1] * voxel_size (closed box).
- Linear voxel index = i + rx * (j + ry * k)   (x fastest, z slowest).
- Triangles are mapped to grid space, p' = (p - origin) / voxel_size, where voxels are unit
  cubes. The overlap test is done there against the box [i-eps, i+1+eps] x [j-eps, j+1+eps] x
  [k-eps, k+1+eps]: `eps` (grid units) makes the result conservative despite rounding, so a
  triangle lying exactly on a voxel boundary (or touching a corner) is in the voxels on both
  sides.
- A triangle is in a voxel iff it overlaps that eps-expanded box by the separating-axis test of
  Akenine-Moeller, "Fast 3D Triangle-Box Overlap Testing" (JGT 2001): 13 axes = the 3 box
  normals, the triangle normal, and the 9 cross products of triangle edges with box axes.
- Only voxels inside the resolution are produced; triangles (or parts) outside are clipped.
- Degenerate triangles (segments, points) are kept: their zero normal and zero cross products
  project everything to 0, which never separates, and the remaining axes (box normals and
  segment-direction x box axes) are exactly the separating axes of a segment or point against a
  box. So a degenerate triangle is in every voxel its segment or point touches.

Result format (CSR, what the GPU count / scan / fill passes produce)
---------------------------------------------------------------------
`offsets` (rx*ry*rz + 1,) int64: exclusive prefix sum of the per-voxel counts.
`tri_ids` (offsets[-1],) int32: triangle indices of voxel v in tri_ids[offsets[v]:offsets[v+1]],
ascending within a voxel.

Comparing a GPU result (float32) with this reference (float64)
--------------------------------------------------------------
Float32 arithmetic moves the decision for (voxel, triangle) pairs whose triangle passes within
about one rounding error of the eps-expanded box. `borderline_pairs(..., eps, delta)` lists the
pairs in voxelize(eps + delta) but not in voxelize(eps - delta); a correct GPU result G satisfies
voxelize(eps - delta) <= G <= voxelize(eps + delta) (as pair sets), i.e. it differs from
voxelize(eps) only on borderline pairs. `compare_to_reference` does this check.
`suggested_delta(resolution)` gives a delta for float32 kernels.
"""
from __future__ import annotations

import functools

import numpy as np

# Candidate (voxel, triangle) pairs tested per batch: bounds the temporary arrays (~100 MB).
CANDIDATE_BUDGET = 1 << 20


# --- public API ------------------------------------------------------------------------------


def voxelize(vertices, faces, origin, voxel_size, resolution, eps: float = 1e-4):
    """Conservative voxelization: (offsets int64, tri_ids int32) in CSR form (module docstring)."""
    origin, voxel_size, res = _grid(origin, voxel_size, resolution)
    half = 0.5 + float(eps)
    if half <= 0.0:
        raise ValueError(f"eps={eps} shrinks the voxel box to nothing")
    tris = _grid_space_triangles(vertices, faces, origin, voxel_size)
    lo, ext = _candidate_boxes(tris, res, float(eps))
    counts = ext.prod(axis=1)

    voxel_parts, tri_parts = [], []
    for first, last, skip, take in _batches(counts, CANDIDATE_BUDGET):
        voxels, local = _overlapping_candidates(
            tris[first:last], lo[first:last], ext[first:last], skip, take, res, half
        )
        voxel_parts.append(voxels)
        tri_parts.append(local + first)
    voxels = np.concatenate(voxel_parts) if voxel_parts else np.zeros(0, np.int64)
    tri_ids = np.concatenate(tri_parts) if tri_parts else np.zeros(0, np.int64)
    return _to_csr(voxels, tri_ids, int(np.prod(res)))


def pairs(offsets, tri_ids) -> np.ndarray:
    """(M, 2) int64 array of (linear voxel index, triangle id), in CSR order."""
    offsets = np.asarray(offsets, dtype=np.int64)
    voxels = np.repeat(np.arange(offsets.size - 1, dtype=np.int64), np.diff(offsets))
    return np.stack([voxels, np.asarray(tri_ids, dtype=np.int64)], axis=1)


def voxel_sets(offsets, tri_ids) -> set[tuple[int, int]]:
    """Python set of (voxel, tri) pairs (convenient for small tests and error messages)."""
    return set(map(tuple, pairs(offsets, tri_ids).tolist()))


def borderline_pairs(vertices, faces, origin, voxel_size, resolution, eps: float, delta: float):
    """(M, 2) int64 pairs in voxelize(eps + delta) but not in voxelize(eps - delta).

    These are the only pairs on which a float32 voxelizer using `eps` may legitimately differ
    from the float64 reference: the triangle passes within `delta` grid units (measured along
    the separating axes) of the eps-expanded voxel box.
    """
    inner, outer = _inner_outer(vertices, faces, origin, voxel_size, resolution, eps, delta)
    n_tri = max(len(np.asarray(faces)), 1)
    keep = np.setdiff1d(_keys(outer, n_tri), _keys(inner, n_tri), assume_unique=True)
    return _unkey(keep, n_tri)


def compare_to_reference(
    offsets, tri_ids, vertices, faces, origin, voxel_size, resolution, eps: float, delta: float
) -> tuple[np.ndarray, np.ndarray]:
    """Check a voxelization G (CSR, e.g. read back from a GPU) against the reference.

    Returns (missing, extra), both (M, 2) int64 (voxel, tri) pairs: `missing` are in
    voxelize(eps - delta) but not in G (a conservative voxelizer must have them), `extra` are in
    G but not in voxelize(eps + delta). Both empty means G is correct. The order of ids within a
    voxel is free (a GPU fill pass with atomics writes them in any order); a malformed CSR
    (wrong length, decreasing offsets, ids out of range, an id twice in a voxel) raises
    ValueError.
    """
    res = _grid(origin, voxel_size, resolution)[2]
    n_tri = max(len(np.asarray(faces)), 1)
    got = _csr_keys(offsets, tri_ids, int(np.prod(res)), n_tri)
    inner, outer = _inner_outer(vertices, faces, origin, voxel_size, resolution, eps, delta)
    missing = np.setdiff1d(_keys(inner, n_tri), got, assume_unique=True)
    extra = np.setdiff1d(got, _keys(outer, n_tri), assume_unique=True)
    return _unkey(missing, n_tri), _unkey(extra, n_tri)


def suggested_delta(resolution) -> float:
    """Borderline width (grid units) for comparing float32 kernels: 2^-24 relative rounding on
    grid-space coordinates up to max(resolution), times a safety factor of 64 for the few
    operations of the transform and the SAT (a heuristic, not a proof)."""
    return 64.0 * 2.0**-24 * float(max(np.atleast_1d(resolution).max(), 1))


# --- grid and triangles ----------------------------------------------------------------------


def _grid(origin, voxel_size, resolution):
    origin = np.broadcast_to(np.asarray(origin, dtype=np.float64), (3,)).copy()
    voxel_size = np.broadcast_to(np.asarray(voxel_size, dtype=np.float64), (3,)).copy()
    res = np.broadcast_to(np.asarray(resolution, dtype=np.int64), (3,)).copy()
    if np.any(res <= 0) or np.any(voxel_size <= 0) or not np.all(np.isfinite(voxel_size)):
        raise ValueError(f"bad grid: voxel_size={voxel_size}, resolution={res}")
    if not np.all(np.isfinite(origin)):
        raise ValueError(f"bad grid origin {origin}")
    return origin, voxel_size, res


def _grid_space_triangles(vertices, faces, origin, voxel_size) -> np.ndarray:
    """(T, 3, 3) float64 corners in grid space (voxels are unit cubes)."""
    vertices = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    tris = (vertices[faces] - origin) / voxel_size
    if not np.all(np.isfinite(tris)):
        raise ValueError("non-finite triangle corner")
    return tris


def _candidate_boxes(tris, res, eps):
    """Per triangle: first candidate voxel (T,3) and extent (T,3) of the voxel range whose
    eps-boxes overlap the triangle's bounding box (the 3 box-normal axes of the SAT), clipped
    to the grid. Voxel i's box [i-eps, i+1+eps] meets [mn, mx] iff mn-1-eps <= i <= mx+eps."""
    mn, mx = tris.min(axis=1), tris.max(axis=1)
    lo = np.ceil(mn - 1.0 - eps)
    hi = np.floor(mx + eps)
    lo = np.clip(lo, 0, res).astype(np.int64)  # clip in float first: no int overflow
    hi = np.clip(hi, -1, res - 1).astype(np.int64)
    ext = np.maximum(hi - lo + 1, 0)
    return lo, ext


def _sat_axes(tris):
    """The 10 non-box-normal SAT axes per triangle: (T, 10, 3) = normal, then e_k x unit_j.

    Any vector is a valid candidate axis, so rounding in the axes themselves cannot make the
    test wrong; degenerate triangles give (near-)zero axes, which never separate.
    """
    v0, v1, v2 = tris[:, 0], tris[:, 1], tris[:, 2]
    edges = np.stack([v1 - v0, v2 - v1, v0 - v2], axis=1)  # (T, 3, 3)
    normal = np.cross(edges[:, 0], edges[:, 1])
    unit = np.eye(3)
    cross = np.cross(edges[:, :, None, :], unit[None, None, :, :])  # (T, 3 edges, 3 units, 3)
    return np.concatenate([normal[:, None, :], cross.reshape(-1, 9, 3)], axis=1)


def _axis_intervals(tris, axes, half):
    """For every axis a: (mid, rad) such that the triangle and the box of half-size `half`
    centred at c overlap along a iff |a.c - mid| <= rad (projected intervals intersect)."""
    proj = np.einsum("tac,tvc->tav", axes, tris)  # (T, 10, 3 vertices)
    pmin, pmax = proj.min(axis=2), proj.max(axis=2)
    box_radius = half * np.abs(axes).sum(axis=2)
    return 0.5 * (pmin + pmax), 0.5 * (pmax - pmin) + box_radius


# --- candidate enumeration and test ----------------------------------------------------------


def _batches(counts, budget):
    """Split the concatenated candidate lists of all triangles into windows of <= budget
    candidates. Yields (first, last, skip, take): triangles [first, last) and, per triangle in
    that range, how many leading candidates to skip and how many to take. A triangle with more
    candidates than the budget is split over several windows."""
    ends = np.cumsum(counts)
    starts = ends - counts
    total = int(ends[-1]) if len(ends) else 0
    for w0 in range(0, total, budget):
        w1 = min(w0 + budget, total)
        first = int(np.searchsorted(ends, w0, side="right"))
        last = int(np.searchsorted(starts, w1, side="left"))
        s, e = starts[first:last], ends[first:last]
        skip = np.maximum(w0 - s, 0)
        take = np.minimum(e, w1) - s - skip
        yield first, last, skip, take


def _overlapping_candidates(tris, lo, ext, skip, take, res, half):
    """Run the SAT on the given candidates; return (linear voxel ids, local triangle ids) of
    the overlapping pairs, triangle-major."""
    owner = np.repeat(np.arange(len(tris)), take)
    first_of_owner = np.cumsum(take) - take
    rank = np.arange(owner.size) - np.repeat(first_of_owner - skip, take)  # index in the box
    ex, ey = ext[owner, 0], ext[owner, 1]
    i = lo[owner, 0] + rank % ex
    rest = rank // ex
    j = lo[owner, 1] + rest % ey
    k = lo[owner, 2] + rest // ey

    axes = _sat_axes(tris)
    mid, rad = _axis_intervals(tris, axes, half)
    centre = (i + 0.5, j + 0.5, k + 0.5)
    keep = np.ones(owner.size, dtype=bool)
    for a in range(axes.shape[1]):
        along = sum(axes[owner, a, c] * centre[c] for c in range(3))
        keep &= np.abs(along - mid[owner, a]) <= rad[owner, a]
    voxels = i + res[0] * (j + res[1] * k)
    return voxels[keep], owner[keep]


def _to_csr(voxels, tri_ids, voxel_count):
    # Candidates arrive triangle-major with ascending triangle ids, so a stable sort by voxel
    # leaves the ids ascending within each voxel.
    order = np.argsort(voxels, kind="stable")
    counts = np.bincount(voxels, minlength=voxel_count)
    offsets = np.zeros(voxel_count + 1, dtype=np.int64)
    np.cumsum(counts, out=offsets[1:])
    return offsets, tri_ids[order].astype(np.int32)


# --- comparison helpers ----------------------------------------------------------------------


def _inner_outer(vertices, faces, origin, voxel_size, resolution, eps, delta):
    if delta < 0:
        raise ValueError("delta must be >= 0")
    inner = pairs(*voxelize(vertices, faces, origin, voxel_size, resolution, eps - delta))
    outer = pairs(*voxelize(vertices, faces, origin, voxel_size, resolution, eps + delta))
    return inner, outer


def _keys(p, n_tri):
    """Unique sortable int64 key per (voxel, tri) pair (sorted when p is in CSR order)."""
    return p[:, 0] * n_tri + p[:, 1]


def _unkey(keys, n_tri):
    return np.stack([keys // n_tri, keys % n_tri], axis=1)


def _csr_keys(offsets, tri_ids, voxel_count, n_tri):
    """Sorted unique keys of a CSR voxelization, after checking its structure."""
    offsets = np.asarray(offsets, dtype=np.int64)
    tri_ids = np.asarray(tri_ids, dtype=np.int64)
    if offsets.shape != (voxel_count + 1,) or offsets[0] != 0 or offsets[-1] != tri_ids.size:
        raise ValueError("CSR offsets have the wrong length or ends")
    if np.any(np.diff(offsets) < 0):
        raise ValueError("CSR offsets decrease")
    if tri_ids.size and (tri_ids.min() < 0 or tri_ids.max() >= n_tri):
        raise ValueError("triangle id out of range")
    keys = np.sort(_keys(pairs(offsets, tri_ids), n_tri))
    if keys.size > 1 and np.any(keys[1:] == keys[:-1]):
        raise ValueError("a triangle id appears twice in one voxel")
    return keys


# --- Line Space shaft candidates (linespace.h), numpy float64 ------------------------------------
# The device decides per (shaft, triangle) in cell-local coordinates (the cell is the unit cube):
# rejected when one facet plane of the shaft volume (the convex hull of its two patches) has all
# three corners outside by more than eps; accepted when every corner is within eps of every
# facet; otherwise by the exact test of the backend: "sat", the separating-axis test (triangle
# normal, triangle edges x cell axes, triangle edges x corner-to-corner directions, margin
# eps * |axis|), or "clip", clipping against the facet planes pushed out by eps (Sutherland-
# Hodgman) = the triangle meets the polytope {x : n_q . x + w_q <= eps}, or "edges", the same
# predicate decided by edges (a triangle edge in that polytope or a polytope edge through the
# triangle, linespace.h: ls_volume_edge_meets). Whatever the device does
# to get there faster (culls, certain cases: linespace.h), its lists must be these, up to float32
# rounding: shaft_candidates(eps - delta) <= device <= shaft_candidates(eps + delta) (the
# decision grows with eps), see linespace_borderline.
FACE_PAIRS = tuple((a, b) for a in range(6) for b in range(a + 1, 6))  # block order of Listing 1


def patch_corners(face: int, patch: int, n: int) -> np.ndarray:
    """(4, 3) corners k = 0..3 of a patch, cell-local, in the order of linespace.h ls_patch_corner."""
    axis, side = divmod(face, 2)
    ui, vi = patch % n, patch // n
    out = np.empty((4, 3))
    for k in range(4):
        out[k, axis] = side
        out[k, (axis + 1) % 3] = (ui + (k & 1)) / n
        out[k, (axis + 2) % 3] = (vi + (k >> 1)) / n
    return out


@functools.lru_cache(maxsize=8)
def shaft_corners(n: int) -> np.ndarray:
    """(15 N^4, 8, 3): the 4 corners of the first patch, then the second's, per shaft id."""
    out = []
    for a, b in FACE_PAIRS:
        for pa in range(n * n):
            for pb in range(n * n):
                out.append(np.vstack([patch_corners(a, pa, n), patch_corners(b, pb, n)]))
    return np.array(out)


@functools.lru_cache(maxsize=8)
def shaft_facets(n: int) -> np.ndarray:
    """(15 N^4, 8, 4): per shaft the outward unit facet planes (n, w) of the hull of its 8
    corners (planes through 3 corners with all 8 on one side; dot(n, p) + w <= 0 inside), the
    unused slots (0, 0, 0, -1) like linespace.h's ls_planes_kernel."""
    corners = shaft_corners(n)
    out = np.tile(np.array([0.0, 0.0, 0.0, -1.0]), (len(corners), 8, 1))
    triples = np.array([(i, j, k) for i in range(8) for j in range(i + 1, 8) for k in range(j + 1, 8)])
    for s, P in enumerate(corners):
        nrm = np.cross(P[triples[:, 1]] - P[triples[:, 0]], P[triples[:, 2]] - P[triples[:, 0]])
        length = np.linalg.norm(nrm, axis=1)
        keep = length > 1e-9
        nrm, origin = nrm[keep] / length[keep, None], P[triples[keep, 0]]
        d = np.einsum("fc,pc->fp", nrm, P) - np.einsum("fc,fc->f", nrm, origin)[:, None]
        facet = ~((d.max(1) > 1e-9) & (d.min(1) < -1e-9))
        flip = np.where(d.max(1) > 1e-9, -1.0, 1.0)[:, None]
        nrm = (nrm * flip)[facet]
        planes = np.concatenate([nrm, -np.einsum("fc,fc->f", nrm, origin[facet])[:, None]], 1)
        planes = np.unique(np.round(planes, 9), axis=0)
        out[s, :len(planes)] = planes
    return out


def shaft_candidates(tris: np.ndarray, n: int, eps: float, test: str) -> np.ndarray:
    """(15 N^4, T) bool: triangle t (tris (T, 3, 3), cell-local float64) is a candidate of shaft s."""
    if test not in ("sat", "clip", "edges"):
        raise ValueError(f"test must be 'sat', 'clip' or 'edges', got {test!r}")
    corners, facets = shaft_corners(n), shaft_facets(n)
    dist = np.einsum("tkc,sfc->stfk", tris, facets[:, :, :3]) + facets[:, None, :, 3, None]  # (S, T, 8, 3)
    out_all = (dist - eps > 0).all(axis=3).any(axis=2)
    in_all = (dist - eps <= 0).all(axis=(2, 3))
    s_idx, t_idx = np.nonzero(~out_all & ~in_all)
    meets = in_all & ~out_all
    for lo in range(0, len(s_idx), 1 << 16):  # bounded temporaries
        s, t = s_idx[lo:lo + (1 << 16)], t_idx[lo:lo + (1 << 16)]
        exact = _sat_meets(tris[t], corners[s], eps) if test == "sat" else _clip_meets(tris[t], facets[s], eps)
        meets[s, t] = exact
    return meets


def linespace_borderline(tris: np.ndarray, n: int, eps: float, delta: float, test: str):
    """(inner, outer) candidate sets at eps - delta and eps + delta: a correct float32 build lies
    between them (like borderline_pairs for the voxelizer)."""
    return shaft_candidates(tris, n, eps - delta, test), shaft_candidates(tris, n, eps + delta, test)


def _sat_meets(tris: np.ndarray, P: np.ndarray, eps: float) -> np.ndarray:
    """No axis of linespace.h ls_sat_meets separates triangle k from the hull of P[k] by more than
    eps * |axis| (the facet normals are the quick test's)."""
    a, b, c = tris[:, 0], tris[:, 1], tris[:, 2]
    edges = [b - a, c - b, a - c]
    dirs = [np.broadcast_to(np.eye(3)[k], a.shape) for k in range(3)] + [P[:, 4 + j] - P[:, i]
                                                                        for i in range(4) for j in range(4)]
    axes = [np.cross(b - a, c - a)] + [np.cross(e, d) for e in edges for d in dirs]
    meets = np.ones(len(tris), bool)
    for ax in axes:
        t = np.einsum("tkc,tc->tk", tris, ax)
        h = np.einsum("tpc,tc->tp", P, ax)
        m = eps * np.linalg.norm(ax, axis=1)
        meets &= ~((t.min(1) > h.max(1) + m) | (t.max(1) < h.min(1) - m))
    return meets


def _clip_meets(tris: np.ndarray, F: np.ndarray, eps: float) -> np.ndarray:
    """Triangle k meets {x : F[k, :, :3] . x + F[k, :, 3] <= eps}: a 2D linear feasibility problem in
    the barycentric coordinates (l1, l2), l1, l2 >= 0, l1 + l2 <= 1, solved by trying every
    vertex of the constraint arrangement (the feasible polygon, if any, has one of them as a
    corner)."""
    a, b, c = tris[:, 0], tris[:, 1], tris[:, 2]
    # Constraint rows g . (l1, l2) <= h: x = a + l1 (b - a) + l2 (c - a).
    g1 = np.einsum("tc,tfc->tf", b - a, F[:, :, :3])
    g2 = np.einsum("tc,tfc->tf", c - a, F[:, :, :3])
    h = eps - F[:, :, 3] - np.einsum("tc,tfc->tf", a, F[:, :, :3])
    T = len(tris)
    G = np.concatenate([np.stack([g1, g2], -1), np.broadcast_to([[-1.0, 0.0], [0.0, -1.0], [1.0, 1.0]], (T, 3, 2))], 1)
    H = np.concatenate([h, np.broadcast_to([0.0, 0.0, 1.0], (T, 3))], 1)
    k = G.shape[1]
    i, j = np.triu_indices(k, 1)
    A = np.stack([G[:, i], G[:, j]], -2)  # (T, pairs, 2, 2)
    rhs = np.stack([H[:, i], H[:, j]], -1)
    det = np.linalg.det(A)
    ok = np.abs(det) > 1e-12
    A[~ok] = np.eye(2)
    pts = np.linalg.solve(A, rhs[..., None])[..., 0]  # (T, pairs, 2)
    slack = np.einsum("tkc,tpc->tpk", G, pts) - H[:, None, :]
    feasible = ok & (slack <= 1e-12 * (1 + np.abs(H[:, None, :]))).all(-1)
    return feasible.any(1)
