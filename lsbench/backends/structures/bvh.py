"""`bvh`: a binary bounding volume hierarchy built on the device, the structure a renderer would
pick instead of the grids and octrees (the thesis' Fig. 4c baseline). Kernels: shaders/common/bvh.h
on scene.h and trace.h. All steps run on the device, written once for both backends:

1-3. The binary hierarchy, one of two (options["bvh_hierarchy"], HIERARCHIES), each a tree over
   ranges of a permutation of the triangle ids (voxel_tris: every leaf is a range of it), its inner
   nodes named as Karras 2012 names them:
   - "binned" (the default): a top-down binned SAH tree (Wald 2007; bvh.h: bvh_sah_*,
     binned_hierarchy below). Nodes of at least SAH_LARGE triangles split a level per round, a work
     item per triangle and per node: centroid bounds and 32 bins per axis by atomics, the boundary
     of least SA(L) n_L + SA(R) n_R, the sides, Device's exclusive scan of them and a stable
     partition; each smaller node is built whole by one work item (16 bins). Against the Morton
     tree, with the same quality pass after it (PoCL, Sponza 256², docs/profiles.md section 22):
     SAH cost 83 against 94, node visits per incoherent ray 7.0 against 8.6, 0.74 of the trace's
     device time on incoherent rays, 0.91 on primary rays; bvh-ls 0.82 and 0.61. The build takes
     0.4-0.7 s where the Morton tree's took 0.2 (BMW 1.2-1.7 s against 0.5; llvmpipe about twice
     the Morton build's time).
   - "morton": 1. Morton codes: a 30-bit code per triangle centroid over the scene bounds (10
     bits per axis). 2. Sort: an LSD radix sort of (code, triangle id), 5 bits per pass, 6 passes;
     each pass is a per-chunk digit count, Device.exclusive_scan of the digit-major counts, and a
     stable scatter (bvh.h). 3. Hierarchy: Karras 2012 (a binary radix tree over the sorted codes,
     one work item per inner node, equal codes ordered by position).
4. Box fit, bottom up with an atomic arrival counter per node (Karras 2012, 4); in the same pass
   the surface-area heuristic decides which subtrees of at most `leaf_size` triangles become
   leaves (bvh.h: bvh_fit_kernel).
5. Quality pass: TREELET_ROUNDS rounds of treelet restructuring (Karras & Aila 2013; treelets of
   5 leaves, bottom up with the same arrival counters; bvh.h: bvh_restructure_kernel, one climb
   per primitive, where work items run one after the other; bvh_restructure_wave_kernel, waves of
   the nodes whose subtrees are done, where they run in SIMD lanes: the same trees, BMW bvh glsl
   build 8.1 -> 2.3 s).
   The SAH cost of the tree after each stage is in the stats: `sah_cost_plain` (the plain LBVH:
   every node of at most leaf_size triangles a leaf), `sah_cost_collapse` (SAH leaves) and
   `sah_cost` (as built), so every build measures the gain; the device time of each kernel is in
   `build_kernel_seconds` (OpenCL). Sponza's Morton tree (262k triangles, leaf size 8, PoCL on 2
   shared cores): SAH cost 177 -> 164 -> 102, binary node visits per primary ray 141 -> 69, about +40 % rays/s,
   for 0.34 s of restructuring (6 rounds; 3 rounds: SAH 107 in 0.15 s). options["bvh_quality"]
   (QUALITIES) stops after a stage.
6. Compaction: the inner nodes that stay nodes are flagged (not collapsed into a leaf), those at
   a depth that the levels per wide node divide head the wide nodes (4-wide: every odd level is
   dropped, a node takes its children's children; 8-wide: two levels of three), which are scanned
   and written in one of the layouts of bvh.h into buffers of exactly that size. Sponza: 4-wide
   nodes take 40 node visits per primary ray where the binary nodes (64 bytes, Aila & Laine 2009)
   took 74, +28 % rays/s on PoCL. The layout (options["bvh_nodes"], NODE_LAYOUTS; "auto" by the
   device):
   - "float8", 256 bytes per node (two float records side by side, slots 0..3 and 4..7): bvh's
     layout where work items run one after the other (PoCL). 8-wide nodes take 8.6 node visits per
     incoherent ray where 4-wide ones took 13.7 (Sponza 512², 4.0 slots used per node of 8 against
     3.0 of 4): 0.91 of the trace's device time on incoherent rays, 0.97 on primary rays (medians
     of 11 alternated launches in one process, hits identical), +15 % node bytes (28.8 MiB in all
     against 25.1). Filling the nodes greedily instead (opening the kept child of largest area
     until 8 slots, top down in waves) gave 4.3 slots per node and no further gain (0.89 against
     0.93, not resolved), so the levels stay (docs/profiles.md, section 19);
   - "float", 128 bytes per node (all four children's boxes side by side in bvh_nodes, 96 bytes;
     refs and leaf counts in bvh_links, 32): bvh-ls's layout there (8-wide gained it 0.98-0.99);
   - "quantized", 64 bytes per node (bvh_qnodes: the boxes in 8 bits per plane on power-of-two
     steps of the node's own box, conservative in float32): where work items run in SIMD lanes
     (llvmpipe, GPUs). llvmpipe loads every lane's value on its own (docs/profiles.md, section 10),
     so half the loads per visit: 0.85-0.90 of the device time there (Sponza and BMW 256²,
     primary and incoherent rays); PoCL's scalar walk pays for the decoding instead (1.13 on Sponza
     incoherent rays) and keeps float boxes (docs/profiles.md, section 14).
7. Records (bvh only): the triangles' records (trace.h, 48 bytes each) gathered into leaf order
   (leaf_order_records), so a leaf's records are adjacent and the trace loads them by list
   position, not through the id (LIST_ORDER_RECORDS). With the walk's prefetch of what it pushes
   (bvh.h, BVH_PREFETCH_ENTRY; CPUs only), Sponza 512² on PoCL: incoherent rays 0.82 of the device
   time, primary rays 0.88 (docs/profiles.md, section 9). bvh-ls keeps the scene's records in
   triangle order: its Line Space lists hold triangle ids.

Speed (`lsbench speedtest --size 512x512`, the best setting of every structure in speedtest.toml,
Sponza from its interior camera, Embree in the same worker on the 2-core machine): one ray per work
item, bvh on PoCL read 0.55-0.58x Embree on primary rays (esvo 512³ 0.50x, grid-ls 64³ N=3 0.43x),
on llvmpipe 0.15x; tinybvh's Aila-Laine kernel on PoCL reached 0.62x on the same Sponza rays. Where
that time went and what was tried (docs/profiles.md, section 7): ~31 node visits of 4 box tests and
~6 triangle tests per primary ray in scalar work items (PoCL runs these divergent loops one work
item at a time; the float4 slab test is their only SIMD). So on such a device coherent rays go in
packets of 8 per work item (bvh.h BVH_PACKET, backends.packet_width; docs/profiles.md, section 8):
0.56 of the single-ray device time on Sponza 512² primary rays, 0.88-1.01x Embree in the speed
test; incoherent rays stay single (packets were 1.5x slower there): 0.45x on Sponza, 0.69-0.94x on
BMW. Where the driver runs work items in SIMD lanes (llvmpipe, GPUs) a node's hit slots are sorted
in registers before they are pushed (traversal below, bvh.h BVH_SORT_SLOTS): llvmpipe's stack
writes are per-lane scatters; Sponza 256² 0.54 (primary) and 0.67 (incoherent) of the device time,
bvh glsl 0.36 -> 0.61-0.64 Mrays/s on primary rays (docs/profiles.md, section 10). There rays
without locality go 16 per work item, a lane starting its next ray where its last one ended (bvh.h
BVH_REFILL, backends.refill_rays): Sponza 256² incoherent 0.86-0.93 of the device time, BMW 0.73
(docs/profiles.md, section 21). And on llvmpipe, whose lanes load their nodes one by one, coherent
closest-hit rays go in packets of 4 per lane in vec4 (the same packet code): 0.78-0.84 of the
one-ray device time on Sponza and BMW primary rays (section 26).

Temporary buffers (released after the build): binned, a second order and two per-position node
indices (4 bytes each per triangle), the sides' scan, a list of small nodes (8 bytes per
triangle) and the large nodes' lists, choices and bins (one 2.7 KiB set of bins per node of a
batch, at most one per SAH_LARGE triangles); morton, keys and ids twice (ping-pong sort), digit
counts (32 per chunk of SORT_CHUNK keys); both: children, ranges, parents, arrival counters,
collapse flags, triangle counts, two costs (4 bytes each per node or primitive) and the fitted
boxes (32 bytes per inner node).

Limits: triangle ids and leaf offsets are 31-bit (bit 31 marks a primitive during the build), so a
scene of 2^31 triangles or more fails naming it; every buffer is checked against the driver's
per-buffer limit at allocation (llvmpipe 128 MiB: 2.1 M quantized 4-wide nodes of 64 bytes, ~16 M
triangles for the binned build's list of small nodes, 8 bytes per triangle, ~30 M for the Morton
sort's buffers; a level's large nodes whose bins overflow one buffer are binned in batches); the
traversal's leaf entries address a slot as 4 * record + slot in 31 bits; leaves hold at most 255
triangles (LEAF_SIZES: the quantized layout counts them in a byte)."""
from __future__ import annotations

import dataclasses

import numpy as np

from ..device import Device, DeviceBuffer, DeviceLimitError
from ..kernels import GRID_UNIFORMS, SCENE_BUFFERS, Buf, KernelSpec, Uniform, trace_spec
from .base import BuildParams, BuildResult, GridGeometry

BVH_HEADERS = ("geometry.h", "scene.h", "bvh.h")
BVH_HEADERS_NO_SCENE = ("geometry.h", "bvh.h")  # kernels that bind no scene buffers (scene.h reads them)
BVH_UNIFORMS = GRID_UNIFORMS + (Uniform("bvh_n", "uint"), Uniform("bvh_leaf_size", "uint"),
                                Uniform("bvh_sah", "uint"), Uniform("bvh_node_count", "uint"))
SORT_UNIFORMS = BVH_UNIFORMS + (Uniform("sort_shift", "uint"), Uniform("sort_chunk", "uint"),
                                Uniform("sort_chunks", "uint"))
SORT_CHUNK = 256  # keys per work item of the sort (a loop of 256 stays far inside llvmpipe's budget)
SORT_BITS, SORT_DIGITS, MORTON_BITS = 5, 32, 30  # must match shaders/common/bvh.h
# The wide node's layouts (shaders/common/bvh.h) and their bytes per node: "float" (bvh_nodes 96
# + bvh_links 32), "float8" (the same, 8-wide: two of those records per node), "quantized"
# (bvh_qnodes); options["bvh_nodes"] picks one, "auto" by the device; NODE_WIDTHS: slots per node.
NODE_LAYOUTS = {"float8": 256, "float": 128, "quantized": 64}
NODE_WIDTHS = {"float8": 8, "float": 4, "quantized": 4}
LEAF_SIZES = (1, 2, 4, 8, 16, 32, 64, 128, 255)  # inputs/checks.py names them
# Leaves of at most 2: the SAH collapse and the treelets then give Sponza 31.3 node visits and 6.3
# triangle tests per primary ray (256², interior camera) where at most 8 gave 34.4 and 7.6 (the
# treelets settle on a better tree: SAH cost 94 vs 102), and the trace 9 % less device time on PoCL
# (median of 25 alternated launches of both builds in one process, Sponza 512² primary; incoherent
# rays 5 %); atrium and spheres test fewer triangles too. 23 % more nodes (11.2 MiB vs 9.1).
DEFAULT_LEAF_SIZE = 2
# The quality pass (options["bvh_quality"]): "none" (the plain LBVH: every subtree of at most
# leaf_size triangles one leaf), "sah" (the SAH decides those leaves), "treelet" (that, then
# TREELET_ROUNDS rounds of treelet restructuring, Karras & Aila 2013; bvh's default),
# "plain-treelet" (the plain leaves, then the restructuring; bvh-ls's default).
QUALITIES = ("none", "sah", "treelet", "plain-treelet")
# The binary tree those passes start from (options["bvh_hierarchy"]): "binned" (build 3 below: a
# top-down binned SAH tree, bvh.h bvh_sah_*; the default) or "morton" (builds 1-3: Morton codes,
# their radix sort and the Karras 2012 hierarchy, a linear BVH).
HIERARCHIES = ("binned", "morton")
TREELET_ROUNDS = 6
MAX_TRIANGLES = 2**31 - 1

MORTON = KernelSpec("bvh_morton", BVH_HEADERS, "bvh_morton_kernel",
                    SCENE_BUFFERS + (Buf("sort_keys", "uint", "w"), Buf("sort_ids", "uint", "w")), BVH_UNIFORMS)
SORT_COUNT = KernelSpec("bvh_sort_count", BVH_HEADERS_NO_SCENE, "bvh_sort_count_kernel",
                        (Buf("sort_keys", "uint", "r"), Buf("sort_counts", "uint", "rw")), SORT_UNIFORMS)
SORT_SCATTER = KernelSpec("bvh_sort_scatter", BVH_HEADERS_NO_SCENE, "bvh_sort_scatter_kernel",
                          (Buf("sort_keys", "uint", "r"), Buf("sort_ids", "uint", "r"), Buf("sort_counts", "uint", "rw"),
                           Buf("sorted_keys", "uint", "w"), Buf("sorted_ids", "uint", "w")), SORT_UNIFORMS)
EMIT = KernelSpec("bvh_emit", BVH_HEADERS_NO_SCENE, "bvh_emit_kernel",
                  (Buf("bvh_keys", "uint", "r"), Buf("bvh_children", "uint", "w"), Buf("bvh_ranges", "uint", "w"),
                   Buf("bvh_parents", "uint", "w")), BVH_UNIFORMS)
FIT = KernelSpec("bvh_fit", BVH_HEADERS, "bvh_fit_kernel",
                 SCENE_BUFFERS + (Buf("voxel_tris", "uint", "r"), Buf("bvh_children", "uint", "r"),
                                  Buf("bvh_ranges", "uint", "r"), Buf("bvh_parents", "uint", "r"),
                                  Buf("bvh_arrivals", "uint", "rw"), Buf("bvh_fit_boxes", "float4", "rw"),
                                  Buf("bvh_costs", "float", "rw"), Buf("bvh_collapse", "uint", "w"),
                                  Buf("bvh_counts", "uint", "rw")), BVH_UNIFORMS)
RESTRUCTURE = KernelSpec("bvh_restructure", BVH_HEADERS, "bvh_restructure_kernel",
                         SCENE_BUFFERS + (Buf("voxel_tris", "uint", "r"), Buf("bvh_children", "uint", "rw"),
                                          Buf("bvh_parents", "uint", "rw"), Buf("bvh_arrivals", "uint", "rw"),
                                          Buf("bvh_fit_boxes", "float4", "rw"), Buf("bvh_costs", "float", "rw"),
                                          Buf("bvh_counts", "uint", "rw"), Buf("bvh_cut", "uint", "rw")), BVH_UNIFORMS)
RESTRUCTURE_WAVE = KernelSpec("bvh_restructure_wave", BVH_HEADERS, "bvh_restructure_wave_kernel",
                              RESTRUCTURE.buffers + (Buf("bvh_wave_in", "uint", "r"), Buf("bvh_wave_out", "uint", "w"),
                                                     Buf("bvh_wave_count", "uint", "rw")), BVH_UNIFORMS)
WAVE_START = KernelSpec("bvh_wave_start", BVH_HEADERS_NO_SCENE, "bvh_wave_start_kernel",
                        (Buf("bvh_parents", "uint", "r"), Buf("bvh_arrivals", "uint", "rw"), Buf("bvh_wave_out", "uint", "w"),
                         Buf("bvh_wave_count", "uint", "rw")), BVH_UNIFORMS)
KEEP = KernelSpec("bvh_keep", BVH_HEADERS_NO_SCENE, "bvh_keep_kernel",
                  (Buf("bvh_counts", "uint", "r"), Buf("bvh_parents", "uint", "r"), Buf("bvh_collapse", "uint", "r"),
                   Buf("bvh_keep", "uint", "w")), BVH_UNIFORMS)
WIDE_FLAGS = KernelSpec("bvh_wide_flags", BVH_HEADERS_NO_SCENE, "bvh_wide_flags_kernel",
                        (Buf("bvh_keep", "uint", "r"), Buf("bvh_parents", "uint", "r"),
                         Buf("bvh_wide_flags", "uint", "w"), Buf("bvh_depth", "uint", "rw")), BVH_UNIFORMS)
WRITE = KernelSpec("bvh_write", BVH_HEADERS, "bvh_write_kernel",
                   SCENE_BUFFERS + (Buf("voxel_tris", "uint", "r"), Buf("bvh_children", "uint", "r"),
                                    Buf("bvh_ranges", "uint", "r"), Buf("bvh_keep", "uint", "r"),
                                    Buf("bvh_ids", "uint", "r"), Buf("bvh_fit_boxes", "float4", "r"),
                                    Buf("bvh_nodes", "float4", "w"), Buf("bvh_links", "uint4", "w")), BVH_UNIFORMS)
# Build 3, the binned SAH hierarchy (bvh.h: bvh_sah_*; HIERARCHIES "binned").
SAH_UNIFORMS = BVH_UNIFORMS + (Uniform("sah_node_base", "uint"), Uniform("sah_node_count", "uint"))
SAH_LARGE = 64  # nodes of at least this many triangles split level by level; must match bvh.h BVH_SAH_LARGE
SAH_BIN_BYTES = 3 * 32 * 7 * 4  # a large node's bins: 3 axes, BVH_SAH_BINS, BVH_SAH_BIN_WORDS uints
SAH_CENTROIDS = KernelSpec("bvh_sah_centroids", BVH_HEADERS, "bvh_sah_centroids_kernel",
                           SCENE_BUFFERS + (Buf("voxel_tris", "uint", "r"), Buf("sah_pos_node", "uint", "r"),
                                            Buf("sah_cbounds", "uint", "rw")), SAH_UNIFORMS)
SAH_BIN = KernelSpec("bvh_sah_bin", BVH_HEADERS, "bvh_sah_bin_kernel",
                     SCENE_BUFFERS + (Buf("voxel_tris", "uint", "r"), Buf("sah_pos_node", "uint", "r"),
                                      Buf("sah_cbounds", "uint", "r"), Buf("sah_bins", "uint", "rw")), SAH_UNIFORMS)
SAH_CHOOSE = KernelSpec("bvh_sah_choose", BVH_HEADERS_NO_SCENE, "bvh_sah_choose_kernel",
                        (Buf("sah_cbounds", "uint", "r"), Buf("sah_bins", "uint", "r"), Buf("sah_split", "uint4", "rw")),
                        SAH_UNIFORMS)
SAH_FLAGS = KernelSpec("bvh_sah_flags", BVH_HEADERS, "bvh_sah_flags_kernel",
                       SCENE_BUFFERS + (Buf("voxel_tris", "uint", "r"), Buf("sah_pos_node", "uint", "r"),
                                        Buf("sah_split", "uint4", "r"), Buf("sah_scan", "uint", "w")), SAH_UNIFORMS)
SAH_EMIT = KernelSpec("bvh_sah_emit", BVH_HEADERS_NO_SCENE, "bvh_sah_emit_kernel",
                      (Buf("sah_active", "uint4", "r"), Buf("sah_split", "uint4", "rw"), Buf("sah_scan", "uint", "r"),
                       Buf("sah_next", "uint4", "w"), Buf("sah_small", "uint4", "w"), Buf("sah_counts", "uint", "rw"),
                       Buf("sah_root", "uint", "rw"), Buf("bvh_children", "uint", "rw"), Buf("bvh_ranges", "uint", "w"),
                       Buf("bvh_parents", "uint", "w")), SAH_UNIFORMS)
SAH_PARTITION = KernelSpec("bvh_sah_partition", BVH_HEADERS_NO_SCENE, "bvh_sah_partition_kernel",
                           (Buf("voxel_tris", "uint", "r"), Buf("sah_pos_node", "uint", "r"), Buf("sah_active", "uint4", "r"),
                            Buf("sah_split", "uint4", "r"), Buf("sah_scan", "uint", "r"),
                            Buf("sah_order_out", "uint", "w"), Buf("sah_pos_node_out", "uint", "w")), SAH_UNIFORMS)
SAH_SMALL = KernelSpec("bvh_sah_small", BVH_HEADERS, "bvh_sah_small_kernel",
                       SCENE_BUFFERS + (Buf("voxel_tris", "uint", "rw"), Buf("sah_small", "uint4", "r"),
                                        Buf("sah_root", "uint", "rw"), Buf("bvh_children", "uint", "rw"),
                                        Buf("bvh_ranges", "uint", "w"), Buf("bvh_parents", "uint", "w"),
                                        Buf("bvh_cut", "uint", "rw")), SAH_UNIFORMS)
SAH_SPECS = (SAH_CENTROIDS, SAH_BIN, SAH_CHOOSE, SAH_FLAGS, SAH_EMIT, SAH_PARTITION, SAH_SMALL)
RECORDS = KernelSpec("bvh_records", BVH_HEADERS_NO_SCENE, "bvh_records_kernel",
                     (Buf("voxel_tris", "uint", "r"), Buf("tri_verts", "float4", "r"),
                      Buf("bvh_records", "float4", "w")), ())
BUILD_SPECS = (MORTON, SORT_COUNT, SORT_SCATTER, EMIT, FIT, RESTRUCTURE, WAVE_START, RESTRUCTURE_WAVE, KEEP, WIDE_FLAGS,
               WRITE, RECORDS) + SAH_SPECS

BVH_TRACE_BUFFERS = (Buf("bvh_nodes", "float4", "t"), Buf("bvh_links", "uint4", "t"), Buf("voxel_tris", "uint", "t"))
FLOAT_NODE_BUFFERS = ("bvh_nodes", "bvh_links")
# bvh reads its triangle records in leaf order (build step 7; trace.h LIST_ORDER_RECORDS); bvh-ls
# keeps the scene's, in triangle order, because its Line Space lists hold triangle ids.
TRACE_BVH = trace_spec("trace_bvh", ("bvh.h",), "trace_bvh_kernel", BVH_TRACE_BUFFERS,
                       GRID_UNIFORMS).with_defines(LIST_ORDER_RECORDS=1)
RECORD_BYTES = 48  # a triangle's record: 3 float4 (trace.h, tri_verts)


def node_layout(device: Device, options: dict, serial_auto: str = "float8") -> str:
    """The node layout of options["bvh_nodes"]: one of NODE_LAYOUTS, or "auto" (the default):
    quantized where the device runs work items in SIMD lanes (Device.serial_work_items false),
    else `serial_auto`."""
    value = options.get("bvh_nodes", "auto")
    if value == "auto":
        return serial_auto if device.serial_work_items else "quantized"
    if value not in NODE_LAYOUTS:
        raise ValueError(f"bvh_nodes must be one of auto, {', '.join(NODE_LAYOUTS)}, got {value!r}")
    return value


def with_node_layout(spec: KernelSpec, layout: str) -> KernelSpec:
    """A kernel written against the float layout's buffers (bvh_nodes, bvh_links), in `layout`:
    for "float8", BVH_NODE_RECORDS 2 defined; for "quantized", bvh_qnodes bound in their place and
    BVH_QUANTIZED defined."""
    if layout == "float":
        return spec
    if layout == "float8":
        return spec.with_defines(BVH_NODE_RECORDS=2)
    access = next(b.access for b in spec.buffers if b.name in FLOAT_NODE_BUFFERS)
    buffers, placed = [], False
    for b in spec.buffers:
        if b.name in FLOAT_NODE_BUFFERS:
            if not placed:
                buffers.append(Buf("bvh_qnodes", "uint4", access))
                placed = True
        else:
            buffers.append(b)
    return dataclasses.replace(spec, buffers=tuple(buffers)).with_defines(BVH_QUANTIZED=1)


def wide_flags(width: int) -> KernelSpec:
    """Build step 7's kernel for nodes of `width` slots (bvh.h: BVH_NODE_RECORDS records of 4)."""
    return WIDE_FLAGS if width == 4 else WIDE_FLAGS.with_defines(BVH_NODE_RECORDS=width // 4)


def wide_depth(stats: dict) -> int:
    """The wide nodes on the deepest path of a built tree: one per levels dropped plus one of the
    binary depth (stats["depth"], 0 for a tree of one node)."""
    return stats["depth"] // (stats["width"] // 4 + 1) + 1


def check_leaf_size(value) -> int:
    """The most triangles per leaf; one of LEAF_SIZES (0: the default)."""
    size = int(value) or DEFAULT_LEAF_SIZE
    if size not in LEAF_SIZES:
        raise ValueError(f"leaf_size must be one of {', '.join(map(str, LEAF_SIZES))}, got {value!r}")
    return size


def _restructure_in_waves(device: Device, bufs: dict, uniforms: dict, n_tris: int, wave_a: DeviceBuffer,
                          wave_b: DeviceBuffer, count_buf: DeviceBuffer) -> None:
    """One round of treelet restructuring as waves of the nodes whose subtrees are done (bvh.h:
    bvh_restructure_wave_kernel), each wave queueing the next in the other list (n_tris entries
    each), until none is left."""
    lists = [wave_a, wave_b]
    device.fill_zero(count_buf)
    device.dispatch(WAVE_START, n_tris, dict(bufs, bvh_wave_out=lists[0], bvh_wave_count=count_buf), uniforms)
    nodes = device.read_uint(count_buf, 0)
    while nodes > 0:
        device.fill_zero(count_buf)
        device.dispatch(RESTRUCTURE_WAVE, nodes, dict(bufs, bvh_wave_in=lists[0], bvh_wave_out=lists[1],
                                                      bvh_wave_count=count_buf), uniforms)
        nodes = device.read_uint(count_buf, 0)
        lists.reverse()


def prepare(device: Device) -> None:
    for spec in BUILD_SPECS:
        device.compile(spec)
    for layout in ("float8", "quantized"):
        device.compile(with_node_layout(WRITE, layout))
    device.compile(wide_flags(NODE_WIDTHS["float8"]))


def sort_by_morton_code(device: Device, scene_buffers: dict, n_tris: int, uniforms: dict
                        ) -> tuple[DeviceBuffer, DeviceBuffer]:
    """Build steps 1-2: the Morton codes and the triangle ids sorted by them (keys, ids)."""
    keys = device.alloc("sort_keys", 4 * n_tris, zero=False)
    ids = device.alloc("sort_ids", 4 * n_tris, zero=False)
    out_keys = device.alloc("sorted_keys", 4 * n_tris, zero=False)
    out_ids = device.alloc("sorted_ids", 4 * n_tris, zero=False)
    chunks = -(-n_tris // SORT_CHUNK)
    counts = device.alloc("sort_counts", 4 * SORT_DIGITS * chunks, zero=False)
    try:
        device.dispatch(MORTON, n_tris, dict(scene_buffers, sort_keys=keys, sort_ids=ids), uniforms)
        for shift in range(0, MORTON_BITS, SORT_BITS):
            u = dict(uniforms, sort_shift=shift, sort_chunk=SORT_CHUNK, sort_chunks=chunks)
            device.dispatch(SORT_COUNT, chunks, {"sort_keys": keys, "sort_counts": counts}, u)
            device.scan_in_place(counts, SORT_DIGITS * chunks)
            device.dispatch(SORT_SCATTER, chunks, {"sort_keys": keys, "sort_ids": ids, "sort_counts": counts,
                                                   "sorted_keys": out_keys, "sorted_ids": out_ids}, u)
            keys, ids, out_keys, out_ids = out_keys, out_ids, keys, ids
    except BaseException:
        for b in (keys, ids, out_keys, out_ids, counts):
            device.release(b)
        raise
    for b in (out_keys, out_ids, counts):
        device.release(b)
    return keys, ids


def binned_hierarchy(device: Device, scene_buffers: dict, n_tris: int, uniforms: dict, tree: dict
                     ) -> tuple[DeviceBuffer, int]:
    """Build 3, "binned" (bvh.h: bvh_sah_*): the top-down binned SAH hierarchy of n_tris >= 2
    triangles into tree's bvh_children, bvh_ranges and bvh_parents (as EMIT writes them). Nodes of
    at least SAH_LARGE triangles split a level per round (centroid bounds and bins in batches that
    fit one buffer, the choice, the sides and their scan, the stable partition into the other order
    buffer); the smaller ones are then built whole, a work item each. Returns the triangle ids in
    the tree's order (voxel_tris) and the rounds."""
    n = n_tris
    order = device.upload("voxel_tris", np.arange(n, dtype=np.uint32))
    temps: list[DeviceBuffer] = [order]  # all released but the order buffer returned

    def temp(name, nbytes, zero=False):
        buf = device.alloc(name, nbytes, zero=zero)
        temps.append(buf)
        return buf

    try:
        other = temp("sah_order_out", 4 * n)
        pos, pos_out = temp("sah_pos_node", 4 * n, zero=True), temp("sah_pos_node_out", 4 * n)  # all in node 0
        most = max(1, n // SAH_LARGE)  # large nodes at one level: disjoint, of at least SAH_LARGE each
        active, following = temp("sah_active", 16 * most), temp("sah_next", 16 * most)
        small = temp("sah_small", 16 * max(1, n // 2))  # disjoint nodes of at least 2
        split = temp("sah_split", 32 * most)
        scan = temp("sah_scan", 4 * (n + 1))
        root = temp("sah_root", 4, zero=True)
        cut = temp("sah_cut", 4, zero=True)
        batch = sah_batch(device, most)
        bins, cbounds = temp("sah_bins", SAH_BIN_BYTES * batch), temp("sah_cbounds", 24 * batch)
        whole = np.array([0, n - 1, 0xFFFFFFFF, 0], np.uint32)  # the root: first, last, parent, side
        if n >= SAH_LARGE:
            device.write(active, whole)
            counts, m = device.upload("sah_counts", np.zeros(2, np.uint32)), 1
        else:
            device.write(small, whole)
            counts, m = device.upload("sah_counts", np.array([0, 1], np.uint32)), 0
        temps.append(counts)
        rounds = 0
        while m:
            device.fill_zero(counts, 4)  # the next level's count; the small list's keeps counting
            for base in range(0, m, batch):
                cnt = min(batch, m - base)
                device.fill_zero(bins, SAH_BIN_BYTES * cnt)
                device.fill_zero(cbounds, 24 * cnt)
                u = dict(uniforms, sah_node_base=base, sah_node_count=cnt)
                level = dict(scene_buffers, voxel_tris=order, sah_pos_node=pos, sah_cbounds=cbounds, sah_bins=bins)
                device.dispatch(SAH_CENTROIDS, n, level, u)
                device.dispatch(SAH_BIN, n, level, u)
                device.dispatch(SAH_CHOOSE, cnt, {"sah_cbounds": cbounds, "sah_bins": bins, "sah_split": split}, u)
            u = dict(uniforms, sah_node_base=0, sah_node_count=m)
            device.dispatch(SAH_FLAGS, n + 1, dict(scene_buffers, voxel_tris=order, sah_pos_node=pos,
                                                   sah_split=split, sah_scan=scan), u)
            device.scan_in_place(scan, n + 1)
            device.dispatch(SAH_EMIT, m, dict(tree, sah_active=active, sah_split=split, sah_scan=scan,
                                              sah_next=following, sah_small=small, sah_counts=counts, sah_root=root), u)
            device.dispatch(SAH_PARTITION, n, {"voxel_tris": order, "sah_pos_node": pos, "sah_active": active,
                                               "sah_split": split, "sah_scan": scan, "sah_order_out": other,
                                               "sah_pos_node_out": pos_out}, u)
            order, other, pos, pos_out, active, following = other, order, pos_out, pos, following, active
            m = device.read_uint(counts, 0)
            rounds += 1
        n_small = device.read_uint(counts, 1)
        if n_small:
            device.dispatch(SAH_SMALL, n_small, dict(scene_buffers, **tree, voxel_tris=order, sah_small=small,
                                                     sah_root=root, bvh_cut=cut), dict(uniforms, sah_node_base=0,
                                                                                        sah_node_count=n_small))
        if device.read_uint(cut, 0):
            raise device.loop_limit_error(f"the binned SAH build's loops (a node of fewer than {SAH_LARGE} "
                                          "triangles, built by one work item)")
    except BaseException:
        for b in temps:
            device.release(b)
        raise
    for b in temps:
        if b is not order:
            device.release(b)
    return order, rounds


def sah_batch(device: Device, most: int) -> int:
    """The large nodes binned at once: all `most` of a level where their bins fit one buffer."""
    return max(1, min(most, device.max_buffer_bytes // SAH_BIN_BYTES))


def check_hierarchy(value: str) -> str:
    if value not in HIERARCHIES:
        raise ValueError(f"bvh_hierarchy must be one of {', '.join(HIERARCHIES)}, got {value!r}")
    return value


def check_quality(value: str) -> str:
    if value not in QUALITIES:
        raise ValueError(f"bvh_quality must be one of {', '.join(QUALITIES)}, got {value!r}")
    return value


def build_bvh(device: Device, scene_buffers: dict, n_tris: int, geometry: GridGeometry, leaf_size: int,
              quality: str = "treelet", layout: str = "float", hierarchy: str = "binned"
              ) -> tuple[dict[str, DeviceBuffer], dict]:
    """Build steps 1-6 (module docstring) with nodes in `layout` (NODE_LAYOUTS). Returns the
    structure's buffers (bvh_nodes and bvh_links, or bvh_qnodes; voxel_tris) and the build's stats."""
    node_bytes = NODE_LAYOUTS[layout]
    width = NODE_WIDTHS[layout]
    records = width // 4  # 4-slot records per node
    sah = check_quality(quality) in ("sah", "treelet")
    check_hierarchy(hierarchy)
    if n_tris > MAX_TRIANGLES:
        raise DeviceLimitError(f"bvh: {n_tris} triangles overflow the 31-bit triangle and leaf indices")
    if n_tris < 1:
        raise ValueError("bvh: the scene has no triangles")
    inner = n_tris - 1
    u = dict(geometry.uniforms(), bvh_n=n_tris, bvh_leaf_size=leaf_size, bvh_sah=int(sah), bvh_node_count=0)
    # One triangle has no hierarchy to build: the Morton path's sort gives its one-entry order.
    binned = hierarchy == "binned" and inner > 0
    if binned:
        keys, tris, temps, made = None, None, [], []
    else:
        keys, tris = sort_by_morton_code(device, scene_buffers, n_tris, u)
        temps, made = [keys], [tris]
    try:
        def temp(name, nbytes, zero=False):
            buf = device.alloc(name, nbytes, zero=zero)
            temps.append(buf)
            return buf

        children = temp("bvh_children", 8 * inner)
        ranges = temp("bvh_ranges", 8 * inner)
        parents = temp("bvh_parents", 4 * (inner + n_tris))
        stats: dict = {"triangles": n_tris, "leaf_size": leaf_size, "quality_pass": quality, "hierarchy": hierarchy}
        if binned:
            tris, stats["hierarchy_rounds"] = binned_hierarchy(
                device, scene_buffers, n_tris, u, {"bvh_children": children, "bvh_ranges": ranges, "bvh_parents": parents})
            made.append(tris)
        boxes = temp("bvh_fit_boxes", 32 * inner)
        costs = temp("bvh_costs", 8 * inner)
        collapse = temp("bvh_collapse", 4 * inner)
        fit_bufs = dict(scene_buffers, voxel_tris=tris, bvh_children=children, bvh_ranges=ranges,
                        bvh_parents=parents, bvh_fit_boxes=boxes, bvh_costs=costs, bvh_collapse=collapse)
        counts = temp("bvh_counts", 4 * inner)
        fit_bufs["bvh_counts"] = counts
        if inner > 0:
            if not binned:
                device.dispatch(EMIT, inner, {"bvh_keys": keys, "bvh_children": children, "bvh_ranges": ranges,
                                              "bvh_parents": parents}, u)
                temps.remove(keys)
                device.release(keys)
            arrivals = temp("bvh_arrivals", 4 * inner, zero=True)
            device.dispatch(FIT, n_tris, dict(fit_bufs, bvh_arrivals=arrivals), u)
            root = device.read(boxes, np.float32, 8)
            root_area = _area(root[:3], root[4:7])
            cost, plain = (float(c) / root_area if root_area > 0 else 0.0 for c in device.read(costs, np.float32, 2))
            stats.update(sah_cost=cost, sah_cost_plain=plain, sah_cost_collapse=cost)
            if quality in ("treelet", "plain-treelet"):
                cut = temp("bvh_cut", 4, zero=True)
                bufs = dict(fit_bufs, bvh_arrivals=arrivals, bvh_cut=cut)
                # one climb per primitive where work items run one after the other (bvh.h:
                # bvh_restructure_kernel), else waves of the nodes ready to restructure
                # (bvh_restructure_wave_kernel)
                waves = None if device.serial_work_items else (
                    temp("bvh_wave_a", 4 * n_tris), temp("bvh_wave_b", 4 * n_tris), temp("bvh_wave_count", 4))
                for _ in range(TREELET_ROUNDS):
                    device.fill_zero(arrivals)
                    if waves is None:
                        device.dispatch(RESTRUCTURE, n_tris, bufs, u)
                    else:
                        _restructure_in_waves(device, bufs, u, n_tris, *waves)
                if device.read_uint(cut, 0):
                    why = "a tree too deep to climb" if waves is None else "a treelet's restructuring in a wave"
                    raise device.loop_limit_error(f"the treelet restructuring's loops ({why})")
                stats["sah_cost"] = float(device.read(costs, np.float32, 1)[0]) / root_area if root_area > 0 else 0.0
            keep = temp("bvh_keep", 4 * inner)
            device.dispatch(KEEP, inner, {"bvh_counts": counts, "bvh_parents": parents, "bvh_collapse": collapse,
                                          "bvh_keep": keep}, u)
            kept_scan, n_binary = device.exclusive_scan(keep, inner, "bvh_kept")
            device.release(kept_scan)
            wide = temp("bvh_wide_flags", 4 * inner)
            depth_buf = device.upload("bvh_depth", np.array([0xFFFFFFFF], np.uint32))  # ~0: depth 0
            temps.append(depth_buf)
            device.dispatch(wide_flags(width), inner,
                            {"bvh_keep": keep, "bvh_parents": parents, "bvh_wide_flags": wide,
                             "bvh_depth": depth_buf}, u)
            stats["depth"] = int(~np.uint32(device.read_uint(depth_buf, 0)) & 0xFFFFFFFF)
            ids, n_nodes = device.exclusive_scan(wide, inner, "bvh_ids")
            temps.append(ids)
        else:
            stats["sah_cost"] = stats["sah_cost_plain"] = stats["sah_cost_collapse"] = 0.0
            ids, n_nodes, n_binary, stats["depth"] = temp("bvh_ids", 4, zero=True), 0, 0, 0
            keep = temp("bvh_keep", 4, zero=True)
        if width * n_nodes >= 2**31:
            raise DeviceLimitError(f"bvh: {n_nodes} nodes overflow the traversal's 31-bit leaf entries "
                                   "(4 * record + slot)")
        if layout != "quantized":
            node_bufs = {"bvh_nodes": device.alloc("bvh_nodes", 96 * records * max(n_nodes, 1), zero=False)}
            made.append(node_bufs["bvh_nodes"])
            node_bufs["bvh_links"] = device.alloc("bvh_links", 32 * records * max(n_nodes, 1), zero=False)
            made.append(node_bufs["bvh_links"])
        else:
            node_bufs = {"bvh_qnodes": device.alloc("bvh_qnodes", node_bytes * max(n_nodes, 1), zero=False)}
            made.append(node_bufs["bvh_qnodes"])
        device.dispatch(with_node_layout(WRITE, layout), max(inner, 1) if n_nodes else 1,
                        dict(scene_buffers, voxel_tris=tris, bvh_children=children, bvh_ranges=ranges, bvh_keep=keep,
                             bvh_ids=ids, bvh_fit_boxes=boxes, **node_bufs),
                        dict(u, bvh_node_count=n_nodes))
        device.finish()
    except BaseException:
        for b in made:
            device.release(b)
        raise
    finally:
        temp_bytes = sum(b.nbytes for b in temps)
        for b in temps:
            device.release(b)
    stats.update({"nodes": max(n_nodes, 1), "binary_nodes": n_binary, "leaves": n_binary + 1,
                  "references": n_tris, "node_layout": layout, "node_bytes": node_bytes, "width": width,
                  "temp_bytes": int(temp_bytes)})
    return {**node_bufs, "voxel_tris": tris}, stats


def _area(lo, hi) -> float:
    e = np.maximum(np.asarray(hi, np.float64) - np.asarray(lo, np.float64), 0.0)
    return float(2.0 * (e[0] * e[1] + e[1] * e[2] + e[2] * e[0]))


def build(device: Device, scene_buffers: dict, n_tris: int, geometry: GridGeometry,
          params: BuildParams) -> BuildResult:
    leaf_size = check_leaf_size(params.leaf_size)
    buffers, stats = build_bvh(device, scene_buffers, n_tris, geometry, leaf_size,
                               quality=params.options.get("bvh_quality", "treelet"),
                               layout=node_layout(device, params.options),
                               hierarchy=params.options.get("bvh_hierarchy", "binned"))
    try:
        buffers["tri_verts"] = leaf_order_records(device, scene_buffers, buffers["voxel_tris"], n_tris)
    except BaseException:
        for b in buffers.values():
            device.release(b)
        raise
    return BuildResult(buffers, geometry.uniforms(), traversal(TRACE_BVH, stats, device, leaf_ranges=True), stats,
                       suspends=False)


def leaf_order_records(device: Device, scene_buffers: dict, voxel_tris: DeviceBuffer, n_tris: int) -> DeviceBuffer:
    """Build step 7: the scene's triangle records gathered into the order of voxel_tris, so that a
    leaf's records lie side by side and the trace loads them by list position (trace.h,
    LIST_ORDER_RECORDS). The structure's tri_verts: it takes the scene's place in the trace's
    bindings, and its bytes are the structure's."""
    records = device.alloc("tri_verts", RECORD_BYTES * n_tris, zero=False)
    try:
        device.dispatch(RECORDS, n_tris, {"voxel_tris": voxel_tris, "tri_verts": scene_buffers["tri_verts"],
                                          "bvh_records": records}, {})
    except BaseException:
        device.release(records)
        raise
    return records


def leaf_range_bits(stats: dict) -> int:
    """The bits of a leaf's triangle count in a stack entry that holds the leaf's range (bvh.h:
    BVH_LEAF_RANGE_BITS, first << bits | count, below the leaf flag): enough for the tree's leaf
    size, or 0 (the entry holds the leaf's cell) where the first triangle would not fit the 31 - bits
    left."""
    bits = int(stats["leaf_size"]).bit_length()
    return bits if stats["triangles"] < 2 ** (31 - bits) else 0


def traversal(spec: KernelSpec, stats: dict, device: Device, leaf_ranges: bool = False) -> KernelSpec:
    """The trace kernel for the built tree: its node layout (stats["node_layout"]), its stack sized
    to the tree: width - 1 entries per wide node of the deepest path plus one node's width (bvh.h:
    trace_bvh; the treelet restructuring may make a tree deeper than the Karras hierarchy's ~64
    levels). Where the driver runs work items in SIMD lanes, a node's hit slots are sorted in
    registers before they are pushed (bvh.h: BVH_SORT_SLOTS). `leaf_ranges` (bvh, whose leaves are
    only a range of voxel_tris; bvh-ls finds a leaf's Line Space by its cell): a leaf's stack entry
    holds its range where it fits (leaf_range_bits)."""
    width = stats["width"]
    stack = (width - 1) * wide_depth(stats) + width
    spec = with_node_layout(spec, stats["node_layout"]).with_defines(BVH_STACK=stack)
    bits = leaf_range_bits(stats) if leaf_ranges else 0
    if bits:
        spec = spec.with_defines(BVH_LEAF_RANGE_BITS=bits)
    return spec if device.serial_work_items else spec.with_defines(BVH_SORT_SLOTS=1)
