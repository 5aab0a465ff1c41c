"""Candidate-list Line Spaces for a set of cells (Delgado Krämer 2019, 3.3.3, 4, 5.1), built on the device.

Written once for every structure that puts Line Spaces into its cells: `grid-ls` passes the
voxels that hold candidates, a later `svo-ls` / `esvo-ls` passes its octree leaves. A cell is a
box (grid space, see shaders/common/grid.h) plus a range of a triangle-id list:

    cells = Cells(count, boxes, ranges, tris, references)
        boxes  : float4 buffer, 2 per cell: (lo.xyz, 0), (hi.xyz, 0) in grid space
        ranges : uint buffer, 2 per cell: begin, end into `tris`
        tris   : uint buffer of triangle ids (e.g. the grid's voxel_tris)
        references : sum of the cells' list lengths (an upper bound is fine: it only decides
                     whether the 32-bit overflow check has to run)
    ls = build_linespaces(device, scene_buffers, geometry, cells, n)
    ls.buffers -> {"ls_shaft_offsets": header, per-cell first sets, 8/16-bit shaft -> set indices,
                   set offsets; "ls_shaft_tris": the distinct sets' candidates, each the
                   position of its triangle in the cell's own list (`ranges` into `tris`, which
                   the structure keeps and its traversal reads), 16 bits where no cell holds more
                   than 65,536 candidates (ls_id_bits), else 32}
    ls.stats   -> shafts, non_empty_shafts, candidate_references (all shafts' lists together),
                  ls_sets, ls_set_references (what is stored: one list per distinct set),
                  ls_id_bits, ...

Shaft s of cell c has the list of its set (layout: shaders/common/linespace.h, read by trace.h's
shaft_list; on the host by shaft_ranges / shaft_lists below): 92-95 % of a cell's non-empty
shafts repeat another shaft's candidate set, so one list per distinct set of a cell takes about
half the bytes of one list per shaft (docs/linespace-build.md). The traversal finds s with
ls_shaft_id() of shaders/common/linespace.h (Listing 1) from the ray's entry and exit face and
patch in cell-local coordinates.

Build: (1) the shaft volumes (convex hull of the two patches) as facet planes, once per N;
(2) masks: per (triangle reference, patch) the bits that decide most (shaft, triangle) pairs with
one AND (linespace.h: ls_masks_kernel; a cell's masks patch-major, so a shaft reads its two
patches' masks as two runs), and each reference's triangle in cell-local coordinates
(ls_local_tris, what the count and fill test), for a batch of cells at a time (LS_MASK_BYTES);
(3) count: one item per (cell, shaft, chunk of at most candidate_chunk() candidates, the
driver's loop budget), taken by a work item each, or where every cell of a batch is one chunk, a
work item per shaft of a group of up to CELLS_PER_ITEM cells (BuildPlan.cell_groups), decides
each candidate, from the masks where they know the answer, else by the facet planes and the exact
test (conservative margin LS_EPS), writes the count where the item's offset goes (not in the head
lists' builds below: a head's row holds it) and keeps each decision as a bit (LS_PAIR_BITS_BYTES:
all cells' bits, over several buffers where the driver asks, or a batch's); (4) sets: per group
of cells (LS_GROUP_SHAFTS) a hash of each shaft's bit row, a hash table per cell that confirms
equal rows bit by bit, sets numbered in the order of their first shaft (the "head"). Where all
cells' bits are kept and the densest cell's row fits one invocation (head_rows_fit; most builds),
each group's heads are listed in shaft order and the set indices packed as the offsets array's
blocks hold them: a work item per cell walks its shafts in order (ls_cell_find_sets_kernel,
ls_cell_head_list_kernel) where the group's densest cell fits the loop budget
(cells_fit_loop_budget), else, as in the other builds, a work item per shaft inserts it, the
smallest shaft of each set becomes its head (ls_insert_kernel .. ls_heads_kernel) and each
shaft's set index comes from the scanned heads per word (ls_head_counts_kernel, ls_shaft_set_kernel);
(5) each head's set length, the sum of its items' counts (over the head lists, its row's bits:
ls_head_len_kernel; else over every shaft, with the set's index left in a head's first item, the
earlier chunks' counts in the others and LS_SKIP in every other shaft's items: ls_set_len_kernel),
exclusive scans of the sets per cell and of those lengths (set offsets), then the offsets array
(ls_layout_kernel; no scan over all items: all shafts' lists together, a stat, the count sums in
64 bits); (6) fill: only the heads write their candidates, each from its set's offset (plus its
shaft's earlier chunks), in list order (over the head lists from the bits: ls_head_fill_kernel;
else every item from the bits, or testing again where not all bits fit). docs/linespace-build.md
measures each step.

Both arrays may pass the driver's per-buffer limit (llvmpipe: 128 MiB per SSBO; PoCL: 2-4 GiB per
buffer here, varying with the host memory in use): each is then split over up to LS_MAX_CHUNKS
buffers of a power-of-two number of entries
(SplitArray: `ls_shaft_offsets`, `ls_shaft_offsets1`, ..., `ls_shaft_tris`, `ls_shaft_tris1`, ...;
kernels read them through the macros of shaders/common/linespace.h), so such a case runs wherever
the device's memory holds it; so may the build's per-shaft arrays (item offsets, set words, set
lengths). Split arrays are scanned chunk by chunk with the earlier chunks' total added
(LS_CARRY). Offsets and shaft indices are 32-bit values: a case past 2^32 - 1 candidates or
shafts raises DeviceLimitError naming the limit (thesis 6.3 saw such cases fail), never truncates.
"""
from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass, field

import numpy as np

from ..device import Device, DeviceBuffer, DeviceLimitError, OverBudgetError
from ..kernels import GRID_UNIFORMS, SCENE_BUFFERS, Buf, KernelSpec, Uniform
from .base import GridGeometry

# Kernels: shaders/common/linespace.h. Kernels that bind no scene buffers leave scene.h out (it
# reads vertices/faces).
LS_HEADERS = ("geometry.h", "scene.h", "linespace.h")
LS_HEADERS_NO_SCENE = ("geometry.h", "linespace.h")
# What a trace kernel binds to read the Line Spaces of its cells (trace.h: cell_line_space,
# shaft_list): the cell -> Line Space index and the shafts' candidate lists.
LS_TRACE_BUFFERS = (Buf("ls_ids", "uint", "t"), Buf("ls_shaft_offsets", "uint", "t"),
                    Buf("ls_shaft_tris", "uint", "t"))
LS_UNIFORMS = GRID_UNIFORMS + (Uniform("ls_n", "uint"), Uniform("ls_shafts", "uint"),
                               Uniform("ls_eps", "float"))
# The build's batch of cells (linespace.h: ls_shaft_kernel, ls_masks_kernel).
LS_BATCH_UNIFORMS = LS_UNIFORMS + (Uniform("ls_chunk", "uint"), Uniform("ls_item_base", "uint"),
                                   Uniform("ls_ref_base", "uint"), Uniform("ls_cell_first", "uint"),
                                   Uniform("ls_cell_end", "uint"), Uniform("ls_bits_base", "uint"),
                                   Uniform("ls_grouped", "uint"))
LS_MAX_PLANES = 8  # must match shaders/common/linespace.h
LS_PLANE_SLOTS = 10  # per shaft in ls_planes: the facet planes, then the axis' two ends (linespace.h)
# Conservative margin of the shaft planes, in cell-local units (the cell is the unit cube): covers
# float rounding of the build's world -> cell mapping and of the traversal's entry/exit points.
LS_EPS = 1e-3
# What the masks' cull margin adds to the largest reach of the shaft volumes pushed out by LS_EPS
# beyond their hulls (linespace.h: ls_masks_kernel, where the margin is argued): ten times the
# edges test's in-triangle tolerance (LS_IN_TRIANGLE_TOL, 1e-5).
LS_CULL_SLACK = 1e-4
UINT32_MAX = 2**32 - 1
# Most buffers the shaft offsets or the candidate list is split over. llvmpipe allows 16 storage
# buffers per compute shader (a trace binding more fails naming GL_MAX_COMPUTE_SHADER_STORAGE_BLOCKS);
# PoCL's global memory (7-14 GiB here) holds fewer than 4 buffers of its 2-4 GiB limit.
LS_MAX_CHUNKS = 4
# llvmpipe ends an invocation's loops after 65535 iterations in all (shaders/common/geometry.h); a
# count or fill work item runs, per candidate of its chunk, at most one iteration of each step's
# loop (linespace.h ls_run_meets: the masks, the facet planes, the edges, the exact test) and one
# of the fill's, plus the exact test's inner loops where the compiler keeps them (SAT: at most 12;
# clipping: 8 planes x 2 loops of at most LS_MAX_POLY = 16 vertices; edges: the hull's 8 corners
# and at most 28 edge slots) and the run and cell loops (< 16), so chunks of 1985 (SAT), 1149
# (edges) or 236 (clipping) candidates stay inside the budget. The queued count of a group of
# one-chunk cells (linespace.h: ls_count_queued; the group's candidates fit one chunk) takes per
# candidate the same step iterations, one to queue its pair, one to put out its bit and two of
# the rows read back, and per LS_PAIR_QUEUE candidates one pass of each loop. PoCL has no such
# limit: one chunk per cell.
LS_LOOP_BUDGET = {"glsl": 65535}
LS_ITERATIONS_PER_CANDIDATE = {"sat": 5 + 12 + 16, "clip": 5 + 8 * 2 * 16 + 16, "edges": 5 + 8 + 28 + 16}
# Most cells one count or fill work item walks for its shaft where every cell is one chunk
# (BuildPlan.cell_groups; linespace.h: ls_shaft_kernel): the shaft's set-up paid once for them.
# On llvmpipe an invocation of the count's large shader costs a core ~150 ns before any pair
# (docs/linespace-build.md), so its items take more cells: Sponza grid-ls glsl 128³ N=2, ls_count
# 7.7-8.2 s at 16, 7.3-7.8 at 64, 6.0-6.3 at 256, 5.9 at 512, 6.4-6.5 at 1024-4096 (the groups must
# also fit one chunk). On PoCL 64 was no faster than 16 (5.67 against 5.30 s, 64³ N=3). GPUs are
# not measured; their GL drivers get llvmpipe's value, as they get its loop budget.
CELLS_PER_ITEM = {"glsl": 256}
CELLS_PER_ITEM_DEFAULT = 16
# Shafts per work item of ls_set_len where work items run in SIMD lanes, taken at a stride of the
# item count (linespace.h).
LS_NONEMPTY_STRIDE = 32
# Pairs per vector block of the count's cull and tests where work items run one after the other
# (linespace.h: LS_RUN_LANES, ls_run_meets): PoCL's 8-wide vectors.
LS_RUN_LANES = 8
# Bytes of cull masks one batch of cells may use (6 N^2 uints per reference); a batch holds at
# least one cell.
LS_MASK_BYTES = 64 * 2**20
LOCAL_TRI_BYTES = 48  # a reference's cell-local triangle (ls_local_tris: 3 float4, or 9 floats coordinate-major)
# Most bytes the count's decisions (one bit per shaft and candidate) may take. The sets are found
# from them; where those of all cells do not fit, the cells go in batches whose bits do, each
# batch's sets are found while its bits are there, and the fill tests the pairs again. Over
# several buffers where the driver's per-buffer limit is less (SplitArray: llvmpipe's 128 MiB).
LS_PAIR_BITS_BYTES = 256 * 2**20
# Bytes per shaft of the sets' hash table: two slots per shaft, each the member and its row's hash
# (linespace.h ls_cell_find_sets_kernel; ls_insert_kernel uses the first half).
LS_SET_TABLE_BYTES = 16
# Pairs a lane's count queues before testing them (linespace.h: ls_count_queued; at most 128):
# Sponza grid-ls glsl 128³ N=2, ls_count 3.67 s at 32, 3.40-3.46 at 64, 3.32-3.37 at 128.
LS_PAIR_QUEUE = 128
# Fewest consecutive one-chunk cells that a batch with cells of several chunks dispatches as
# groups of the queued count (the rest of the batch: an item per chunk).
LS_GROUPED_RUN = 64
# Shafts whose sets are found in one group (the hash table takes LS_SET_TABLE_BYTES per shaft, the
# slots and heads 4.1 more): 64 MiB of table, under llvmpipe's 128 MiB per buffer.
LS_GROUP_SHAFTS = 1 << 22
# Cache lines of 16 words that the count's work items spread their stats over (linespace.h).
LS_STAT_BUCKETS = 32
# Bits of the row hash kept (linespace.h: ls_row_hash); tests set fewer, so that different sets
# collide and only the word-by-word compare tells them apart.
LS_HASH_MASK = 0xFFFFFFFF
# The shaft -> set index is 16 bits wide (linespace.h): a cell may hold at most 2^16 sets.
LS_MAX_SETS_PER_CELL = 1 << 16
# The sets' candidate ids are positions in their cell's plain list (linespace.h, LS_LOCAL_ID): 16
# bits, two per word, where every cell holds at most this many candidates, else 32.
LS_IDS16_MAX_CANDIDATES = 1 << 16


def candidate_id_bits(densest: int) -> int:
    """Bits of a set's cell-local candidate id for cells of at most `densest` candidates."""
    return 16 if densest <= LS_IDS16_MAX_CANDIDATES else 32


def candidate_words(entries: int, id_bits: int) -> int:
    """Words of ls_shaft_tris holding `entries` cell-local ids of `id_bits` bits."""
    return -(-int(entries) * id_bits // 32)

LS_PLANES = KernelSpec(
    "ls_planes", LS_HEADERS_NO_SCENE, "ls_planes_kernel", (Buf("ls_planes", "float4", "w"),), LS_UNIFORMS)
# The edges of each shaft volume pushed out by LS_EPS (the "edges" exact test): LS_EDGE_SLOTS float4.
LS_EDGE_SLOTS = 1 + 2 * 28 + 8  # must match shaders/common/linespace.h (LS_MAX_EDGES, the hull's corners)
LS_EDGES = KernelSpec(
    "ls_edges", LS_HEADERS_NO_SCENE, "ls_edges_kernel",
    (Buf("ls_planes", "float4", "r"), Buf("ls_edges", "float4", "w"), Buf("ls_reach", "float", "w")), LS_UNIFORMS)
# Only each shaft's reach (the cull margin's), where another exact test runs: no table of edges.
LS_REACH = dataclasses.replace(
    LS_EDGES, buffers=tuple(b for b in LS_EDGES.buffers if b.name != "ls_edges")).with_defines(LS_REACH_ONLY=1)
_CELL_BUFFERS = (Buf("ls_cell_boxes", "float4", "r"), Buf("ls_cell_ranges", "uint", "r"),
                 Buf("ls_cell_tris", "uint", "r"), Buf("ls_ref_bases", "uint", "r"))
# The count's and fill's hot reads (the planes, the masks, the cell-local triangles, the edges of
# _with_test) are texels on GLSL ("t", kernels.Buf).
_ITEM_BUFFERS = (Buf("ls_planes", "float4", "t"), Buf("ls_item_bases", "uint", "r"), Buf("ls_cell_groups", "uint", "r"),
                 Buf("ls_masks", "uint", "t"), Buf("ls_local_tris", "float4", "t"))
# The count and the fill read no cell boxes (the masks pass made everything cell-local) and no
# triangle ids (the fill writes cell-local positions, i - the cell's range begin).
_PAIR_CELL_BUFFERS = tuple(b for b in _CELL_BUFFERS if b.name not in ("ls_cell_boxes", "ls_cell_tris"))
# The count and the fill read each reference's triangle in cell-local coordinates from the masks
# pass (ls_local_tris, 48 bytes per reference of the batch), not through the scene's faces and
# vertices: TRIANGLE_RECORDS leaves scene.h's indexed loads out, and they bind no scene buffer.
_PAIR_DEFINES = (("TRIANGLE_RECORDS", "1"),)
# The count's decisions, one bit per (shaft, candidate), read by the fill (LS_PAIR_BITS).
LS_PAIR_BITS_COUNT = Buf("ls_pair_bits", "uint", "rw")
LS_PAIR_BITS_FILL = Buf("ls_pair_bits", "uint", "r")
LS_MASKS = KernelSpec(
    "ls_masks", LS_HEADERS, "ls_masks_kernel",
    SCENE_BUFFERS + _CELL_BUFFERS + (Buf("ls_masks", "uint", "w"), Buf("ls_local_tris", "float4", "w")),
    LS_BATCH_UNIFORMS + (Uniform("ls_cull_margin", "float"),))
# The count pass writes each item's count where its offset will be; the scan turns them into
# offsets in place (no second array of the offsets' size where every cell is one chunk).
LS_COUNT = KernelSpec(
    "ls_count", LS_HEADERS, "ls_shaft_kernel",
    _PAIR_CELL_BUFFERS + _ITEM_BUFFERS + (Buf("ls_item_offsets", "uint", "w"), Buf("ls_stats", "uint", "rw")),
    LS_BATCH_UNIFORMS, _PAIR_DEFINES)
# The fill writes the sets' candidate ids; read-write for the atomic OR of a word that two items
# share (16-bit ids, linespace.h ls_put_candidate).
LS_FILL_TRIS = Buf("ls_shaft_tris", "uint", "rw")
# The scanned set lengths (each set's offset in the lists), which the fill's items add to
# (linespace.h: ls_item_first).
LS_FILL_SET_OFFSETS = Buf("ls_set_lens", "uint", "r")
LS_FILL = KernelSpec(
    "ls_fill", LS_HEADERS, "ls_shaft_kernel",
    _PAIR_CELL_BUFFERS + _ITEM_BUFFERS + (Buf("ls_item_offsets", "uint", "r"), LS_FILL_SET_OFFSETS, LS_FILL_TRIS),
    LS_BATCH_UNIFORMS, _PAIR_DEFINES)
# The fill from the count's pair bits binds only what it reads (llvmpipe: 16 storage buffers per
# kernel, and both arrays may be split over 4).
LS_FILL_FROM_BITS = KernelSpec(
    "ls_fill", LS_HEADERS_NO_SCENE, "ls_shaft_kernel",
    (Buf("ls_cell_ranges", "uint", "r"), Buf("ls_ref_bases", "uint", "r"),
     Buf("ls_item_bases", "uint", "r"), Buf("ls_cell_groups", "uint", "r"), LS_PAIR_BITS_FILL, Buf("ls_item_offsets", "uint", "r"),
     LS_FILL_SET_OFFSETS, LS_FILL_TRIS),
    LS_BATCH_UNIFORMS, (("LS_PAIR_BITS", "1"),))


def _sets_kernel(name: str, buffers: tuple, uniforms: tuple = LS_BATCH_UNIFORMS) -> KernelSpec:
    """A kernel of the sets' steps: linespace.h's <name>_kernel, no scene buffers."""
    return KernelSpec(name, LS_HEADERS_NO_SCENE, f"{name}_kernel", buffers, uniforms)


def _uints(*names: str) -> tuple:
    """Buf(name, "uint", access) for each "name:access"."""
    return tuple(Buf(name, "uint", access) for name, access in (item.split(":") for item in names))


# Finding the distinct sets of a group of cells (linespace.h: ls_insert_kernel .. ls_shaft_set_kernel).
_ROW_BUFFERS = _uints("ls_cell_ranges:r", "ls_ref_bases:r") + (LS_PAIR_BITS_FILL,)
LS_INSERT = _sets_kernel("ls_insert", _ROW_BUFFERS + _uints("ls_set_table:rw", "ls_set_slot:w"))
LS_HEADS = _sets_kernel("ls_heads", _uints("ls_set_table:r", "ls_set_slot:rw", "ls_set_heads:rw", "ls_cell_sets:rw"))
LS_HEAD_COUNTS = _sets_kernel("ls_head_counts", _uints("ls_set_heads:r", "ls_head_counts:w"))
LS_SHAFT_SET = _sets_kernel("ls_shaft_set", _uints("ls_set_slot:r", "ls_set_heads:r", "ls_head_counts:r",
                                                   "ls_shaft_sets:w"))
# The head lists' builds: a work item per cell finds its sets in shaft order, then lists its heads
# (linespace.h: ls_cell_find_sets_kernel, ls_cell_head_list_kernel), in place of ls_insert ..
# ls_shaft_set, where a cell's rows fit one invocation's loop budget (cells_fit_loop_budget).
LS_CELL_FIND_SETS = _sets_kernel("ls_cell_find_sets", _ROW_BUFFERS + _uints(
    "ls_set_table:rw", "ls_set_slot:rw", "ls_shaft_sets:w", "ls_group_sets:w", "ls_stats:rw"))
LS_CELL_HEAD_LIST = _sets_kernel("ls_cell_head_list", _uints("ls_set_slot:r", "ls_group_sets:r", "ls_cell_sets:w",
                                                             "ls_head_list:w"))
# Before and after the scans: set lengths (and what the fill's items need), the offsets array.
LS_SET_LEN = _sets_kernel("ls_set_len", _uints("ls_item_bases:r", "ls_item_offsets:rw", "ls_shaft_sets:r",
                                               "ls_cell_sets:r", "ls_set_lens:w", "ls_stats:rw"), LS_UNIFORMS)
# Where all cells' pair bits are kept and the densest row fits the loop budget: each group's heads
# listed in shaft order (ls_shaft_set, which also packs the set indices as the offsets' blocks), and
# the set lengths and the fill over those lists only (linespace.h: ls_head_len_kernel,
# ls_head_fill_kernel), not over every shaft and item.
LS_SHAFT_SET_LIST = dataclasses.replace(
    LS_SHAFT_SET, buffers=LS_SHAFT_SET.buffers + _ROW_BUFFERS + _uints("ls_head_list:w", "ls_stats:rw")
).with_defines(LS_HEAD_LIST=1)
_HEAD_UNIFORMS = LS_UNIFORMS + (Uniform("ls_head_base", "uint"),)
LS_HEAD_LEN = _sets_kernel("ls_head_len", _ROW_BUFFERS + _uints("ls_head_list:r", "ls_set_lens:w"),
                          _HEAD_UNIFORMS + (Uniform("ls_bits_base", "uint"),))
LS_HEAD_FILL = _sets_kernel("ls_head_fill", _uints("ls_head_list:r", "ls_cell_ranges:r", "ls_ref_bases:r")
                            + (LS_PAIR_BITS_FILL, LS_FILL_SET_OFFSETS, LS_FILL_TRIS),
                            _HEAD_UNIFORMS + (Uniform("ls_bits_base", "uint"),))
LS_LAYOUT = _sets_kernel("ls_layout", _uints("ls_cell_sets:r", "ls_shaft_sets:r", "ls_set_lens:r",
                                             "ls_shaft_offsets:w"))
# The head lists' builds: the layout copies the packed blocks and the sets' offsets, and this writes
# each block's first word (linespace.h: ls_first_sets_kernel).
LS_FIRST_SETS = _sets_kernel("ls_first_sets", _uints("ls_cell_sets:r", "ls_shaft_offsets:w"))
# A split offset array is scanned chunk by chunk; this adds the earlier chunks' total.
LS_CARRY = KernelSpec(
    "ls_carry", LS_HEADERS_NO_SCENE, "ls_carry_kernel",
    (Buf("ls_carry_chunk", "uint", "rw"),), LS_UNIFORMS + (Uniform("ls_carry", "uint"),))

BUILD_SPECS = (LS_PLANES, LS_EDGES, LS_REACH, LS_COUNT, LS_FILL, LS_INSERT, LS_HEADS, LS_HEAD_COUNTS,
               LS_SHAFT_SET, LS_SHAFT_SET_LIST, LS_HEAD_LEN, LS_HEAD_FILL, LS_HEAD_FILL.with_defines(LS_IDS16=1),
               LS_SET_LEN, LS_LAYOUT, LS_LAYOUT.with_defines(LS_HEAD_LIST=1), LS_FIRST_SETS, LS_CARRY)

# The undecided triangle/shaft pairs (the facet planes neither separate nor contain the triangle)
# get an exact test: Sutherland-Hodgman clipping against the facet planes (thesis 3.3.3), the
# separating-axis test, or "edges": the clipper's predicate (does the triangle meet the volume of
# the planes pushed out by the margin?) decided by edges, a triangle edge in the volume or a
# volume edge through the triangle (linespace.h: ls_volume_edge_meets). All three are conservative
# with the same margin and give the same candidates up to that margin; each device uses the one
# its driver runs fastest (Device.line_space_test; docs/linespace-build.md measures them).
# Override with LSBENCH_LS_TEST=clip|sat|edges.
EXACT_TESTS = ("clip", "sat", "edges")


def exact_test(device: Device) -> str:
    choice = os.environ.get("LSBENCH_LS_TEST") or device.line_space_test
    if choice not in EXACT_TESTS:
        raise ValueError(f"LSBENCH_LS_TEST must be one of {', '.join(EXACT_TESTS)}, got {choice!r}")
    return choice


def _with_test(device: Device, spec: KernelSpec) -> KernelSpec:
    test = exact_test(device)
    if test == "clip":
        return spec.with_defines(LS_CLIP_SH=1)
    if test == "edges" and spec.name in (LS_COUNT.name, LS_FILL.name):
        return dataclasses.replace(spec, buffers=spec.buffers + (Buf("ls_edges", "float4", "t"),)).with_defines(
            LS_EXACT_EDGES=1)
    return spec


def shafts_per_cell(n: int) -> int:
    """15 N^4: 15 unordered pairs of different faces, N^2 x N^2 patch pairs each (3.3.3)."""
    return 15 * n**4


@dataclass
class Cells:
    count: int
    boxes: DeviceBuffer  # float4 x 2 per cell, grid space
    ranges: DeviceBuffer  # uint x 2 per cell: begin, end into tris
    tris: DeviceBuffer  # uint triangle ids
    references: int  # sum (or an upper bound) of the cells' list lengths


@dataclass(frozen=True)
class SplitArray:
    """A uint array of `entries` values stored over `chunks` buffers of 2^shift entries each
    (the last one shorter): entry i lives in buffer i >> shift at i & (2^shift - 1). One buffer
    while the array fits the driver's per-buffer limit; otherwise the fewest power-of-two chunks
    under it, so a Line Space past the limit runs wherever the device's memory holds it.

    Kernels reach the array only through two macros (defaults for one buffer in linespace.h):
    `<macro>(i)` reads entry i, `<macro>_STORE(i, v)` writes it (`<macro>_OR(i, v)`: an atomic OR). `defines()` gives the split
    versions, a chain of chunk compares; the chunk is uniform along a shaft's range except where
    the range crosses a boundary, so the compare costs a shift and a branch per access."""
    base: str  # the first buffer's name; the others are base1, base2, ...
    macro: str
    entries: int
    chunks: int = 1
    shift: int = 32

    @property
    def names(self) -> list[str]:
        return [self.base] + [f"{self.base}{i}" for i in range(1, self.chunks)]

    def chunk_entries(self, i: int) -> int:
        return min(self.entries, (i + 1) << self.shift) - (i << self.shift)

    def defines(self, access: str = "rw") -> tuple[tuple[str, str], ...]:
        """The macros of a kernel that binds the array's buffers with `access` ("t": read as texels)."""
        if self.chunks <= 1:
            return ()
        mask = f"((i) & {(1 << self.shift) - 1}u)"

        def load(name):
            return f"LD_U({name}, {mask})" if access == "t" else f"V({name})[{mask}]"
        read = load(self.names[-1])
        for k in range(self.chunks - 2, -1, -1):
            read = f"(((i) >> {self.shift}u) == {k}u ? {load(self.names[k])} : {read})"
        store = " else ".join(
            (f"if (ls_chunk_ == {k}u) " if k < self.chunks - 1 else "") + f"V({name})[ls_entry_] = (v);"
            for k, name in enumerate(self.names))
        atomic_or = " else ".join(
            (f"if (ls_chunk_ == {k}u) " if k < self.chunks - 1 else "") + f"ATOMIC_OR(V({name})[ls_entry_], v);"
            for k, name in enumerate(self.names))
        return ((f"{self.macro}(i)", read),
                (f"{self.macro}_STORE(i, v)",
                 f"{{ uint ls_chunk_ = (i) >> {self.shift}u; uint ls_entry_ = {mask}; {store} }}"),
                (f"{self.macro}_OR(i, v)",
                 f"{{ uint ls_chunk_ = (i) >> {self.shift}u; uint ls_entry_ = {mask}; {atomic_or} }}"))

    def bind(self, spec: KernelSpec) -> KernelSpec:
        """`spec` with the array's further buffers (same access as the first) and macros."""
        if self.chunks <= 1 or not any(b.name == self.base for b in spec.buffers):
            return spec
        access = next(b.access for b in spec.buffers if b.name == self.base)
        extra = tuple(Buf(name, "uint", access) for name in self.names[1:])
        return dataclasses.replace(spec, buffers=spec.buffers + extra, defines=spec.defines + self.defines(access))

    def alloc(self, device: Device, zero: bool) -> dict[str, DeviceBuffer]:
        made: dict[str, DeviceBuffer] = {}
        try:
            for i, name in enumerate(self.names):
                made[name] = device.alloc(name, 4 * self.chunk_entries(i), zero=zero)
        except Exception:
            for b in made.values():
                device.release(b)
            raise
        return made

    def fill_zero(self, device: Device, bufs: dict[str, DeviceBuffer], entries: int) -> None:
        """Zero the array's first `entries` values."""
        for i, name in enumerate(self.names):
            count = min(entries - (i << self.shift), self.chunk_entries(i))
            if count > 0:
                device.fill_zero(bufs[name], 4 * count)


def split_chunk_bytes(device: Device) -> int:
    """Bytes of one buffer of a split array on this device (a power of two entries)."""
    return 4 << ((device.max_buffer_bytes // 4).bit_length() - 1)


def split_array(device: Device, base: str, macro: str, entries: int, limit: int | None = None) -> SplitArray:
    """`entries` values in as few buffers as `limit` bytes each (the driver's) allow."""
    limit = device.max_buffer_bytes if limit is None else int(limit)
    entries = max(int(entries), 1)
    if 4 * entries <= limit:
        return SplitArray(base, macro, entries)
    shift = (limit // 4).bit_length() - 1  # 2^shift entries fit one buffer
    chunks = -(-entries // (1 << shift))
    if chunks > LS_MAX_CHUNKS:
        raise DeviceLimitError(
            f"buffer '{base}' needs {4 * entries / 2**20:.1f} MiB: more than {LS_MAX_CHUNKS} "
            f"buffers of the driver's per-buffer limit of {limit / 2**20:.0f} MiB ({device.limit_name})")
    return SplitArray(base, macro, entries, chunks, shift)


@dataclass
class LineSpaces:
    n: int
    shafts_per_cell: int
    buffers: dict[str, DeviceBuffer]
    stats: dict = field(default_factory=dict)
    splits: tuple[SplitArray, ...] = ()  # offsets and candidates, where split over buffers
    id_bits: int = 32  # the sets' cell-local candidate ids (candidate_id_bits)

    def trace_spec(self, spec: KernelSpec) -> KernelSpec:
        for split in self.splits:
            spec = split.bind(spec)
        return spec.with_defines(LS_IDS16=1) if self.id_bits == 16 else spec


def uniforms(geometry: GridGeometry, n: int) -> dict:
    return dict(geometry.uniforms(), ls_n=int(n), ls_shafts=shafts_per_cell(n), ls_eps=float(LS_EPS))


def _count_fill_specs(device: Device, fill_from_bits: bool, item_counts: bool = True,
                      count_stats: bool = True) -> tuple[KernelSpec, KernelSpec]:
    """The count (always keeping its decisions as pair bits: the sets are found from them) and
    the fill: from the bits where those of all cells fit, else testing the pairs again. Without
    `item_counts` (the head lists' builds: ls_head_len counts a head's row) the count writes no
    count per item and binds no ls_item_offsets; without `count_stats` (ls_cell_find_sets counts
    them from the rows) it sums neither non-empty shafts nor candidates."""
    count = _with_test(device, LS_COUNT)
    buffers = count.buffers if item_counts else tuple(b for b in count.buffers if b.name != "ls_item_offsets")
    count = dataclasses.replace(count, buffers=buffers + (LS_PAIR_BITS_COUNT,)).with_defines(LS_PAIR_BITS=1)
    if not item_counts:
        count = count.with_defines(LS_NO_ITEM_COUNTS=1)
    if not count_stats:
        count = count.with_defines(LS_NO_COUNT_STATS=1)
    fill = LS_FILL_FROM_BITS if fill_from_bits else _with_test(device, LS_FILL)
    if device.serial_work_items:  # each step of the pair test a vector loop of its own (linespace.h: ls_run_meets)
        count, fill = _cull_runs(count), _cull_runs(fill)  # (the fill from pair bits tests nothing)
    return count, fill


def _grouped_count(device: Device, count: KernelSpec) -> KernelSpec:
    """The count as it runs over groups of one-chunk cells: where the lanes are shafts (llvmpipe,
    GPUs) it queues the pairs the masks leave over the group's cells and tests them LS_PAIR_QUEUE
    at a time (linespace.h: ls_count_queued); cells of several chunks keep the loops per run."""
    return count if device.serial_work_items else count.with_defines(LS_PAIR_QUEUE=f"{LS_PAIR_QUEUE}u")


def _cull_runs(spec: KernelSpec) -> KernelSpec:
    """`spec` with LS_CULL_RUNS, the cell-local triangles read as plain floats (linespace.h LS_TRI_ARGS)."""
    if not any(b.name == "ls_local_tris" for b in spec.buffers):
        return spec
    buffers = tuple(Buf(b.name, "float", b.access) if b.name == "ls_local_tris" else b for b in spec.buffers)
    uniforms = spec.uniforms + (Uniform("ls_tri_stride", "uint"),)
    return dataclasses.replace(spec, buffers=buffers, uniforms=uniforms).with_defines(
        LS_CULL_RUNS=1, LS_RUN_LANES=f"{LS_RUN_LANES}u")


def _masks_spec(device: Device) -> KernelSpec:
    """ls_masks as the count reads its triangles: coordinate-major where work items run one after the other."""
    return _cull_runs(LS_MASKS) if device.serial_work_items else LS_MASKS


def _set_len_spec(device: Device, one_chunk: bool) -> KernelSpec:
    """ls_set_len as this device runs it: an item per shaft (work items one after the other) or
    LS_NONEMPTY_STRIDE shafts at a stride per item (SIMD lanes: one atomic for their non-empty ones);
    where every cell is one chunk, shaft s's item is s (LS_ONE_CHUNK: no lookup of the cell's items)."""
    spec = LS_SET_LEN.with_defines(LS_ONE_CHUNK=1) if one_chunk else LS_SET_LEN
    if device.serial_work_items:
        return spec
    strided = dataclasses.replace(spec, uniforms=spec.uniforms + (Uniform("ls_shaft_total", "uint"),))
    return strided.with_defines(LS_NONEMPTY_STRIDE=f"{LS_NONEMPTY_STRIDE}u")


def prepare(device: Device) -> None:
    """Compile the build's kernels in the variants it dispatches (arrays in one buffer each), so
    that no compile falls inside the timed build."""
    for spec in BUILD_SPECS:
        device.compile(_with_test(device, spec))
    device.compile(_masks_spec(device))  # as the build dispatches it
    for one_chunk in (True, False):
        device.compile(_set_len_spec(device, one_chunk))
    for fill_from_bits in (True, False):
        count, fill = _count_fill_specs(device, fill_from_bits)
        for spec in (count, _grouped_count(device, count), fill, fill.with_defines(LS_IDS16=1)):
            device.compile(spec)
    count = _count_fill_specs(device, True, item_counts=False)[0]
    for spec in (count, _grouped_count(device, count)):
        device.compile(spec)


def check_min_candidates(k: int) -> int:
    k = int(k)
    if k < 0:
        raise ValueError(f"ls_min_candidates must be >= 0, got {k}")
    return k


def check_n(n: int) -> int:
    n = int(n)
    if n < 1:
        raise ValueError(f"Line Space needs ls_n >= 1 patches per face edge, got {n}")
    return n


def selection_stats(ls: LineSpaces, candidate_cells: int, k: int) -> dict:
    """Stats of the K selection (ls_min_candidates) every Line Space structure records: of the
    cells with candidates (voxels, octree leaves), how many got no Line Space, and the per-cell
    part of ls_shaft_offsets they do not need (first set + shaft indices; their sets are not
    counted here: compare memory_bytes with a K = 0 build for the whole saving)."""
    skipped = candidate_cells - ls.stats["linespace_cells"]
    per_cell = offset_entries(1, ls.n, 0) - offset_entries(0, ls.n, 0)
    return {"candidate_cells": candidate_cells, "linespace_skipped_cells": skipped,
            "ls_min_candidates": k, "ls_offsets_bytes_saved": 4 * skipped * per_cell}


def cells_fit_loop_budget(device: Device, densest: int, per_cell: int) -> bool:
    """Whether one invocation may find a cell's sets (linespace.h: ls_cell_find_sets_kernel): within
    the driver's loop budget it clears the cell's table (2 x 15 N^4 slots of two words) and, per shaft, hashes
    its row and compares it with two slots' rows (the words of the group's densest row each),
    in half the budget. Where more probes than that spend it, the kernel says so and that group's
    sets are found by the passes per shaft."""
    budget = LS_LOOP_BUDGET.get(device.backend)
    words = -(-densest // 32)
    return budget is None or 4 * per_cell + per_cell * (2 + 3 * words) <= budget // 2


def head_rows_fit(device: Device, densest: int) -> bool:
    """Whether one invocation may walk the densest cell's whole row of pair bits within the
    driver's loop budget: ls_head_len and ls_head_fill loop over its words and its set bits, and
    ls_shaft_set over its words (linespace.h), where the count and the fill per item see one chunk."""
    budget = LS_LOOP_BUDGET.get(device.backend)
    return budget is None or densest + -(-densest // 32) <= budget


def candidate_chunk(device: Device) -> int:
    """Most candidates one count or fill work item walks: the driver's loop budget over the
    iterations a candidate may take (LS_LOOP_BUDGET), unbounded (2^32 - 1) where there is none."""
    budget = LS_LOOP_BUDGET.get(device.backend)
    return UINT32_MAX if budget is None else max(1, budget // LS_ITERATIONS_PER_CANDIDATE[exact_test(device)])


@dataclass(frozen=True)
class BuildPlan:
    """How the count and fill passes cover the cells: cell c has chunks(c) = ceil(len / chunk)
    (at least 1) chunks and 15 N^4 chunks(c) work items from item_bases[c]; its references are
    numbered densely from ref_bases[c] (the cull masks); `batches` are cell ranges [c0, c1) whose
    masks, and whose cell-local triangles (LOCAL_TRI_BYTES per reference), each fit LS_MASK_BYTES
    (at least one cell each)."""
    chunk: int
    item_bases: np.ndarray  # cells + 1, int64
    ref_bases: np.ndarray  # cells + 1, int64
    batches: tuple[tuple[int, int], ...]

    @property
    def items(self) -> int:
        return int(self.item_bases[-1])

    def batch_refs(self, c0: int, c1: int) -> int:
        return int(self.ref_bases[c1] - self.ref_bases[c0])

    def one_chunk(self, c0: int, c1: int, per_cell: int) -> bool:
        """Every cell of [c0, c1) is one chunk: a work item's cells are then found by a division
        instead of a search over the cells (linespace.h: ls_shaft_kernel)."""
        return int(self.item_bases[c1] - self.item_bases[c0]) == per_cell * (c1 - c0)

    def one_chunk_runs(self, c0: int, c1: int, per_cell: int, shortest: int) -> list[tuple[int, int]]:
        """The runs [a, b) of at least `shortest` consecutive one-chunk cells in [c0, c1), in order."""
        one = (self.item_bases[c0 + 1:c1 + 1] - self.item_bases[c0:c1]) == per_cell
        steps = np.diff(np.concatenate([[0], one.astype(np.int8), [0]]))
        starts, ends = np.flatnonzero(steps == 1), np.flatnonzero(steps == -1)
        keep = ends - starts >= shortest
        return [(c0 + int(a), c0 + int(b)) for a, b in zip(starts[keep], ends[keep])]

    def cell_groups(self, c0: int, c1: int, per_cell: int, cells_per_item: int) -> np.ndarray | None:
        """Where every cell of [c0, c1) is one chunk, the groups of consecutive cells that one
        count or fill work item walks for its shaft (linespace.h: ls_shaft_kernel, ls_cell_groups):
        each group's first cell, then c1. A group is an aligned block of `cells_per_item` cells
        (a power of two) whose candidates, plus one for each cell (its own loop iterations, far
        fewer than a candidate's), fit one chunk, so that a work item's loops stay inside the
        driver's budget as one chunk's do; a block that does not fit is halved, down to single
        cells. None where a cell has more than one chunk (a work item is then one chunk)."""
        if not self.one_chunk(c0, c1, per_cell):
            return None
        cut = np.zeros(c1 - c0 + 1, bool)
        cut[[0, -1]] = True
        open_cells = np.ones(c1 - c0, bool)  # not yet in a group
        size = int(cells_per_item)
        while True:
            starts = np.arange(c0, c1, size)
            ends = np.minimum(starts + size, c1)
            load = self.ref_bases[ends] - self.ref_bases[starts] + (ends - starts)
            fits = open_cells[starts - c0] & ((load <= self.chunk) | (size == 1))
            cut[starts[fits] - c0] = True
            cut[ends[fits] - c0] = True
            open_cells &= ~np.repeat(fits, size)[: c1 - c0]
            if size == 1:
                return (c0 + np.flatnonzero(cut)).astype(np.uint32)
            size //= 2


def plan_build(ranges: np.ndarray, per_cell: int, patches: int, chunk: int,
               mask_bytes: int = LS_MASK_BYTES, bits_bytes: int | None = None) -> BuildPlan:
    """ranges: (cells, 2) begin, end of each cell's list. bits_bytes: where given, a batch's pair
    bits (one per shaft and reference) fit it too."""
    lengths = (ranges[:, 1].astype(np.int64) - ranges[:, 0]).clip(min=0)
    chunks = np.maximum(1, -(-lengths // chunk))
    item_bases = np.concatenate([[0], np.cumsum(per_cell * chunks)])
    ref_bases = np.concatenate([[0], np.cumsum(lengths)])
    max_refs = max(1, mask_bytes // max(4 * patches, LOCAL_TRI_BYTES))  # masks and local triangles each fit
    if bits_bytes is not None:
        max_refs = max(1, min(max_refs, 8 * bits_bytes // per_cell))
    batches, c0, cells = [], 0, len(lengths)
    while c0 < cells:
        c1 = int(np.searchsorted(ref_bases, ref_bases[c0] + max_refs, side="right")) - 1
        c1 = min(max(c1, c0 + 1), cells)
        batches.append((c0, c1))
        c0 = c1
    return BuildPlan(int(chunk), item_bases, ref_bases, tuple(batches))


@dataclass(frozen=True)
class ListSizes:
    """What the lists of a set of Line Spaces hold besides their fixed per-cell part: the distinct
    candidate sets of all cells together, the candidate ids of those sets and their width."""
    sets: int
    references: int
    id_bits: int = 32  # candidate_id_bits of the densest cell (no matter with no references)

    @classmethod
    def of(cls, stats: dict) -> "ListSizes":
        return cls(int(stats.get("ls_sets", 0)), int(stats.get("ls_set_references", 0)),
                   int(stats.get("ls_id_bits", 32)))


def offset_entries(cells: int, n: int, sets: int) -> int:
    """Entries of ls_shaft_offsets (layout: shaders/common/linespace.h): per cell its first set and
    15 N^4 set indices (8 bits, 4 per word, where 15 N^4 <= 256; else 16 bits, 2 per word), then
    sets + 1 set offsets."""
    return cells * _block_words(shafts_per_cell(n)) + sets + 1


def _index_bits(per_cell: int) -> int:
    """Width of a shaft's set index (linespace.h ls_index_log2): a cell has at most per_cell sets."""
    return 8 if per_cell <= 256 else 16


def _block_words(per_cell: int) -> int:
    per_word = 32 // _index_bits(per_cell)
    return 1 + -(-per_cell // per_word)


def predicted_bytes(device: Device, cells: int, n: int, lists: ListSizes) -> dict[str, int]:
    """The bytes of each buffer build_linespaces returns for `cells` Line Spaces of N = n whose
    distinct sets are `lists` (lsbench/model/bytes.py): exact given `lists`, which a model
    estimates from a sample of cells before the build. Split arrays as split_array splits them
    (DeviceLimitError where they would need more buffers than LS_MAX_CHUNKS)."""
    if cells * shafts_per_cell(n) == 0:
        return {"ls_shaft_offsets": 4, "ls_shaft_tris": 4}
    out = {}
    for array in (split_array(device, "ls_shaft_offsets", "LS_OFFSET", offset_entries(cells, n, lists.sets)),
                  split_array(device, "ls_shaft_tris", "LS_CANDIDATE", candidate_words(lists.references, lists.id_bits))):
        out.update({name: max(4 * array.chunk_entries(i), 4) for i, name in enumerate(array.names)})
    return out


def build_linespaces(device: Device, scene_buffers: dict, geometry: GridGeometry, cells: Cells,
                     n: int, budget_bytes: int | None = None, other_bytes: int = 0) -> LineSpaces:
    """Line Spaces of all cells: cull masks -> count (with pair bits) -> the distinct sets of each
    cell -> scans -> fill of each set's list, all on the device, in batches of cells (their masks
    and bits), groups of cells (the sets' hash tables) and chunks of candidates (the driver's loop
    budget). budget_bytes (BuildParams.budget_bytes): where the structure, its `other_bytes` and
    these Line Spaces together, would pass it, the build stops with OverBudgetError once the
    count pass and the sets' scans have sized the lists, before they are allocated and filled."""
    n = check_n(n)
    per_cell = shafts_per_cell(n)
    patches = 6 * n * n
    n_shafts = cells.count * per_cell
    if per_cell > LS_MAX_SETS_PER_CELL:
        raise DeviceLimitError(f"N={n}: {per_cell} shafts per cell may hold more distinct sets than "
                               f"the 16-bit set indices ({LS_MAX_SETS_PER_CELL}) number")
    # The limits in the order a bigger device would meet them: buffers per array, device memory,
    # then the 32-bit indices (which no device with less than 16 GiB for the offsets reaches).
    # Checked (for the offsets' fixed part) before the long count pass.
    fixed_entries = offset_entries(cells.count, n, 0)
    split_array(device, "ls_shaft_offsets", "LS_OFFSET", fixed_entries)
    device.check_memory("ls_shaft_offsets", 4 * fixed_entries)
    if n_shafts + 1 > UINT32_MAX:
        raise DeviceLimitError(
            f"{cells.count} Line Spaces x {per_cell} shafts = {n_shafts} shafts overflow 32-bit "
            "shaft indices (uint, 2^32 - 1)")
    u = uniforms(geometry, n)
    if n_shafts == 0:  # no cell gets a Line Space (e.g. ls_min_candidates above every list)
        no_offsets = device.alloc("ls_shaft_offsets", 4)
        no_tris = device.alloc("ls_shaft_tris", 4)
        no_tris.used_bytes = 0
        stats = {"ls_n": n, "shafts_per_cell": per_cell, "linespace_cells": 0, "shafts": 0,
                 "non_empty_shafts": 0, "candidate_references": 0, "ls_sets": 0, "ls_set_references": 0,
                 "ls_bytes": 8, "ls_exact_test": exact_test(device), "ls_offset_buffers": 1, "ls_tri_buffers": 1,
                 "ls_candidate_chunk": candidate_chunk(device), "ls_work_items": 0, "ls_cell_batches": 0,
                 "ls_pair_bits": False, "ls_id_bits": 32}
        return LineSpaces(n, per_cell, {"ls_shaft_offsets": no_offsets, "ls_shaft_tris": no_tris}, stats)
    ranges = device.read(cells.ranges, np.uint32, 2 * cells.count).reshape(-1, 2)
    densest = int((ranges[:, 1].astype(np.int64) - ranges[:, 0]).max())
    id_bits = candidate_id_bits(densest)
    mask_bytes = min(LS_MASK_BYTES, device.max_buffer_bytes)
    plan = plan_build(ranges, per_cell, patches, candidate_chunk(device), mask_bytes)
    if plan.items + 1 > UINT32_MAX:
        raise DeviceLimitError(
            f"{plan.items} count/fill work items (shafts x chunks of {plan.chunk} candidates) overflow "
            "32-bit item indices (uint, 2^32 - 1)")
    # The pair bits of all cells where they fit (the fill then reads them), else of one batch;
    # over as many buffers as the driver's per-buffer limit asks, up to LS_MAX_CHUNKS.
    bits_limit = min(LS_PAIR_BITS_BYTES, LS_MAX_CHUNKS * split_chunk_bytes(device))
    pairs = int(plan.ref_bases[-1]) * per_cell
    all_bits = pairs < UINT32_MAX and 4 * (-(-pairs // 32)) <= bits_limit
    if all_bits:
        try:
            device.check_memory("ls_pair_bits", 4 * (-(-pairs // 32)))
        except DeviceLimitError:
            all_bits = False
    if not all_bits:
        plan = plan_build(ranges, per_cell, patches, plan.chunk, mask_bytes, bits_limit)
        pairs = max(plan.batch_refs(c0, c1) for c0, c1 in plan.batches) * per_cell
    group_cells = max(1, min(cells.count, LS_GROUP_SHAFTS // per_cell,
                             device.max_buffer_bytes // (LS_SET_TABLE_BYTES * per_cell)))
    group_shafts = group_cells * per_cell
    temps: list[DeviceBuffer] = []  # released however the build ends
    kept: list[DeviceBuffer] = []  # released only if it fails

    def temp(name: str, nbytes: int, zero: bool = True) -> DeviceBuffer:
        temps.append(device.alloc(name, max(int(nbytes), 4), zero=zero))
        return temps[-1]

    def drop(*bufs: DeviceBuffer) -> None:
        """Release temporaries that no later pass reads, before the next allocations: memory just
        freed is memory the driver may hand out again, where fresh pages cost their first touch
        (~10 us per 4 KiB page on the VM of docs/linespace-build.md's thirty-first session)."""
        for b in bufs:
            temps.remove(b)
            device.release(b)

    try:
        planes = temp("ls_planes", 16 * LS_PLANE_SLOTS * per_cell, zero=False)
        device.dispatch(LS_PLANES, per_cell, {"ls_planes": planes}, u)
        # The pushed volumes' edges (the "edges" exact test) and their reach beyond the hulls: the
        # largest sizes the masks' cull margin, whichever test runs (linespace.h: ls_masks_kernel).
        by_edges = exact_test(device) == "edges"
        edges = temp("ls_edges", 16 * LS_EDGE_SLOTS * per_cell if by_edges else 4, zero=False)
        reach = temp("ls_reach", 4 * per_cell, zero=False)
        device.dispatch(LS_EDGES if by_edges else LS_REACH, per_cell,
                        {"ls_planes": planes, "ls_edges": edges, "ls_reach": reach}, u)
        cull_margin = max(float(device.read(reach, np.float32).max()), LS_EPS) + LS_CULL_SLACK
        # ls_stats: words 0 (non-empty shafts of several chunks: ls_set_len, or ls_shaft_set with
        # head lists), 1 (cut loops), 2 (cells whose sets' probes the loop budget cut:
        # ls_cell_find_sets) and 3 (ls_cell_find_sets' non-empty shafts of several chunks; with
        # cell_stats, of all, and 4, 5 all shafts' candidates, low and high), then
        # the count's LS_STAT_BUCKETS lines of 16 words (non-empty shafts, candidates low and high)
        stats_buf = temp("ls_stats", 64 * (1 + LS_STAT_BUCKETS))
        item_bases, ref_bases = (device.upload(name, values.astype(np.uint32)) for name, values in
                                 (("ls_item_bases", plan.item_bases), ("ls_ref_bases", plan.ref_bases)))
        temps.extend((item_bases, ref_bases))
        most_refs = max(plan.batch_refs(c0, c1) for c0, c1 in plan.batches)
        # + LS_RUN_LANES words: the count's cull reads whole vector blocks past a run (linespace.h ls_run_meets)
        masks = temp("ls_masks", 4 * (most_refs * patches + LS_RUN_LANES), zero=False)
        # coordinate-major where the pair steps are vector loops (linespace.h LS_TRI_ARGS): 9 rows of
        # tri_stride floats, LS_RUN_LANES past the last reference, as a block reads whole vectors
        tri_stride = most_refs + LS_RUN_LANES
        masks_spec = _masks_spec(device)
        local_tris = temp("ls_local_tris", max(LOCAL_TRI_BYTES * most_refs, 9 * 4 * tri_stride), zero=False)
        bits = split_array(device, "ls_pair_bits", "LS_BITS", -(-pairs // 32))
        bits_bufs = bits.alloc(device, zero=all_bits)
        temps.extend(bits_bufs.values())
        cell_bufs = dict(scene_buffers, ls_planes=planes, ls_edges=edges, ls_cell_boxes=cells.boxes, ls_cell_ranges=cells.ranges,
                         ls_cell_tris=cells.tris, ls_item_bases=item_bases, ls_ref_bases=ref_bases, ls_masks=masks,
                         ls_local_tris=local_tris, **bits_bufs)
        # Builds with all cells' bits: lists of each group's heads (ls_head_len, ls_head_fill), and
        # no count per item (the heads' rows hold their counts)
        by_heads = all_bits and head_rows_fit(device, densest)
        items = split_array(device, "ls_item_offsets", "LS_ITEM", plan.items if not by_heads else 1)
        item_bufs = {}
        if not by_heads:
            device.check_memory("ls_item_offsets", 4 * plan.items)
            item_bufs = items.alloc(device, zero=True)
            temps.extend(item_bufs.values())
        # A set word per shaft, or in the head lists' builds the offsets array's blocks (packed set indices)
        block_words = _block_words(per_cell)
        shaft_sets = split_array(device, "ls_shaft_sets", "LS_SHAFT_SET",
                                 cells.count * block_words if by_heads else n_shafts)
        shaft_set_bufs = shaft_sets.alloc(device, zero=False)
        temps.extend(shaft_set_bufs.values())
        cell_sets = temp("ls_cell_sets", 4 * (cells.count + 1))  # sets per cell, then the first set
        group_bufs = dict(ls_cell_ranges=cells.ranges, ls_ref_bases=ref_bases, **bits_bufs,
                          ls_set_table=temp("ls_set_table", LS_SET_TABLE_BYTES * group_shafts, zero=False),
                          ls_set_slot=temp("ls_set_slot", 4 * group_shafts, zero=False),
                          ls_set_heads=temp("ls_set_heads", 4 * (-(-group_shafts // 32)), zero=False),
                          ls_head_counts=temp("ls_head_counts", 4 * (-(-group_shafts // 32)), zero=False),
                          ls_cell_sets=cell_sets, ls_stats=stats_buf, **shaft_set_bufs)

        def hashed(spec: KernelSpec) -> KernelSpec:  # tests: a hash that collides (LS_HASH_MASK)
            return spec if LS_HASH_MASK == 0xFFFFFFFF else spec.with_defines(LS_HASH_MASK=f"{LS_HASH_MASK}u")

        insert_spec = bits.bind(hashed(LS_INSERT))
        head_lists: list[tuple[DeviceBuffer, int, int]] = [] if by_heads else None
        shaft_set_spec = bits.bind(shaft_sets.bind(LS_SHAFT_SET_LIST if head_lists is not None else LS_SHAFT_SET))
        # The sets of a cell found by one work item, in shaft order (linespace.h:
        # ls_cell_find_sets_kernel), in the head lists' builds, in each group whose densest cell fits
        # the driver's loop budget; the other groups by the passes per shaft.
        cell_lens = ranges[:, 1].astype(np.int64) - ranges[:, 0]
        groups_fit = set() if head_lists is None else {  # the first cells of those groups (all cells' bits: from 0)
            g0 for g0 in range(0, cells.count, group_cells)
            if cells_fit_loop_budget(device, int(cell_lens[g0:g0 + group_cells].max()), per_cell)}
        by_cells = bool(groups_fit)
        # ... and where no loop budget can cut a cell, the stats from its rows, not from the count
        cell_stats = by_cells and device.backend not in LS_LOOP_BUDGET
        if by_cells:
            group_bufs["ls_group_sets"] = temp("ls_group_sets", 4 * (group_cells + 1), zero=False)
            cell_find_sets = bits.bind(shaft_sets.bind(hashed(LS_CELL_FIND_SETS)))
            if cell_stats:
                cell_find_sets = cell_find_sets.with_defines(LS_CELL_STATS=1)
        # Cells whose sets the loop budget kept from one invocation (ls_stats[2]), and the non-empty
        # shafts of several chunks that ls_cell_find_sets counted (ls_stats[3]) in groups it finished
        cut_cells, cells_non_empty, counted_before = 0, 0, 0
        groups_by_cells, groups = 0, 0

        def batch_uniforms(c0: int, c1: int, bits_base: int = 0) -> dict:
            return dict(u, ls_chunk=min(plan.chunk, UINT32_MAX), ls_item_base=int(plan.item_bases[c0]),
                        ls_ref_base=int(plan.ref_bases[c0]), ls_cell_first=c0, ls_cell_end=c1,
                        ls_bits_base=bits_base, ls_grouped=0, ls_cull_margin=cull_margin,
                        ls_tri_stride=tri_stride)

        no_groups = temp("ls_cell_groups", 4)
        cells_per_item = CELLS_PER_ITEM.get(device.backend, CELLS_PER_ITEM_DEFAULT)
        cell_groups = {(c0, c1): plan.cell_groups(c0, c1, per_cell, cells_per_item)  # count and fill
                       for c0, c1 in plan.batches}

        def shaft_pass(spec: KernelSpec, c0: int, c1: int, bufs: dict, uniforms: dict,
                       grouped_spec: KernelSpec | None = None) -> None:
            """One count or fill dispatch over the batch [c0, c1): a work item per shaft of each
            group of cells (BuildPlan.cell_groups), or per shaft and chunk of one cell. With
            `grouped_spec` (the queued count) the groups run it, and a batch with cells of several
            chunks is dispatched in parts: its long runs of one-chunk cells as groups, the rest
            per chunk."""
            groups = cell_groups[(c0, c1)]
            if groups is None:
                parts = plan.one_chunk_runs(c0, c1, per_cell, LS_GROUPED_RUN) if grouped_spec else []
                edges = [c0] + [c for run in parts for c in run] + [c1]
                for k, (a, b) in enumerate(zip(edges[:-1], edges[1:])):
                    if a == b:
                        continue
                    part = dict(uniforms, ls_cell_first=a, ls_cell_end=b, ls_item_base=int(plan.item_bases[a]))
                    if k % 2 == 1:  # a run of one-chunk cells
                        grouped(grouped_spec, plan.cell_groups(a, b, per_cell, cells_per_item), bufs, part)
                    else:
                        device.dispatch(spec, int(plan.item_bases[b] - plan.item_bases[a]),
                                        dict(bufs, ls_cell_groups=no_groups), part)
                return
            grouped(grouped_spec or spec, groups, bufs, uniforms)

        def grouped(spec: KernelSpec, groups: np.ndarray, bufs: dict, uniforms: dict) -> None:
            group_buf = device.upload("ls_cell_groups", groups)
            try:
                device.dispatch(spec, per_cell * (len(groups) - 1), dict(bufs, ls_cell_groups=group_buf),
                                dict(uniforms, ls_grouped=1))
            finally:
                device.release(group_buf)

        def find_sets(c0: int, c1: int, bits_base: int) -> None:
            nonlocal cut_cells, cells_non_empty, counted_before, groups_by_cells, groups
            for g0 in range(c0, c1, group_cells):
                g1 = min(g0 + group_cells, c1)
                shafts = (g1 - g0) * per_cell
                bu = batch_uniforms(g0, g1, bits_base)
                groups += 1
                if g0 in groups_fit:  # each cell clears its own table
                    device.dispatch(cell_find_sets, g1 - g0, group_bufs, bu)
                    # Where a driver has a loop budget, each group's words 2 and 3, so that a group
                    # some cell of which was cut is found again below and counted there only
                    cut, counted = (int(v) for v in device.read(stats_buf, np.uint32, 4)[2:]) \
                        if device.backend in LS_LOOP_BUDGET else (0, 0)
                    group_counted, counted_before = counted - counted_before, counted
                    if cut == cut_cells:
                        cells_non_empty += group_counted
                        groups_by_cells += 1
                        heads = device.scan_in_place(group_bufs["ls_group_sets"], g1 - g0 + 1)  # sets of the cells before
                        base = head_lists[-1][1] + head_lists[-1][2] if head_lists else 0  # heads of the groups before
                        head_lists.append((temp("ls_head_list", 4 * heads, zero=False), base, heads))
                        device.dispatch(LS_CELL_HEAD_LIST, g1 - g0, dict(group_bufs, ls_head_list=head_lists[-1][0]), bu)
                        continue
                    cut_cells = cut  # the loop budget cut some cell's probes: this group by the passes below
                device.fill_zero(group_bufs["ls_set_table"], 8 * shafts)
                words = -(-shafts // 32)
                device.fill_zero(group_bufs["ls_set_heads"], 4 * words)
                for spec in (insert_spec, LS_HEADS):
                    device.dispatch(spec, shafts, group_bufs, bu)
                device.dispatch(LS_HEAD_COUNTS, words, group_bufs, bu)  # heads per word, scanned:
                heads = device.scan_in_place(group_bufs["ls_head_counts"], words)  # heads before each word
                if head_lists is None:
                    device.dispatch(shaft_set_spec, shafts, group_bufs, bu)  # a work item per shaft
                    continue
                base = head_lists[-1][1] + head_lists[-1][2] if head_lists else 0  # heads of the groups before
                head_lists.append((temp("ls_head_list", 4 * heads, zero=False), base, heads))
                device.dispatch(shaft_set_spec, (g1 - g0) * block_words, dict(group_bufs, ls_head_list=head_lists[-1][0]),
                                bu)  # a work item per word of the cells' blocks

        count_spec, fill_spec = _count_fill_specs(device, all_bits, item_counts=not by_heads, count_stats=not cell_stats)
        count = bits.bind(count_spec if by_heads else items.bind(count_spec))
        grouped_count = _grouped_count(device, count)
        for c0, c1 in plan.batches:
            bits_base = 0 if all_bits else int(plan.ref_bases[c0])
            bu = batch_uniforms(c0, c1, bits_base)
            device.dispatch(masks_spec, plan.batch_refs(c0, c1), cell_bufs, bu)
            if not all_bits:
                bits.fill_zero(device, bits_bufs, -(-plan.batch_refs(c0, c1) * per_cell // 32))
            shaft_pass(count, c0, c1, dict(cell_bufs, ls_stats=stats_buf, **item_bufs), bu, grouped_count)
            if not all_bits:  # this batch's sets, while its bits are there
                find_sets(c0, c1, bits_base)
        if all_bits:
            find_sets(0, cells.count, 0)
        # All shafts' lists together, summed in 64 bits by the count (no scan over the items: each
        # shaft's items are summed where needed, ls_set_len and the fill). The sets' lists hold no
        # more, so below 2^32 - 1 no 32-bit offset of theirs can wrap.
        stat_words = device.read(stats_buf, np.uint32, 16 * (1 + LS_STAT_BUCKETS)).reshape(-1, 16).astype(np.int64)
        if cell_stats:  # ls_cell_find_sets summed them (words 3-5 of the first line)
            stat_words[1:] = 0
            stat_words[1, 0], stat_words[1, 2], stat_words[1, 3] = stat_words[0, 3:6]
        total = int(stat_words[1:, 2].sum() + (stat_words[1:, 3].sum() << 32))
        if total >= UINT32_MAX:
            raise DeviceLimitError(
                f"Line Space candidate lists (N={n}, {cells.count} cells) pass 2^32 - 1 "
                "references: over the 32-bit candidate offsets")
        n_sets = device.scan_in_place(cell_sets, cells.count + 1)
        # The sets are found: their tables are done, and so are the masks where the fill reads the bits
        drop(*(group_bufs[name] for name in ("ls_set_table", "ls_set_slot", "ls_set_heads", "ls_head_counts",
                                             "ls_group_sets") if name in group_bufs))
        if head_lists is not None:
            drop(masks, local_tris)
        set_lens = split_array(device, "ls_set_lens", "LS_SET_LEN", n_sets + 1)
        set_len_bufs = set_lens.alloc(device, zero=True)
        temps.extend(set_len_bufs.values())
        sets_bufs = dict(ls_item_bases=item_bases, ls_cell_sets=cell_sets, ls_stats=stats_buf,
                         **item_bufs, **shaft_set_bufs, **set_len_bufs)

        def bound(spec: KernelSpec) -> KernelSpec:
            return set_lens.bind(shaft_sets.bind(items.bind(spec)))

        if head_lists is not None:
            listed = sum(h for _, _, h in head_lists)
            if listed != n_sets:
                raise RuntimeError(f"Line Space build: the groups' heads ({listed}) differ from the cells' sets ({n_sets})")
            head_len = bits.bind(set_lens.bind(LS_HEAD_LEN))
            for head_list, base, heads in head_lists:
                device.dispatch(head_len, heads, dict(cell_bufs, ls_head_list=head_list, **set_len_bufs),
                                dict(u, ls_head_base=base, ls_bits_base=0))  # all cells' bits
        else:
            set_len = bound(_set_len_spec(device, one_chunk=plan.items == n_shafts))
            if device.serial_work_items:
                device.dispatch(set_len, n_shafts, sets_bufs, u)
            else:
                device.dispatch(set_len, -(-n_shafts // LS_NONEMPTY_STRIDE), sets_bufs, dict(u, ls_shaft_total=n_shafts))
        set_refs = _scan_split(device, set_lens, set_len_bufs, u)  # lengths -> offsets into the lists
        offset_count = offset_entries(cells.count, n, n_sets)
        if budget_bytes is not None:  # the two arrays' bytes, as allocated below
            needed = other_bytes + 4 * offset_count + 4 * max(candidate_words(set_refs, id_bits), 1)
            if needed > budget_bytes:
                raise OverBudgetError(needed, budget_bytes, "known from its Line Space count pass; the lists "
                                      "were not filled")
        offsets = split_array(device, "ls_shaft_offsets", "LS_OFFSET", offset_count)
        device.check_memory("ls_shaft_offsets", 4 * offsets.entries)
        offset_bufs = offsets.alloc(device, zero=False)
        kept.extend(offset_bufs.values())
        layout = LS_LAYOUT.with_defines(LS_HEAD_LIST=1) if by_heads else LS_LAYOUT  # blocks packed already
        device.dispatch(offsets.bind(bound(layout)), offsets.entries, dict(sets_bufs, **offset_bufs),
                        batch_uniforms(0, cells.count))
        if by_heads:
            device.dispatch(offsets.bind(LS_FIRST_SETS), cells.count, dict(ls_cell_sets=cell_sets, **offset_bufs),
                            batch_uniforms(0, cells.count))
        drop(*shaft_set_bufs.values())  # read only by the layout
        candidates = split_array(device, "ls_shaft_tris", "LS_CANDIDATE", candidate_words(set_refs, id_bits))
        device.check_memory("ls_shaft_tris", 4 * candidates.entries)
        # 16-bit ids: an item's first and last word may be shared with its neighbour's, ORed in (ls_put_candidate)
        tris_bufs = candidates.alloc(device, zero=id_bits == 16)
        kept.extend(tris_bufs.values())
        if head_lists is not None:
            head_fill = bits.bind(candidates.bind(set_lens.bind(LS_HEAD_FILL.with_defines(LS_IDS16=1) if id_bits == 16 else LS_HEAD_FILL)))
            for head_list, base, heads in head_lists:
                device.dispatch(head_fill, heads, dict(cell_bufs, ls_head_list=head_list, **set_len_bufs, **tris_bufs),
                                dict(u, ls_head_base=base, ls_bits_base=0))  # all cells' bits
        else:
            fill = bits.bind(candidates.bind(set_lens.bind(items.bind(fill_spec.with_defines(LS_IDS16=1) if id_bits == 16 else fill_spec))))
            fill_bufs = dict(cell_bufs, **item_bufs, **set_len_bufs, **tris_bufs)
            masks_ready = all_bits or len(plan.batches) == 1
            for c0, c1 in plan.batches:
                bu = batch_uniforms(c0, c1, 0 if all_bits else int(plan.ref_bases[c0]))
                if not masks_ready:
                    device.dispatch(masks_spec, plan.batch_refs(c0, c1), cell_bufs, bu)
                shaft_pass(fill, c0, c1, fill_bufs, bu)
        first_line = device.read(stats_buf, np.uint32, 16).astype(np.int64)
        non_empty = int(first_line[0] + cells_non_empty + stat_words[1:, 0].sum())
        cut = int(first_line[1])
        if cut:
            raise device.loop_limit_error(f"the candidate loops of {cut} shafts: these cells hold too many "
                                          "triangles for one invocation")
    except Exception:
        for b in kept:
            device.release(b)
        raise
    finally:
        for b in temps:
            device.release(b)
    device.finish()
    if set_refs == 0:  # the buffers are sized exactly, except the 4-byte stand-in for an empty list
        tris_bufs["ls_shaft_tris"].used_bytes = 0
    stats = {
        "ls_n": n,
        "shafts_per_cell": per_cell,
        "linespace_cells": cells.count,
        "shafts": n_shafts,
        "non_empty_shafts": non_empty,
        "candidate_references": total,  # all shafts' lists together, as one list per shaft held them
        "ls_sets": n_sets,
        "ls_set_references": set_refs,
        "ls_id_bits": id_bits,
        "ls_bytes": sum(b.nbytes for b in offset_bufs.values()) + sum(b.nbytes for b in tris_bufs.values()),
        "ls_exact_test": exact_test(device),
        "ls_cull_margin": cull_margin,
        "ls_offset_buffers": offsets.chunks,
        "ls_tri_buffers": candidates.chunks,
        "ls_candidate_chunk": plan.chunk,
        "ls_work_items": plan.items,
        "ls_cell_batches": len(plan.batches),
        "ls_pair_bits": all_bits,
        "ls_pair_bits_buffers": bits.chunks,
        "ls_head_lists": head_lists is not None,  # set lengths and fill over the heads' rows
        "ls_set_groups": groups,  # groups of cells whose sets were found together
        "ls_sets_by_cells": groups_by_cells,  # ... a cell's by one work item (ls_cell_find_sets)
        "ls_sets_cells_cut": cut_cells,  # ... whose loops the budget cut, so their groups went per shaft
    }
    splits = tuple(a for a in (offsets, candidates) if a.chunks > 1)
    return LineSpaces(n, per_cell, dict(**offset_bufs, **tris_bufs), stats, splits, id_bits)


def _scan_split(device: Device, array: SplitArray, bufs: dict[str, DeviceBuffer], u: dict) -> int:
    """Exclusive prefix sum over a split array, in place: each chunk on its own, then the sum of
    the chunks before it added (LS_CARRY). Returns the total (which may pass 32 bits: the caller
    checks)."""
    carry = 0
    for i, name in enumerate(array.names):
        entries = array.chunk_entries(i)
        chunk_total = device.scan_in_place(bufs[name], entries)
        if carry:
            device.dispatch(LS_CARRY, entries, {"ls_carry_chunk": bufs[name]}, dict(u, ls_carry=carry & UINT32_MAX))
        carry += chunk_total
    return carry


# ---- Reading the layout on the host (tests, the model's sample) ---------------------------------
def read_array(device: Device, buffers: dict[str, DeviceBuffer], base: str) -> np.ndarray:
    """A split array's buffers (base, base1, base2, ...) read back as one int64 array."""
    names = sorted((k for k in buffers if k == base or (k.startswith(base) and k[len(base):].isdigit())),
                   key=lambda k: (len(k), k))
    return np.concatenate([device.read(buffers[k], np.uint32) for k in names]).astype(np.int64)


def shaft_ranges(offset_words: np.ndarray, per_cell: int) -> tuple[np.ndarray, np.ndarray]:
    """(begin, end) in ls_shaft_tris of every shaft of every Line Space (cell-major), decoded from
    ls_shaft_offsets as trace.h's shaft_list reads it."""
    words = np.asarray(offset_words, np.int64)
    blocks = _blocks(words, per_cell)
    packed = blocks[:, 1:, None]
    bits = _index_bits(per_cell)
    shifts = bits * np.arange(32 // bits, dtype=np.int64)
    local = ((packed >> shifts) & ((1 << bits) - 1)).reshape(len(blocks), -1)[:, :per_cell]
    sets = (blocks[:, :1] + local).ravel()
    return words[sets], words[sets + 1]


def _blocks(words: np.ndarray, per_cell: int) -> np.ndarray:
    """The per-cell blocks (cells, _block_words(per_cell)) of ls_shaft_offsets."""
    width = _block_words(per_cell)
    cells = int(words[0]) // width if len(words) > 1 else 0  # the first block points just past the blocks
    return words[:cells * width].reshape(cells, width)


def candidate_entries(tri_words: np.ndarray, id_bits: int) -> np.ndarray:
    """The sets' cell-local candidate ids, one per entry, from the words of ls_shaft_tris
    (linespace.h LS_LOCAL_ID: 16-bit ids low half first)."""
    words = np.asarray(tri_words, np.int64)
    if id_bits == 32:
        return words
    return np.stack([words & 0xFFFF, words >> 16], axis=1).ravel()


def shaft_lists(offset_words: np.ndarray, tri_words: np.ndarray, per_cell: int, id_bits: int,
                cell_begins: np.ndarray, cell_tris: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The lists expanded to one per shaft: (CSR offsets, shafts + 1 entries; the triangle ids).
    Line Space c's ids index its cell's plain list, cell_tris from cell_begins[c] (as
    test_candidates in trace.h reads them)."""
    begin, end = shaft_ranges(offset_words, per_cell)
    counts = end - begin
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    where = np.repeat(begin - offsets[:-1], counts) + np.arange(int(offsets[-1]))
    local = candidate_entries(tri_words, id_bits)[where]
    cell = np.repeat(np.arange(len(counts)) // per_cell, counts)
    return offsets, np.asarray(cell_tris, np.int64)[np.asarray(cell_begins, np.int64)[cell] + local]


def cell_set_sizes(offset_words: np.ndarray, per_cell: int) -> tuple[np.ndarray, np.ndarray]:
    """(distinct sets, their candidate ids) of each Line Space, from ls_shaft_offsets."""
    words = np.asarray(offset_words, np.int64)
    first = np.append(_blocks(words, per_cell)[:, 0], len(words) - 1)  # the last offset ends the last set
    return np.diff(first), np.diff(words[first])
