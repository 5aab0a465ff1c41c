"""`svo` and `esvo` on both backends: the tree read back from the device equals a numpy
reference built from the voxel occupancy; hits agree with Embree and with `grid`."""
from __future__ import annotations

import numpy as np
import pytest

from lsbench import backends
from lsbench.backends import BuildParams, DeviceLimitError
from lsbench.backends.structures import grid, svo
from lsbench.oracle.embree import embree_closest
from lsbench.inputs.rays import RaySet, primary_rays
from lsbench.inputs.scene import Camera, Scene
from lsbench.inputs.scenes import load_scene
from lsbench.oracle.verify import compare

from conftest import scene_path

OCTREES = ("svo", "esvo")
# Sponza (Crytek, cm): the interior view of tests/test_grid.py.
SPONZA_CAMERA = Camera(eye=(1100.0, 180.0, -40.0), target=(-900.0, 420.0, 40.0), up=(0, 1, 0), fov_deg=65.0)

POPCOUNT8 = np.array([bin(i).count("1") for i in range(256)])
_scenes: dict = {}


def scene(name: str) -> Scene:
    if name not in _scenes:
        _scenes[name] = load_scene(scene_path("sponza.ply") if name == "sponza" else name)
    return _scenes[name]


def extent(sc: Scene) -> float:
    lo, hi = sc.bounds
    return float(np.linalg.norm(hi - lo))


# --- numpy reference and decoding of the device buffers ---------------------------------------
def reference_levels(occupied: np.ndarray, depth: int) -> list[set]:
    """Cells (x, y, z) needed on every level 0..depth: the ancestors of the non-empty voxels."""
    coords = np.argwhere(occupied)  # (n, 3) as (x, y, z): occupied is indexed [x, y, z]
    return [set(map(tuple, np.unique(coords >> (depth - level), axis=0).tolist())) for level in range(depth + 1)]


def decode(built) -> tuple[list[set], dict]:
    """Walk the tree from the root on the host: cells per level, and leaf cell -> leaf index."""
    d = built.device
    depth = built.stats["depth"]
    octant = np.array([[k & 1, (k >> 1) & 1, (k >> 2) & 1] for k in range(8)])
    ids, cells = np.array([0]), np.zeros((1, 3), np.int64)
    levels = [{(0, 0, 0)}]
    if built.structure == "svo":
        pool = d.read(built.buffers["svo_nodes"], np.uint32).reshape(-1, 8).astype(np.int64)
    else:
        desc = d.read(built.buffers["esvo_nodes"], np.uint32).astype(np.int64)
    for level in range(depth):
        if built.structure == "svo":
            children = pool[ids]  # (n, 8), 0 = empty
            valid = children != 0
        else:
            mask = desc[ids] & 0xFF
            valid = ((mask[:, None] >> np.arange(8)) & 1) == 1
            below = mask[:, None] & ((1 << np.arange(8)) - 1)
            rank = POPCOUNT8[below]
            children = (desc[ids] >> 8)[:, None] + rank
        n, k = np.nonzero(valid)
        ids = children[n, k]
        cells = 2 * cells[n] + octant[k]
        levels.append(set(map(tuple, cells.tolist())))
    if built.structure == "svo":
        ids = ids - 1  # leaf index + 1 on the last level
    return levels, dict(zip(map(tuple, cells.tolist()), ids.tolist()))


def device_voxel_lists(built):
    """The voxel lists the octree was built from, built again with the same geometry."""
    d = built.device
    vox, _ = grid.build_voxel_lists(d, built.scene_buffers, int(d.read(built.scene_buffers["faces"], np.uint32).size // 3),
                                    built.geometry)
    offsets = d.read(vox["voxel_offsets"], np.uint32).astype(np.int64)
    tris = d.read(vox["voxel_tris"], np.uint32)
    for b in vox.values():
        d.release(b)
    return offsets, tris


# --- structure ------------------------------------------------------------------------------
@pytest.mark.parametrize("structure", OCTREES)
@pytest.mark.parametrize("scene_name,res", [("atrium", 32), ("spheres", 16)])
def test_levels_and_leaves_equal_reference(device, structure, scene_name, res):
    sc = scene(scene_name)
    built = backends.build(device, structure, sc, BuildParams(resolution=(res, res, res)))
    depth = built.stats["depth"]
    assert 2 ** depth == res
    # The voxel lists cover the scene's box in the cube's voxels; the rest of the cube is empty.
    box = built.geometry.resolution
    assert built.geometry.cube == res and max(box) == res and min(box) >= 1
    assert np.allclose(built.geometry.voxel_size, built.geometry.voxel_size[0])  # cubic voxels
    offsets, ref_tris = device_voxel_lists(built)
    counts = np.diff(offsets)
    occupied = np.zeros((res,) * 3, bool)
    # voxel = x + Rx (y + Ry z)
    occupied[: box[0], : box[1], : box[2]] = (counts > 0).reshape(box[::-1]).transpose(2, 1, 0)
    want = reference_levels(occupied, depth)
    got, leaf_of = decode(built)

    assert [len(s) for s in want[:depth]] == built.stats["nodes_per_level"]
    assert built.stats["leaves"] == len(want[depth]) == int(occupied.sum())
    assert built.stats["empty_fraction"] == pytest.approx(1 - occupied.sum() / np.prod(box))
    for level in range(depth + 1):
        assert got[level] == want[level], f"level {level}"

    # Every leaf links to its voxel's candidates: same (first, count), same triangle set.
    d = built.device
    leaves = d.read(built.buffers["leaves"], np.uint32).reshape(-1, 2).astype(np.int64)[: built.stats["leaves"]]
    tris = d.read(built.buffers["voxel_tris"], np.uint32)
    assert sorted(leaf_of.values()) == list(range(len(leaves)))
    for (x, y, z), leaf in leaf_of.items():
        v = x + box[0] * (y + box[1] * z)
        first, count = leaves[leaf]
        assert (first, count) == (offsets[v], counts[v])
        assert sorted(tris[first:first + count]) == sorted(ref_tris[offsets[v]:offsets[v + 1]])

    # Buffers sized to what is used (thesis 5.3).
    node_bytes = 32 if structure == "svo" else 4
    nodes = built.buffers[f"{structure}_nodes"]
    assert nodes.nbytes == nodes.used == node_bytes * built.stats["nodes"]
    assert built.buffers["leaves"].nbytes == 8 * built.stats["leaves"]
    built.release()


@pytest.mark.parametrize("structure", OCTREES)
@pytest.mark.parametrize("res", [(32, 32, 16), (48, 48, 48), (1, 1, 1)])
def test_resolution_must_be_cubic_power_of_two(device, structure, res):
    with pytest.raises(ValueError, match="cubic|power of two"):
        backends.build(device, structure, scene("spheres"), BuildParams(resolution=res))


def test_esvo_pointer_overflow_is_a_device_limit(device, monkeypatch):
    monkeypatch.setattr(svo, "ESVO_POINTER_LIMIT", 100)
    with pytest.raises(DeviceLimitError, match="24-bit"):
        backends.build(device, "esvo", scene("spheres"), BuildParams(resolution=(32, 32, 32)))


# --- hits -------------------------------------------------------------------------------------
def _trace(device, structure, sc, res, rays, work=False):
    built = backends.build(device, structure, sc, BuildParams(resolution=(res, res, res)))
    hits = backends.trace(built, rays, work=work)
    built.release()
    return hits


@pytest.mark.parametrize("structure", OCTREES)
@pytest.mark.parametrize("scene_name,res", [("spheres", 32), ("atrium", 64)])
def test_agrees_with_embree(device, structure, scene_name, res):
    sc = scene(scene_name)
    rays = primary_rays(sc, 64, 64)
    hits = _trace(device, structure, sc, res, rays, work=True)
    ref_p, ref_t = embree_closest(sc, rays)
    acc = compare(hits.prim_ids, hits.distances, ref_p, ref_t, scene_extent=extent(sc))
    assert acc.agreement >= 0.9999, acc.to_dict()
    # Profiling counters: every ray that enters the cube visits a node; hits test candidates.
    hit = hits.prim_ids >= 0
    assert (hits.work[hit, 0] > 0).all() and (hits.work[hit, 1] > 0).all()
    assert (hits.work[:, 2] == 0).all()  # no Line Space lookups


def test_sponza_agrees_with_embree_and_grid(device):
    sc = scene("sponza")
    rays = primary_rays(sc, 64, 64, SPONZA_CAMERA)
    ref_p, ref_t = embree_closest(sc, rays)
    grid_hits = _trace(device, "grid", sc, 64, rays)
    for structure in OCTREES:
        hits = _trace(device, structure, sc, 64, rays)
        acc = compare(hits.prim_ids, hits.distances, ref_p, ref_t, scene_extent=extent(sc))
        assert acc.agreement >= 0.9999, (structure, acc.to_dict())
        same = compare(hits.prim_ids, hits.distances, grid_hits.prim_ids, grid_hits.distances,
                       scene_extent=extent(sc))
        assert same.agreement == 1.0, (structure, "vs grid", same.to_dict())


def random_case(seed=3, n_tris=1500, n_rays=6000):
    """Triangle soup and rays from inside and outside the cube, a quarter of them parallel to
    an axis or a coordinate plane (zero and negative-zero direction components)."""
    rng = np.random.default_rng(seed)
    c = rng.uniform(-1, 1, (n_tris, 1, 3))
    v = (c + rng.normal(0, 0.06, (n_tris, 3, 3))).reshape(-1, 3).astype(np.float32)
    sc = Scene("soup", v, np.arange(3 * n_tris, dtype=np.uint32).reshape(-1, 3), "test")
    o = rng.uniform(-1.6, 1.6, (n_rays, 3))
    d = rng.normal(size=(n_rays, 3))
    k = n_rays // 8
    d[:k, 1:] = 0.0
    d[k:2 * k, 0] = -0.0
    d[2 * k:2 * k + 50] = (0.0, 0.0, -1.0)
    d[2 * k + 50:2 * k + 100] = (0.0, 1.0, 0.0)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return sc, RaySet("soup", o.astype(np.float32), d.astype(np.float32))


@pytest.mark.parametrize("structure", OCTREES)
def test_random_rays_all_resolutions_small(device, structure):
    sc, rays = random_case()
    ref_p, ref_t = embree_closest(sc, rays)
    for res in (2, 4, 16, 64):
        hits = _trace(device, structure, sc, res, rays)
        acc = compare(hits.prim_ids, hits.distances, ref_p, ref_t, scene_extent=extent(sc))
        assert acc.agreement >= 0.9999, (res, acc.to_dict())
