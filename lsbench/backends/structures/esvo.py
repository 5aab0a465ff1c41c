"""`esvo`: the octree of `svo` in the compact layout of Laine & Karras (2010) as simplified in
Delgado Krämer 2019, 5.2.1: one 32-bit child descriptor per internal node (24-bit pointer to the first child,
8-bit valid mask, Listing 2), children contiguous in slot order, leaves only on the last level
with their candidate lists. Traversal: PUSH / ADVANCE / POP in [1,2]^3 with mirrored axes
(thesis 5.2.2). Kernels: shaders/common/esvo.h (descriptors and traversal) on octree.h, the build
and leaf handling shared with `svo`.

Same device build as `svo` (svo.build_octree); only the create kernel writes descriptors
instead of 8-uint blocks (4 instead of 32 bytes per internal node). A pointer that would not
fit in 24 bits raises DeviceLimitError instead of wrapping (no far pointers, as in the thesis).
"""
from __future__ import annotations

from ..device import Device
from ..kernels import GRID_UNIFORMS, Buf, trace_spec
from .base import BuildParams, BuildResult, GridGeometry
from . import svo

TRACE_ESVO = trace_spec("trace_esvo", ("octree.h", "esvo.h"), "trace_esvo_kernel",
                        (Buf("esvo_nodes", "uint", "t"),) + svo.LEAF_LISTS, GRID_UNIFORMS)


def prepare(device: Device) -> None:
    svo.prepare(device)
    device.compile(svo.CREATE_ESVO)


def build(device: Device, scene_buffers: dict, n_tris: int, geometry: GridGeometry,
          params: BuildParams) -> BuildResult:
    svo.octree_depth(params.resolution)  # ValueError before any work
    buffers, stats = svo.build_octree(device, scene_buffers, n_tris, geometry, "esvo")
    spec = svo.walk(TRACE_ESVO, stats["depth"], device)
    return BuildResult(buffers, geometry.uniforms(), spec, stats)
