"""Test helpers: build a structure, trace rays, explain every disagreement with Embree."""
from __future__ import annotations

import numpy as np

from lsbench import backends
from lsbench.backends import BuildParams
from lsbench.inputs.rays import adversarial_rays
from lsbench.oracle.classifier import classify_disagreements
from lsbench.oracle.embree import embree_closest


def check_structure(device, structure: str, scene, resolution, ls_n: int = 0, rays=None) -> dict:
    """Build `structure` on `device`, trace `rays` (default: the adversarial set) and classify
    every disagreement against Embree (lsbench.oracle.classifier). The classifier's dict plus
    'rays', 'categories' (adversarial label per ray, or 'given'), 'hits' and 'ref'."""
    if rays is None:
        rays, cats = adversarial_rays(scene)
    else:
        cats = np.full(rays.count, "given", dtype=object)
    built = backends.build(device, structure, scene, BuildParams(resolution=tuple(resolution), ls_n=ls_n))
    try:
        hits = backends.trace(built, rays)
    finally:
        built.release()
    ref_p, ref_t = embree_closest(scene, rays)
    out = classify_disagreements(scene, rays, hits.prim_ids, hits.distances, ref_p, ref_t)
    out.update({"rays": rays, "categories": cats, "hits": hits, "ref": (ref_p, ref_t)})
    return out


def structure_params(structure: str, cubic_res: int = 16, grid_res=(12, 16, 9)) -> dict:
    """Build parameters every registered structure accepts: octrees (cubic power-of-two
    structures) a cube, Line Space structures N = 2, the others a non-cubic grid."""
    info = backends.structure_info(structure)
    ls_n = 2 if info.line_space else 0
    if info.cubic_power_of_two:
        return {"resolution": (cubic_res,) * 3, "ls_n": ls_n}
    return {"resolution": tuple(grid_res), "ls_n": ls_n}


def explain(out: dict, limit: int = 5) -> str:
    """The first unexplained rays of a check_structure result, for an assertion message."""
    rays, cats, hits = out["rays"], out["categories"], out["hits"]
    ref_p, ref_t = out["ref"]
    return "; ".join(f"ray {i} ({cats[i]}) o={rays.origins[i].tolist()} d={rays.directions[i].tolist()}: "
                     f"backend {hits.prim_ids[i]}@{hits.distances[i]:.7g}, embree {ref_p[i]}@{ref_t[i]:.7g}"
                     for i in out["unexplained"][:limit])


def dense_cell_case(triangles: int = 70000):
    """A cloud of `triangles` small triangles in one cell (one far triangle stretches the bounds,
    so the cloud stays in one cell of a 2^3 octree too) and 64 rays into it: llvmpipe's loop
    budget of 65535 iterations per invocation (LP_MAX_TGSI_LOOP_ITERATIONS) cannot test them all.
    Returns (scene, rays)."""
    from lsbench.inputs.rays import RaySet
    from lsbench.inputs.scene import Scene

    rng = np.random.default_rng(2)
    v = (rng.uniform(0.2, 0.8, (triangles, 1, 3)) + rng.normal(0, 0.002, (triangles, 3, 3))).reshape(-1, 3)
    v = np.vstack([v, [[9.0, 9.0, 9.0], [9.5, 9.0, 9.0], [9.0, 9.5, 9.0]]])
    faces = np.arange(3 * (triangles + 1), dtype=np.uint32).reshape(-1, 3)
    scene = Scene("dense-cell", v.astype(np.float32), faces, "test")
    o = np.tile(np.float32([[0.5, 0.5, -1.0]]), (64, 1)) + rng.uniform(-0.05, 0.05, (64, 3)).astype(np.float32)
    return scene, RaySet("into-the-cell", o, np.tile(np.float32([[0.0, 0.0, 1.0]]), (64, 1)))
