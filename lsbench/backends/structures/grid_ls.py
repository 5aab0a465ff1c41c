"""`grid-ls`: uniform grid whose non-empty voxels hold a candidate-list Line Space (Delgado Krämer 2019, 3.3.3,
5.1, Algorithm 2). Build: the grid's voxel lists (grid.build_voxel_lists), a compaction of the
voxels that get a Line Space (flags -> scan: voxel -> Line Space index), their cells (voxel box +
list range), then linespace.build_linespaces. Kernels: shaders/common/grid_ls.h (the build steps
and the voxel's shaft lookup) on linespace.h; the trace is grid.h's DDA walk with that lookup
(LEAF_LINE_SPACE).

BuildParams.ls_n = N (patches per face edge, >= 1; 0 is taken as 1 here, grid-ls always has a
Line Space). BuildParams.ls_min_candidates = K: only voxels with more than K candidates get a
Line Space, the others keep their plain list (stats: linespace_skipped_voxels and the offsets
memory saved)."""
from __future__ import annotations

from ..device import Device
from ..kernels import Buf, KernelSpec, Uniform, trace_spec
from . import grid, linespace
from .base import BuildParams, BuildResult, GridGeometry

GLS_BUILD_HEADERS = ("geometry.h", "grid_ls.h")

GLS_FLAGS = KernelSpec(
    "gls_flags", GLS_BUILD_HEADERS, "gls_flags_kernel",
    (Buf("voxel_offsets", "uint", "r"), Buf("ls_flags", "uint", "w")),
    linespace.LS_UNIFORMS + (Uniform("ls_min_count", "uint"),))
GLS_CELLS = KernelSpec(
    "gls_cells", GLS_BUILD_HEADERS, "gls_cells_kernel",
    (Buf("voxel_offsets", "uint", "r"), Buf("ls_ids", "uint", "r"), Buf("ls_cell_boxes", "float4", "w"),
     Buf("ls_cell_ranges", "uint", "w")),
    linespace.LS_UNIFORMS)
TRACE_GRID_LS = trace_spec(
    "trace_grid_ls", ("grid.h", "grid_ls.h"), "trace_grid_kernel",
    grid.VOXEL_LISTS + linespace.LS_TRACE_BUFFERS, linespace.LS_UNIFORMS, line_space=True)


def prepare(device: Device) -> None:
    grid.prepare(device)
    linespace.prepare(device)
    for spec in (GLS_FLAGS, GLS_CELLS):
        device.compile(spec)


def build(device: Device, scene_buffers: dict, n_tris: int, geometry: GridGeometry,
          params: BuildParams) -> BuildResult:
    n = linespace.check_n(params.ls_n or 1)
    k = linespace.check_min_candidates(params.ls_min_candidates)
    buffers, stats = grid.build_voxel_lists(device, scene_buffers, n_tris, geometry)
    grid.add_occupancy(device, buffers, geometry)
    u = dict(linespace.uniforms(geometry, n), ls_min_count=k)
    n_vox = geometry.voxel_count
    # Compaction: voxel -> Line Space index (exclusive scan of the flags; see grid_ls.h).
    flags = device.alloc("ls_flags", 4 * n_vox, zero=False)
    device.dispatch(GLS_FLAGS, n_vox, {"voxel_offsets": buffers["voxel_offsets"], "ls_flags": flags}, u)
    ls_ids, n_cells = device.exclusive_scan(flags, n_vox, "ls_ids")
    device.release(flags)
    non_empty = grid.occupied_voxels(device, buffers["voxel_bits"])
    boxes = device.alloc("ls_cell_boxes", 32 * max(n_cells, 1), zero=False)
    ranges = device.alloc("ls_cell_ranges", 8 * max(n_cells, 1), zero=False)
    device.dispatch(GLS_CELLS, n_vox, {"voxel_offsets": buffers["voxel_offsets"], "ls_ids": ls_ids,
                                      "ls_cell_boxes": boxes, "ls_cell_ranges": ranges}, u)
    cells = linespace.Cells(n_cells, boxes, ranges, buffers["voxel_tris"], stats["references"])
    # What the structure keeps besides its Line Spaces: the plain lists stay, also where every
    # non-empty voxel has a Line Space, since its shafts' ids are positions in them (linespace.h).
    kept = sum(b.nbytes for b in buffers.values()) + ls_ids.nbytes  # lists, occupancy bits, ids
    try:
        ls = linespace.build_linespaces(device, scene_buffers, geometry, cells, n, params.budget_bytes, kept)
    except Exception:
        for b in (boxes, ranges, ls_ids, *buffers.values()):
            device.release(b)
        raise
    device.release(boxes)
    device.release(ranges)
    buffers["ls_ids"] = ls_ids
    buffers.update(ls.buffers)
    stats.update(ls.stats)
    stats.update(linespace.selection_stats(ls, non_empty, k))
    stats.update({
        "non_empty_voxels": non_empty,
        "linespace_voxels": n_cells,
        "linespace_skipped_voxels": non_empty - n_cells,
        "bytes": {name: b.used for name, b in buffers.items()},
    })
    return BuildResult(buffers, u, ls.trace_spec(TRACE_GRID_LS), stats)


def predicted_bytes(device: Device, voxels: int, references: int, ls_cells: int,
                    n: int, lists: linespace.ListSizes) -> dict[str, int]:
    """The bytes of each buffer build returns (lsbench/model/bytes.py): the grid's lists (which
    the Line Spaces' cell-local ids index), the voxel -> Line Space index, and the Line Spaces of
    `ls_cells` voxels whose distinct sets are `lists`."""
    out = grid.predicted_bytes(voxels, references)
    out["ls_ids"] = 4 * (voxels + 1)
    out.update(linespace.predicted_bytes(device, ls_cells, n, lists))
    return out

