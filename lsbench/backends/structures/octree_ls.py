"""`svo-ls` and `esvo-ls`: the adaptive Line Space (Delgado Krämer 2019, 4, 5.1, Algorithm 3): the octrees of
`svo` (node pool) and `esvo` (Laine & Karras descriptors) with a candidate-list Line Space in
their leaves.

Build, all on the device:
1. the octree, exactly as `svo` / `esvo` build it (svo.build_octree);
2. while its bit pyramid exists: flag the leaves that get a Line Space (more than K =
   ls_min_candidates candidates), exclusive scan -> ls_ids (leaf -> Line Space index), and write
   each such leaf's cell (its voxel's box in grid space, its candidate range in voxel_tris)
   (shaders/common/octree_ls.h, on octree.h);
3. the Line Spaces of those cells: linespace.build_linespaces (count -> scan -> fill, the same
   code as grid-ls).

Trace: the svo / esvo traversal (svo.h, esvo.h) unchanged, compiled with LEAF_LINE_SPACE: at
every leaf oct_test_leaf (octree.h) asks ols_leaf_shaft (octree_ls.h) for the shaft of the ray's
chord through the leaf, found from its entry and exit face and patch (linespace.h: ls_chord), and
tests only that shaft's candidates.

Our octrees keep leaves only on the last level (thesis 5.2.1), so the leaves are the grid's
non-empty voxels; what the octree adds over grid-ls is the hierarchical skipping of empty space.
"""
from __future__ import annotations

from dataclasses import dataclass

from ..device import Device, DeviceBuffer
from ..kernels import Buf, KernelSpec, Uniform, trace_spec
from . import esvo, linespace, svo
from .base import BuildParams, BuildResult, GridGeometry

OLS_BUILD_HEADERS = svo.BUILD_HEADERS + ("octree_ls.h",)
OLS_UNIFORMS = svo.OCT_UNIFORMS + (Uniform("ls_min_count", "uint"),)
LEAF_FLAGS = KernelSpec(
    "oct_ls_flags", OLS_BUILD_HEADERS, "oct_ls_flags_kernel",
    (Buf("leaves", "uint", "r"), Buf("ls_flags", "uint", "w")), OLS_UNIFORMS)
LEAF_CELLS = KernelSpec(
    "oct_ls_cells", OLS_BUILD_HEADERS, "oct_ls_cells_kernel",
    (Buf("level_words", "uint", "r"), Buf("oct_bits", "uint", "r"), Buf("oct_ranks", "uint", "r"),
     Buf("leaves", "uint", "r"), Buf("ls_ids", "uint", "r"), Buf("ls_cell_boxes", "float4", "w"),
     Buf("ls_cell_ranges", "uint", "w")), OLS_UNIFORMS)

# Traversal: the octree's own kernel with LEAF_LINE_SPACE (the leaf lookup of octree_ls.h) and the
# Line Space buffers bound.
TRACE_SVO_LS = trace_spec(
    "trace_svo_ls", ("octree.h", "octree_ls.h", "svo.h"), "trace_svo_kernel",
    (Buf("svo_nodes", "uint", "t"),) + svo.LEAF_LISTS + linespace.LS_TRACE_BUFFERS, linespace.LS_UNIFORMS,
    line_space=True)
TRACE_ESVO_LS = trace_spec(
    "trace_esvo_ls", ("octree.h", "octree_ls.h", "esvo.h"), "trace_esvo_kernel",
    (Buf("esvo_nodes", "uint", "t"),) + svo.LEAF_LISTS + linespace.LS_TRACE_BUFFERS, linespace.LS_UNIFORMS,
    line_space=True)


@dataclass(frozen=True)
class LineSpaceOctree:
    """One octree layout with Line Spaces in its leaves (the registry's prepare/build pair)."""
    layout: str  # "svo" or "esvo" (svo.LAYOUTS)
    trace: KernelSpec

    def prepare(self, device: Device) -> None:
        (svo if self.layout == "svo" else esvo).prepare(device)
        linespace.prepare(device)
        for spec in (LEAF_FLAGS, LEAF_CELLS):
            device.compile(spec)

    def predicted_bytes(self, device: Device, nodes: int, leaves: int, references: int, ls_cells: int,
                        n: int, lists: linespace.ListSizes) -> dict[str, int]:
        """The bytes of each buffer build returns (lsbench/model/bytes.py): the octree's, the leaf
        -> Line Space index, and the Line Spaces of `ls_cells` leaves whose distinct sets are `lists`."""
        out = svo.predicted_bytes(self.layout, nodes, leaves, references)
        out["ls_ids"] = 4 * (leaves + 1)
        out.update(linespace.predicted_bytes(device, ls_cells, n, lists))
        return out

    def build(self, device: Device, scene_buffers: dict, n_tris: int, geometry: GridGeometry,
              params: BuildParams) -> BuildResult:
        svo.octree_depth(params.resolution)  # ValueError before any work
        n = linespace.check_n(params.ls_n or 1)  # an LS structure always has a Line Space
        k = linespace.check_min_candidates(params.ls_min_candidates)
        made: dict[str, DeviceBuffer] = {}  # the hook's buffers, released here if anything fails

        def leaf_cells(pyramid: dict, leaves: DeviceBuffer, n_leaves: int) -> None:
            u = dict(pyramid["uniforms"], ls_min_count=k)
            flags = device.alloc("ls_flags", 4 * max(n_leaves, 1), zero=False)
            try:
                device.dispatch(LEAF_FLAGS, n_leaves, {"leaves": leaves, "ls_flags": flags}, u)
                made["ls_ids"], made["n_cells"] = device.exclusive_scan(flags, n_leaves, "ls_ids")
            finally:
                device.release(flags)
            n_cells = made["n_cells"]
            made["ls_cell_boxes"] = device.alloc("ls_cell_boxes", 32 * max(n_cells, 1), zero=False)
            made["ls_cell_ranges"] = device.alloc("ls_cell_ranges", 8 * max(n_cells, 1), zero=False)
            device.dispatch(LEAF_CELLS, pyramid["leaf_cells"],
                            {"level_words": pyramid["level_words"], "oct_bits": pyramid["oct_bits"],
                             "oct_ranks": pyramid["oct_ranks"], "leaves": leaves, "ls_ids": made["ls_ids"],
                             "ls_cell_boxes": made["ls_cell_boxes"],
                             "ls_cell_ranges": made["ls_cell_ranges"]}, u)

        buffers: dict[str, DeviceBuffer] = {}
        try:
            buffers, stats = svo.build_octree(device, scene_buffers, n_tris, geometry, self.layout,
                                              leaf_hook=leaf_cells)
            n_cells = made.pop("n_cells")
            cells = linespace.Cells(n_cells, made["ls_cell_boxes"], made["ls_cell_ranges"],
                                    buffers["voxel_tris"], stats["references"])
            kept = sum(b.nbytes for b in buffers.values()) + made["ls_ids"].nbytes
            ls = linespace.build_linespaces(device, scene_buffers, geometry, cells, n, params.budget_bytes, kept)
        except BaseException:
            for b in list(made.values()) + list(buffers.values()):
                if isinstance(b, DeviceBuffer):
                    device.release(b)
            raise
        device.release(made.pop("ls_cell_boxes"))
        device.release(made.pop("ls_cell_ranges"))
        buffers["ls_ids"] = made.pop("ls_ids")
        buffers.update(ls.buffers)
        # The leaves' plain lists stay even when every leaf has a Line Space: a leaf that the walk
        # meets off its chord tests them instead of a shaft (ols_leaf_shaft in octree_ls.h); they cost
        # 4 bytes per reference, a small part of the Line Spaces.
        stats.update(ls.stats)
        stats.update(linespace.selection_stats(ls, stats["leaves"], k))
        stats.update({
            "linespace_leaves": n_cells,
            "linespace_skipped_leaves": stats["leaves"] - n_cells,
            "bytes": {name: b.used for name, b in buffers.items()},
        })
        uniforms = linespace.uniforms(geometry, n)
        return BuildResult(buffers, uniforms, ls.trace_spec(svo.walk(self.trace, stats["depth"], device)), stats)


svo_ls = LineSpaceOctree("svo", TRACE_SVO_LS)
esvo_ls = LineSpaceOctree("esvo", TRACE_ESVO_LS)
