"""Ray reordering: a ray set without locality is traced in the order of its origins' cells
(shaders/common/ray_order.h), on the device and inside the timed trace.

Why: a ray set whose consecutive rays start far apart (the incoherent set: origins uniform in the
bounds; a ray file in any order) makes every ray's walk fetch its own nodes, cells and triangles.
Traced in the order of the cell of their origins (4 bits per axis over the scene's bounds, Morton
order), rays traced one after another share the first part of their walks. The sort (a counting
sort with atomics, ray_order.h) is in the timed trace, so rays/s counts it: what a renderer would
pay to trace such rays this way. The rays and hits stay in the set's order: work item g traces ray
order_ids[g] (trace.h, ORDERED_RAYS; in slices, the first slice's list). Measured in
docs/profiles.md, section 9.

When (`choose`, backends.trace_order): rays of an image already go in tiles (launch_order), and
rays that start where the rays before them started (shadow, ambient occlusion, diffuse: their
origins are the primary hits in pixel order) gain nothing, so only sets where under
ORDER_MAX_LOCALITY of the consecutive rays start in the same cell of a 16³ grid over the bounds are
candidates (Sponza 128² from the interior camera: incoherent 0.00, adversarial 0.24; shadow 0.80,
diffuse 0.85, ambient occlusion 0.96), and only for single-ray kernels (packets are taken for
coherent rays). Whether the sort pays depends on the scene and the structure: on Sponza it cut
the whole trace (sort included) to 0.60-0.87 of the given order's time, on BMW it made bvh 1.25x
and grid-ls 1.15x slower (its small structures stay in the cache, so only the sort's cost is
left). So such a set is traced in the faster of the two orders as measured on its first trace
(the sort included) and recorded (`trace_order`, `trace_order_probe`). Env LSBENCH_RAY_ORDER
(ORDER_CHOICES) forces it.
"""
from __future__ import annotations

import os

import numpy as np

from .device import Device, DeviceBuffer
from .kernels import Buf, KernelSpec, Uniform

ORDER_BITS = 4  # must match shaders/common/ray_order.h
ORDER_CELLS = 1 << (3 * ORDER_BITS)
ORDER_MAX_LOCALITY = 0.5
ORDER_CHOICES = ("auto", "given", "origin-cells")

_HEADERS = ("ray_order.h",)
_UNIFORMS = (Uniform("order_origin", "float4"), Uniform("order_scale", "float4"))
ZERO = KernelSpec("ray_order_zero", _HEADERS, "ray_order_zero_kernel", (Buf("order_counts", "uint", "w"),))
COUNT = KernelSpec("ray_order_count", _HEADERS, "ray_order_count_kernel",
                   (Buf("rays", "float4", "r"), Buf("order_counts", "uint", "rw")), _UNIFORMS)
SCAN = KernelSpec("ray_order_scan", _HEADERS, "ray_order_scan_kernel", (Buf("order_counts", "uint", "rw"),),
                  local_size=1)
PLACE = KernelSpec("ray_order_place", _HEADERS, "ray_order_place_kernel",
                   (Buf("rays", "float4", "r"), Buf("order_counts", "uint", "rw"), Buf("order_ids", "uint", "w")),
                   _UNIFORMS)


def _grid(bounds, per_axis: int) -> tuple[np.ndarray, np.ndarray]:
    """(low corner, cells per unit along each axis) of a grid of per_axis³ cells over `bounds`
    (lo, hi); a flat axis gets cells of unit extent."""
    lo, hi = (np.asarray(b, np.float64) for b in bounds)
    return lo, per_axis / np.where(hi > lo, hi - lo, 1.0)


def origin_locality(rays, bounds) -> float:
    """The fraction of consecutive rays (in the set's order) whose origins lie in the same cell of
    a 16³ grid over `bounds` (lo, hi)."""
    if rays.count < 2:
        return 1.0
    lo, scale = _grid(bounds, 16)
    cells = np.clip(((np.asarray(rays.origins, np.float64) - lo) * scale).astype(np.int64), 0, 15)
    key = (cells[:, 0] * 16 + cells[:, 1]) * 16 + cells[:, 2]
    return float(np.mean(key[1:] == key[:-1]))


_WITHOUT_LOCALITY: dict[tuple, bool] = {}


def without_locality(rays, bounds) -> bool:
    """Whether under ORDER_MAX_LOCALITY of the set's consecutive rays start in the same cell
    (origin_locality): the sets a trace may sort (choose) or refill (backends.refill_rays). Kept
    per ray set content and bounds, since every trace of a set asks, twice (4.7 ms for 262,144 rays)."""
    lo, hi = (np.asarray(b, np.float64) for b in bounds)
    key = (rays.content_hash, tuple(lo), tuple(hi))
    if key not in _WITHOUT_LOCALITY:
        if len(_WITHOUT_LOCALITY) >= 64:
            _WITHOUT_LOCALITY.clear()
        _WITHOUT_LOCALITY[key] = origin_locality(rays, bounds) < ORDER_MAX_LOCALITY
    return _WITHOUT_LOCALITY[key]


def choose(rays, bounds, image: bool, width: int) -> str:
    """The order a trace of `rays` runs in: "given" (image tiles, packets, or rays with locality),
    "origin-cells" (env LSBENCH_RAY_ORDER forces it), or "measure": a set without locality, whose
    gain depends on the scene and structure, so the host times both orders (backends.trace_order)."""
    forced = os.environ.get("LSBENCH_RAY_ORDER", "").strip().lower() or "auto"
    if forced not in ORDER_CHOICES:
        raise ValueError(f"LSBENCH_RAY_ORDER must be one of {', '.join(ORDER_CHOICES)}, got {forced!r}")
    if image or width > 1 or rays.count < 2:
        return "given"
    if forced != "auto":
        return forced
    return "measure" if without_locality(rays, bounds) else "given"


def uniforms(bounds) -> dict:
    """The sort's uniforms: its cells over the structure's bounds (ray_order.h: order_cell)."""
    lo, scale = _grid(bounds, 1 << ORDER_BITS)
    return {"order_origin": (float(lo[0]), float(lo[1]), float(lo[2]), 0.0),
            "order_scale": (float(scale[0]), float(scale[1]), float(scale[2]), 0.0)}


def alloc(device: Device, n: int) -> dict[str, DeviceBuffer]:
    """The sort's buffers for n rays: the counts per cell and the ray id of every launch slot."""
    return {"order_counts": device.alloc("order_counts", 4 * ORDER_CELLS, zero=False),
            "order_ids": device.alloc("order_ids", 4 * n, zero=False)}


def sort_steps(n: int, order_uniforms: dict) -> list:
    """(spec, work items, uniforms) of the launches before the trace: rays -> order_ids."""
    return [(ZERO, ORDER_CELLS, {}), (COUNT, n, order_uniforms), (SCAN, 1, {}), (PLACE, n, order_uniforms)]
