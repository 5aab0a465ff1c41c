"""`bvh-ls`: the BVH of `bvh` with a candidate-list Line Space in its large leaves (Delgado Krämer
2019, 7: the Line Space inside a structure of another kind). Kernels: shaders/common/bvh.h (the
cells and the leaf lookup) on linespace.h and octree_ls.h.

Build, all on the device:
1. the BVH as `bvh` builds it (bvh.build_bvh; the binned SAH tree, bvh_hierarchy "binned"), but
   with plain leaves: every subtree of at most leaf_size triangles (default 16) is one leaf, then
   the treelet restructuring above them (bvh_quality "plain-treelet"). The binned tree against the
   Morton one (Sponza 256², PoCL, N = 2, K = 8): 0.82 of the trace's device time on incoherent
   rays, 0.61 on primary rays (docs/profiles.md, section 22). The SAH collapse of `bvh` knows nothing of Line Spaces and keeps
   leaves of ~2 triangles, which no Line Space can speed up; here the Line Space is what makes a
   large leaf cheap to test (bvh_quality = "treelet" asks for the SAH leaves);
2. the cells: every child slot of a node record (cell = 4 * record + slot) that is a leaf of more than
   K = ls_min_candidates triangles is flagged, an exclusive scan gives ls_ids (slot -> Line Space),
   and each such leaf's box (padded so that no side is under 5 % of the longest: bvh.h
   bvh_ls_box) and its range of voxel_tris become a cell;
3. the Line Spaces of those cells: linespace.build_linespaces (the cell API of grid-ls and the
   octrees).

Trace: `bvh`'s walk compiled with LEAF_LINE_SPACE: a leaf with a Line Space tests only the shaft
of the ray's chord through its box, found from the chord's entry and exit face and patch by
octree_ls.h's ols_leaf_shaft (Algorithm 3), the lookup the octree leaves make. On llvmpipe,
whose SIMD lanes load their nodes one by one, coherent closest-hit rays go in `bvh`'s packets of 4
per lane (backends.packet_width), each leaf then looked up and tested lane by lane for the lanes
whose ray meets its box (bvh.h: BVH_PACKET_LEAF): 0.78-0.81 of the one-ray device time on Sponza
and BMW 256² primary rays. On PoCL the same packets gained nothing (Sponza 0.99, BMW 1.20), so
there its rays go one per work item (StructureInfo.serial_packets; docs/profiles.md, section 27)."""
from __future__ import annotations

from ..device import Device, DeviceBuffer
from ..kernels import GRID_UNIFORMS, SCENE_BUFFERS, Buf, KernelSpec, Uniform, trace_spec
from . import bvh, linespace
from .base import BuildParams, BuildResult, GridGeometry

BLS_UNIFORMS = GRID_UNIFORMS + (Uniform("ls_min_count", "uint"),)
CELL_FLAGS = KernelSpec("bvh_ls_flags", bvh.BVH_HEADERS_NO_SCENE, "bvh_ls_flags_kernel",
                        (Buf("bvh_links", "uint4", "r"), Buf("ls_flags", "uint", "w")), BLS_UNIFORMS)
CELLS = KernelSpec("bvh_ls_cells", bvh.BVH_HEADERS, "bvh_ls_cells_kernel",
                   SCENE_BUFFERS + (Buf("bvh_nodes", "float4", "r"), Buf("bvh_links", "uint4", "r"),
                                    Buf("ls_ids", "uint", "r"), Buf("ls_cell_boxes", "float4", "w"),
                                    Buf("ls_cell_ranges", "uint", "w")), BLS_UNIFORMS)
TRACE_BVH_LS = trace_spec("trace_bvh_ls", ("octree_ls.h", "bvh.h"), "trace_bvh_kernel",
                          bvh.BVH_TRACE_BUFFERS + linespace.LS_TRACE_BUFFERS,
                          linespace.LS_UNIFORMS, line_space=True)
DEFAULT_LEAF_SIZE = 16  # a Line Space pays off only over a leaf of many candidates


class LineSpaceBVH:
    """The catalogue's prepare/build pair of bvh-ls."""

    def prepare(self, device: Device) -> None:
        bvh.prepare(device)
        linespace.prepare(device)
        for spec in (CELL_FLAGS, CELLS):
            for layout in bvh.NODE_LAYOUTS:
                device.compile(bvh.with_node_layout(spec, layout))

    def build(self, device: Device, scene_buffers: dict, n_tris: int, geometry: GridGeometry,
              params: BuildParams) -> BuildResult:
        leaf_size = bvh.check_leaf_size(params.leaf_size or DEFAULT_LEAF_SIZE)
        n = linespace.check_n(params.ls_n or 1)
        k = linespace.check_min_candidates(params.ls_min_candidates)
        layout = bvh.node_layout(device, params.options, serial_auto="float")
        buffers, stats = bvh.build_bvh(device, scene_buffers, n_tris, geometry, leaf_size,
                                       quality=params.options.get("bvh_quality", "plain-treelet"), layout=layout,
                                       hierarchy=params.options.get("bvh_hierarchy", "binned"))
        node_bufs = {name: buffers[name] for name in buffers if name != "voxel_tris"}
        slots = stats["width"] * stats["nodes"]
        u = dict(geometry.uniforms(), ls_min_count=k)
        made: list[DeviceBuffer] = []
        try:
            flags = device.alloc("ls_flags", 4 * slots, zero=False)
            try:
                device.dispatch(bvh.with_node_layout(CELL_FLAGS, layout), slots, {**node_bufs, "ls_flags": flags}, u)
                ls_ids, n_cells = device.exclusive_scan(flags, slots, "ls_ids")
            finally:
                device.release(flags)
            made.append(ls_ids)
            boxes = device.alloc("ls_cell_boxes", 32 * max(n_cells, 1), zero=False)
            made.append(boxes)
            ranges = device.alloc("ls_cell_ranges", 8 * max(n_cells, 1), zero=False)
            made.append(ranges)
            device.dispatch(bvh.with_node_layout(CELLS, layout), slots,
                            {**scene_buffers, **node_bufs, "ls_ids": ls_ids, "ls_cell_boxes": boxes,
                             "ls_cell_ranges": ranges}, u)
            cells = linespace.Cells(n_cells, boxes, ranges, buffers["voxel_tris"], stats["references"])
            kept = sum(b.nbytes for b in buffers.values()) + ls_ids.nbytes
            ls = linespace.build_linespaces(device, scene_buffers, geometry, cells, n, params.budget_bytes, kept)
        except BaseException:
            for b in made + list(buffers.values()):
                device.release(b)
            raise
        device.release(boxes)
        device.release(ranges)
        buffers["ls_ids"] = ls_ids
        buffers.update(ls.buffers)
        stats.update(ls.stats)
        stats.update(linespace.selection_stats(ls, stats["leaves"], k))
        stats.update({"linespace_leaves": n_cells, "linespace_skipped_leaves": stats["leaves"] - n_cells,
                      "bytes": {name: b.used for name, b in buffers.items()}})
        spec = bvh.traversal(TRACE_BVH_LS, stats, device)
        if not device.serial_work_items:
            # A leaf's lookup and candidate loop outside the node visits' loop (bvh.h: BVH_WHILE_WHILE):
            # llvmpipe paid them once per visit (docs/profiles.md, section 17: 0.77-0.92 of the device
            # time; bvh's leaves of 2 gain nothing, PoCL neither).
            spec = spec.with_defines(BVH_WHILE_WHILE=1)
        return BuildResult(buffers, linespace.uniforms(geometry, n), ls.trace_spec(spec), stats, suspends=False)


bvh_ls = LineSpaceBVH()
