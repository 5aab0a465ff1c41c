"""One case, end to end: scene -> rays -> Embree -> GPU build -> GPU trace -> verify -> timing
-> record. Runs inside a worker process (lsbench/running/runner.py) or directly (`lsbench trace`)."""
from __future__ import annotations

import math
import statistics
import traceback
from pathlib import Path

import numpy as np

from lsbench.inputs.scenario import Case, RunSettings


def case_fields(case: Case) -> dict:
    return {
        "key": case.key, "scene": case.scene, "structure": case.structure, "backend": case.backend,
        "resolution": case.resolution, "ls_n": case.ls_n, "ls_min_candidates": case.ls_min_candidates,
        "rays": case.rays, "width": case.width, "height": case.height,
    }


def failed_record(case: Case, reason: str, env: dict | None = None) -> dict:
    rec = case_fields(case)
    rec.update({"status": "failed", "reason": reason, "agreement": None})
    rec.update(env or {})
    return rec


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


def execute(case: Case, settings: RunSettings, env: dict | None = None, dump_hits: str | None = None,
            heatmap_dir: str | None = None, scene=None, rays=None) -> dict:
    """Run one case and return its record. Driver limits and driver errors become a failed
    record with the reason; bad input (scene/rays) raises SceneError/RayError to the caller."""
    from lsbench import backends
    from lsbench.backends import BuildParams, DeviceError, DeviceLimitError
    from lsbench.backends.structures.base import parse_resolution

    from lsbench.oracle.embree import embree_closest
    from lsbench.inputs.rays import make_rays
    from lsbench.inputs.scenes import load_scene
    from lsbench.oracle.classifier import accuracy_fields

    if scene is None:
        scene = load_scene(case.scene)
    if rays is None:
        rays = make_rays(case.rays, scene, case.width, case.height, case.camera_object())
    rec = case_fields(case)
    rec.update({"scene": scene.name, "scene_source": scene.source, "scene_hash": scene.content_hash,
                "triangles": scene.triangle_count, "ray_count": rays.count, "rays_hash": rays.content_hash})
    rec.update(env or {})
    ref_prim, ref_t = embree_closest(scene, rays)
    if settings.embree_timing:
        from lsbench.oracle.embree import embree_trace_seconds

        emb = embree_trace_seconds(scene, rays, repeats=3)
        med = statistics.median(emb)
        rec.update({"embree_trace_seconds": med,
                    "embree_rays_per_second": rays.count / med if med > 0 else None})
    built = None
    try:
        device = backends.get_device(case.backend)
        info = device.info()
        rec.update({"device": info["device"], "driver": info["driver"],
                    "backend_version": info["backend_version"]})
        params = BuildParams(resolution=parse_resolution(case.resolution), ls_n=case.ls_n,
                             ls_min_candidates=case.ls_min_candidates)
        built = backends.build(device, case.structure, scene, params)
        rec.update({"build_seconds": built.build_seconds, "memory_bytes": built.memory_bytes,
                    "buffers": built.memory(), "stats": built.stats})
        hits = backends.trace(built, rays)
        # verify's counts and |dt|, and the float64 class of every disagreement (the gate's input)
        rec.update(accuracy_fields(scene, rays, hits.prim_ids, hits.distances, ref_prim, ref_t,
                                   rel_tol=settings.rel_tol))
        if dump_hits:
            np.savez(dump_hits, origins=rays.origins, directions=rays.directions,
                     prim_ids=hits.prim_ids, distances=hits.distances,
                     embree_prim_ids=ref_prim, embree_distances=ref_t)
        timing = backends.time_trace(built, rays, settings.warmup, settings.repeats)
        rec.update(timing_fields(timing.seconds, timing.clock, rays.count, rays.width > 0))
        if heatmap_dir:
            from lsbench.profile import heatmaps as profile

            rec["heatmaps"] = profile.write_heatmaps(built, rays, heatmap_dir, case.key)
            rec["work_clock"] = profile.clock_info(device)
        rec["status"] = "ok"
        rec["reason"] = ""
    except (DeviceLimitError, DeviceError, ValueError, MemoryError) as exc:
        rec.update({"status": "failed", "reason": f"{type(exc).__name__}: {exc}".splitlines()[0][:500],
                    "agreement": None})
    except Exception as exc:  # a bug: keep the case's record, with where it happened
        tb = traceback.extract_tb(exc.__traceback__)[-1]
        rec.update({"status": "failed", "agreement": None,
                    "reason": f"{type(exc).__name__}: {exc} ({Path(tb.filename).name}:{tb.lineno})"[:500]})
    finally:
        if built is not None:
            built.release()
    return rec
