"""The fitted-setting model (issue 17): predicted bytes against the built structure, the work
prediction against the device's counters, auto settings, the budget, `lsbench fit`."""
from __future__ import annotations

import pytest

from lsbench import backends
from lsbench.backends import BuildParams
from lsbench.inputs.scenes import load_scene
from lsbench.model.bytes import predict_bytes
from lsbench.model.stats import line_space_sample, voxel_counts


def _scene_buffers(device, scene):
    import numpy as np

    return {"vertices": device.upload("vertices", np.ascontiguousarray(scene.vertices, np.float32).ravel()),
            "faces": device.upload("faces", np.ascontiguousarray(scene.faces, np.uint32).ravel())}


@pytest.mark.parametrize("structure,resolution,n,k", [
    ("grid", (12, 7, 9), 0, 0), ("svo", (16, 16, 16), 0, 0), ("esvo", (8, 8, 8), 0, 0),
    ("grid-ls", (6, 5, 4), 2, 0), ("grid-ls", (8, 8, 8), 1, 6), ("svo-ls", (8, 8, 8), 2, 3),
    ("esvo-ls", (8, 8, 8), 1, 0)])
def test_predicted_bytes_equal_the_built_structure(device, structure, resolution, n, k):
    """Every buffer's bytes as predicted from the count pass (and, for a Line Space, from the
    built candidate count: exact once built) equal those the build allocates; the sample's
    estimate of the candidates is within a factor of the truth (an estimate: said so)."""
    scene = load_scene("cornell")
    params = BuildParams(resolution=resolution, ls_n=n, ls_min_candidates=k)
    built = backends.build(device, structure, scene, params)
    try:
        bufs = _scene_buffers(device, scene)
        counts = voxel_counts(device, bufs, scene.triangle_count, built.geometry)
        allocated = {name: b["allocated"] for name, b in built.memory().items()}
        if backends.structure_info(structure).line_space:
            exact = predict_bytes(device, structure, counts, n, k,
                                  candidates=built.stats["candidate_references"])
            sample = line_space_sample(device, bufs, scene.triangle_count, built.geometry, counts, n)
            estimate = predict_bytes(device, structure, counts, n, k, sample=sample)
            assert not estimate.exact
            truth = built.stats["candidate_references"]
            assert 0.5 * truth <= estimate.buffers["ls_shaft_tris"] / 4 <= 2 * truth
        else:
            exact = predict_bytes(device, structure, counts)
        assert exact.exact
        assert exact.buffers == allocated
        assert exact.total == built.memory_bytes
        for b in bufs.values():
            device.release(b)
    finally:
        built.release()
