"""One case, end to end: scene -> rays -> Embree -> GPU build -> GPU trace -> verify -> work
counters -> timing -> record. Runs inside a worker process (lsbench/running/runner.py) or directly
(`lsbench trace`). The record it returns is lsbench.results.record.Record as a dict."""
from __future__ import annotations

import dataclasses
import math
import statistics
import time
import traceback
from pathlib import Path

import numpy as np

from lsbench.inputs.scenario import Case, RunSettings
from lsbench.results.record import Record, result_settings


def case_inputs(scene, rays) -> dict:
    """Record fields that describe a case's loaded inputs: which scene and rays, by content."""
    return {"scene": scene.name, "scene_source": scene.source, "scene_hash": scene.content_hash,
            "triangles": scene.triangle_count, "rays_hash": rays.content_hash, "ray_count": rays.count}


def new_record(case: Case, settings: RunSettings, env: dict | None = None, inputs: dict | None = None) -> Record:
    """A record of `case` that names what it runs (status failed until execute says ok). env:
    environment.record_env(); inputs: case_inputs() and device fields where already known."""
    try:
        params = case.build_params()
        resolution, n, k, leaf = params.resolution, params.ls_n, params.ls_min_candidates, params.leaf_size
    except ValueError:  # "auto" (chosen when it runs), or a resolution or structure that does not parse
        resolution, leaf = (None, None, None), case.leaf_size
        n, k = (None if v == "auto" else v for v in (case.ls_n, case.ls_min_candidates))
    camera = None
    if case.camera is not None:
        eye, target, up, fov = case.camera
        camera = {"eye": list(eye), "target": list(target), "up": list(up), "fov": float(fov)}
    path_like = "/" in case.scene or Path(case.scene).suffix
    rec = Record(key=case.key, scene=Path(case.scene).stem if path_like else case.scene,
                 scene_source=case.scene, structure=case.structure, backend=case.backend,
                 resolution=str(case.resolution), resolution_x=resolution[0], resolution_y=resolution[1],
                 resolution_z=resolution[2], ls_n=n, ls_min_candidates=k, rays=case.rays,
                 leaf_size=leaf,
                 ray_params={key: list(v) if isinstance(v, tuple) else v for key, v in case.ray_params},
                 query=case.query,
                 width=case.width, height=case.height, camera=camera, settings=result_settings(settings))
    rec.update(**(env or {}))
    rec.update(**(inputs or {}))
    return rec


def failed_record(case: Case, settings: RunSettings, reason: str, env: dict | None = None,
                  inputs: dict | None = None) -> dict:
    rec = new_record(case, settings, env, inputs)
    rec.update(status="failed", reason=reason)
    return rec.to_dict()


def timing_fields(seconds: list[float], clock: str, ray_count: int, is_image: bool) -> dict:
    med = statistics.median(seconds)
    mean = statistics.fmean(seconds)
    cv = statistics.pstdev(seconds) / mean if len(seconds) > 1 and mean > 0 else 0.0
    return {
        "trace_seconds": med, "trace_seconds_all": list(seconds), "trace_seconds_min": min(seconds),
        "trace_seconds_max": max(seconds), "trace_cv": cv, "clock": clock,
        "rays_per_second": ray_count / med if med > 0 else math.inf,
        "fps": (1.0 / med if med > 0 else math.inf) if is_image else None,
    }


def work_fields(work: np.ndarray) -> dict:
    """Mean traversal iterations, candidate (ray/triangle) tests and Line Space lookups per ray,
    from the profiling kernel's counters (what papers report per ray; Delgado Krämer 2019, Fig. 4)."""
    from lsbench.profile.heatmaps import CHANNELS

    means = work.astype(np.float64).mean(axis=0) if len(work) else np.zeros(len(CHANNELS))
    return {f"{name}_per_ray": float(means[i]) for i, name in enumerate(CHANNELS) if name != "clock"}


def chosen_fields(params) -> dict:
    """The record's setting fields of an auto case, as the cost model chose them (BuildParams)."""
    return dict(resolution_x=params.resolution[0], resolution_y=params.resolution[1],
                resolution_z=params.resolution[2], ls_n=params.ls_n, ls_min_candidates=params.ls_min_candidates)


def _build_within(device, structure: str, scene, params, budget_bytes: int | None):
    """Build `params` under the device-memory budget: (built, None, seconds) when it fits, else
    (built or None, the OverBudgetError, seconds): None where the build stopped as soon as it knew
    (a Line Space after its count pass, BuildParams.budget_bytes), the structure where only the
    built one showed it."""
    from lsbench import backends
    from lsbench.backends.device import OverBudgetError

    t0 = time.perf_counter()
    try:
        built = backends.build(device, structure, scene, dataclasses.replace(params, budget_bytes=budget_bytes))
    except OverBudgetError as exc:
        return None, exc, time.perf_counter() - t0
    if budget_bytes is not None and built.memory_bytes > budget_bytes:
        return built, OverBudgetError(built.memory_bytes, budget_bytes, "built"), built.build_seconds
    return built, None, built.build_seconds


def execute(case: Case, settings: RunSettings, env: dict | None = None, dump_hits: str | None = None,
            heatmap_dir: str | None = None, scene=None, rays=None, truth=None) -> dict:
    """Run one case and return its record (a dict, lsbench.results.record). Driver limits and
    driver errors become a failed record with the reason; bad input (scene/rays) raises
    SceneError/RayError to the caller. scene, rays, truth: the case's Scene, RaySet and Embree's
    (prim_ids, t) for them when the caller has them (a cluster computes the truth once per scene
    and rays); None = load, make or look them up here."""
    from lsbench import backends
    from lsbench.backends import DeviceError, DeviceLimitError

    from lsbench.oracle.embree import embree_closest
    from lsbench.inputs.rays import make_rays
    from lsbench.inputs.scenes import load_scene
    from lsbench.oracle.classifier import judge_hits
    from lsbench.model.cost import bytes_at_least, resolve_case
    from lsbench.profile.simd import simd_fields

    if scene is None:
        scene = load_scene(case.scene)
    if rays is None:
        rays = make_rays(case.rays, scene, case.width, case.height, case.camera_object(), case.ray_params)
    rec = new_record(case, settings, env, case_inputs(scene, rays))
    ref_prim, ref_t = truth if truth is not None else embree_closest(scene, rays)
    built = None
    try:
        device = backends.get_device(case.backend)
        info = device.info()
        rec.update(device=info["device"], driver=info["driver"], backend_version=info["backend_version"])
        budget = case.budget_mib if case.budget_mib is not None else settings.budget_mib
        budget_bytes = int(budget * 2**20) if budget else None
        rec.update(budget_mib=budget)
        # "auto" parameters: the cost model picks them under the budget (lsbench/model/cost.py)
        params, choice = resolve_case(case, device, scene, rays, ref_t, budget_bytes)
        if choice is not None:
            rec.update(auto=choice.record())
        if params is None:
            raise DeviceLimitError(choice.no_fit_reason(budget))
        if choice is not None:
            rec.update(**chosen_fields(params))
        if budget_bytes is not None and choice is None:
            # A setting that cannot fit fails before its build (a Line Space build can take minutes)
            at_least, exact = bytes_at_least(device, case.structure, scene, params)
            if at_least > budget_bytes:
                rec.update(predicted={"memory_bytes": at_least, "memory_bytes_exact": exact})
                raise DeviceLimitError(
                    f"the structure needs {'' if exact else 'at least '}{at_least / 2**20:.1f} MiB (predicted from "
                    f"the count pass, not built), over the device-memory budget of {budget:g} MiB (budget_mib, --budget)")
        built, over, seconds = _build_within(device, case.structure, scene, params, budget_bytes)
        while choice is not None and over is not None and choice.next_after_overshoot(over.needed_bytes, seconds):
            # The chosen Line Space's estimated lists came out over the budget: the next that fits.
            if built is not None:
                built.release()
                built = None
            params = choice.params()
            rec.update(**chosen_fields(params), auto=choice.record())
            built, over, seconds = _build_within(device, case.structure, scene, params, budget_bytes)
        if choice is not None:
            rec.update(auto=choice.record())
        if built is not None:
            rec.update(build_seconds=built.build_seconds, memory_bytes=built.memory_bytes,
                       buffers=built.memory(), stats=built.stats)
            if choice is not None:
                rec.update(predicted=choice.predicted(device, built))
        elif choice is None and over is not None:  # stopped: the bytes its count pass gave, exact
            rec.update(predicted={"memory_bytes": over.needed_bytes, "memory_bytes_exact": True})
        if over is not None:
            again = f" (auto: {len(choice.rebuilt)} chosen settings built over it)" if choice is not None else ""
            raise DeviceLimitError(over.reason(budget) + again)
        hits = backends.trace(built, rays)
        rec.update(trace_slices=hits.slices, slice_budget=hits.slice_budget, trace_packet=hits.packet,
                   trace_refill=hits.refill, trace_order=hits.order, trace_order_probe=hits.order_probe)
        # verify's counts and |dt|, and the float64 class of every disagreement (the gate's input)
        rec.accuracy, rec.classification = judge_hits(scene, rays, hits.prim_ids, hits.distances,
                                                      ref_prim, ref_t, rel_tol=settings.rel_tol)
        if dump_hits:
            np.savez(dump_hits, origins=rays.origins, directions=rays.directions,
                     prim_ids=hits.prim_ids, distances=hits.distances,
                     embree_prim_ids=ref_prim, embree_distances=ref_t)
        try:  # the counter kernel binds one more buffer: a driver limit there leaves the case ok
            counted = backends.trace(built, rays, work=True)
            work = counted.work
            rec.update(**work_fields(work), **simd_fields(work, backends.launch_order(rays), info, counted.packet),
                       work_counters_error="")
        except (DeviceLimitError, DeviceError) as exc:
            rec.update(work_counters_error=f"{type(exc).__name__}: {exc}".splitlines()[0][:500])
        # Embree traces the same rays once after each timed launch, so the ratio of the two speeds
        # is taken under one load: timed apart (Embree first, then the build, then the launches),
        # the ratio of one case swung 3x on the shared 2-core machine (speedtest, issue 16)
        embree_seconds: list[float] = []
        time_embree = None
        if settings.embree_timing:
            from lsbench.oracle.embree import embree_timer

            timer = embree_timer(scene, rays)

            def time_embree():
                embree_seconds.append(timer())
        timing = backends.time_trace(built, rays, settings.warmup, settings.repeats, time_embree)
        rec.update(**timing_fields(timing.seconds, timing.clock, rays.count, rays.width > 0))
        if embree_seconds:
            med = statistics.median(embree_seconds)
            rec.update(embree_trace_seconds=med, embree_rays_per_second=rays.count / med if med > 0 else None)
        if heatmap_dir:
            from lsbench.profile import heatmaps as profile

            rec.update(heatmaps=profile.write_heatmaps(built, rays, heatmap_dir, case.key),
                       work_clock=profile.clock_info(device))
        from lsbench.oracle.image import image_accuracy  # ΔE of the shaded picture (camera rays only)

        rec.update(**image_accuracy(scene, rays, hits.prim_ids, hits.distances, ref_prim, ref_t,
                                    rec.accuracy, heatmap_dir, case.key))
        rec.update(status="ok", reason="")
    except (DeviceLimitError, DeviceError, ValueError, MemoryError) as exc:
        rec.update(status="failed", reason=f"{type(exc).__name__}: {exc}".splitlines()[0][:500])
    except Exception as exc:  # a bug: keep the case's record, with where it happened
        tb = traceback.extract_tb(exc.__traceback__)[-1]
        rec.update(status="failed",
                   reason=f"{type(exc).__name__}: {exc} ({Path(tb.filename).name}:{tb.lineno})"[:500])
    finally:
        if built is not None:
            built.release()
    if rec.status != "ok":
        rec.accuracy = rec.classification = None  # accuracy columns are measured only for an ok case
    return rec.to_dict()
