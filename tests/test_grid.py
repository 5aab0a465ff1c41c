"""`grid` on both backends: voxel lists equal the numpy reference; hits agree with Embree."""
from __future__ import annotations

import numpy as np
import pytest

from lsbench import backends
from lsbench.backends import BuildParams, DeviceLimitError
from lsbench.backends.structures.base import BOX_EPS
from lsbench.oracle import reference
from lsbench.oracle.embree import embree_closest
from lsbench.inputs.rays import primary_rays
from lsbench.inputs.scene import Camera, Scene
from lsbench.inputs.scenes import load_scene
from lsbench.oracle.verify import compare

from conftest import scene_path
from helpers import dense_cell_case

# Sponza (Crytek, cm): an interior view down the atrium like the thesis' images.
SPONZA_CAMERA = Camera(eye=(1100.0, 180.0, -40.0), target=(-900.0, 420.0, 40.0), up=(0, 1, 0), fov_deg=65.0)


@pytest.mark.parametrize("n", [1, 255, 4096, 4097, 65_537, 1_048_577 + 13])
def test_prefix_sum_is_the_numpy_cumsum(device, n):
    """The device's in-place exclusive scan (every build's offsets) across block boundaries (GLSL:
    256 invocations x 16 items per block, recursing over the block sums), its total mod 2^32."""
    values = np.random.default_rng(n).integers(0, 2**31, n, dtype=np.uint64).astype(np.uint32)
    buf = device.upload("scan_test", values)
    total = device.scan_in_place(buf, n)
    got = device.read(buf, np.uint32)[:n]
    device.release(buf)
    want = np.concatenate([np.zeros(1, np.uint64), np.cumsum(values.astype(np.uint64))[:-1]]) % 2**32
    np.testing.assert_array_equal(got, want.astype(np.uint32))
    assert total == int(values.astype(np.uint64).sum()) & 0xFFFFFFFF


def voxel_lists(built):
    d = built.device
    return (d.read(built.buffers["voxel_offsets"], np.uint32).astype(np.int64),
            d.read(built.buffers["voxel_tris"], np.uint32))


@pytest.mark.parametrize("scene_name,resolution", [
    ("cornell", (16, 16, 16)), ("spheres", (24, 24, 24)), ("atrium", (32, 16, 24)), ("teapot", (40, 20, 28)),
])
def test_voxel_lists_equal_reference(device, scene_name, resolution):
    scene = load_scene(scene_path("teapot.ply") if scene_name == "teapot" else scene_name)
    built = backends.build(device, "grid", scene, BuildParams(resolution=resolution))
    offsets, tris = voxel_lists(built)
    g = built.geometry
    # The reference runs in float64; the device in float32. They may differ only on pairs whose
    # overlap is decided within float rounding of the eps-expanded box.
    missing, extra = reference.compare_to_reference(
        offsets, tris, scene.vertices, scene.faces, g.origin, g.voxel_size, g.resolution,
        eps=BOX_EPS, delta=reference.suggested_delta(g.resolution))
    assert len(missing) == 0, f"{len(missing)} voxel/triangle pairs outside the borderline band are missing"
    assert len(extra) == 0, f"{len(extra)} pairs outside the borderline band are extra"
    assert built.stats["references"] == len(tris)
    # The walk's occupancy bits (grid.h: grid_occupancy): bit v & 31 of word v >> 5 set where voxel
    # v's list is not empty, the last word's bits past the voxels clear.
    non_empty = np.zeros(32 * -(-g.voxel_count // 32), bool)
    non_empty[:g.voxel_count] = np.diff(offsets) > 0
    want = np.packbits(non_empty, bitorder="little").view("<u4")
    np.testing.assert_array_equal(device.read(built.buffers["voxel_bits"], np.uint32), want)
    built.release()


@pytest.mark.parametrize("cells", [None, 0, 8, "default"])
def test_glsl_voxelizer_split_equals_reference(cells):
    """GLSL voxelizes through the raster pipeline (None: every triangle, as on GPU drivers), or on
    llvmpipe the triangles whose bounds hold at most compute_voxel_cells voxels through the compute
    kernel and the others through the raster pipeline, listed by the compute pass (0: all of them
    listed). Every split gives the reference's voxel lists."""
    device = backends.get_device("glsl")
    scene = load_scene("atrium")
    resolution = (64, 32, 48)
    kept = device.compute_voxel_cells
    try:
        if cells != "default":
            device.compute_voxel_cells = cells
        built = backends.build(device, "grid", scene, BuildParams(resolution=resolution))
        offsets, tris = voxel_lists(built)
        g = built.geometry
        if cells == 8:  # both paths take triangles at this split
            corners = (scene.vertices[scene.faces] - g.origin) / g.voxel_size
            span = np.floor(corners.max(1) + 1e-3) - np.floor(corners.min(1) - 1e-3) + 1
            bounds = np.prod(np.clip(span, 1, None), axis=1)
            assert (bounds <= 4).any() and (bounds > 16).any()
        missing, extra = reference.compare_to_reference(
            offsets, tris, scene.vertices, scene.faces, g.origin, g.voxel_size, g.resolution,
            eps=BOX_EPS, delta=reference.suggested_delta(g.resolution))
        assert len(missing) == 0 and len(extra) == 0, (len(missing), len(extra))
        assert built.stats["references"] == len(tris)
        built.release()
    finally:
        device.compute_voxel_cells = kept


def _agreement(device, scene, structure, resolution, rays, **params):
    built = backends.build(device, structure, scene, BuildParams(resolution=resolution, **params))
    hits = backends.trace(built, rays)
    built.release()
    ref_p, ref_t = embree_closest(scene, rays)
    lo, hi = scene.bounds
    return compare(hits.prim_ids, hits.distances, ref_p, ref_t, scene_extent=float(np.linalg.norm(hi - lo))), hits


@pytest.mark.parametrize("resolution", [(64, 64, 64), (48, 24, 40)])
def test_atrium_agrees_with_embree(device, resolution):
    scene = load_scene("atrium")
    rays = primary_rays(scene, 160, 120)
    acc, _ = _agreement(device, scene, "grid", resolution, rays)
    assert acc.agreement >= 0.9999, acc.to_dict()
    assert acc.missed + acc.extra + acc.wrong <= 1


def test_sponza_256_agrees_with_embree(device):
    scene = load_scene(scene_path("sponza.ply"))
    rays = primary_rays(scene, 256, 256, SPONZA_CAMERA)
    acc, hits = _agreement(device, scene, "grid", (64, 64, 64), rays)
    assert (hits.prim_ids >= 0).mean() > 0.9  # an interior view: nearly every ray hits
    assert acc.agreement >= 0.9999, acc.to_dict()


def test_spheres_and_cornell_exact(device):
    for name in ("spheres", "cornell"):
        scene = load_scene(name)
        acc, _ = _agreement(device, scene, "grid", (32, 32, 32), primary_rays(scene, 96, 96))
        assert acc.agreement == 1.0, (name, acc.to_dict())


def test_backends_give_identical_hits():
    scene = load_scene("atrium")
    rays = primary_rays(scene, 96, 96)
    out = []
    for name in backends.BACKENDS:
        built = backends.build(backends.get_device(name), "grid", scene, BuildParams(resolution=(32, 32, 32)))
        out.append(backends.trace(built, rays))
        built.release()
    same = out[0].prim_ids == out[1].prim_ids
    assert same.mean() >= 0.9999
    np.testing.assert_allclose(out[0].distances[same], out[1].distances[same], rtol=1e-5)


def test_work_counters_count_voxels_and_tests(device):
    """A ray through k empty voxels to one triangle: k+1 iterations, 1 candidate test."""
    from lsbench.inputs.rays import RaySet
    from lsbench.inputs.scene import Scene

    # One triangle filling the x = 7.5 slab of an 8x1x1 grid over [0, 8] x [0, 1] x [0, 1].
    v = np.array([[7.5, -1, -1], [7.5, 3, -1], [7.5, -1, 3], [0, 0, 0], [8, 1, 1]], np.float32)
    f = np.array([[0, 1, 2], [3, 3, 3], [4, 4, 4]], np.uint32)  # two points pin the bounds
    scene = Scene("line", v, f, "test")
    built = backends.build(device, "grid", scene, BuildParams(resolution=(8, 1, 1)))
    rays = RaySet("one", np.array([[-1, 0.5, 0.5]], np.float32), np.array([[1, 0, 0]], np.float32))
    hits = backends.trace(built, rays, work=True)
    built.release()
    assert hits.prim_ids[0] == 0
    assert hits.distances[0] == pytest.approx(8.5, rel=1e-5)
    iterations, tests = hits.work[0, 0], hits.work[0, 1]
    assert iterations == 8  # voxels 0..6 empty (7) + voxel 7 with the triangle
    assert tests >= 1 and tests <= 3  # the triangle, and the point-triangles of voxels 0 and 7


@pytest.mark.parametrize("structure,n", [("grid", 0), ("svo", 0), ("esvo", 0), ("grid-ls", 1)])
def test_driver_loop_limit_is_sliced(device, structure, n):
    """llvmpipe ends all loops of a shader invocation after 65535 iterations in all
    (LP_MAX_TGSI_LOOP_ITERATIONS), silently. 70,000 triangles in one cell make every ray pass
    that: the traversal runs in bounded slices there (Device.loop_budget, shaders/common/trace.h)
    and the Line Space count and fill in chunks of candidates (linespace.py: candidate_chunk), and
    every driver must agree with Embree."""
    scene, rays = dense_cell_case(70000)
    res = (2, 2, 2)
    llvmpipe = "llvmpipe" in str(device.info().get("device", ""))
    built = backends.build(device, structure, scene, BuildParams(resolution=res, ls_n=n))
    try:
        hits = backends.trace(built, rays)
    finally:
        built.release()
    assert hits.slices > 1 if llvmpipe else hits.slices == 1  # 70,000 tests in one cell
    ref_p, ref_t = embree_closest(scene, rays)
    acc = compare(hits.prim_ids, hits.distances, ref_p, ref_t, scene_extent=1.0)
    assert acc.agreement == 1.0, acc
