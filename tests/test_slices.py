"""Traversal in bounded slices (issue 14; shaders/common/trace.h): a launch runs at most B loop
iterations per ray and the host launches the unfinished rays again. Sliced hits are bit-identical
to one launch on OpenCL for every structure and both queries, and GLSL on llvmpipe, whose loop
limit cut rays of BMW at 32^3 before, runs real scenes with Embree's agreement."""
from __future__ import annotations

import numpy as np
import pytest

from lsbench import backends
from lsbench.backends import BuildParams
from lsbench.inputs.rays import RaySet, adversarial_rays, make_rays
from lsbench.inputs.scenes import load_scene
from lsbench.oracle.classifier import judge_hits
from lsbench.oracle.embree import embree_closest

from conftest import scene_path
from helpers import structure_params

STRUCTURES = ["grid", "grid-ls", "svo", "esvo", "svo-ls", "esvo-ls"]


@pytest.fixture(scope="module")
def tiny_rays():
    """Cornell box (36 triangles): the adversarial set (grazing, axis-parallel, along cell planes,
    boundary and degenerate rays) and 400 incoherent rays; for any-hit the same rays, each ending
    at a seeded distance up to the scene's diagonal."""
    scene = load_scene("cornell")
    adversarial, _ = adversarial_rays(scene)
    incoherent = make_rays("incoherent", scene, 20, 20, None, {"seed": 3})
    origins = np.concatenate([adversarial.origins, incoherent.origins]).astype(np.float32)
    directions = np.concatenate([adversarial.directions, incoherent.directions]).astype(np.float32)
    closest = RaySet("slices-closest", origins, directions)
    diagonal = float(np.linalg.norm(np.subtract(*scene.bounds)))
    tmax = np.random.default_rng(7).uniform(0.05, 1.0, len(origins)).astype(np.float32) * diagonal
    return scene, {"closest": closest, "any": RaySet("slices-any", origins, directions, tmax=tmax, query="any")}


def _bits(hits):
    return hits.prim_ids, hits.distances.view(np.uint32)


@pytest.mark.parametrize("backend,query", [("opencl", "closest"), ("opencl", "any"), ("glsl", "closest")])
@pytest.mark.parametrize("structure", STRUCTURES)
def test_slices_give_the_hits_of_one_launch(tiny_rays, structure, backend, query):
    scene, sets = tiny_rays
    rays = sets[query]
    device = backends.get_device(backend)
    if backend == "opencl":
        assert device.loop_budget is None  # PoCL: one launch runs whole rays unless a budget is forced
    built = backends.build(device, structure, scene, BuildParams(**structure_params(structure, cubic_res=16)))
    try:
        whole = backends.trace(built, rays, budget=None)
        whole_work = backends.trace(built, rays, work=True, budget=None).work
        assert whole.slices == 1
        hit = whole.prim_ids >= 0
        assert 0.2 < hit.mean() < 0.95  # rays that hit and rays that miss
        slices = {}
        for budget in (backends.MIN_SLICE_BUDGET, 16, 1000):
            part = backends.trace(built, rays, budget=budget)
            slices[budget] = part.slices
            # a cell tested twice or skipped at a slice boundary would change some id, t or count
            for a, b in zip(_bits(part), _bits(whole)):
                np.testing.assert_array_equal(a, b)
            work = backends.trace(built, rays, work=True, budget=budget)
            np.testing.assert_array_equal(work.work[:, :3], whole_work[:, :3])  # steps, tests, lookups
            steps = whole_work[:, 0] + whole_work[:, 1]
            # each launch pays at most B loop iterations per ray, so the longest ray needs this many
            assert part.slices >= int(np.ceil(steps.max() / budget)), (budget, part.slices, steps.max())
        assert slices[16] > 1  # sliced for real
    finally:
        built.release()


def test_a_cell_longer_than_the_budget_resumes_inside_its_list(tiny_rays):
    """grid 1^3: the one voxel lists all 36 triangles, so B = 5 cuts its list seven times."""
    scene, sets = tiny_rays
    device = backends.get_device("opencl")
    built = backends.build(device, "grid", scene, BuildParams(resolution=(1, 1, 1)))
    try:
        whole = backends.trace(built, sets["closest"], work=True, budget=None)
        part = backends.trace(built, sets["closest"], work=True, budget=5)
        assert whole.work[:, 1].max() == scene.triangle_count
        assert part.slices >= int(np.ceil((scene.triangle_count + 1) / 5))
        for a, b in zip(_bits(part), _bits(whole)):
            np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(part.work[:, :3], whole.work[:, :3])
    finally:
        built.release()


def test_timed_trace_sums_the_slices(tiny_rays):
    scene, sets = tiny_rays
    device = backends.get_device("opencl")
    built = backends.build(device, "svo", scene, BuildParams(resolution=(16,) * 3))
    try:
        calls = []
        timing = backends.time_trace(built, sets["closest"], 1, 3, lambda: calls.append(1), budget=16)
        assert len(timing.seconds) == 3 and len(calls) == 3 and all(s > 0 for s in timing.seconds)
        assert "summed over the slices" in timing.clock
    finally:
        built.release()


def test_budget_comes_from_the_device_or_the_environment(monkeypatch):
    device = backends.get_device("opencl")
    assert backends.slice_budget(device) is None
    monkeypatch.setenv("LSBENCH_SLICE_BUDGET", "64")
    assert backends.slice_budget(device) == 64
    assert backends.slice_budget(device, None) is None  # an argument wins
    monkeypatch.setenv("LSBENCH_SLICE_BUDGET", "none")
    assert backends.slice_budget(backends.get_device("glsl")) is None
    monkeypatch.setenv("LSBENCH_SLICE_BUDGET", "0")
    with pytest.raises(ValueError, match="LSBENCH_SLICE_BUDGET"):
        backends.slice_budget(device)
    # below 4 a ray could suspend at the same step in every launch (an octree leaf needs its tick,
    # the walk's 2 extra loop iterations and one test)
    monkeypatch.setenv("LSBENCH_SLICE_BUDGET", "3")
    with pytest.raises(ValueError, match=">= 4 or 'none', got '3'"):
        backends.slice_budget(device)
    with pytest.raises(ValueError, match="got 3"):
        backends.slice_budget(device, 3)


# GLSL on llvmpipe: a few thousand incoherent rays on real scenes. Before the slices (main at
# 68314f8) BMW at 32^3 failed: grid 8 and svo 88 of 4,000 rays cut by the 65535-iteration limit
# (whole SIMD groups counted); Sponza at 64^3 passed with none cut (30,000 rays too), and must
# still pass with the slices compiled in.
REAL_CASES = [("sponza.ply", "grid", 64), ("sponza.ply", "svo", 64), ("bmw_m6.ply", "grid", 32),
              ("bmw_m6.ply", "svo", 32)]


@pytest.fixture(scope="module")
def real_scenes():
    return {}


@pytest.mark.parametrize("scene_file,structure,res", REAL_CASES)
def test_glsl_runs_incoherent_rays_on_real_scenes(real_scenes, scene_file, structure, res):
    if scene_file not in real_scenes:
        real_scenes[scene_file] = load_scene(scene_path(scene_file))
    scene = real_scenes[scene_file]
    rays = make_rays("incoherent", scene, 50, 50, None, {"count": 2500, "seed": 1})
    ref_p, ref_t = embree_closest(scene, rays)
    glsl = backends.get_device("glsl")
    assert glsl.loop_budget is not None  # llvmpipe bounds a launch's loops
    results = {}
    for name in ("glsl", "opencl"):
        built = backends.build(backends.get_device(name), structure, scene, BuildParams(resolution=(res,) * 3))
        try:
            hits = backends.trace(built, rays)
        finally:
            built.release()
        acc, cl = judge_hits(scene, rays, hits.prim_ids, hits.distances, ref_p, ref_t)
        assert cl.unexplained == 0, (name, acc, cl)
        results[name] = (hits, acc)
    (gl_hits, gl_acc), (cl_hits, cl_acc) = results["glsl"], results["opencl"]
    assert gl_acc.agreement == cl_acc.agreement, (gl_acc, cl_acc)
    assert np.array_equal(gl_hits.prim_ids, cl_hits.prim_ids)
    if scene_file == "bmw_m6.ply":  # the rays that passed llvmpipe's limit ran in more launches
        assert gl_hits.slices > 1 and cl_hits.slices == 1


def test_glsl_reruns_groups_the_driver_still_cut_with_half_the_budget():
    """A budget far over llvmpipe's limit: the cut groups keep their state and run again with half
    the budget, down to one that fits (the probe of scene.h as the guard, no longer a failure)."""
    scene = load_scene(scene_path("bmw_m6.ply"))
    rays = make_rays("incoherent", scene, 20, 20, None, {"count": 400, "seed": 1})
    glsl, opencl = backends.get_device("glsl"), backends.get_device("opencl")
    built = backends.build(glsl, "grid", scene, BuildParams(resolution=(16,) * 3))
    try:
        with pytest.raises(backends.DeviceLimitError, match="cut short"):
            backends.trace(built, rays, budget=None)  # one launch: the limit cuts some rays
        hits = backends.trace(built, rays, budget=2**20)
        assert hits.slices > 1
    finally:
        built.release()
    reference = backends.build(opencl, "grid", scene, BuildParams(resolution=(16,) * 3))
    try:
        np.testing.assert_array_equal(hits.prim_ids, backends.trace(reference, rays).prim_ids)
    finally:
        reference.release()


def test_records_name_the_slice_budget_in_force(monkeypatch):
    """A record says how many loop iterations one launch allowed per ray (record.slice_budget):
    llvmpipe's own budget, none on PoCL, or the forced LSBENCH_SLICE_BUDGET (which also splits the
    trace into more launches: trace_slices)."""
    from lsbench.inputs.scenario import Case, RunSettings
    from lsbench.running.execute import execute

    settings = RunSettings(width=16, height=16, repeats=1, warmup=0, embree_timing=False)
    run = {b: execute(Case("cornell", "grid", b, "8", width=16, height=16), settings) for b in ("glsl", "opencl")}
    assert run["glsl"]["slice_budget"] == backends.get_device("glsl").loop_budget
    assert run["opencl"]["slice_budget"] is None and run["opencl"]["trace_slices"] == 1
    monkeypatch.setenv("LSBENCH_SLICE_BUDGET", "4")
    forced = execute(Case("cornell", "grid", "opencl", "8", width=16, height=16), settings)
    assert forced["status"] == "ok" and forced["unexplained"] == 0
    assert forced["slice_budget"] == 4 and forced["trace_slices"] > 1


@pytest.mark.parametrize("structure", ["bvh", "bvh-ls"])
def test_a_walk_that_cannot_suspend_runs_in_one_launch(tiny_rays, structure):
    """bvh and bvh-ls keep their walk's state in a stack, so they cannot suspend at a budget
    (BuildResult.suspends): on llvmpipe, and with any budget given, their rays run whole in one
    launch (no slice state, no ray list), with the hits of that launch, Embree's agreement, and a
    record saying no budget was in force."""
    scene, sets = tiny_rays
    rays = sets["closest"]
    device = backends.get_device("glsl")
    built = backends.build(device, structure, scene, BuildParams(**structure_params(structure)))
    try:
        assert built.suspends is False
        hits = [backends.trace(built, rays), backends.trace(built, rays, budget=5)]
        timing = backends.time_trace(built, rays, warmup=0, repeats=1, budget=5)
    finally:
        built.release()
    assert "slices" not in timing.clock
    ref_p, ref_t = embree_closest(scene, rays)
    for h in hits:
        assert h.slices == 1 and h.slice_budget is None
        np.testing.assert_array_equal(_bits(h)[0], _bits(hits[0])[0])
        _, cl = judge_hits(scene, rays, h.prim_ids, h.distances, ref_p, ref_t)
        assert cl.unexplained == 0, cl
