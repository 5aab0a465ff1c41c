"""Scenes by name: `load_scene(spec)` takes a built-in name (see `builtin_names()`) or a file path.

The public entry point of scene input: built-in scenes are in lsbench/inputs/builtin_scenes.py,
file loading in lsbench/inputs/meshes.py.
"""
from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from lsbench.inputs.builtin_scenes import BUILTIN_SCENES, builtin_names
from lsbench.inputs.meshes import load_mesh_file
from lsbench.inputs.scene import Camera, Scene, SceneError

__all__ = ["builtin_names", "default_camera", "load_scene"]


def load_scene(spec: str) -> Scene:
    """A built-in scene by name, or a triangle file (OBJ, PLY, glTF/GLB, STL, ... )."""
    builder = BUILTIN_SCENES.get(spec)
    if builder is not None:
        return builder()
    path = Path(spec)
    # a bare word that is no built-in is most likely a typo of one: say which names exist
    if not (path.exists() or path.suffix or os.sep in spec or "/" in spec):
        raise SceneError(
            f"unknown scene {spec!r}: not a built-in ({', '.join(builtin_names())}) "
            "and not a file path"
        )
    return load_mesh_file(path)


def default_camera(scene: Scene) -> Camera:
    """scene.camera if set, else a view of the whole bounding box from outside, up = +Y."""
    if scene.camera is not None:
        return scene.camera
    lo, hi = (b.astype(np.float64) for b in scene.bounds)
    centre = (lo + hi) / 2
    radius = max(float(np.linalg.norm(hi - lo)) / 2, 1e-6)
    fov = 60.0
    # the bounding sphere fits a cone of half-angle fov/2 from this distance
    distance = radius / math.sin(math.radians(fov / 2))
    direction = np.array([0.4, 0.3, 1.0]) / np.linalg.norm([0.4, 0.3, 1.0])
    eye = centre + direction * distance
    return Camera(eye=tuple(map(float, eye)), target=tuple(map(float, centre)), up=(0.0, 1.0, 0.0),
                  fov_deg=fov)
