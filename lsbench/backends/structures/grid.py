"""`grid`: uniform grid with a triangle list per voxel (thesis 3.3.1), built by conservative
voxelization (3.4) in two passes with a prefix sum between them, traversed by 3D-DDA.
Kernels: shaders/common/grid.h; GLSL voxelizes with the raster pipeline (shaders/glsl/voxelize.*),
OpenCL with a compute kernel."""
from __future__ import annotations

from ..device import Device, DeviceBuffer, DeviceLimitError
from ..kernels import GRID_UNIFORMS, RAY_BUFFERS, SCENE_BUFFERS, Buf, KernelSpec
from .base import BuildParams, GridGeometry

GRID_HEADERS = ("geometry.h", "scene.h", "grid.h")

VOXELIZE_COUNT = KernelSpec(
    "voxelize_count", GRID_HEADERS, "voxelize_kernel",
    SCENE_BUFFERS + (Buf("voxel_counts", "uint", "rw"),), GRID_UNIFORMS)
VOXELIZE_FILL = KernelSpec(
    "voxelize_fill", GRID_HEADERS, "voxelize_kernel",
    SCENE_BUFFERS + (Buf("voxel_offsets", "uint", "r"), Buf("voxel_cursor", "uint", "rw"),
                     Buf("voxel_tris", "uint", "w")),
    GRID_UNIFORMS, defines=(("VOXELIZE_FILL", "1"),))
TRACE_GRID = KernelSpec(
    "trace_grid", GRID_HEADERS, "trace_grid_kernel",
    SCENE_BUFFERS + (Buf("voxel_offsets", "uint", "r"), Buf("voxel_tris", "uint", "r")) + RAY_BUFFERS,
    GRID_UNIFORMS)


def prepare(device: Device) -> None:
    """Compile everything the build uses, so build timings never include a compile."""
    for spec in (VOXELIZE_COUNT, VOXELIZE_FILL):
        if device.backend == "glsl":
            device.raster_program(spec)
        else:
            device.kernel(spec)


def _voxelize(device: Device, spec: KernelSpec, n_tris: int, buffers: dict, uniforms: dict,
              geometry: GridGeometry) -> None:
    if device.backend == "glsl":
        viewport = max(geometry.resolution)
        device.rasterize_triangles(spec, n_tris, buffers, dict(uniforms, viewport_size=float(viewport)), viewport)
    else:
        device.dispatch(spec, n_tris, buffers, uniforms)


def build_voxel_lists(device: Device, scene_buffers: dict, n_tris: int, geometry: GridGeometry
                      ) -> tuple[dict[str, DeviceBuffer], dict]:
    """Count -> exclusive scan -> fill. Returns voxel_offsets (CSR, voxels+1 entries) and
    voxel_tris, sized exactly to the references found."""
    uniforms = geometry.uniforms()
    n_vox = geometry.voxel_count
    counts = device.alloc("voxel_counts", 4 * n_vox)
    _voxelize(device, VOXELIZE_COUNT, n_tris, dict(scene_buffers, voxel_counts=counts), uniforms, geometry)
    offsets, total = device.exclusive_scan(counts, n_vox, "voxel_offsets")
    if total >= 2**32 - 1:
        raise DeviceLimitError(f"{total} voxel references overflow 32-bit offsets")
    tris = device.alloc("voxel_tris", 4 * total, zero=False)
    device.fill_zero(counts)  # reused as the per-voxel write cursor of the fill pass
    _voxelize(device, VOXELIZE_FILL, n_tris,
              dict(scene_buffers, voxel_offsets=offsets, voxel_cursor=counts, voxel_tris=tris),
              uniforms, geometry)
    device.finish()
    device.release(counts)
    stats = {"voxels": n_vox, "references": total}
    return {"voxel_offsets": offsets, "voxel_tris": tris}, stats


def build(device: Device, scene_buffers: dict, n_tris: int, geometry: GridGeometry,
          params: BuildParams):
    buffers, stats = build_voxel_lists(device, scene_buffers, n_tris, geometry)
    return buffers, geometry.uniforms(), TRACE_GRID, stats
