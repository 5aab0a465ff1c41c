"""Reference voxelizer: hand cases, CSR structure, degenerate triangles, and two independent
checks (polygon clipping against the box, dense point sampling on the triangle)."""
import itertools

import numpy as np
import pytest

from lsbench.oracle import reference
from lsbench.oracle.reference import (
    borderline_pairs, compare_to_reference, pairs, voxel_sets, voxelize,
)


def linear(ijk, res):
    i, j, k = ijk
    return i + res[0] * (j + res[1] * k)


def voxels_of(offsets, tri_ids, tri=0):
    return {v for v, t in voxel_sets(offsets, tri_ids) if t == tri}


def ijk_set(res, ijks):
    return {linear(ijk, res) for ijk in ijks}


def assert_valid_csr(offsets, tri_ids, res):
    assert offsets.dtype == np.int64 and tri_ids.dtype == np.int32
    assert offsets.shape == (int(np.prod(res)) + 1,)
    assert offsets[0] == 0 and offsets[-1] == tri_ids.size
    assert np.all(np.diff(offsets) >= 0)
    for v in np.flatnonzero(np.diff(offsets)):
        ids = tri_ids[offsets[v]:offsets[v + 1]]
        assert np.all(np.diff(ids) > 0), f"voxel {v}: ids not strictly ascending"


# --- independent checks ----------------------------------------------------------------------


def clip_overlaps(tri, lo, hi):
    """Triangle (3,3) meets the closed box [lo, hi]: clip it against the 6 box planes
    (Sutherland-Hodgman) and see whether anything is left. Works for segments and points."""
    poly = [np.asarray(p, dtype=np.float64) for p in tri]
    for axis in range(3):
        for sign, bound in ((1.0, lo[axis]), (-1.0, hi[axis])):
            kept = []
            for a, b in zip(poly, poly[1:] + poly[:1]):
                da, db = sign * (a[axis] - bound), sign * (b[axis] - bound)
                if da >= 0:
                    kept.append(a)
                if (da >= 0) != (db >= 0):
                    kept.append(a + da / (da - db) * (b - a))
            poly = kept
            if not poly:
                return False
    return True


def clip_voxelize(grid_tris, res, eps):
    """Brute-force set of (voxel, tri) pairs in grid space, by clipping."""
    found = set()
    for t, tri in enumerate(grid_tris):
        mn, mx = tri.min(axis=0), tri.max(axis=0)
        for ijk in itertools.product(*(range(r) for r in res)):
            lo = np.array(ijk) - eps
            hi = np.array(ijk) + 1.0 + eps
            if np.any(mx < lo) or np.any(mn > hi):  # bounding boxes apart: no overlap
                continue
            if clip_overlaps(tri, lo, hi):
                found.add((linear(ijk, res), t))
    return found


def sampled_voxels(grid_tri, res, n=40):
    """Voxels containing points sampled densely on the triangle (incl. edges and corners)."""
    a, b = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
    keep = a + b <= n
    u, v = a[keep] / n, b[keep] / n
    p = grid_tri[0] + u[:, None] * (grid_tri[1] - grid_tri[0]) + v[:, None] * (grid_tri[2] - grid_tri[0])
    ijk = np.floor(p).astype(np.int64)
    inside = np.all((ijk >= 0) & (ijk < np.asarray(res)), axis=1)
    return {linear(c, res) for c in ijk[inside]}


def random_triangles(rng, count, res):
    """Triangles of mixed sizes, partly outside the grid, plus segments and points."""
    centres = rng.uniform(-0.5, np.asarray(res) + 0.5, size=(count, 1, 3))
    scales = rng.choice([0.2, 0.7, 2.0], size=(count, 1, 1))
    tris = centres + scales * rng.normal(size=(count, 3, 3))
    tris[::7, 2] = tris[::7, 0] + 0.37 * (tris[::7, 1] - tris[::7, 0])  # collinear: segments
    tris[3::11, 1:] = tris[3::11, :1]  # points
    return tris


# --- hand cases ------------------------------------------------------------------------------


def test_triangle_inside_one_voxel():
    res = (4, 5, 6)
    origin = np.array([-1.0, 2.0, 0.5])
    size = np.array([0.5, 0.25, 2.0])
    inside = np.array([[1.2, 2.1, 3.3], [1.8, 2.2, 3.9], [1.5, 2.9, 3.1]])  # grid coords in (1,2,3)
    verts = origin + inside * size
    offsets, tri_ids = voxelize(verts, [[0, 1, 2]], origin, size, res)
    assert_valid_csr(offsets, tri_ids, res)
    assert voxel_sets(offsets, tri_ids) == {(1 + 4 * (2 + 5 * 3), 0)}


def test_triangle_on_voxel_boundary_is_in_both_sides():
    """A big triangle in the plane x = 2.0, which is exactly the boundary between voxel
    columns i=3 and i=4 (origin x = -1, voxel size 0.75)."""
    res = (8, 4, 4)
    origin, size = np.array([-1.0, 0.0, 0.0]), np.array([0.75, 1.0, 1.0])
    verts = np.array([[2.0, -1, -1], [2.0, 20, -1], [2.0, -1, 20]])
    offsets, tri_ids = voxelize(verts, [[0, 1, 2]], origin, size, res)
    want = ijk_set(res, [(i, j, k) for i in (3, 4) for j in range(4) for k in range(4)])
    assert voxels_of(offsets, tri_ids) == want


def test_point_on_voxel_corner_is_in_all_eight_voxels():
    res = (4, 4, 4)
    verts = np.array([[2.0, 2.0, 2.0]])
    offsets, tri_ids = voxelize(verts, [[0, 0, 0]], (0, 0, 0), (1, 1, 1), res)
    assert voxels_of(offsets, tri_ids) == ijk_set(res, itertools.product((1, 2), repeat=3))


def test_degenerate_segments():
    res = (4, 4, 4)
    verts = np.array([[0.5, 0.5, 0.5], [3.5, 0.5, 0.5], [2.5, 1.5, 0.5], [1.0, 0.5, 0.5]])
    faces = [[0, 1, 3], [0, 0, 2]]  # collinear corners; repeated index
    offsets, tri_ids = voxelize(verts, faces, (0, 0, 0), (1, 1, 1), res)
    assert voxels_of(offsets, tri_ids, 0) == ijk_set(res, [(i, 0, 0) for i in range(4)])
    # (0.5,0.5)->(2.5,1.5) crosses y=1 exactly at x=1.5: voxels (0,0) (1,0) (1,1) (2,1).
    want = ijk_set(res, [(0, 0, 0), (1, 0, 0), (1, 1, 0), (2, 1, 0)])
    assert voxels_of(offsets, tri_ids, 1) == want


def test_clipped_to_the_grid():
    res = (4, 4, 4)
    outside = np.array([[5.0, 5, 5], [6, 5, 5], [5, 6, 5]])
    offsets, tri_ids = voxelize(outside, [[0, 1, 2]], (0, 0, 0), (1, 1, 1), res)
    assert tri_ids.size == 0 and offsets.shape == (65,)
    # Reaching in from outside along z=0.5 up to x=1.5: voxels (0,0,0), (1,0,0) only.
    partial = np.array([[-9.0, 0.5, 0.5], [1.5, 0.5, 0.5], [-9.0, 0.6, 0.5]])
    offsets, tri_ids = voxelize(partial, [[0, 1, 2]], (0, 0, 0), (1, 1, 1), res)
    assert voxels_of(offsets, tri_ids) == ijk_set(res, [(0, 0, 0), (1, 0, 0)])


def test_diagonal_triangle_is_not_in_its_bbox_corners():
    """The SAT must reject voxels that only the bounding box touches (triangle normal axis)."""
    res = (4, 4, 4)
    verts = np.array([[4.0, 0, 0], [0, 4.0, 0], [0, 0, 4.0]])  # plane x+y+z = 4
    offsets, tri_ids = voxelize(verts, [[0, 1, 2]], (0, 0, 0), (1, 1, 1), res)
    got = voxels_of(offsets, tri_ids)
    # A voxel meets the plane iff i+j+k <= 4 <= i+j+k+3 (and the triangle's x,y,z >= 0 part).
    want = ijk_set(res, [c for c in itertools.product(range(4), repeat=3) if 1 <= sum(c) <= 4])
    assert got == want


def test_empty_mesh():
    offsets, tri_ids = voxelize(np.zeros((0, 3)), np.zeros((0, 3), int), (0, 0, 0), (1, 1, 1), (2, 3, 4))
    assert offsets.shape == (25,) and not offsets.any() and tri_ids.size == 0


def test_bad_grid_raises():
    with pytest.raises(ValueError):
        voxelize(np.zeros((3, 3)), [[0, 1, 2]], (0, 0, 0), (1, 0, 1), (2, 2, 2))
    with pytest.raises(ValueError):
        voxelize(np.full((3, 3), np.nan), [[0, 1, 2]], (0, 0, 0), (1, 1, 1), (2, 2, 2))


# --- independent checks on random triangles --------------------------------------------------


@pytest.fixture(scope="module")
def random_case():
    rng = np.random.default_rng(11)
    res = (4, 3, 5)
    origin = np.array([-2.0, 1.0, 0.25])
    size = np.array([0.5, 1.5, 0.75])
    grid_tris = random_triangles(rng, 400, res)
    verts = (origin + grid_tris * size).reshape(-1, 3)
    faces = np.arange(verts.shape[0]).reshape(-1, 3)
    # Grid-space corners as voxelize sees them (the mapping is the definition, not under test).
    grid_tris = (verts.reshape(-1, 3, 3) - origin) / size
    return res, origin, size, verts, faces, grid_tris


def test_matches_clipping_up_to_borderline(random_case):
    res, origin, size, verts, faces, grid_tris = random_case
    eps = 1e-4
    offsets, tri_ids = voxelize(verts, faces, origin, size, res, eps)
    assert_valid_csr(offsets, tri_ids, res)
    got = voxel_sets(offsets, tri_ids)
    inner = clip_voxelize(grid_tris, res, eps - 1e-9)
    outer = clip_voxelize(grid_tris, res, eps + 1e-9)
    assert inner - got == set(), "reference misses pairs that clipping finds"
    assert got - outer == set(), "reference has pairs that clipping rejects"
    assert len(got) > 300  # the case is not trivial


def test_contains_every_sampled_voxel(random_case):
    res, origin, size, verts, faces, grid_tris = random_case
    offsets, tri_ids = voxelize(verts, faces, origin, size, res)
    got = voxel_sets(offsets, tri_ids)
    for t, tri in enumerate(grid_tris):
        missing = {v for v in sampled_voxels(tri, res) if (v, t) not in got}
        assert not missing, f"triangle {t}: sampled points in voxels {missing}"


def test_batching_does_not_change_the_result(random_case, monkeypatch):
    """Tiny budgets split single triangles' candidate boxes over several batches."""
    res, origin, size, verts, faces, _ = random_case
    want = voxelize(verts, faces, origin, size, res)
    for budget in (1, 7, 100):
        monkeypatch.setattr(reference, "CANDIDATE_BUDGET", budget)
        got = voxelize(verts, faces, origin, size, res)
        np.testing.assert_array_equal(got[0], want[0])
        np.testing.assert_array_equal(got[1], want[1])


def test_eps_grows_the_set_monotonically(random_case):
    res, origin, size, verts, faces, _ = random_case
    sets = [voxel_sets(*voxelize(verts, faces, origin, size, res, eps)) for eps in (0, 1e-4, 0.1)]
    assert sets[0] <= sets[1] <= sets[2]


# --- comparison helpers ----------------------------------------------------------------------


def near_boundary_case():
    """Triangle in the plane x = 3 - 5e-5 (grid units): in column i=3 only thanks to eps=1e-4."""
    x = 3.0 - 5e-5
    verts = np.array([[x, -1, -1], [x, 20, -1], [x, -1, 20]])
    return verts, [[0, 1, 2]], (0, 0, 0), (1, 1, 1), (4, 4, 4)


def test_borderline_pairs_are_the_near_boundary_column():
    case = near_boundary_case()
    border = borderline_pairs(*case, eps=1e-4, delta=1e-4)
    assert border.dtype == np.int64 and border.shape[1] == 2
    want = {(linear((3, j, k), (4, 4, 4)), 0) for j in range(4) for k in range(4)}
    assert set(map(tuple, border.tolist())) == want
    assert borderline_pairs(*case, eps=1e-4, delta=1e-5).size == 0


def test_compare_to_reference_accepts_borderline_and_any_order():
    case = near_boundary_case()
    offsets, tri_ids = voxelize(*case, eps=1e-4)
    missing, extra = compare_to_reference(offsets, tri_ids, *case, eps=1e-4, delta=1e-4)
    assert missing.size == 0 and extra.size == 0
    # Without the borderline column (what a float32 kernel might produce): still accepted.
    inner = voxelize(*case, eps=0.0)
    missing, extra = compare_to_reference(*inner, *case, eps=1e-4, delta=1e-4)
    assert missing.size == 0 and extra.size == 0


def test_compare_to_reference_reports_errors():
    rng = np.random.default_rng(5)
    res = (4, 4, 4)
    tris = rng.uniform(0, 4, size=(20, 3, 3))
    tris[19] = [[0.2, 0.2, 0.2], [0.5, 0.2, 0.2], [0.2, 0.5, 0.3]]  # only in voxel 0
    case = (tris.reshape(-1, 3), np.arange(60).reshape(-1, 3), (0, 0, 0), (1, 1, 1), res)
    offsets, tri_ids = voxelize(*case)
    p = pairs(offsets, tri_ids)
    # Drop one pair and add one far-away pair, then rebuild a CSR with ids in reverse order.
    dropped = p[0]
    fake = np.array([[63, 19]])
    bad = np.concatenate([p[1:], fake])
    bad = bad[np.lexsort((-bad[:, 1], bad[:, 0]))]
    bad_offsets = np.zeros(65, np.int64)
    np.cumsum(np.bincount(bad[:, 0], minlength=64), out=bad_offsets[1:])
    missing, extra = compare_to_reference(bad_offsets, bad[:, 1], *case, eps=1e-4, delta=1e-6)
    assert missing.tolist() == [dropped.tolist()]
    assert extra.tolist() == fake.tolist()
    # A duplicate id in one voxel is a malformed result.
    dup_offsets = offsets.copy()
    dup_ids = np.insert(tri_ids, offsets[p[0, 0]], p[0, 1])
    dup_offsets[p[0, 0] + 1:] += 1
    with pytest.raises(ValueError):
        compare_to_reference(dup_offsets, dup_ids, *case, eps=1e-4, delta=1e-6)
