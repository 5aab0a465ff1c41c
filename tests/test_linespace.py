"""`grid-ls` and the Line Space build on both backends.

- Shaft candidate lists are conservative: every triangle that a segment between two points of a
  shaft's patches meets is a candidate of that shaft (numpy, segments sampled independently of
  the device's facet planes), for N = 1, 2, 3 and both exact tests (clipping, SAT).
- They are the numpy reference's (lsbench/oracle/reference.py: shaft_candidates) up to float32
  rounding, also when a cell's candidates are split over several work items (the driver's loop
  budget) and for a cell past llvmpipe's budget of 65535 loop iterations.
- Hits agree with Embree, and with `grid` up to ties; ls_min_candidates keeps the hits and saves
  memory; the 32-bit and buffer-size limits raise DeviceLimitError instead of truncating.
"""
from __future__ import annotations

import numpy as np
import pytest

from lsbench import backends
from lsbench.backends import BuildParams, DeviceLimitError
from lsbench.backends.structures import linespace
from lsbench.oracle import reference
from lsbench.oracle.embree import embree_closest
from lsbench.inputs.rays import RaySet, primary_rays
from lsbench.inputs.scene import Camera, Scene
from lsbench.inputs.scenes import load_scene
from lsbench.oracle.verify import compare

from conftest import scene_path

# Sponza (Crytek, cm): an interior view down the atrium (all rays hit).
SPONZA_CAMERA = Camera(eye=(1300.0, 300.0, -50.0), target=(-1000.0, 450.0, 0.0), up=(0, 1, 0), fov_deg=60.0)
FACE_PAIRS = list(reference.FACE_PAIRS)  # block order of Listing 1


def random_scene(n_tris=40, size=0.3, seed=3) -> Scene:
    rng = np.random.default_rng(seed)
    centres = rng.uniform(-1, 1, (n_tris, 1, 3))
    v = (centres + rng.normal(0, size, (n_tris, 3, 3))).reshape(-1, 3).astype(np.float32)
    return Scene("random", v, np.arange(3 * n_tris, dtype=np.uint32).reshape(-1, 3), "test")


def random_rays(scene: Scene, n=4000, seed=5) -> RaySet:
    rng = np.random.default_rng(seed)
    lo, hi = scene.bounds
    o = rng.uniform(lo - 0.5, hi + 0.5, (n, 3)).astype(np.float32)
    d = rng.normal(size=(n, 3))
    return RaySet("random", o, (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32))


def accuracy(scene, hits, ref_p, ref_t):
    lo, hi = scene.bounds
    return compare(hits.prim_ids, hits.distances, ref_p, ref_t, scene_extent=float(np.linalg.norm(hi - lo)))


# --- numpy reference of the shaft geometry ----------------------------------------------------
def patch_points(face: int, patch: int, n: int, r: np.ndarray) -> np.ndarray:
    """Cell-local points of a patch; r (K, 2) in [0, 1] are positions inside the patch."""
    axis, side = divmod(face, 2)
    ui, vi = patch % n, patch // n
    p = np.empty((len(r), 3))
    p[:, axis] = side
    p[:, (axis + 1) % 3] = (ui + r[:, 0]) / n
    p[:, (axis + 2) % 3] = (vi + r[:, 1]) / n
    return p


def shaft_segments(n: int, samples: int, rng) -> tuple[np.ndarray, np.ndarray]:
    """(15 N^4, K, 3) start and end points per shaft id (Listing 1 order); corners and edges of the
    patches are among the samples, since rays along the shaft's boundary are the hard cases."""
    edge = np.array([[0, 0], [1, 1], [0, 1], [1, 0], [0.5, 0], [1, 0.5]])
    starts, ends = [], []
    for a, b in FACE_PAIRS:
        for pa in range(n * n):
            for pb in range(n * n):
                ra = np.vstack([edge, rng.uniform(0, 1, (samples - len(edge), 2))])
                rb = np.vstack([edge[::-1], rng.uniform(0, 1, (samples - len(edge), 2))])
                starts.append(patch_points(a, pa, n, ra))
                ends.append(patch_points(b, pb, n, rb))
    return np.array(starts), np.array(ends)


def segments_hit(p, q, tris) -> np.ndarray:
    """(M, T) bool: segment p[m]->q[m] meets triangle t (float64 Moeller-Trumbore, t in [0, 1])."""
    d = (q - p)[:, None, :]
    v0, v1, v2 = tris[None, :, 0], tris[None, :, 1], tris[None, :, 2]
    e1, e2 = v1 - v0, v2 - v0
    h = np.cross(d, e2)
    det = np.einsum("mtk,mtk->mt", e1 * np.ones_like(h), h)
    with np.errstate(divide="ignore", invalid="ignore"):
        f = 1.0 / det
        s = p[:, None, :] - v0
        u = f * np.einsum("mtk,mtk->mt", s, h)
        qv = np.cross(s, e1)
        v = f * np.einsum("mtk,mtk->mt", d, qv)
        t = f * np.einsum("mtk,mtk->mt", e2 * np.ones_like(qv), qv)
        return (np.abs(det) > 1e-12) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t >= 0) & (t <= 1)


def read_layout(built):
    """read_linespaces(built) and the offsets array's words as stored (the sets' layout)."""
    return read_linespaces(built), linespace.read_array(built.device, built.buffers, "ls_shaft_offsets")


def assert_same_layout(built, whole) -> None:
    """`built` stores the offsets words of `whole` (read_layout of another build of the same case)
    and every shaft the same triangles (a voxel's list may come in another order between builds)."""
    (_, offs, cand), words = read_layout(built)
    (_, whole_offs, whole_cand), whole_words = whole
    np.testing.assert_array_equal(words, whole_words)
    np.testing.assert_array_equal(offs, whole_offs)
    for lo, hi in zip(offs[:-1], offs[1:]):
        assert sorted(cand[lo:hi]) == sorted(whole_cand[lo:hi])


def read_linespaces(built):
    """ls_ids and the shafts' lists expanded to one per shaft (CSR offsets, triangle ids), decoded
    from the shared-sets layout as the traversal reads it (linespace.shaft_lists): each Line Space's
    ids index its cell's plain list (a voxel's in grid-ls, a leaf's in svo-ls / esvo-ls)."""
    d = built.device
    read = lambda name: d.read(built.buffers[name], np.uint32).astype(np.int64)
    ls_ids = read("ls_ids")
    list_begins = read("leaves")[0::2] if "leaves" in built.buffers else read("voxel_offsets")[:-1]
    cell_begins = list_begins[np.flatnonzero(np.diff(ls_ids))]  # in Line Space order: ls_ids ascends
    offsets, candidates = linespace.shaft_lists(linespace.read_array(d, built.buffers, "ls_shaft_offsets"),
                                                linespace.read_array(d, built.buffers, "ls_shaft_tris"),
                                                built.stats["shafts_per_cell"], built.stats["ls_id_bits"],
                                                cell_begins, read("voxel_tris"))
    return ls_ids, offsets, candidates


@pytest.mark.parametrize("n,test_kind", [(1, None), (2, "clip"), (2, "sat"), (2, "edges"), (3, None), (3, "edges")])
def test_shaft_candidates_hold_every_triangle_a_shaft_segment_meets(device, monkeypatch, n, test_kind):
    """test_kind: the exact triangle/shaft test (None: the backend's default)."""
    if test_kind is not None:
        monkeypatch.setenv("LSBENCH_LS_TEST", test_kind)
    scene = random_scene()
    res = (3, 3, 2)
    built = backends.build(device, "grid-ls", scene, BuildParams(resolution=res, ls_n=n))
    default = "edges"  # Device.line_space_test, both backends
    assert built.stats["ls_exact_test"] == (test_kind or default)
    ls_ids, offs, cand = read_linespaces(built)
    per_cell = 15 * n**4
    g = built.geometry
    origin, size = np.asarray(g.origin), np.asarray(g.voxel_size)
    tris = scene.vertices[scene.faces].astype(np.float64)
    rng = np.random.default_rng(n)
    starts, ends = shaft_segments(n, 12 if n < 3 else 8, rng)
    voxels = np.flatnonzero(np.diff(ls_ids))
    assert len(voxels) == built.stats["linespace_voxels"] > 0
    voxel_offsets = device.read(built.buffers["voxel_offsets"], np.uint32, g.voxel_count + 1)
    assert built.stats["non_empty_voxels"] == np.count_nonzero(np.diff(voxel_offsets)) == len(voxels)  # K = 0
    hits_total = 0
    culled = 0
    for vox in voxels:
        cell = np.array([vox % res[0], (vox // res[0]) % res[1], vox // (res[0] * res[1])])
        c = ls_ids[vox]
        p = origin + (cell + starts.reshape(-1, 3)) * size
        q = origin + (cell + ends.reshape(-1, 3)) * size
        hit = segments_hit(p, q, tris).reshape(per_cell, -1, len(tris)).any(axis=1)  # (shafts, T)
        base = offs[c * per_cell:(c + 1) * per_cell + 1]
        counts = np.diff(base)
        is_cand = np.zeros_like(hit)
        is_cand[np.repeat(np.arange(per_cell), counts), cand[base[0]:base[-1]]] = True
        missing = np.argwhere(hit & ~is_cand)
        assert len(missing) == 0, f"voxel {vox}: (shaft, triangle) pairs missing: {missing[:10].tolist()}"
        hits_total += int(hit.sum())
        culled += int(per_cell * len(set(cand[base[0]:base[-1]].tolist())) - counts.sum())
    assert hits_total > 100  # the scene really puts triangles into shafts
    assert culled > 0 or n == 1  # the Line Space does cull: not every shaft holds the whole list
    assert built.stats["shafts"] == per_cell * len(voxels)
    assert built.stats["candidate_references"] == len(cand)
    built.release()


def voxel_lists(device, scene, res) -> dict[int, np.ndarray]:
    """The plain grid's list per non-empty voxel (grid-ls drops its own once every voxel has a
    Line Space)."""
    grid = backends.build(device, "grid", scene, BuildParams(resolution=res))
    offs = device.read(grid.buffers["voxel_offsets"], np.uint32).astype(np.int64)
    tris = device.read(grid.buffers["voxel_tris"], np.uint32).astype(np.int64)
    grid.release()
    return {v: tris[offs[v]:offs[v + 1]] for v in np.flatnonzero(np.diff(offs))}


def assert_reference_lists(device, scene, res, n, test_kind, built, delta=1e-4):
    """Every Line Space cell's shaft lists lie between the numpy reference at eps -/+ delta, and
    the borderline (pairs only one of them holds) is a small part of the candidates."""
    lists = voxel_lists(device, scene, res)
    ls_ids, offs, cand = read_linespaces(built)
    per_cell = 15 * n**4
    sets, _ = linespace.cell_set_sizes(linespace.read_array(device, built.buffers, "ls_shaft_offsets"), per_cell)
    g = built.geometry
    grid_tris = (scene.vertices[scene.faces].astype(np.float64) - np.asarray(g.origin)) / np.asarray(g.voxel_size)
    inner_total = border = 0
    for vox in np.flatnonzero(np.diff(ls_ids)):
        cell = np.array([vox % res[0], (vox // res[0]) % res[1], vox // (res[0] * res[1])])
        ids = np.sort(lists[vox])
        inner, outer = reference.linespace_borderline(grid_tris[ids] - cell, n, linespace.LS_EPS, delta, test_kind)
        base = offs[ls_ids[vox] * per_cell:(ls_ids[vox] + 1) * per_cell + 1]
        got = np.zeros_like(inner)
        rows = np.repeat(np.arange(per_cell), np.diff(base))
        cols = np.searchsorted(ids, cand[base[0]:base[-1]])
        assert (ids[cols.clip(max=len(ids) - 1)] == cand[base[0]:base[-1]]).all(), "a candidate not in the voxel"
        got[rows, cols] = True
        assert np.diff(base).sum() == got.sum(), "a triangle twice in one shaft"
        assert not (inner & ~got).any(), f"voxel {vox}: reference candidates missing {np.argwhere(inner & ~got)[:5]}"
        assert not (got & ~outer).any(), f"voxel {vox}: candidates the reference rejects {np.argwhere(got & ~outer)[:5]}"
        # One list per distinct set: the cell stores exactly as many sets as its shafts have
        # different candidate sets (none stored twice, no two different ones merged).
        assert sets[ls_ids[vox]] == len(np.unique(got, axis=0)), f"voxel {vox}: sets stored twice or merged"
        inner_total += int(inner.sum())
        border += int((outer & ~inner).sum())
    assert inner_total > 100 and border <= 0.01 * inner_total, (inner_total, border)


@pytest.mark.parametrize("n,test_kind", [(1, "sat"), (1, "edges"), (2, "clip"), (2, "sat"), (2, "edges"),
                                         (3, "clip"), (3, "edges")])
def test_shaft_candidates_are_the_numpy_reference(device, monkeypatch, n, test_kind):
    monkeypatch.setenv("LSBENCH_LS_TEST", test_kind)
    scene, res = random_scene(), (3, 3, 2)
    built = backends.build(device, "grid-ls", scene, BuildParams(resolution=res, ls_n=n))
    assert built.stats["ls_work_items"] == built.stats["shafts"]  # one chunk per cell here
    assert_reference_lists(device, scene, res, n, test_kind, built)
    _, offs, _ = read_linespaces(built)  # the count of non-empty shafts (32 per atomic on PoCL)
    assert built.stats["non_empty_shafts"] == np.count_nonzero(np.diff(offs)) > 32
    built.release()


@pytest.mark.parametrize("pair_bits", [True, False])
def test_dense_cells_give_the_reference_lists(device, monkeypatch, pair_bits):
    """Cells of more than 64 candidates: on PoCL the count and the fill take each shaft's
    candidates in runs of 32 (each step a vector loop: linespace.h ls_run_meets), so a cell spans
    several runs, and its pair bits start anywhere in a word. The lists are the numpy reference's,
    from the count's pair bits and from a fill that tests the pairs again."""
    monkeypatch.setenv("LSBENCH_LS_TEST", "edges")
    if not pair_bits:
        monkeypatch.setattr(linespace, "LS_PAIR_BITS_BYTES", 0)
    scene, res = random_scene(n_tris=200, size=0.3, seed=9), (2, 2, 1)
    assert max(len(ids) for ids in voxel_lists(device, scene, res).values()) > 64
    built = backends.build(device, "grid-ls", scene, BuildParams(resolution=res, ls_n=2))
    assert built.stats["ls_pair_bits"] == pair_bits
    assert_reference_lists(device, scene, res, 2, "edges", built)
    built.release()


def grazing_planes_scene(count=24, seed=5) -> Scene:
    """Large triangles (edges far outside the 2 x 2 x 2 grid) in planes through points within
    0.002 of the grid's corners, edges and faces, at random slants: their edges never meet a
    shaft, so the exact test's second half decides, mostly where the plane only grazes the
    shafts' hulls or the volumes pushed out by eps beyond them (linespace.h ls_volume_edge_meets)."""
    rng = np.random.default_rng(seed)
    tris = []
    for _ in range(count):
        point = rng.integers(0, 3, 3).astype(float) + rng.uniform(-0.002, 0.002, 3)
        normal = rng.normal(size=3)
        normal[rng.integers(0, 3)] *= rng.choice([0.0, 1e-3, 1.0])  # some nearly along a face
        normal /= np.linalg.norm(normal)
        u = np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 1.0, 0.0])
        u /= np.linalg.norm(u)
        v = np.cross(normal, u)
        tris.append([point + 20 * u, point - 10 * u + 17 * v, point - 10 * u - 17 * v])
    v = np.asarray(tris, np.float32).reshape(-1, 3)
    box = np.array([[0, 0, 0], [2, 2, 2]], np.float32)  # the bounds: a 2 x 2 x 2 grid of unit cells
    faces = np.arange(len(v), dtype=np.uint32).reshape(-1, 3)
    # Two tiny triangles at opposite corners fix the scene's bounds to the box.
    v = np.vstack([v, box[0], box[0] + 1e-3 * np.eye(3, dtype=np.float32)[:2], box[1], box[1] - 1e-3 * np.eye(3, dtype=np.float32)[:2]])
    faces = np.vstack([faces, len(tris) * 3 + np.arange(6, dtype=np.uint32).reshape(2, 3)])
    return Scene("grazing", v.astype(np.float32), faces, "test")


@pytest.mark.parametrize("n", [2, 3])
def test_planes_grazing_the_shafts_give_the_reference_lists(device, monkeypatch, n):
    """The exact test's second half finds one point of the triangle's plane inside the pushed
    volume (the axis, a hull corner segment, the reach bound, the volume's edges): on planes that
    graze the shafts its lists are the numpy reference's, within the band around eps."""
    monkeypatch.setenv("LSBENCH_LS_TEST", "edges")
    scene = grazing_planes_scene()
    built = backends.build(device, "grid-ls", scene, BuildParams(resolution=(2, 2, 2), ls_n=n))
    assert_reference_lists(device, scene, (2, 2, 2), n, "edges", built)
    built.release()


@pytest.mark.parametrize("per_item", [16, 256])
def test_cell_groups_cover_the_batch_inside_one_chunk(per_item):
    """BuildPlan.cell_groups: consecutive groups that cover the batch, at most `per_item` cells
    each, every group's candidates plus one per cell inside one chunk, a block halved only where it
    does not fit; and no groups where a cell needs more than one chunk."""
    rng = np.random.default_rng(3)
    chunk = 100 if per_item == 16 else 600  # sparse cells for the large blocks: some fit whole
    lengths = rng.integers(0, 40, 1000) * (rng.random(1000) < (0.9 if per_item == 16 else 0.05))
    lengths[rng.integers(0, 1000, 30 if per_item == 16 else 3)] = chunk - 1  # dense cells (a chunk with their own loop)
    ends = np.cumsum(lengths)
    ranges = np.stack([ends - lengths, ends], axis=1)
    plan = linespace.plan_build(ranges, 15, 24, chunk=chunk)
    load = lambda a, b: plan.ref_bases[b] - plan.ref_bases[a] + (b - a)  # candidates, plus one per cell
    for c0, c1 in ((0, 1000), (13, 700), (999, 1000)):
        groups = plan.cell_groups(c0, c1, 15, per_item).astype(np.int64)
        assert groups[0] == c0 and groups[-1] == c1 and np.all(np.diff(groups) >= 1)
        sizes = np.diff(groups)
        assert sizes.max() <= per_item and load(groups[:-1], groups[1:]).max() <= chunk
        for g0, size in zip(groups[:-2], sizes[:-1]):  # a smaller group: its aligned parent block did not fit
            size = int(size)  # (the last group may be a block cut short by c1)
            if size < per_item:
                p0 = c0 + (g0 - c0) // (2 * size) * (2 * size)
                assert load(p0, min(p0 + 2 * size, c1)) > chunk
        assert c1 - c0 < per_item or sizes.max() > per_item // 4  # large groups form
    starts = np.arange(0, 1000, per_item)
    assert load(starts, np.minimum(starts + per_item, 1000)).max() > chunk  # some block did not fit
    assert linespace.plan_build(ranges, 15, 24, chunk=chunk - 2).cell_groups(0, 1000, 15, per_item) is None


@pytest.mark.parametrize("split", ["chunks", "chunks-by-cells", "chunks-per-shaft", "batches", "groups", "mixed"])
def test_candidates_split_over_chunks_are_the_reference(device, monkeypatch, split):
    """Cells with more candidates than one work item may walk (the driver's loop budget): each
    shaft is counted in chunks, and its list is the one-chunk build's, in list order: with the
    set lengths and fill over the heads' whole rows ("chunks": the real budget is far above these
    cells' rows; "chunks-by-cells": and each cell's sets found by one work item, which counts the
    non-empty shafts of such cells), and with both over every shaft and chunk ("chunks-per-shaft":
    rows past the budget). Likewise with the cells' masks in several batches and a fill that tests again (no
    pair bits), with work items walking groups of 4 cells (the last group shorter), and ("mixed")
    with chunks of 3 candidates where the runs of one-chunk cells go as groups (of the queued count
    where the lanes are shafts; linespace.py shaft_pass) between cells of several chunks."""
    scene, res, n = random_scene(), (3, 3, 2), 2
    whole = backends.build(device, "grid-ls", scene, BuildParams(resolution=res, ls_n=n))
    whole_layout = read_layout(whole)
    assert whole.stats["ls_cell_batches"] == 1 and whole.stats["ls_pair_bits"] and whole.stats["ls_head_lists"]
    whole.release()
    runs = []  # "mixed": the runs of one-chunk cells dispatched as groups
    if split.startswith("chunks") or split == "mixed":
        per_candidate = linespace.LS_ITERATIONS_PER_CANDIDATE[exact_kind(device)]
        monkeypatch.setitem(linespace.LS_LOOP_BUDGET, device.backend, 3 * per_candidate)
    if split == "mixed":
        monkeypatch.setattr(linespace, "LS_GROUPED_RUN", 1)
        one_chunk_runs = linespace.BuildPlan.one_chunk_runs
        monkeypatch.setattr(linespace.BuildPlan, "one_chunk_runs",
                            lambda plan, *args: runs.extend(one_chunk_runs(plan, *args)) or one_chunk_runs(plan, *args))
    elif split.startswith("chunks"):
        monkeypatch.setattr(linespace, "head_rows_fit", lambda d, densest: split != "chunks-per-shaft")
        monkeypatch.setattr(linespace, "cells_fit_loop_budget", lambda d, densest, per_cell: split == "chunks-by-cells")
    elif split == "batches":
        monkeypatch.setattr(linespace, "LS_MASK_BYTES", 4 * 24 * 30)  # 30 references of 6 N^2 masks
        monkeypatch.setattr(linespace, "LS_PAIR_BITS_BYTES", 0)
    else:
        monkeypatch.setitem(linespace.CELLS_PER_ITEM, device.backend, 4)
    built = backends.build(device, "grid-ls", scene, BuildParams(resolution=res, ls_n=n))
    st = built.stats
    if split.startswith("chunks"):
        assert st["ls_candidate_chunk"] == 3 and st["ls_work_items"] > 2 * st["shafts"], st
        assert st["ls_head_lists"] == (split != "chunks-per-shaft"), st
        assert st["ls_sets_by_cells"] == (st["ls_set_groups"] if split == "chunks-by-cells" else 0), st
        assert st["ls_sets_cells_cut"] == 0, st
    elif split == "groups":
        assert st["ls_work_items"] == st["shafts"] and st["linespace_cells"] > 4, st
    elif split == "mixed":
        assert st["ls_candidate_chunk"] == 3 and st["ls_work_items"] > st["shafts"], st
        assert runs, runs
    else:
        assert st["ls_cell_batches"] > 3 and not st["ls_pair_bits"], st
    assert_reference_lists(device, scene, res, n, exact_kind(device), built)
    ls_ids, offs, _ = read_linespaces(built)
    assert st["non_empty_shafts"] == np.count_nonzero(np.diff(offs))
    np.testing.assert_array_equal(ls_ids, whole_layout[0][0])
    assert_same_layout(built, whole_layout)
    built.release()


@pytest.mark.parametrize("mask", [0, 1])
def test_sets_are_confirmed_word_by_word(device, monkeypatch, mask):
    """The sets come from a hash of each shaft's decision bits, but equality is decided by
    comparing the bits: with a hash of 0 or 1 bit (every set collides with others) the lists are
    the full hash's, shaft by shaft, and the sets are laid out the same."""
    scene, res, n = random_scene(), (3, 3, 2), 2
    whole = backends.build(device, "grid-ls", scene, BuildParams(resolution=res, ls_n=n))
    whole_layout = read_layout(whole)
    whole.release()
    monkeypatch.setattr(linespace, "LS_HASH_MASK", mask)
    built = backends.build(device, "grid-ls", scene, BuildParams(resolution=res, ls_n=n))
    assert_reference_lists(device, scene, res, n, exact_kind(device), built)
    assert_same_layout(built, whole_layout)
    built.release()


def test_sets_found_again_where_the_loop_budget_cuts_a_cell(device, monkeypatch):
    """A cell's sets are found by one work item, all its probes in one invocation: with a hash of
    0 bits every row probes past all the sets before it, which on llvmpipe spends the loop budget
    (N = 3: 1,215 shafts a cell). The cut cells are counted and their groups found again per
    shaft, so the lists, the layout and the stats are the full hash's; PoCL has no budget."""
    scene, res, n = random_scene(), (2, 2, 2), 3
    whole = backends.build(device, "grid-ls", scene, BuildParams(resolution=res, ls_n=n))
    assert whole.stats["ls_sets_by_cells"] == whole.stats["ls_set_groups"] == 1, whole.stats
    assert whole.stats["ls_sets_cells_cut"] == 0, whole.stats
    whole_layout, whole_stats = read_layout(whole), whole.stats
    whole.release()
    monkeypatch.setattr(linespace, "LS_HASH_MASK", 0)
    built = backends.build(device, "grid-ls", scene, BuildParams(resolution=res, ls_n=n))
    st = built.stats
    cut = device.backend == "glsl"
    assert (st["ls_sets_cells_cut"] > 0) == cut and st["ls_sets_by_cells"] == (0 if cut else 1), st
    for key in ("non_empty_shafts", "candidate_references", "ls_sets", "ls_set_references"):
        assert st[key] == whole_stats[key], key
    assert_same_layout(built, whole_layout)
    assert_reference_lists(device, scene, res, n, exact_kind(device), built)
    built.release()


@pytest.mark.parametrize("structure", ["grid-ls", "esvo-ls"])
def test_pair_bits_split_over_buffers(device, monkeypatch, structure):
    """All cells' pair bits kept over 3 or 4 buffers where one would pass the driver's per-buffer
    limit (llvmpipe: 128 MiB): the count's ORs, the rows read across a buffer boundary, the sets
    and the fill from the bits give the one-buffer build's lists and layout."""
    scene, res, n = random_scene(), (3, 3, 2) if structure == "grid-ls" else (4, 4, 4), 2
    whole = backends.build(device, structure, scene, BuildParams(resolution=res, ls_n=n))
    assert whole.stats["ls_pair_bits_buffers"] == 1 and whole.stats["ls_pair_bits"], whole.stats
    whole_layout = read_layout(whole)
    whole.release()
    split_array = linespace.split_array

    def small_bits(d, base, macro, entries, limit=None):  # a chunk of a quarter to half of the bits
        if base == "ls_pair_bits":
            limit = 4 << max(0, (int(entries) - 1).bit_length() - 2)
        return split_array(d, base, macro, entries, limit)

    monkeypatch.setattr(linespace, "split_array", small_bits)
    built = backends.build(device, structure, scene, BuildParams(resolution=res, ls_n=n))
    st = built.stats
    assert st["ls_pair_bits"] and st["ls_head_lists"] and st["ls_pair_bits_buffers"] in (3, 4), st
    assert_same_layout(built, whole_layout)
    if structure == "grid-ls":  # (the octrees' lists against their reference: test_octree_ls.py)
        assert_reference_lists(device, scene, res, n, exact_kind(device), built)
    built.release()


def test_sets_by_cells_in_the_groups_that_fit(device, monkeypatch):
    """Groups of cells whose densest cell fits the loop budget find their sets a cell per work
    item, the others per shaft, in one build (a group per cell here; a budget that half the cells
    pass): the lists and layout are those of the build with every group by cells."""
    scene, res, n = random_scene(), (3, 3, 2), 2
    whole = backends.build(device, "grid-ls", scene, BuildParams(resolution=res, ls_n=n))
    whole_layout = read_layout(whole)
    lists = voxel_lists(device, scene, res)
    lens = [len(lists[v]) for v in np.flatnonzero(np.diff(whole_layout[0][0]))]  # the Line Space cells' candidates
    whole.release()
    half = sorted(lens)[len(lens) // 2]
    monkeypatch.setattr(linespace, "LS_GROUP_SHAFTS", 15 * n**4)  # a cell per group
    monkeypatch.setattr(linespace, "cells_fit_loop_budget", lambda d, densest, per_cell: densest < half)
    built = backends.build(device, "grid-ls", scene, BuildParams(resolution=res, ls_n=n))
    st = built.stats
    assert st["ls_set_groups"] == len(lens) and 0 < st["ls_sets_by_cells"] < len(lens), st
    assert st["ls_sets_by_cells"] == sum(1 for k in lens if k < half), st
    assert_same_layout(built, whole_layout)
    assert_reference_lists(device, scene, res, n, exact_kind(device), built)
    built.release()


def test_cells_fit_the_loop_budget():
    """One work item finds a cell's sets where clearing its table (two words per slot) and, per shaft,
    a hash and two compares of its row take at most half the driver's loop budget (the rest for
    further probes)."""
    glsl, opencl = (type("D", (), {"backend": b}) for b in ("glsl", "opencl"))
    budget = linespace.LS_LOOP_BUDGET["glsl"]
    per_cell = 15 * 3**4
    assert linespace.cells_fit_loop_budget(glsl, 32 * 6, per_cell)  # 6 words: 4,860 + 1,215 x 20 <= 32,767
    assert not linespace.cells_fit_loop_budget(glsl, 32 * 6 + 1, per_cell)  # 7 words: ... x 23 > 32,767
    assert 4 * per_cell + per_cell * 20 <= budget // 2 < 4 * per_cell + per_cell * 23
    assert linespace.cells_fit_loop_budget(opencl, 2**31, 15 * 8**4)  # no budget


def exact_kind(device) -> str:
    return device.line_space_test


def test_cell_past_the_loop_budget(device):
    """One cell with 70,000 candidates: more than llvmpipe's 65535 loop iterations per invocation
    (the count used to fail there naming the limit); on GLSL the shafts are counted in chunks."""
    rng = np.random.default_rng(2)
    count = 70_000
    centres = rng.uniform(0.05, 0.95, (count, 1, 3))
    v = (centres + rng.normal(0, 0.01, (count, 3, 3))).reshape(-1, 3)
    v = np.vstack([v, [[0, 0, 0], [1, 1, 1]]]).astype(np.float32)  # two points pin the bounds
    faces = np.arange(3 * count, dtype=np.uint32).reshape(-1, 3)
    scene = Scene("dense", v, faces, "test")
    built = backends.build(device, "grid-ls", scene, BuildParams(resolution=(1, 1, 1), ls_n=1))
    st = built.stats
    assert st["linespace_cells"] == 1
    assert st["ls_id_bits"] == 32  # over 65,536 candidates: a position needs more than 16 bits
    if device.backend == "glsl":
        assert st["ls_work_items"] == 15 * -(-count // st["ls_candidate_chunk"]) > 15
    assert_reference_lists(device, scene, (1, 1, 1), 1, exact_kind(device), built)
    built.release()


def shaft_plane_slots(device, n: int) -> np.ndarray:
    """The device's ls_planes for N = n: (15 n^4 shafts, LS_PLANE_SLOTS, 4) floats."""
    geometry = backends.geometry_for("grid-ls", random_scene(), BuildParams((2, 2, 2)))
    shafts = 15 * n**4
    buf = device.alloc("ls_planes", 16 * linespace.LS_PLANE_SLOTS * shafts)
    device.dispatch(linespace.LS_PLANES, shafts, {"ls_planes": buf}, linespace.uniforms(geometry, n))
    slots = device.read(buf, np.float32).reshape(shafts, linespace.LS_PLANE_SLOTS, 4)
    device.release(buf)
    return slots


def test_shaft_volumes_are_hulls_of_their_patches(device):
    """The device's facet planes: every patch corner is inside every plane, and each plane touches
    at least three corners (a real facet); after them the shaft's axis (its patches' centres) and
    the patches' mask indices."""
    n = 2
    slots = shaft_plane_slots(device, n)
    planes = slots[:, :linespace.LS_MAX_PLANES]
    s = 0
    for a, b in FACE_PAIRS:
        for pa in range(n * n):
            for pb in range(n * n):
                pts = np.vstack([patch_points(a, pa, n, np.array([[0, 0], [0, 1], [1, 0], [1, 1.0]])),
                                 patch_points(b, pb, n, np.array([[0, 0], [0, 1], [1, 0], [1, 1.0]]))])
                real = planes[s][np.abs(planes[s][:, :3]).sum(1) > 0]
                assert len(real) >= 5
                dist = pts @ real[:, :3].T + real[:, 3]
                assert dist.max() < 1e-5
                assert (np.abs(dist) < 1e-5).sum(0).min() >= 3
                centres = np.vstack([patch_points(a, pa, n, np.array([[0.5, 0.5]])),
                                     patch_points(b, pb, n, np.array([[0.5, 0.5]]))])
                np.testing.assert_allclose(slots[s, 8:, :3], centres, atol=1e-6)
                assert list(slots[s, 8:, 3]) == [a * n * n + pa, b * n * n + pb]
                s += 1


@pytest.mark.parametrize("n", [1, 2, 3])
def test_cull_margin_covers_the_pushed_volumes(device, n):
    """The masks' cull margin (linespace.h: ls_masks_kernel) is at least how far any shaft's volume
    with its facet planes pushed out by LS_EPS reaches past its hull, and not much more. The
    volume's vertices are found here in float64, independently of the device's edges: every
    feasible intersection of three pushed facet planes, and its distance to the nearest patch
    corner."""
    built = backends.build(device, "grid-ls", random_scene(), BuildParams((2, 2, 2), ls_n=n))
    margin = built.stats["ls_cull_margin"]
    built.release()
    planes = shaft_plane_slots(device, n)[:, :linespace.LS_MAX_PLANES]
    corner_uv = np.array([[0, 0], [0, 1], [1, 0], [1, 1.0]])
    triples = np.array([t for t in np.ndindex(8, 8, 8) if t[0] < t[1] < t[2]])
    reach = 0.0
    s = 0
    for a, b in FACE_PAIRS:
        for pa in range(n * n):
            for pb in range(n * n):
                corners = np.vstack([patch_points(a, pa, n, corner_uv), patch_points(b, pb, n, corner_uv)])
                real = planes[s][np.abs(planes[s][:, :3]).sum(1) > 0].astype(np.float64)
                s += 1
                usable = triples[(triples < len(real)).all(1)]
                normals = real[usable, :3]  # (triples, 3 planes, xyz)
                solvable = np.abs(np.linalg.det(normals)) > 1e-9
                rhs = linespace.LS_EPS - real[usable, 3]  # n . x + w = eps on each of the three
                vertices = np.linalg.solve(normals[solvable], rhs[solvable][..., None])[..., 0]
                inside = (vertices @ real[:, :3].T + real[:, 3] <= linespace.LS_EPS + 1e-9).all(1)
                dist = np.linalg.norm(vertices[inside][:, None] - corners[None], axis=2).min(1)
                assert len(dist) >= 6
                reach = max(reach, float(dist.max()))
    assert linespace.LS_EPS <= reach
    assert reach + linespace.LS_CULL_SLACK <= margin <= 1.02 * reach + 1e-5 + linespace.LS_CULL_SLACK, (reach, margin)


@pytest.mark.parametrize("scene_name,resolution,size", [
    ("spheres", (12, 12, 12), (40, 30)), ("atrium", (12, 6, 9), (40, 30)),
])
def test_builtin_scenes_agree_with_embree_and_grid(device, scene_name, resolution, size):
    scene = load_scene(scene_name)
    assert_agrees_with_embree_and_plain_twin(device, "grid-ls", "grid", scene, primary_rays(scene, *size),
                                             resolution, n=2)


@pytest.mark.parametrize("id_bits", [16, 32])
@pytest.mark.parametrize("structure,plain", [("grid-ls", "grid"), ("svo-ls", "svo")])
def test_candidate_ids_of_either_width_trace_as_the_plain_twin(device, monkeypatch, structure, plain, id_bits):
    """The sets' cell-local ids, 16 bits (every cell here) or 32 (forced; cells past 65,536
    candidates), give the plain twin's hits and agree with Embree: random rays from everywhere,
    so lists of every length and both halves of a word are read."""
    if id_bits == 32:
        monkeypatch.setattr(linespace, "LS_IDS16_MAX_CANDIDATES", 0)
    scene = random_scene(300, size=0.08, seed=5)
    built = backends.build(device, structure, scene, BuildParams(resolution=(8, 8, 8), ls_n=2))
    assert built.stats["ls_id_bits"] == id_bits
    built.release()
    assert_agrees_with_embree_and_plain_twin(device, structure, plain, scene, random_rays(scene), (8, 8, 8), 2)


def assert_agrees_with_embree_and_plain_twin(device, structure, plain, scene, rays, resolution, n):
    """A Line Space structure agrees with Embree and equals its plain twin (grid-ls: grid; svo-ls:
    svo; ...) up to ties, with the same walk, per ray no more triangle tests (a shaft holds a
    subset of its cell's list), fewer in all, and one lookup per cell visited at most."""
    ref_p, ref_t = embree_closest(scene, rays)
    twin = backends.build(device, plain, scene, BuildParams(resolution=resolution))
    twin_hits = backends.trace(twin, rays, work=True)
    twin.release()
    built = backends.build(device, structure, scene, BuildParams(resolution=resolution, ls_n=n))
    hits = backends.trace(built, rays, work=True)
    built.release()
    acc = accuracy(scene, hits, ref_p, ref_t)
    assert acc.agreement >= 0.9999, acc
    same = accuracy(scene, hits, twin_hits.prim_ids, twin_hits.distances)
    assert same.disagreements == 0, same
    assert (hits.work[:, 0] == twin_hits.work[:, 0]).all()
    assert (hits.work[:, 1] <= twin_hits.work[:, 1]).all()
    assert hits.work[:, 1].sum() < twin_hits.work[:, 1].sum()
    assert 0 < hits.work[:, 2].sum() <= hits.work[:, 0].sum()


@pytest.mark.parametrize("n", [1, 4])
def test_random_rays_agree_with_embree(device, n):
    """Rays from everywhere (also inside the grid), non-cubic voxels, N up to 4."""
    scene = random_scene(300, size=0.08, seed=11)
    rays = random_rays(scene)
    ref_p, ref_t = embree_closest(scene, rays)
    built = backends.build(device, "grid-ls", scene, BuildParams(resolution=(7, 4, 5), ls_n=n))
    hits = backends.trace(built, rays)
    built.release()
    acc = accuracy(scene, hits, ref_p, ref_t)
    assert acc.agreement >= 0.9999, acc


@pytest.mark.parametrize("structure", ["grid-ls", "svo-ls", "esvo-ls"])
def test_min_candidates_keeps_hits_and_saves_memory(device, structure):
    """K: only cells (voxels, octree leaves) with more than K candidates get a Line Space."""
    scene = random_scene(300, size=0.08, seed=11)
    rays = random_rays(scene, 3000)
    params = dict(resolution=(8, 8, 8), ls_n=2)
    full = backends.build(device, structure, scene, BuildParams(**params))
    full_hits = backends.trace(full, rays)
    full_bytes = full.memory_bytes
    full.release()
    for k in (4, 10**6):
        part = backends.build(device, structure, scene, BuildParams(ls_min_candidates=k, **params))
        hits = backends.trace(part, rays)
        st = part.stats
        part.release()
        assert st["ls_min_candidates"] == k
        assert st["linespace_skipped_cells"] == st["candidate_cells"] - st["linespace_cells"]
        # per cell: its first set and 240 8-bit shaft indices, four per word
        assert st["ls_offsets_bytes_saved"] == 4 * (1 + 60) * st["linespace_skipped_cells"]
        if k == 4:
            assert 0 < st["linespace_cells"] < st["candidate_cells"]
            assert part.memory_bytes < full_bytes
        else:  # no cell gets a Line Space: the plain grid or octree
            assert st["linespace_cells"] == 0 and st["shafts"] == 0
        same = accuracy(scene, hits, full_hits.prim_ids, full_hits.distances)
        assert same.disagreements == 0, same


def test_sponza(device):
    """Sponza at 64^3, N = 2 where the driver allows it (PoCL); llvmpipe's 128 MiB per SSBO does
    not hold its 200 MB of candidates, so there 32^3, N = 1."""
    scene = load_scene(scene_path("sponza.ply"))
    rays = primary_rays(scene, 48, 48, SPONZA_CAMERA)
    res, n = (64, 2) if device.max_buffer_bytes >= 2**30 else (32, 1)
    built = backends.build(device, "grid-ls", scene, BuildParams(resolution=(res,) * 3, ls_n=n))
    hits = backends.trace(built, rays)
    built.release()
    acc = accuracy(scene, hits, *embree_closest(scene, rays))
    assert acc.agreement >= 0.9999, acc


# --- limits -------------------------------------------------------------------------------------
def test_32bit_limits_raise(device, monkeypatch):
    scene = random_scene()
    monkeypatch.setattr(linespace, "UINT32_MAX", 1000)  # pretend 32 bits end at 1000
    with pytest.raises(DeviceLimitError, match="32-bit"):
        backends.build(device, "grid-ls", scene, BuildParams(resolution=(3, 3, 2), ls_n=2))


def test_buffer_limit_raises_naming_it(device, monkeypatch):
    scene = random_scene()
    monkeypatch.setattr(type(device), "max_buffer_bytes", property(lambda self: 64 * 1024))
    with pytest.raises(DeviceLimitError, match=device.limit_name):
        backends.build(device, "grid-ls", scene, BuildParams(resolution=(3, 3, 2), ls_n=3))


@pytest.mark.parametrize("structure", ["grid-ls", "svo-ls", "esvo-ls"])
@pytest.mark.parametrize("size,limit,id_bits", [(0.5, 8192, 32), (0.3, 6144, 32), (0.5, 6144, 32),  # 2, 3, 4 buffers
                                                (0.5, 6144, 16)])  # 2 buffers of 16-bit ids
def test_candidates_split_over_buffers_past_the_limit(device, monkeypatch, structure, size, limit, id_bits):
    """A candidate list past the per-buffer limit is split over several buffers (up to 4) and
    traces exactly as the whole list; past 4 buffers the case fails naming the limit. 32-bit ids
    (forced: these cells are far under 65,536 candidates) make lists long enough for 4 buffers
    that still hold every other buffer of the case; 16-bit ids ORed across a buffer boundary
    (linespace.h ls_put_candidate) are checked with 2."""
    if id_bits == 32:
        monkeypatch.setattr(linespace, "LS_IDS16_MAX_CANDIDATES", 0)
    # Every other buffer of the case stays under `limit`: the triangle records (48 bytes per
    # triangle) and the slice state (68 bytes per ray where the trace runs in slices). The "edges"
    # exact test's table of shaft edges (912 bytes per shaft, 13,680 at N=1) would not: the split
    # does not depend on the exact test, so this build uses the SAT, which needs no table.
    monkeypatch.setenv("LSBENCH_LS_TEST", "sat")
    scene = random_scene(120, size=size, seed=7)
    rays = random_rays(scene, 80)
    params = BuildParams(resolution=(4, 4, 4), ls_n=1)
    whole = backends.build(device, structure, scene, params)
    whole_hits = backends.trace(whole, rays)
    assert whole.stats["ls_id_bits"] == id_bits
    candidates = linespace.candidate_words(whole.stats["ls_set_references"], id_bits)  # the words ls_shaft_tris holds
    whole.release()
    monkeypatch.setattr(type(device), "max_buffer_bytes", property(lambda self: limit))
    split = backends.build(device, structure, scene, params)
    chunks = split.stats["ls_tri_buffers"]
    chunk_bytes = 4 << ((limit // 4).bit_length() - 1)  # a power-of-two number of entries
    assert chunks == -(-4 * candidates // chunk_bytes) and 2 <= chunks <= 4, (candidates, chunks)
    names = ["ls_shaft_tris"] + [f"ls_shaft_tris{i}" for i in range(1, chunks)]
    assert sum(split.buffers[n].used for n in names) == 4 * candidates
    assert all(split.buffers[n].nbytes <= limit for n in names)
    hits = backends.trace(split, rays, work=True)  # the profiling kernel binds one buffer more
    split.release()
    np.testing.assert_array_equal(hits.prim_ids, whole_hits.prim_ids)
    np.testing.assert_array_equal(hits.distances, whole_hits.distances)
    monkeypatch.setattr(linespace, "LS_MAX_CHUNKS", chunks - 1)
    with pytest.raises(DeviceLimitError, match=f"more than {chunks - 1} buffers.*{device.limit_name}"):
        backends.build(device, structure, scene, params)


@pytest.mark.parametrize("structure", ["grid-ls", "svo-ls", "esvo-ls"])
@pytest.mark.parametrize("n_tris,size,limit,chunks", [(150, 0.2, 16384, 2), (40, 0.1, 4096, 3), (80, 0.12, 4096, 4)])
def test_offsets_split_over_buffers_past_the_limit(device, monkeypatch, structure, n_tris, size, limit, chunks):
    """Shaft offsets past the per-buffer limit are split too (the cells the thesis could not run,
    Sponza N=3 at 256^3, had 2.5 GiB of offsets in the one-list-per-shaft layout): the split
    build gives the whole build's offsets entry for entry and traces exactly as the whole one.
    The build's per-shaft arrays (item offsets, set words) are split in two as well, so their
    chunk-wise scan with carries and split macros are in the comparison; the candidates stay one
    buffer. grid-ls keeps no pair bits here, so that its build has item offsets (the head lists'
    builds, the octrees' here, have none: ls_head_len counts a head's row)."""
    if structure == "grid-ls":
        monkeypatch.setattr(linespace, "LS_PAIR_BITS_BYTES", 0)
    scene = random_scene(n_tris, size=size, seed=7)  # 42 to 61 cells with candidates at 4^3
    rays = random_rays(scene, 190)
    params = BuildParams(resolution=(4, 4, 4), ls_n=2)
    whole = backends.build(device, structure, scene, params)
    whole_hits = backends.trace(whole, rays)
    whole_offsets = device.read(whole.buffers["ls_shaft_offsets"], np.uint32)
    whole.release()
    split_array = linespace.split_array
    monkeypatch.setattr(linespace, "split_array", lambda d, base, macro, entries: split_array(
        d, base, macro, entries, limit={"ls_shaft_offsets": limit, "ls_item_offsets": 2**15,
                                        "ls_shaft_sets": 2**15}.get(base)))
    split = backends.build(device, structure, scene, params)
    assert split.stats["ls_offset_buffers"] == chunks == -(-4 * len(whole_offsets) // limit)
    assert split.stats["ls_tri_buffers"] == 1
    names = ["ls_shaft_offsets"] + [f"ls_shaft_offsets{i}" for i in range(1, chunks)]
    assert all(split.buffers[n].nbytes <= limit for n in names)
    np.testing.assert_array_equal(np.concatenate([device.read(split.buffers[n], np.uint32) for n in names]),
                                  whole_offsets)
    hits = backends.trace(split, rays, work=True)
    split.release()
    np.testing.assert_array_equal(hits.prim_ids, whole_hits.prim_ids)
    np.testing.assert_array_equal(hits.distances, whole_hits.distances)
    monkeypatch.setattr(linespace, "LS_MAX_CHUNKS", chunks - 1)
    with pytest.raises(DeviceLimitError, match="buffer 'ls_(shaft|item)_offsets' needs .* more than"):
        backends.build(device, structure, scene, params)


def test_head_rows_fit_the_loop_budget(monkeypatch):
    """The head lists walk a cell's whole row in one invocation (its words, then its set bits):
    taken only where the densest cell's row and words fit the driver's loop budget."""
    glsl, opencl = (type("D", (), {"backend": b}) for b in ("glsl", "opencl"))
    budget = linespace.LS_LOOP_BUDGET["glsl"]
    densest = budget * 32 // 33
    assert linespace.head_rows_fit(glsl, densest) and not linespace.head_rows_fit(glsl, densest + 1)
    assert densest + -(-densest // 32) <= budget < densest + 1 + -(-(densest + 1) // 32)
    assert linespace.head_rows_fit(opencl, 2**31)  # no budget
