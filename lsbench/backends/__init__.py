"""Backends: the same interface for GLSL (moderngl) and OpenCL (pyopencl).

    device = get_device("glsl" | "opencl")
    built = build(device, "grid", scene, BuildParams(resolution=(64, 64, 64)))
    hits = trace(built, rays)                # rays.query "closest": prim id + distance per ray;
                                             # "any": a hit in [tmin, tmax) per ray, or -1
    timing = time_trace(built, rays, 1, 5)   # device time of the trace kernel

Where the device bounds a launch's loops (Device.loop_budget: llvmpipe), a trace runs in bounded
slices: each launch runs at most that many loop iterations per ray and the unfinished rays are
launched again (shaders/common/trace.h). budget= (or env LSBENCH_SLICE_BUDGET, "none" = unbounded)
forces a budget on any device, e.g. to test the slices on OpenCL.

Where the device runs work items one at a time on a CPU (Device.packet_width: PoCL, 8) or loads
each SIMD lane's node on its own (llvmpipe, 4 per lane) and the rays are coherent (packet_width
below: primary rays, and on PoCL shadow rays to a light), a structure with a packet traversal (bvh;
bvh-ls in SIMD lanes only) traces a packet of rays per work item in the vector lanes
(shaders/common/bvh.h); env LSBENCH_PACKET = auto (default), 1 (a ray per work item), 8 or 16
(OpenCL) or 4 (GLSL) decides it by hand.

A ray set without locality (consecutive rays starting far apart: the incoherent set) is traced in
the order of its origins' cells, sorted on the device inside the timed trace (ray_order.py; env
LSBENCH_RAY_ORDER = auto, given or origin-cells). Where work items run in SIMD lanes (llvmpipe,
GPUs), a structure whose kernel refills lanes (bvh, bvh-ls) traces such a set REFILL_RAYS rays per
work item instead, a lane starting its next ray where its last one ended (refill_rays below; env
LSBENCH_REFILL = auto, 1 for one ray per work item, or a number of rays).
"""
from __future__ import annotations

import functools
import os
import time

import numpy as np

from . import ray_order
from .device import Device, DeviceError, DeviceLimitError, Timing
from .structures import CATALOGUE, STRUCTURES, StructureInfo, display_order, structure_info
from .kernels import SLICE_WORDS
from .structures.base import (BuildParams, BuildResult, Built, GridGeometry, Hits, for_query, ordered, packeted,
                              refilled, sliced, with_work_counters)

BACKENDS = ("glsl", "opencl")
# Hit id of a ray whose traversal loops the driver cut short (cut_hit, shaders/common/trace.h).
LOOP_CUT_PRIM = -2
# Hit id of a ray a sliced launch suspended (SLICE_PENDING, shaders/common/trace.h).
SLICE_PENDING = -3
# The smallest slice budget that always gets a ray further: a resumed step pays its tick, the 2
# loop iterations of an octree walk's return to a leaf (trace.h: trace_revisit) and then at least
# one candidate test. Below it a ray could suspend at the same place in every launch.
MIN_SLICE_BUDGET = 4
# Marks "no budget given" apart from None (unbounded) in trace() and time_trace().
DEVICE_BUDGET = "device"
_devices: dict[str, Device] = {}


def get_device(name: str) -> Device:
    if name not in BACKENDS:
        raise ValueError(f"unknown backend {name!r}; choose one of {', '.join(BACKENDS)}")
    if name not in _devices:
        if name == "glsl":
            from .glsl import GLSLDevice

            _devices[name] = GLSLDevice()
        else:
            from .opencl import OpenCLDevice

            _devices[name] = OpenCLDevice()
    return _devices[name]


def structure_names() -> list[str]:
    return list(STRUCTURES)


def geometry_for(structure: str, scene, params: BuildParams, bounds=None) -> GridGeometry:
    """The grid geometry `structure` builds over `scene` (bounds: scene.bounds, when the caller
    has them already: they cost a pass over the faces)."""
    lo, hi = scene.bounds if bounds is None else bounds
    cubic = structure_info(structure).cubic_power_of_two or params.bounding_cube
    return GridGeometry.over_bounds(lo, hi, params.resolution, cubic=cubic)


def triangle_records(scene) -> np.ndarray:
    """The traversals' copy of the triangles (kernels.TRACE_SCENE_BUFFERS): per triangle its three
    vertices as float4, in face order, flattened; the w components hold the unit normal (shaders/
    common/geometry.h: triangle_plane_t), zero for a zero-area triangle. The normal is the cross
    product of the two shortest edges (which meet at the largest angle) in float64, where the
    products of float32 coordinates are exact, so a sliver's normal is as good as any other's."""
    tris = np.asarray(scene.vertices, np.float32)[np.asarray(scene.faces, np.int64)]
    records = np.zeros((len(tris), 3, 4), np.float32)
    records[:, :, :3] = tris
    v = tris.astype(np.float64)
    edges = np.stack([v[:, 1] - v[:, 0], v[:, 2] - v[:, 1], v[:, 0] - v[:, 2]], axis=1)
    longest = np.argmax(np.einsum("fkj,fkj->fk", edges, edges), axis=1)
    rows = np.arange(len(tris))
    normal = np.cross(edges[rows, (longest + 1) % 3], edges[rows, (longest + 2) % 3])
    length = np.linalg.norm(normal, axis=1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        normal = np.where(length > 0, normal / length, 0.0)
    records[:, :, 3] = normal
    return records.ravel()


def build(device: Device, structure: str, scene, params: BuildParams) -> Built:
    module = structure_info(structure).recipe
    geometry = geometry_for(structure, scene, params)
    module.prepare(device)  # compiles are never part of the build time
    _warm_up(device)
    scene_buffers = {
        "vertices": device.upload("vertices", np.ascontiguousarray(scene.vertices, np.float32).ravel()),
        "faces": device.upload("faces", np.ascontiguousarray(scene.faces, np.uint32).ravel()),
        "tri_verts": device.upload("tri_verts", triangle_records(scene)),
    }
    device.finish()
    device.start_kernel_log()
    t0 = time.perf_counter()
    result = module.build(device, scene_buffers, scene.triangle_count, geometry, params)
    device.finish()
    seconds = time.perf_counter() - t0
    stats = dict(result.stats)
    kernel_seconds = device.kernel_seconds()
    if kernel_seconds is not None:  # device time per build kernel, where the backend has it
        stats["build_kernel_seconds"] = kernel_seconds
    defect = os.environ.get("LSBENCH_PLANT_DEFECT", "")
    if defect.startswith(("drop-reference", "drop-triangle")):
        _plant_dropped_triangle(device, result.buffers, scene, int(defect.split(":")[1]) if ":" in defect else None)
    return Built(structure, device, params, geometry, scene_buffers, result.buffers, result.uniforms,
                 result.trace_spec, build_seconds=seconds, stats=stats, suspends=result.suspends)


_warm: set[int] = set()


def _warm_up(device: Device) -> None:
    """Compile the prefix-sum kernels (built lazily by pyopencl and glsl.py) on a tiny input, so
    the first case's build time holds no compile either."""
    if id(device) in _warm:
        return
    src = device.upload("warm_up", np.ones(600, np.uint32))  # > 1 scan block: every kernel
    out, _ = device.exclusive_scan(src, 600, "warm_up_scan")
    device.finish()
    device.release(src)
    device.release(out)
    _warm.add(id(device))


# The rays of an image go to the device in RAY_TILE x RAY_TILE pixel tiles, one per work group of
# 64 items (KernelSpec.local_size), instead of in rows: the lanes of a SIMD group then walk
# neighbouring cells, nodes and shafts. Measured with `lsbench speedtest --repeats 9` (issue 16,
# Sponza 256², interior camera, Embree timed between the launches, rows/tiles alternated twice):
# on PoCL every structure gained 2-5 % in × Embree (esvo 256³ 0.311-0.317 -> 0.329-0.332, grid
# 128³ 0.193-0.195 -> 0.198-0.203, esvo-ls 64³ N=2 0.195-0.200 -> 0.204); on llvmpipe the change
# stayed inside the run-to-run spread (±10 %).
RAY_TILE = 8


def launch_order(rays) -> np.ndarray | None:
    """Ray ids in the order the device traces them: an image's rays tile by tile (tiles row by
    row, pixels row by row within a tile; edge tiles are cut to the image), None for any other ray
    set (traced as given). Hits are put back in the ray set's order (trace)."""
    if rays.width <= 0 or rays.height <= 0 or rays.width * rays.height != rays.count:
        return None
    return _tile_order(rays.width, rays.height)


# A trace asks for its image's order up to four times (packets, the order probe, the ray buffer,
# the hits), and a timed case traces the same image many times: the sort took 14 of the 38 ms
# of wall time of one backends.trace of bvh on PoCL (Sponza 256², whose device time is 14 ms).
@functools.lru_cache(maxsize=16)
def _tile_order(width: int, height: int) -> np.ndarray:
    y, x = np.divmod(np.arange(width * height), width)
    order = np.lexsort((x % RAY_TILE, y % RAY_TILE, x // RAY_TILE, y // RAY_TILE))  # last key sorts first
    order.setflags(write=False)  # shared by every caller
    return order


def _in_ray_order(values: np.ndarray, order: np.ndarray | None) -> np.ndarray:
    """Per-launch-item values (rows) back in the ray set's order."""
    if order is None:
        return values
    out = np.empty_like(values)
    out[order] = values
    return out


def _ray_buffer(rays, order: np.ndarray | None) -> np.ndarray:
    """float4 pairs per ray, in launch order: origin.xyz + tmin, direction.xyz + tmax (the ray's
    own; inf where the ray set has none)."""
    def pick(values):
        return values if order is None else np.asarray(values)[order]

    n = rays.count
    packed = np.empty((n, 2, 4), np.float32)
    packed[:, 0, :3] = pick(rays.origins)
    packed[:, 0, 3] = rays.tmin
    packed[:, 1, :3] = pick(rays.directions)
    packed[:, 1, 3] = pick(rays.tmax_array)
    return packed.ravel()


# A packet of rays visits the union of the nodes its rays need, so it pays only where its rays take
# about the same way. PoCL, Sponza from the interior camera (docs/profiles.md, section 8), device
# time of the packet kernel over the single-ray one, with ray_coherence in brackets: primary rays
# 512² 0.57 (0.9999), 64² 0.78 (0.998), 32² 0.90 (0.993); shadow rays to a point light 0.75 (0.9997;
# BMW 0.67 at 0.998); the 512² primary rays each turned at random by up to 2 degrees 0.85 (0.9994),
# by up to 10 degrees 1.13 (0.986); ambient occlusion 1.02 (0.31), diffuse 1.07 (0.22), incoherent
# 1.54 (-0.61). Packets from this coherence up.
PACKET_MIN_COHERENCE = 0.99


def ray_coherence(rays, width: int) -> float:
    """How parallel the rays of a packet are: over the groups of `width` consecutive rays in launch
    order, the median of each group's smallest cosine between a ray's direction and the group's
    mean direction (1: parallel rays; a group of opposite rays -1). Computed once per ray set
    content, image size and width (every trace of a set asks: 8 of its 38 ms of wall time above)."""
    return _ray_coherence(rays.content_hash, rays.width, rays.height, int(width), rays)


_COHERENCE: dict[tuple, float] = {}


def _ray_coherence(content: str, image_w: int, image_h: int, width: int, rays) -> float:
    key = (content, image_w, image_h, width)
    if key not in _COHERENCE:
        if len(_COHERENCE) >= 64:
            _COHERENCE.clear()
        _COHERENCE[key] = _measure_coherence(rays, width)
    return _COHERENCE[key]


def _measure_coherence(rays, width: int) -> float:
    n = rays.count // width * width
    if n == 0:
        return -1.0
    order = launch_order(rays)
    d = np.asarray(rays.directions if order is None else np.asarray(rays.directions)[order], np.float64)[:n]
    d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)
    groups = d.reshape(-1, width, 3)
    mean = groups.sum(axis=1)
    mean /= np.maximum(np.linalg.norm(mean, axis=1, keepdims=True), 1e-300)
    return float(np.median(np.einsum("gwk,gk->gw", groups, mean).min(axis=1)))


# Rays per work item the packet kernel compiles for, per backend (bvh.h: float8 / float16 lanes in
# OpenCL C, vec4 in GLSL).
PACKET_WIDTHS = {"opencl": (8, 16), "glsl": (4,)}


def packet_width(built: Built, rays, budget: int | None) -> int:
    """Rays per work item for this trace: the device's packet_width where the structure has a
    packet traversal, one launch runs whole rays (no slices) and the rays are coherent
    (ray_coherence >= PACKET_MIN_COHERENCE) and their query is one of the device's packet_queries
    (and, where work items run one at a time, the structure's packets pay there: serial_packets);
    else 1. Env LSBENCH_PACKET (auto, 1, or one of the backend's PACKET_WIDTHS) overrides the choice."""
    device = built.device
    allowed = ("auto", "1") + tuple(str(w) for w in PACKET_WIDTHS.get(device.backend, ()))
    forced = os.environ.get("LSBENCH_PACKET", "").strip().lower() or "auto"
    if forced not in allowed:
        raise ValueError(f"LSBENCH_PACKET must be one of {', '.join(allowed)} on {device.backend}, got {forced!r}")
    info = structure_info(built.structure)
    if budget is not None or not info.packets:
        return 1
    if forced != "auto":
        return int(forced)
    width = device.packet_width
    if width <= 1 or (device.serial_work_items and not info.serial_packets):
        return 1
    if rays.query not in device.packet_queries or ray_coherence(rays, width) < PACKET_MIN_COHERENCE:
        return 1
    return width


# Rays per work item of a refilled trace (bvh.h BVH_REFILL): a lane's rays run one after the other,
# so its SIMD group waits for its longest walk once per REFILL_RAYS rays instead of once per ray.
# llvmpipe, medians of alternated launches in one process, the same hits and counters
# (docs/profiles.md, section 21): bvh on Sponza 256² incoherent rays 0.88-0.93 of the one-ray
# kernel's device time at 16 rays per item (0.86 at 32), BMW 0.73; bvh-ls 0.94-1.00 and 0.79.
# Shadow, ambient occlusion, diffuse and primary rays, whose lanes end together, took 1.02-1.33 of
# the time, so only sets without locality are refilled (refill_rays). 16 leaves a lane's rays
# 4096 loop iterations each of llvmpipe's budget of 65535 per SIMD group before a cut (trace).
REFILL_RAYS = 16


def refill_rays(built: Built, rays, budget: int | None) -> int:
    """Rays per work item of a refilled trace: REFILL_RAYS where the structure's kernel refills
    lanes (StructureInfo.refill), the device runs work items in SIMD lanes (Device.serial_work_items
    false: llvmpipe, GPUs; on PoCL a work item's rays would run one after the other anyway), one
    launch runs whole rays, and the rays have no locality (an image's tiles and sets whose
    consecutive rays start together keep lanes that end together: ray_order.choose's test); else 1,
    also for a set whose refilled trace the driver's loop budget cut (Built.refill_cut). Env
    LSBENCH_REFILL: auto (default), or the rays per work item (1: none) wherever the kernel refills."""
    forced = os.environ.get("LSBENCH_REFILL", "").strip().lower() or "auto"
    if forced != "auto" and not (forced.isdigit() and int(forced) >= 1):
        raise ValueError(f"LSBENCH_REFILL must be auto or a whole number of rays >= 1, got {forced!r}")
    if budget is not None or not structure_info(built.structure).refill or rays.count < 2:
        return 1
    if _refill_key(rays) in built.refill_cut:
        return 1
    if forced != "auto":
        return int(forced)
    if built.device.serial_work_items or launch_order(rays) is not None:
        return 1
    return REFILL_RAYS if ray_order.without_locality(rays, _bounds(built)) else 1


def _refill_key(rays) -> tuple:
    """A ray set's key in Built.refill_cut: its content and query."""
    return (rays.content_hash, rays.query)


def _launch_spec(spec, n: int, uniforms: dict, width: int, refill: int = 1):
    """(kernel, work items, uniforms) of a launch over n rays at `width` rays per work item in
    packets, or `refill` one after the other per lane."""
    if refill > 1:
        return refilled(spec, refill), -(-n // refill), dict(uniforms, packet_rays=n)
    if width <= 1:
        return spec, n, uniforms
    return packeted(spec, width), -(-n // width), dict(uniforms, packet_rays=n)


def trace_order(built: Built, rays, width: int, budget: int | None, refill: int = 1) -> tuple[str, dict | None]:
    """The order the rays of this trace go to the device in, and the probe that chose it: "given"
    (an image's tiles, or the set's own order) or "origin-cells" (sorted on the device by their
    origins' cells over the structure's bounds), as ray_order.choose says; where it says
    "measure", the faster of the two in whole timed traces (the sort included): two rounds of one
    warm-up and one timed trace of each order, alternated, the minimum kept. Measured once per
    structure and ray set (Built.ray_orders), so the verified, counted and timed traces run the
    same order; a refilled trace (refill_rays) is measured with its refilled kernel."""
    choice = ray_order.choose(rays, _bounds(built), launch_order(rays) is not None, width)
    if choice == "measure" and 4 * max(ray_order.ORDER_CELLS, rays.count) > built.device.max_buffer_bytes:
        choice = "given"  # the sort's buffers would not fit the driver's per-buffer limit
    if choice != "measure":
        return choice, None
    key = (rays.content_hash, rays.query, budget, refill)
    if key not in built.ray_orders:
        probe = {order: [] for order in ("given", "origin-cells")}
        for _ in range(2):
            for order, seconds in probe.items():
                seconds.append(min(_timed_trace(built, rays, width, budget, order, 1, 1, None, refill).seconds))
        best = {order: min(seconds) for order, seconds in probe.items()}
        built.ray_orders[key] = (min(best, key=best.get), best)
    return built.ray_orders[key]


def _bounds(built: Built):
    g = built.geometry
    lo = np.asarray(g.origin, np.float64)
    return lo, lo + np.asarray(g.voxel_size, np.float64) * np.asarray(g.resolution, np.float64)


def _trace_buffers(built: Built, rays, work: bool, order: str = "given", refill: int = 1):
    """The trace's buffers. A refilled trace's hit ids start as LOOP_CUT_PRIM: once llvmpipe's loop
    budget is spent, every loop runs its body once more and ends, so a lane's rays not yet started
    are never stored, and must read as cut (trace: the set is traced again one ray per item)."""
    d = built.device
    bufs = dict(built.scene_buffers)
    bufs.update(built.buffers)
    bufs["rays"] = d.upload("rays", _ray_buffer(rays, launch_order(rays)))
    if refill > 1:
        bufs["hit_prim"] = d.upload("hit_prim", np.full(rays.count, LOOP_CUT_PRIM, np.int32))
    else:
        bufs["hit_prim"] = d.alloc("hit_prim", 4 * rays.count, zero=False)
    bufs["hit_t"] = d.alloc("hit_t", 4 * rays.count, zero=False)
    if work:
        bufs["work"] = d.alloc("work", 16 * rays.count)
    if order == "origin-cells":
        bufs.update(ray_order.alloc(d, rays.count))
    return bufs


_TRACE_BUFFERS = ("rays", "hit_prim", "hit_t", "work", "slice_state", "order_counts", "order_ids")


def _sort_steps(built: Built, rays, order: str) -> list:
    """The launches before the trace kernel (ray_order.sort_steps), none for the given order."""
    if order != "origin-cells":
        return []
    return ray_order.sort_steps(rays.count, ray_order.uniforms(_bounds(built)))


def _release(device, bufs, names):
    for n in names:
        if n in bufs:
            device.release(bufs[n])


def slice_budget(device: Device, budget=DEVICE_BUDGET) -> int | None:
    """The loop iterations per ray of one traversal launch: `budget` where given (None =
    unbounded), else env LSBENCH_SLICE_BUDGET (a positive integer or "none"), else the device's."""
    if budget == DEVICE_BUDGET:
        forced = os.environ.get("LSBENCH_SLICE_BUDGET", "").strip().lower()
        if not forced:
            return device.loop_budget
        if forced == "none":
            return None
        if not forced.isdigit() or int(forced) < MIN_SLICE_BUDGET:
            raise ValueError(f"LSBENCH_SLICE_BUDGET must be an integer >= {MIN_SLICE_BUDGET} or 'none', got {forced!r}")
        budget = int(forced)
    if budget is not None and int(budget) < MIN_SLICE_BUDGET:
        raise ValueError(f"a slice budget must be an integer >= {MIN_SLICE_BUDGET} or None, got {budget!r}")
    return None if budget is None else int(budget)


def _walk_budget(built: Built, budget) -> int | None:
    """The slice budget of a trace of `built`: slice_budget's, or None (one launch) for a walk that
    cannot suspend (Built.suspends false: bvh, bvh-ls), whose rays run whole in the first slice
    anyway, so the slices' state loads, list and read-back would be all they add (bvh glsl, BMW
    256² primary rays: 0.79 of the device time in one launch; docs/profiles.md, section 19). A ray
    whose loops the driver still cuts fails the trace as in slices (LOOP_CUT_PRIM)."""
    return slice_budget(built.device, budget) if built.suspends else None


def _dispatch(d: Device, *args) -> None:
    """An untimed slice launch (_run_slices' `launch`)."""
    d.dispatch(*args)


def _run_slices(d: Device, spec, n: int, bufs: dict, uniforms: dict, budget: int, launch, first=None) -> int:
    """Traversal in bounded slices (shaders/common/trace.h): launch the kernel over the unfinished
    rays, `budget` loop iterations each, until every ray has its hit; returns the launches made.
    hit_prim says which rays are left (SLICE_PENDING); a ray whose loops the driver still cut
    (LOOP_CUT_PRIM: llvmpipe's limit is per SIMD group) kept its earlier state and runs again with
    half the budget; cut at MIN_SLICE_BUDGET, the case fails naming the limit. `first`: the first
    slice's ray list when the rays go in another order than given (ray_order: order_ids, read
    back; the later lists keep its order)."""
    state = bufs["slice_state"]
    d.fill_zero(state)  # phase 0: every ray starts fresh
    list_base = SLICE_WORDS * n
    pending = np.arange(n, dtype=np.uint32) if first is None else first()
    slices = 0
    while pending.size:
        d.write(state, pending, 4 * list_base)
        launch(d, spec, int(pending.size), bufs, dict(uniforms, slice_budget=budget, slice_list_base=list_base))
        slices += 1
        prim = d.read(bufs["hit_prim"], np.int32, n)
        cut = prim[pending] == LOOP_CUT_PRIM
        if cut.any():
            if budget <= MIN_SLICE_BUDGET:
                raise d.loop_limit_error(f"the traversal loops of {int(cut.sum())} of {n} rays at a slice "
                                         f"budget of {budget} loop iterations per ray")
            budget = max(MIN_SLICE_BUDGET, budget // 2)
        pending = pending[(prim[pending] == SLICE_PENDING) | cut]
    return slices


# The bytes a trace keeps per ray in its widest buffer (_trace_buffers): the ray's two float4, or in
# bounded slices its slice state, 4 * (SLICE_WORDS + 1). A buffer may not exceed the driver's
# per-buffer limit (llvmpipe: 128 MiB), so llvmpipe held at most 1.97 M rays in slices, and a
# 1920 x 1080 image (2.07 M) failed there; ray_parts splits such a set.
RAY_BYTES = 32
SLICED_RAY_BYTES = 4 * (SLICE_WORDS + 1)


def rays_per_part(device: Device, budget: int | None) -> int:
    """The most rays one trace's buffers hold on `device` (budget: the trace's slice budget, None
    for one launch)."""
    return max(1, device.max_buffer_bytes // (SLICED_RAY_BYTES if budget is not None else RAY_BYTES))


def ray_parts(rays, most: int) -> list:
    """The ray set as consecutive parts of at most `most` rays, traced one after the other. An
    image splits into whole rows of RAY_TILE-pixel tiles, so each part's launch order (its tiles)
    is the image's, and the SIMD groups of the parts are those of the whole image (simd_fields);
    an image too wide for one row of tiles, and every other set, into plain ranges."""
    n = rays.count
    if n <= most:
        return [rays]
    if launch_order(rays) is not None and most >= RAY_TILE * rays.width:
        rows = most // (RAY_TILE * rays.width) * RAY_TILE
        return [rays.part(r * rays.width, min(r + rows, rays.height) * rays.width) for r in range(0, rays.height, rows)]
    return [rays.part(s, min(s + most, n)) for s in range(0, n, most)]


def _joined(parts: list) -> Hits:
    """The Hits of a trace in parts (ray_parts), in the ray set's order: the launches summed, the
    choices per part (packets, refill, order) where the parts agree, else the largest or all."""
    if len(parts) == 1:
        return parts[0]
    orders = sorted({h.order for h in parts})
    work = None if parts[0].work is None else np.concatenate([h.work for h in parts])
    return Hits(np.concatenate([h.prim_ids for h in parts]), np.concatenate([h.distances for h in parts]), work=work,
                slices=sum(h.slices for h in parts), slice_budget=parts[0].slice_budget,
                packet=max(h.packet for h in parts), refill=max(h.refill for h in parts), order="+".join(orders),
                order_probe=None if all(h.order_probe is None for h in parts) else {
                    "parts": [h.order_probe for h in parts]})


def trace(built: Built, rays, work: bool = False, budget=DEVICE_BUDGET) -> Hits:
    """The hit of every ray for the ray set's query (rays.query: closest, or any hit in
    [tmin, tmax)); work=True runs the profiling kernel with per-ray counters. `budget`: loop
    iterations per ray and launch (slice_budget: the device's unless given). A set whose buffers
    would exceed the driver's per-buffer limit is traced in parts (ray_parts)."""
    parts = ray_parts(rays, rays_per_part(built.device, _walk_budget(built, budget)))
    return _joined([_trace_part(built, part, work, budget) for part in parts])


def _trace_part(built: Built, rays, work: bool = False, budget=DEVICE_BUDGET) -> Hits:
    """trace() of a set that fits the trace's buffers."""
    d = built.device
    spec = for_query(built.trace_spec, rays.query)
    spec = with_work_counters(spec, d) if work else spec
    budget = _walk_budget(built, budget)
    width = packet_width(built, rays, budget)
    refill = refill_rays(built, rays, budget) if width == 1 else 1
    ordered, probe = trace_order(built, rays, width, budget, refill)
    if refill > 1 and _refill_key(rays) in built.refill_cut:  # the order's probe saw a cut
        return _trace_part(built, rays, work, budget)
    before = _sort_steps(built, rays, ordered)
    bufs = _trace_buffers(built, rays, work, ordered, refill)
    try:
        if budget is not None:
            bufs["slice_state"] = d.alloc("slice_state", 4 * (SLICE_WORDS + 1) * rays.count)
        slices = _launch_trace(built, spec, rays.count, bufs, budget, width, before, _dispatch, refill)
        d.finish()
        order = launch_order(rays)  # an image's tiles; a sorted order stores its hits in place
        hits = Hits(_in_ray_order(d.read(bufs["hit_prim"], np.int32, rays.count), order),
                    _in_ray_order(d.read(bufs["hit_t"], np.float32, rays.count), order), slices=slices,
                    slice_budget=budget, packet=width, refill=refill, order=ordered, order_probe=probe)
        if work:
            hits.work = _in_ray_order(d.read(bufs["work"], np.uint32, 4 * rays.count).reshape(-1, 4), order)
    finally:
        _release(d, bufs, _TRACE_BUFFERS)
    cut = int(np.count_nonzero(hits.prim_ids == LOOP_CUT_PRIM))
    if cut and refill > 1:
        # a lane's rays share the SIMD group's loop budget: one ray per work item from now on
        built.refill_cut.add(_refill_key(rays))
        return _trace_part(built, rays, work, budget)
    if cut:
        raise d.loop_limit_error(f"the traversal loops of {cut} of {rays.count} rays: they meet more "
                                 "candidates than that (a finer resolution or a Line Space cuts them)")
    return hits


def time_trace(built: Built, rays, warmup: int = 1, repeats: int = 5, between=None,
               budget=DEVICE_BUDGET) -> Timing:
    """Device time of the plain (counter-free) trace kernel of the ray set's query, warm-up
    launches not counted; `between()` runs after each timed launch, untimed (Device.time_dispatch).
    In bounded slices (slice_budget) a timed trace is all its slices, their device times summed,
    warm-up traces and `between()` around whole traces; in a sorted order (trace_order) the sort's
    launches are in it too. A set traced in parts (ray_parts) is timed part after part, each
    repeat the sum of its parts' times, `between()` after the last part of each."""
    parts = ray_parts(rays, rays_per_part(built.device, _walk_budget(built, budget)))
    if len(parts) == 1:
        return _time_part(built, rays, warmup, repeats, between, budget)
    seconds, clocks = [], []
    for i in range(repeats):
        timings = [_time_part(built, part, warmup if i == 0 else 0, 1, None, budget) for part in parts]
        seconds.append(sum(t.seconds[0] for t in timings))
        for t in timings:
            if t.clock not in clocks:
                clocks.append(t.clock)
        if between is not None:
            between()
    return Timing(seconds, "; ".join(clocks) + f", summed over {len(parts)} parts of at most "
                  f"{max(p.count for p in parts)} rays (the driver's per-buffer limit)")


def _time_part(built: Built, rays, warmup: int = 1, repeats: int = 5, between=None,
               budget=DEVICE_BUDGET) -> Timing:
    """time_trace() of a set that fits the trace's buffers."""
    budget = _walk_budget(built, budget)
    width = packet_width(built, rays, budget)
    refill = refill_rays(built, rays, budget) if width == 1 else 1
    order = trace_order(built, rays, width, budget, refill)[0]
    key = _refill_key(rays)
    if refill > 1 and key in built.refill_cut:  # the order's probe saw the loop budget cut it
        return _time_part(built, rays, warmup, repeats, between, budget)
    timing = _timed_trace(built, rays, width, budget, order, warmup, repeats, between, refill)
    if refill > 1 and key in built.refill_cut:  # the timed launches saw it: one ray per item
        return _time_part(built, rays, warmup, repeats, between, budget)
    return timing


def _timed_trace(built: Built, rays, width: int, budget: int | None, ordered: str, warmup: int, repeats: int,
                 between, refill: int = 1) -> Timing:
    """Device time of whole traces (time_trace). A refilled trace whose rays the driver's loop
    budget cut (LOOP_CUT_PRIM in the hits of its last launch) marks its ray set in Built.refill_cut."""
    d = built.device
    spec = for_query(built.trace_spec, rays.query)
    before = _sort_steps(built, rays, ordered)
    bufs = _trace_buffers(built, rays, False, ordered, refill)
    try:
        if budget is None and not before:
            kernel, items, uniforms = _launch_spec(spec, rays.count, built.uniforms, width, refill)
            timing = d.time_dispatch(kernel, items, bufs, uniforms, warmup, repeats, between)
            _note_refill_cut(built, rays, bufs, refill)
            return timing
        if budget is not None:
            bufs["slice_state"] = d.alloc("slice_state", 4 * (SLICE_WORDS + 1) * rays.count)

        def whole_trace(launch):
            _launch_trace(built, spec, rays.count, bufs, budget, width, before, launch, refill)

        for _ in range(max(warmup, 1)):
            whole_trace(_dispatch)
        d.finish()
        seconds, clocks = [], set()
        for _ in range(repeats):
            spent = []

            def timed(dev, *args):
                s, clock = dev.dispatch_timed(*args)
                spent.append(s)
                clocks.add(clock)

            whole_trace(timed)
            seconds.append(sum(spent))
            if between is not None:
                between()
        parts = ([] if budget is None else ["summed over the slices"]) + (["with the rays' sort"] if before else [])
        _note_refill_cut(built, rays, bufs, refill)
        return Timing(seconds, " + ".join(sorted(clocks)) + ", " + ", ".join(parts))
    finally:
        _release(d, bufs, _TRACE_BUFFERS)


def _note_refill_cut(built: Built, rays, bufs: dict, refill: int) -> None:
    """After a refilled timed trace: a ray the loop budget cut (or never started: the hit ids start
    as LOOP_CUT_PRIM) marks the set in Built.refill_cut, so it is timed again one ray per item."""
    if refill > 1 and np.any(built.device.read(bufs["hit_prim"], np.int32, rays.count) == LOOP_CUT_PRIM):
        built.refill_cut.add(_refill_key(rays))


def _launch_trace(built: Built, spec, n: int, bufs: dict, budget: int | None, width: int, sort_steps: list,
                  launch, refill: int = 1) -> int:
    """One whole trace through `launch` (_dispatch, or a timed one): the sort's launches, then the
    trace kernel in one launch (ORDERED_RAYS after a sort) or in slices (the first slice's ray list
    is the sorted order, read back after the sort); returns the trace's launches."""
    d = built.device
    for step, items, uniforms in sort_steps:
        launch(d, step, items, bufs, uniforms)
    if budget is None:
        kernel, items, uniforms = _launch_spec(ordered(spec) if sort_steps else spec, n, built.uniforms, width,
                                               refill)
        launch(d, kernel, items, bufs, uniforms)
        return 1
    first = (lambda: d.read(bufs["order_ids"], np.uint32, n)) if sort_steps else None
    return _run_slices(d, sliced(spec), n, bufs, built.uniforms, budget, launch, first)


def _plant_dropped_triangle(device: Device, buffers: dict, scene, victim: int | None) -> None:
    """Test-only fault injection, so tests can show that the gate catches a structure that lost a
    candidate. LSBENCH_PLANT_DEFECT=drop-reference[:TRI] or drop-triangle[:TRI]: triangle TRI
    (default the one listed in most voxels) leaves every voxel list (voxel_tris: grid, the octrees'
    and the BVH's leaves, the cells of a Line Space structure), its entries overwritten by another
    triangle. The two names are one mutation now: a Line Space shaft lists positions in its cell's
    plain list (shaders/common/linespace.h), so the triangle leaves every shaft with it, the same
    mutation for every structure. (Dropping it from one voxel only is no defect any more: the
    traversals keep a hit found in an earlier voxel that lists the triangle, shaders/common/grid.h.)"""
    tris = device.read(buffers["voxel_tris"], np.uint32)
    if victim is None:
        victim = int(np.argmax(np.bincount(tris)))
    other = (victim + 1) % scene.triangle_count
    dropped = tris == victim
    tris[dropped] = other
    buffers["voxel_tris"] = device.upload("voxel_tris", tris)
    if "tri_verts" in buffers:  # records in list order (bvh): the same entries
        records = device.read(buffers["tri_verts"], np.float32).reshape(-1, 12)
        records[dropped] = triangle_records(scene).reshape(-1, 12)[other]
        buffers["tri_verts"] = device.upload("tri_verts", records.ravel())
