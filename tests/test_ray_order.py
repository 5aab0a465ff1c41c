"""Ray reordering (backends/ray_order.py, shaders/common/ray_order.h): a ray set without locality is
traced in the order of its origins' cells, sorted on the device inside the timed trace. The hits
must be the set-order trace's, bit for bit, and Embree's; the sort a permutation in cell order."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from lsbench import backends
from lsbench.backends import BuildParams, ray_order
from lsbench.inputs.rays import RaySet, make_rays
from lsbench.inputs.scenes import load_scene
from lsbench.oracle.classifier import classify_disagreements
from lsbench.oracle.embree import embree_closest


def _far_offset_cornell():
    """The Cornell box (2 units wide) moved far from the origin, where float32 is ~1e-4 coarse."""
    scene = load_scene("cornell")
    moved = (np.asarray(scene.vertices, np.float64) + (300.0, -700.0, 1200.0)).astype(np.float32)
    return dataclasses.replace(scene, vertices=moved, _hash=None)


def _incoherent(scene, n=3000, seed=3):
    rng = np.random.default_rng(seed)
    lo, hi = (np.asarray(b, np.float64) for b in scene.bounds)
    pad = 0.2 * (hi - lo)
    origins = rng.uniform(lo - pad, hi + pad, (n, 3))  # some outside the bounds: the nearest cell
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return RaySet("incoherent-test", origins.astype(np.float32), d.astype(np.float32))


@pytest.mark.parametrize("structure,resolution", [("grid", (12, 16, 9)), ("esvo", (16, 16, 16)),
                                                  ("grid-ls", (8, 8, 8)), ("bvh", (1, 1, 1))])
def test_reordered_hits_are_the_given_orders_and_embrees(device, monkeypatch, structure, resolution):
    scene = _far_offset_cornell()
    rays = _incoherent(scene)
    built = backends.build(device, structure, scene, BuildParams(resolution=resolution,
                                                                ls_n=2 if structure.endswith("-ls") else 0))
    try:
        monkeypatch.setenv("LSBENCH_RAY_ORDER", "given")
        given = backends.trace(built, rays, work=True)
        monkeypatch.setenv("LSBENCH_RAY_ORDER", "origin-cells")
        ordered = backends.trace(built, rays, work=True)
        timing = backends.time_trace(built, rays, warmup=1, repeats=2)
        # in bounded slices (the llvmpipe path, forced on either backend): the slices run on the
        # sorted rays between the sort and the hits' return
        sliced = backends.trace(built, rays, budget=7)
        # and in one launch (ORDERED_RAYS), the path of GPUs and PoCL, forced on llvmpipe too
        whole = backends.trace(built, rays, budget=None)
    finally:
        built.release()
    assert given.order == "given" and ordered.order == "origin-cells" and sliced.order == "origin-cells"
    assert sliced.slices > 1 or structure == "bvh"  # bvh runs its rays whole in one launch (Built.suspends)
    assert whole.order == "origin-cells" and whole.slices == 1
    for hits in (ordered, sliced, whole):
        assert np.array_equal(hits.prim_ids, given.prim_ids)
        assert np.array_equal(hits.distances, given.distances)
    assert np.array_equal(ordered.work[:, :3], given.work[:, :3]), "counters not put back in ray order"
    assert len(timing.seconds) == 2 and min(timing.seconds) > 0 and "sort" in timing.clock
    ref_p, ref_t = embree_closest(scene, rays)
    out = classify_disagreements(scene, rays, ordered.prim_ids, ordered.distances, ref_p, ref_t)
    assert len(out["unexplained"]) == 0


def test_the_device_sort_is_a_permutation_in_cell_order(device):
    scene = _far_offset_cornell()
    rays = _incoherent(scene, n=5000, seed=4)
    built = backends.build(device, "grid", scene, BuildParams(resolution=(4, 4, 4)))
    bufs = backends._trace_buffers(built, rays, False, "origin-cells")
    try:
        for step, items, uniforms in backends._sort_steps(built, rays, "origin-cells"):
            device.dispatch(step, items, bufs, uniforms)
        ids = device.read(bufs["order_ids"], np.uint32, rays.count)
    finally:
        backends._release(device, bufs, backends._TRACE_BUFFERS)
        built.release()
    assert np.array_equal(np.sort(ids), np.arange(rays.count))
    # the numpy reference of the cells: 16 per axis over the structure's bounds, Morton order
    lo, hi = backends._bounds(built)
    u = ray_order.uniforms((lo, hi))
    c = (rays.origins[ids].astype(np.float32) - np.float32(u["order_origin"][:3])) * np.float32(u["order_scale"][:3])
    q = np.clip(c, 0, 15).astype(np.int64)
    key = np.zeros(len(q), np.int64)
    for bit in range(4):
        for axis in range(3):
            key |= ((q[:, axis] >> bit) & 1) << (3 * bit + axis)
    assert np.all(np.diff(key) >= 0), "rays not in the order of their origins' cells"
    assert len(np.unique(key)) > 100


def test_which_sets_are_reordered(monkeypatch):
    scene = load_scene("cornell")
    bounds = scene.bounds
    primary = make_rays("primary", scene, 32, 32, None, ())
    incoherent = make_rays("incoherent", scene, 32, 32, None, ())
    ao = make_rays("ao", scene, 32, 32, None, ())
    assert ray_order.choose(primary, bounds, image=True, width=1) == "given"
    assert ray_order.choose(incoherent, bounds, image=False, width=1) == "measure"
    assert ray_order.choose(incoherent, bounds, image=False, width=8) == "given"  # packets keep their order
    assert ray_order.origin_locality(ao, bounds) > 0.5
    assert ray_order.choose(ao, bounds, image=False, width=1) == "given"
    monkeypatch.setenv("LSBENCH_RAY_ORDER", "origin-cells")
    assert ray_order.choose(ao, bounds, image=False, width=1) == "origin-cells"
    assert ray_order.choose(primary, bounds, image=True, width=1) == "given"
    monkeypatch.setenv("LSBENCH_RAY_ORDER", "sorted")
    with pytest.raises(ValueError, match="LSBENCH_RAY_ORDER must be one of auto, given, origin-cells, got 'sorted'"):
        ray_order.choose(ao, bounds, image=False, width=1)


def test_the_order_of_a_set_without_locality_is_measured_once(device, monkeypatch):
    scene = _far_offset_cornell()
    rays = _incoherent(scene, n=2000, seed=5)
    built = backends.build(device, "grid", scene, BuildParams(resolution=(12, 16, 9)))
    try:
        monkeypatch.setenv("LSBENCH_RAY_ORDER", "given")
        given = backends.trace(built, rays)
        assert given.order_probe is None and not built.ray_orders
        monkeypatch.setenv("LSBENCH_RAY_ORDER", "auto")
        first = backends.trace(built, rays)
        again = backends.trace(built, rays, work=True)
        backends.time_trace(built, rays, warmup=1, repeats=1)
    finally:
        built.release()
    assert len(built.ray_orders) == 1, "the order was measured more than once"
    (order, probe), = built.ray_orders.values()
    assert set(probe) == {"given", "origin-cells"} and min(probe.values()) > 0
    assert order == min(probe, key=probe.get)
    assert first.order == again.order == order and first.order_probe == probe
    assert np.array_equal(first.prim_ids, given.prim_ids) and np.array_equal(first.distances, given.distances)
