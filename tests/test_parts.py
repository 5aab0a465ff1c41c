"""A ray set whose trace buffers exceed the driver's per-buffer limit is traced in parts
(backends.ray_parts): llvmpipe's 128 MiB held at most 1.97 M rays in slices, so a 1920 x 1080 image
failed there. The parts give the hits, counters and SIMD groups of one trace."""
from __future__ import annotations

import numpy as np
import pytest

from lsbench import backends
from lsbench.backends import BuildParams
from lsbench.inputs.rays import make_rays
from lsbench.inputs.scenes import load_scene
from lsbench.oracle.classifier import judge_hits
from lsbench.oracle.embree import embree_closest

from helpers import structure_params


def test_a_part_of_an_image_in_whole_rows_stays_an_image():
    scene = load_scene("cornell")
    rays = make_rays("primary", scene, 6, 4, None, ())
    rows = rays.part(6, 18)
    assert (rows.width, rows.height, rows.count) == (6, 2, 12)
    np.testing.assert_array_equal(rows.directions, rays.directions[6:18])
    assert rays.part(3, 18).width == 0 and rays.part(3, 18).count == 15  # not whole rows: not an image
    shadow = make_rays("shadow", scene, 6, 4, None, ())
    cut = shadow.part(1, 5)
    np.testing.assert_array_equal(cut.tmax, shadow.tmax[1:5])
    assert (cut.query, cut.width) == ("any", 0)
    with pytest.raises(ValueError, match=r"start < stop within its 24 rays, got \[5, 5\)"):
        rays.part(5, 5)


def test_an_image_splits_in_whole_rows_of_tiles():
    scene = load_scene("cornell")
    rays = make_rays("primary", scene, 20, 30, None, ())  # 30 rows: parts of 16 rows and 14
    parts = backends.ray_parts(rays, 16 * 20 + 7)
    assert [(p.width, p.height) for p in parts] == [(20, 16), (20, 14)]
    # each part's launch order, offset, is the whole image's (the SIMD groups are the image's)
    joined = np.concatenate([backends.launch_order(p) + 16 * 20 * k for k, p in enumerate(parts)])
    np.testing.assert_array_equal(joined, backends.launch_order(rays))
    assert [p.count for p in backends.ray_parts(rays, 100)] == [100] * 6  # narrower than a row of tiles
    assert backends.ray_parts(rays, 600) == [rays]


@pytest.mark.parametrize("backend", ["opencl", "glsl"])
@pytest.mark.parametrize("structure", ["grid", "esvo-ls", "bvh"])
def test_parts_give_the_hits_of_one_trace(monkeypatch, backend, structure):
    scene = load_scene("cornell")
    device = backends.get_device(backend)
    built = backends.build(device, structure, scene, BuildParams(**structure_params(structure, cubic_res=16)))
    sets = [make_rays("primary", scene, 40, 36, None, ()), make_rays("incoherent", scene, 50, 50, None, {"seed": 4}),
            make_rays("ao", scene, 40, 36, None, {"samples": 2})]
    try:
        whole = {s.name: (backends.trace(built, s), backends.trace(built, s, work=True).work) for s in sets}
        monkeypatch.setattr(backends, "rays_per_part", lambda device, budget: 1000)
        for rays in sets:
            hits = backends.trace(built, rays)
            parts = -(-rays.count // 1000) if rays.width == 0 else -(-rays.height // 24)  # 1000 rays: 24 rows of 40
            assert hits.slices >= parts, (rays.name, hits.slices)
            np.testing.assert_array_equal(hits.prim_ids, whole[rays.name][0].prim_ids)
            np.testing.assert_array_equal(hits.distances.view(np.uint32), whole[rays.name][0].distances.view(np.uint32))
            np.testing.assert_array_equal(backends.trace(built, rays, work=True).work[:, :3], whole[rays.name][1][:, :3])
            ref_p, ref_t = embree_closest(scene, rays, use_cache=False)
            acc, cls = judge_hits(scene, rays, hits.prim_ids, hits.distances, ref_p, ref_t)
            assert cls.unexplained == 0 and acc.agreement > 0.99
        calls = []
        timing = backends.time_trace(built, sets[1], 1, 3, lambda: calls.append(1))
        assert len(timing.seconds) == 3 and len(calls) == 3 and all(s > 0 for s in timing.seconds)
        assert "summed over 3 parts of at most 1000 rays" in timing.clock
    finally:
        built.release()


def test_the_part_size_follows_the_widest_buffer():
    device = backends.get_device("opencl")
    limit = device.max_buffer_bytes
    assert backends.rays_per_part(device, None) == limit // 32  # the rays' two float4
    assert backends.rays_per_part(device, 64) == limit // (4 * (backends.SLICE_WORDS + 1))  # the slice state


def test_a_ray_set_too_large_for_one_buffer_is_traced_on_llvmpipe():
    """1920 x 1080 primary rays: 2.07 M rays, 141 MB of slice state, over llvmpipe's 128 MiB."""
    device = backends.get_device("glsl")
    if device.max_buffer_bytes >= 2_073_600 * backends.SLICED_RAY_BYTES or device.loop_budget is None:
        pytest.skip("this GL driver holds a full-HD image's slice state in one buffer")
    scene = load_scene("cornell")
    rays = make_rays("primary", scene, 1920, 1080, None, ())
    built = backends.build(device, "grid", scene, BuildParams(resolution=(8, 8, 8)))
    try:
        hits = backends.trace(built, rays)
    finally:
        built.release()
    ref_p, ref_t = embree_closest(scene, rays, use_cache=False)
    acc, cls = judge_hits(scene, rays, hits.prim_ids, hits.distances, ref_p, ref_t)
    assert cls.unexplained == 0 and acc.agreement > 0.999
