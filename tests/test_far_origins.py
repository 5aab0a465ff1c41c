"""Rays from far away into a scene far from the world origin: every structure, on both backends,
finds what Embree finds.

An origin 1e4 scene diagonals from the box lies millions of voxels away, where float32 grid
coordinates are 0.25 voxels apart (128³) and a walk's t values 0.016 apart. Walks that computed their
entry and their steps there drifted off the ray's line: on the floor below, the grid at 128³ lost
242 of these 1024 rays, at 256³ 530 (1e3 diagonals away: 31 and 181). trace.h's make_grid_ray
now places a far ray's frame on its line by the box in double, and the walks measure t from there."""
from __future__ import annotations

import numpy as np
import pytest

from helpers import check_structure, explain
from lsbench import backends
from lsbench.inputs.rays import RaySet
from lsbench.inputs.scene import Scene

STRUCTURES = backends.structure_names()
OFFSET = np.array([1.0e4, -2.5e4, 3.0e4])  # the scene's place: float32 steps of 1-2 mm there


def far_floor_and_rays(rays: int = 1024, diagonals: float = 1e4):
    """A 10 x 10 floor at OFFSET under an empty 10-unit box (two small triangles in its top corners
    span it), and rays from `diagonals` scene diagonals away aimed at points of the floor at least
    1 unit from its edges: each ray crosses the empty grid and hits the floor, far from any edge
    but the floor's own diagonal."""
    rng = np.random.default_rng(19)
    floor = np.array([[0, 0, 0], [10, 0, 0], [10, 0, 10], [0, 0, 0], [10, 0, 10], [0, 0, 10]], float)
    corners = np.array([[0, 10, 0], [0.1, 10, 0], [0, 10, 0.1], [10, 10, 10], [9.9, 10, 10], [10, 10, 9.9]])
    v = np.vstack([floor, corners]) + OFFSET
    faces = np.arange(len(v), dtype=np.uint32).reshape(-1, 3)
    scene = Scene("far-floor", v.astype(np.float32), faces, "test")
    target = OFFSET + np.c_[rng.uniform(1, 9, rays), np.zeros(rays), rng.uniform(1, 9, rays)]
    toward = rng.normal(size=(rays, 3))
    toward[:, 1] = np.abs(toward[:, 1]) + 0.3  # from above
    toward /= np.linalg.norm(toward, axis=1, keepdims=True)
    diag = float(np.linalg.norm(np.ptp(v, axis=0)))
    origins = (target + toward * diagonals * diag).astype(np.float32)
    d = target - origins.astype(np.float64)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return scene, RaySet("far-origins", origins, d.astype(np.float32))


@pytest.mark.parametrize("structure", STRUCTURES)
def test_far_origins_hit_the_floor(device, structure):
    scene, rays = far_floor_and_rays()
    info = backends.structure_info(structure)
    # fine cells, where the old walks drifted most; the Line Space structures walk as their plain
    # twins do (grid.h, svo.h, esvo.h), so they run coarser and quicker
    if info.cubic_power_of_two:
        resolution = (64 if info.line_space else 256,) * 3
    else:
        resolution = (32, 24, 40) if info.line_space else (160, 128, 144)
    out = check_structure(device, structure, scene, resolution, 2 if info.line_space else 0, rays=rays)
    assert out["unexplained"] == [], explain(out)
    assert (out["ref"][0] >= 0).all()  # Embree: every ray hits the floor
    # exact agreement but for rays near the floor's diagonal (a tie between its two triangles)
    assert out["counts"].get("agree", 0) >= 0.99 * rays.count, out["counts"]


@pytest.mark.parametrize("structure,resolution", [("grid", (128, 128, 128)), ("esvo", (256, 256, 256))])
def test_adversarial_scene_on_fine_cells(device, structure, resolution):
    """The built-in adversarial scene (strips in the bounding planes, slivers, 1e4 units out) under
    the adversarial rays, whose `far` rays start 1e4 diagonals away: the old grid walk had 10
    unexplained at 128³ (32 at 256³)."""
    from lsbench.inputs.scenes import load_scene

    out = check_structure(device, structure, load_scene("adversarial"), resolution)
    assert out["unexplained"] == [], explain(out)
