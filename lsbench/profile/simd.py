"""SIMD efficiency of a traversal, from the per-ray work counters (issue 16, "divergence made
measurable"). The thesis blames the adaptive Line Space's slowness on warp divergence, seen only
through Nsight (Delgado Kraemer 2019, 6.3, Table 4, Fig. 20); this measures it on every device.

Rays are grouped as the device runs them: `width` consecutive items in dispatch order
(backends.launch_order: an image's rays in 8x8 tiles, so a group of 32 is an 8x4 block of pixels).
The lanes of a group run the walk in lock step, each loop as often as its busiest lane, so for a
counter c (walk steps, candidate tests) a group spends width x max(c) lane-slots on sum(c) useful
ones. Per group the efficiency is mean(c) / max(c); the case's figure is the average over groups
weighted by max(c) (the slots each group issues), which is sum(c) / sum(lanes x max(c)): the
fraction of issued lane-slots that did work, the definition behind Nsight's "SIMD efficiency"
(active lanes per executed instruction, averaged over instructions). Groups where no lane counted
anything issue nothing and weigh 0; a case where no group counted anything has no figure (None).
The last group holds the rays left over (its missing lanes are no rays, so not counted).

The figure comes from per-ray totals, so it is an upper bound: two lanes that each test 4
candidates, one in its first voxel and one in its second, count as fully efficient, although a
SIMD group runs those tests in different iterations of the walk.

Widths: WARP = 32 (an NVIDIA warp) for every case, so cases compare across devices; and the
device's own group width where known (`device_simd_width`, which says where the figure comes from).
"""
from __future__ import annotations

import re

import numpy as np

WARP = 32
# Counters (heatmaps.CHANNELS) whose lock-step cost is measured, with the names of their record fields.
COUNTERS = {"iterations": "steps", "candidate_tests": "tests"}


def groups_in_dispatch_order(values: np.ndarray, order: np.ndarray | None, width: int) -> list[np.ndarray]:
    """values (one per ray, in the ray set's order) as the device's groups of `width` consecutive
    items; order: backends.launch_order(rays) (ray id of each launch item), None = as given."""
    v = np.asarray(values) if order is None else np.asarray(values)[order]
    return [v[i:i + width] for i in range(0, len(v), width)]


def group_efficiency(values: np.ndarray, order: np.ndarray | None, width: int) -> tuple[np.ndarray, np.ndarray]:
    """(mean/max per group, max per group) in dispatch order; NaN where the group's max is 0."""
    groups = groups_in_dispatch_order(values.astype(np.float64), order, width)
    if not groups:
        return np.zeros(0), np.zeros(0)
    means = np.array([g.mean() for g in groups])
    maxes = np.array([g.max() for g in groups])
    with np.errstate(invalid="ignore", divide="ignore"):
        eff = np.where(maxes > 0, means / np.where(maxes > 0, maxes, 1.0), np.nan)
    return eff, maxes


def issued_per_ray(values: np.ndarray, width: int, weights: np.ndarray | None = None) -> float:
    """Lane-slots per ray that groups of `width` consecutive rows issue for a per-ray counter:
    each group's max times its rows (the last group short), over all rows; the mean at width 1.
    weights: per row, equal within a group (the cost model's drawn rays, model/cost.py)."""
    if len(values) == 0:
        return 0.0
    w = np.ones(len(values)) if weights is None else np.asarray(weights, np.float64)
    starts = np.arange(0, len(values), max(width, 1))
    group_max = np.repeat(np.maximum.reduceat(np.asarray(values, np.float64), starts),
                          np.diff(np.append(starts, len(values))))
    return float(group_max @ w) / float(w.sum())


def simd_efficiency(values: np.ndarray, order: np.ndarray | None, width: int) -> float | None:
    """sum(c) / sum(lanes x max(c)) over the groups (the module docstring), None when no lane counted."""
    v = np.asarray(values, np.float64) if order is None else np.asarray(values, np.float64)[order]
    issued = issued_per_ray(v, width) * len(v)
    return float(v.sum() / issued) if issued > 0 else None


def simd_lanes(device) -> int:
    """The lanes a SIMD group of `device` (a backends Device) runs in lock step, 1 where not known
    (device_simd_width): the width of the cost model's ray groups and of its fitted constants."""
    return device_simd_width(device.info())[0] or 1


def per_ray_group_efficiency(values: np.ndarray, order: np.ndarray | None, width: int) -> np.ndarray:
    """Each ray's group efficiency (mean/max of its group), in the ray set's order: the image
    of the heatmaps (every ray of a group painted with the group's value; NaN where its group
    counted nothing)."""
    eff, _ = group_efficiency(values, order, width)
    in_launch = np.repeat(eff, width)[:len(values)]
    if order is None:
        return in_launch
    out = np.empty(len(values), np.float64)
    out[order] = in_launch
    return out


def device_simd_width(info: dict) -> tuple[int | None, str]:
    """(lanes that run in lock step on this device, where the figure comes from), from
    Device.info(); (None, why) where it is not known."""
    name = str(info.get("device", ""))
    vendor = str(info.get("vendor", "")).lower()
    backend = info.get("backend")
    bits = re.search(r"llvmpipe \(LLVM [^,]*, (\d+) bits\)", name)
    if bits:
        return int(bits.group(1)) // 32, (f"llvmpipe runs {bits.group(1)}-bit vectors of 32-bit lanes ("
                                          "the renderer string), all lanes of a group through every branch under a mask")
    if "nvidia" in vendor:
        return 32, "NVIDIA warp of 32 threads"
    pocl = "portable computing language" in str(info.get("driver", "")).lower()
    if backend == "opencl" and pocl and "CPU" in str(info.get("device_type", "")):
        return 1, ("PoCL CPU device: the traversal kernels run one work-item at a time (the compiled "
                   "work-group function loops over its items calling the scalar walk; docs/profiles.md), "
                   "so divergence costs nothing there")
    return None, f"group width of {name or 'this device'} not known"


def simd_fields(work: np.ndarray, order: np.ndarray | None, info: dict, packet: int = 1) -> dict:
    """The record's SIMD efficiency fields (docs/record.md) from the per-ray counters `work`
    (uint4 per ray in the ray set's order, base.WORK_CHANNELS), the launch order and Device.info();
    packet > 1: the trace ran that many rays per work item in vector lanes (Hits.packet)."""
    from lsbench.backends.structures.base import WORK_CHANNELS

    width, source = device_simd_width(info)
    if packet > 1:  # a SIMD group's work items (PoCL: one) each trace a packet
        items = width or 1
        width, source = packet * items, (f"packet traversal: {packet} rays per work item in vector lanes "
                                         "(shaders/common/bvh.h), each lane counting its packet's work"
                                         + (f", {items} work items per SIMD group" if items > 1 else ""))
    out: dict = {"simd_width_device": width, "simd_width_source": source}
    for counter, short in COUNTERS.items():
        column = work[:, WORK_CHANNELS.index(counter)] if len(work) else np.zeros(0)
        out[f"simd_efficiency_{short}_w32"] = simd_efficiency(column, order, WARP)
        out[f"simd_efficiency_{short}_device"] = simd_efficiency(column, order, width) if width else None
    return out
