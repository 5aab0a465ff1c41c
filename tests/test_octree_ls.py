"""`svo-ls` and `esvo-ls` (the adaptive Line Space: Line Spaces in the octree leaves) on both
backends.

- Structure contents: every leaf's Line Space equals grid-ls' Line Space of the same voxel on the
  same (cubic) grid, shaft for shaft (test_linespace checks grid-ls' shafts against a numpy
  reference of the shaft geometry, so the leaves inherit that guarantee), and the leaf -> voxel
  order is the Morton order of the non-empty voxels.
- Hits agree with Embree (built-in scenes, rays from inside the octree, Sponza) and with the plain
  octree up to ties, with the same walk and fewer triangle tests.
- A buffer past the driver's limit raises DeviceLimitError naming it (ls_min_candidates for all
  three Line Space structures: test_linespace).
"""
from __future__ import annotations

import numpy as np
import pytest

from lsbench import backends
from lsbench.backends import BuildParams, DeviceLimitError
from lsbench.oracle.embree import embree_closest
from lsbench.inputs.rays import primary_rays
from lsbench.inputs.scene import Camera
from lsbench.inputs.scenes import load_scene

from conftest import scene_path
from test_linespace import (accuracy, assert_agrees_with_embree_and_plain_twin, random_rays, random_scene,
                            read_linespaces)

LS_OCTREES = {"svo-ls": "svo", "esvo-ls": "esvo"}
SPONZA_CAMERA = Camera(eye=(1100.0, 180.0, -40.0), target=(-900.0, 420.0, 40.0), up=(0, 1, 0), fov_deg=65.0)


def morton(x, y, z) -> np.ndarray:
    code = np.zeros_like(x, dtype=np.int64)
    for bit in range(10):
        code |= ((x >> bit) & 1) << (3 * bit) | ((y >> bit) & 1) << (3 * bit + 1) | ((z >> bit) & 1) << (3 * bit + 2)
    return code


def shaft_triples(cells: np.ndarray, offsets: np.ndarray, tris: np.ndarray, shafts: int) -> np.ndarray:
    """(cell label, shaft, triangle) rows of Line Spaces 0..len(cells)-1, sorted: a shaft's list
    order depends on the fill's thread timing, its content does not."""
    counts = np.diff(offsets[: len(cells) * shafts + 1])
    shaft = np.repeat(np.arange(len(cells) * shafts), counts)
    rows = np.stack([cells[shaft // shafts], shaft % shafts, tris[offsets[0]: offsets[len(cells) * shafts]]], 1)
    return rows[np.lexsort(rows.T[::-1])]


@pytest.mark.parametrize("structure", LS_OCTREES)
@pytest.mark.parametrize("n", [1, 2])
def test_leaf_linespaces_equal_grid_ls_voxels(device, monkeypatch, structure, n):
    scene = load_scene("spheres")
    res = 8
    # grid-ls on the octree's bounding cube, so both build the same voxels.
    params = BuildParams(resolution=(res,) * 3, ls_n=n, bounding_cube=True)
    ref = backends.build(device, "grid-ls", scene, params)
    oct_ = backends.build(device, structure, scene, params)
    assert ref.geometry == oct_.geometry
    d = device
    shafts = 15 * n**4
    voxel_offsets = d.read(ref.buffers["voxel_offsets"], np.uint32).astype(np.int64)
    ref_ids = d.read(ref.buffers["ls_ids"], np.uint32).astype(np.int64)
    non_empty = np.flatnonzero(np.diff(voxel_offsets) > 0)
    assert (np.diff(ref_ids)[non_empty] == 1).all()  # K = 0: every non-empty voxel has one
    ref_rows = shaft_triples(non_empty, *read_linespaces(ref)[1:], shafts)

    # Leaves come in Morton order of the non-empty voxels; each has a Line Space, its own.
    rx, ry, _ = oct_.geometry.resolution  # the scene's box in the cube's voxels (8 x 4 x 8)
    assert oct_.geometry.resolution != (res,) * 3
    x, y, z = non_empty % rx, (non_empty // rx) % ry, non_empty // (rx * ry)
    leaf_voxels = non_empty[np.argsort(morton(x, y, z))]
    st = oct_.stats
    assert st["leaves"] == len(leaf_voxels) == st["linespace_leaves"] == st["linespace_cells"]
    assert st["linespace_skipped_leaves"] == 0 and st["shafts"] == shafts * st["leaves"]
    counts = d.read(oct_.buffers["leaves"], np.uint32).astype(np.int64).reshape(-1, 2)[:, 1]
    assert (counts == np.diff(voxel_offsets)[leaf_voxels]).all()
    ls_ids = d.read(oct_.buffers["ls_ids"], np.uint32).astype(np.int64)
    assert (ls_ids == np.arange(len(leaf_voxels) + 1)).all()
    rows = shaft_triples(leaf_voxels, *read_linespaces(oct_)[1:], shafts)
    assert st["candidate_references"] == len(rows) == ref.stats["candidate_references"]
    np.testing.assert_array_equal(rows, ref_rows)
    ref.release()
    oct_.release()


@pytest.mark.parametrize("structure", LS_OCTREES)
@pytest.mark.parametrize("scene_name,res,n", [("atrium", 32, 2), ("spheres", 16, 3)])
def test_agrees_with_embree_and_the_plain_octree(device, structure, scene_name, res, n):
    scene = load_scene(scene_name)
    assert_agrees_with_embree_and_plain_twin(device, structure, LS_OCTREES[structure], scene,
                                             primary_rays(scene, 48, 36), (res,) * 3, n)


@pytest.mark.parametrize("structure", LS_OCTREES)
@pytest.mark.parametrize("n", [1, 4])
def test_random_rays_from_inside_agree_with_embree(device, structure, n):
    """Origins everywhere, many inside leaves (the chord's entry lies behind the origin)."""
    scene = random_scene(300, size=0.08, seed=11)
    rays = random_rays(scene)
    built = backends.build(device, structure, scene, BuildParams(resolution=(8, 8, 8), ls_n=n))
    hits = backends.trace(built, rays)
    built.release()
    acc = accuracy(scene, hits, *embree_closest(scene, rays))
    assert acc.agreement >= 0.9999, acc


@pytest.mark.parametrize("structure", LS_OCTREES)
def test_sponza(device, structure):
    """Sponza from inside the atrium at 64^3, N = 2 (125 MB of candidates: within llvmpipe's
    128 MiB per SSBO too)."""
    scene = load_scene(scene_path("sponza.ply"))
    rays = primary_rays(scene, 48, 48, SPONZA_CAMERA)
    built = backends.build(device, structure, scene, BuildParams(resolution=(64,) * 3, ls_n=2))
    hits = backends.trace(built, rays)
    built.release()
    acc = accuracy(scene, hits, *embree_closest(scene, rays))
    assert acc.agreement >= 0.9999, acc


@pytest.mark.parametrize("structure", LS_OCTREES)
def test_buffer_limit_raises_naming_it(device, monkeypatch, structure):
    scene = random_scene()
    monkeypatch.setattr(type(device), "max_buffer_bytes", property(lambda self: 64 * 1024))
    with pytest.raises(DeviceLimitError, match=device.limit_name):
        backends.build(device, structure, scene, BuildParams(resolution=(4, 4, 4), ls_n=3))
