"""Structure registry: name -> module with prepare(device) and build(device, scene_buffers,
n_tris, geometry, params) -> (buffers, uniforms, trace_spec, stats)."""
from __future__ import annotations

from . import grid, grid_ls
from . import esvo, svo
from .octree_ls import esvo_ls, svo_ls

STRUCTURES = {
    "grid": grid,
    "grid-ls": grid_ls,
    "svo": svo,
    "esvo": esvo,
    "svo-ls": svo_ls,
    "esvo-ls": esvo_ls,
}

# Octrees need a cubic, power-of-two grid over the scene's bounding cube.
CUBIC_STRUCTURES: set[str] = {"svo", "esvo", "svo-ls", "esvo-ls"}
