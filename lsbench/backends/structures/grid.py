"""`grid`: uniform grid with a triangle list per voxel (Delgado Krämer 2019, 3.3.1), built by conservative
voxelization (3.4) in two passes with a prefix sum between them, traversed by 3D-DDA.
Kernels: shaders/common/grid.h (voxelization, the DDA walk and the grid's voxel visit) on
scene.h and trace.h. Device.voxelize runs the voxelization, through the raster pipeline or as a
compute kernel, as the device does it best (the same voxel lists either way)."""
from __future__ import annotations

import numpy as np

from ..device import Device, DeviceBuffer, DeviceLimitError
from ..kernels import GRID_UNIFORMS, SCENE_BUFFERS, Buf, KernelSpec, Uniform, trace_spec
from .base import BuildParams, BuildResult, GridGeometry

VOXELIZE_HEADERS = ("geometry.h", "scene.h", "grid.h")

VOXELIZE_COUNT = KernelSpec(
    "voxelize_count", VOXELIZE_HEADERS, "voxelize_kernel",
    SCENE_BUFFERS + (Buf("voxel_counts", "uint", "rw"),), GRID_UNIFORMS)
# The count pass over z layers [voxel_slab.x, voxel_slab.y) only (grid.h: VOXEL_SLAB), for the
# cost model's counts of large grids (model/stats.py: voxel_counts).
VOXELIZE_COUNT_SLAB = KernelSpec(
    "voxelize_count", VOXELIZE_HEADERS, "voxelize_kernel", VOXELIZE_COUNT.buffers,
    GRID_UNIFORMS + (Uniform("voxel_slab", "int4"),), (("VOXEL_SLAB", "1"),))
VOXELIZE_FILL = KernelSpec(
    "voxelize_fill", VOXELIZE_HEADERS, "voxelize_kernel",
    SCENE_BUFFERS + (Buf("voxel_offsets", "uint", "r"), Buf("voxel_cursor", "uint", "rw"),
                     Buf("voxel_tris", "uint", "w")),
    GRID_UNIFORMS)
# The voxel offsets stay a storage buffer: the walk reads them only at a non-empty voxel, and for
# incoherent rays (8 MiB at 128³, out of cache) llvmpipe's lane-by-lane loads beat its texel
# fetches (Sponza 256² incoherent: 0.870 of the time, primary 1.035; docs/profiles.md, section 17).
# The occupancy bits (grid.h: grid_occupancy) are what every step reads, as texels.
VOXEL_LISTS = (Buf("voxel_offsets", "uint", "r"), Buf("voxel_tris", "uint", "t"), Buf("voxel_bits", "uint", "t"))
TRACE_GRID = trace_spec("trace_grid", ("grid.h",), "trace_grid_kernel", VOXEL_LISTS, GRID_UNIFORMS)
GRID_OCCUPANCY = KernelSpec(
    "grid_occupancy", ("geometry.h", "grid.h"), "grid_occupancy_kernel",
    (Buf("voxel_offsets", "uint", "r"), Buf("voxel_bits", "uint", "w")), GRID_UNIFORMS)


def prepare(device: Device) -> None:
    """Compile everything the build uses, so build timings never include a compile."""
    for spec in (VOXELIZE_COUNT, VOXELIZE_FILL):
        device.compile_voxelizer(spec)
    device.compile(GRID_OCCUPANCY)


def build_voxel_lists(device: Device, scene_buffers: dict, n_tris: int, geometry: GridGeometry
                      ) -> tuple[dict[str, DeviceBuffer], dict]:
    """Count -> exclusive scan -> fill. Returns voxel_offsets (CSR, voxels+1 entries) and
    voxel_tris, sized exactly to the references found."""
    uniforms = geometry.uniforms()
    n_vox = geometry.voxel_count
    counts = device.alloc("voxel_counts", 4 * n_vox)
    device.voxelize(VOXELIZE_COUNT, n_tris, dict(scene_buffers, voxel_counts=counts), uniforms, geometry.resolution)
    offsets, total = device.exclusive_scan(counts, n_vox, "voxel_offsets")
    if total >= 2**32 - 1:
        raise DeviceLimitError(f"{total} voxel references overflow 32-bit offsets")
    tris = device.alloc("voxel_tris", 4 * total, zero=False)
    device.fill_zero(counts)  # reused as the per-voxel write cursor of the fill pass
    device.voxelize(VOXELIZE_FILL, n_tris,
                    dict(scene_buffers, voxel_offsets=offsets, voxel_cursor=counts, voxel_tris=tris),
                    uniforms, geometry.resolution)
    device.finish()
    device.release(counts)
    stats = {"voxels": n_vox, "references": total}
    return {"voxel_offsets": offsets, "voxel_tris": tris}, stats


def add_occupancy(device: Device, lists: dict[str, DeviceBuffer], geometry: GridGeometry) -> None:
    """The DDA walk's occupancy bits (grid.h: grid_occupancy) from the lists, as lists["voxel_bits"]."""
    words = occupancy_words(geometry.voxel_count)
    bits = device.alloc("voxel_bits", 4 * words, zero=False)
    device.dispatch(GRID_OCCUPANCY, words, {"voxel_offsets": lists["voxel_offsets"], "voxel_bits": bits},
                    geometry.uniforms())
    lists["voxel_bits"] = bits


def occupancy_words(voxels: int) -> int:
    return -(-voxels // 32)


def occupied_voxels(device: Device, bits: DeviceBuffer) -> int:
    """Voxels with at least one candidate (for the stats): the set occupancy bits (the last word's
    bits past the voxels are clear)."""
    return int(np.bitwise_count(device.read(bits, np.uint32)).sum())


def predicted_bytes(voxels: int, references: int) -> dict[str, int]:
    """The bytes of each buffer of the grid's lists and occupancy bits (build_voxel_lists,
    add_occupancy), from the count pass's statistics (lsbench/model/bytes.py): exact, as
    Device.alloc sizes them (4 bytes at least)."""
    return {"voxel_offsets": 4 * (voxels + 1), "voxel_tris": max(4 * references, 4),
            "voxel_bits": 4 * occupancy_words(voxels)}


def build(device: Device, scene_buffers: dict, n_tris: int, geometry: GridGeometry,
          params: BuildParams) -> BuildResult:
    buffers, stats = build_voxel_lists(device, scene_buffers, n_tris, geometry)
    add_occupancy(device, buffers, geometry)
    return BuildResult(buffers, geometry.uniforms(), TRACE_GRID, stats)
