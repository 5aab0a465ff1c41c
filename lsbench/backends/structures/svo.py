"""`svo`: sparse voxel octree with a node pool of 8 child indices per node, leaves only on the
last level, a candidate list per leaf, stack traversal (Delgado Krämer 2019, 3.3.2, Algorithm 1).
Kernels: shaders/common/octree.h (the build shared with `esvo`, the leaf handling) and svo.h
(the node-pool nodes and their traversal), on scene.h and trace.h.

The build (shared with `esvo`, see `build_octree`) runs on the device from the voxel lists of
`grid` (same conservative voxelization):

1. flag: a bit pyramid, one bit per cell and level. The leaf level gets "voxel non-empty", each
   level above "some child flagged" (the thesis' flagging step, level by level up to the root;
   one work item per 32 cells, no atomics).
2. count: popcount per word, exclusive prefix sum. The rank of a flagged bit is its node id
   (levels in order, root = 0, Morton order inside a level), so the node and leaf counts of
   every level are known before anything is allocated: the node buffers are allocated at
   exactly their size (thesis 5.3 allocated the worst case: 3.25 GB for 7 MB of nodes).
   The thesis (3.3.2) hands out child blocks with an atomic counter; the prefix sum gives the
   same sizes and contiguous child blocks, but in a layout that does not depend on thread
   timing (Listing 2 computes the same offsets serially, one thread per level).
3. create: every internal node writes its children (svo: 8 uints; esvo: one descriptor), one
   work item per cell of the internal levels.
4. link leaves: one work item per cell of the leaf level; every leaf gets (first, count) of its voxel's candidates in voxel_tris; the
   dense voxel_offsets (4 bytes per voxel) is released after the build.

The octree covers its bounding cube (R = 2^L voxels per edge), but the voxel lists cover only the
scene's box in the cube's voxels (GridGeometry.over_bounds, cubic): the cube's cells outside the box
are empty without being voxelized, and no buffer but the bit pyramid spans the cube.

Temporary buffers: the voxel lists' dense offsets (4 bytes per voxel of the box), the pyramid and
its ranks, R^3/32 * 8/7 words each (1 bit per voxel of the cube).
"""
from __future__ import annotations

import numpy as np

from ..device import Device, DeviceBuffer, DeviceLimitError
from ..kernels import GRID_UNIFORMS, Buf, KernelSpec, Uniform, trace_spec
from .base import BuildParams, BuildResult, GridGeometry
from . import grid

BUILD_HEADERS = ("geometry.h", "octree.h")  # build kernels bind no scene buffers
OCT_UNIFORMS = GRID_UNIFORMS + (Uniform("oct_depth", "uint"), Uniform("oct_level", "uint"))
MAX_DEPTH = 10  # Morton codes of 3 * depth bits must fit a uint

_LW = Buf("level_words", "uint", "r")
FLAG_LEAVES = KernelSpec("oct_flag_leaves", BUILD_HEADERS, "oct_flag_leaves_kernel",
                         (Buf("voxel_offsets", "uint", "r"), _LW, Buf("oct_bits", "uint", "rw")), OCT_UNIFORMS)
FLAG_UP = KernelSpec("oct_flag_up", BUILD_HEADERS, "oct_flag_up_kernel",
                     (_LW, Buf("oct_bits", "uint", "rw")), OCT_UNIFORMS)
POPCOUNT = KernelSpec("oct_popcount", BUILD_HEADERS, "oct_popcount_kernel",
                      (Buf("oct_bits", "uint", "r"), Buf("oct_counts", "uint", "w")), OCT_UNIFORMS)
LEVEL_COUNTS = KernelSpec("oct_level_counts", BUILD_HEADERS, "oct_level_counts_kernel",
                          (_LW, Buf("oct_ranks", "uint", "r"), Buf("oct_level_counts", "uint", "w")),
                          OCT_UNIFORMS)
LINK_LEAVES = KernelSpec("oct_leaves", BUILD_HEADERS, "oct_leaves_kernel",
                         (_LW, Buf("oct_bits", "uint", "r"), Buf("oct_ranks", "uint", "r"),
                          Buf("voxel_offsets", "uint", "r"), Buf("leaves", "uint", "w")), OCT_UNIFORMS)


def create_spec(layout: str) -> KernelSpec:
    """Build step 3 in a layout: <layout>_create_kernel of shaders/common/<layout>.h."""
    return KernelSpec(f"{layout}_create", BUILD_HEADERS + (f"{layout}.h",), f"{layout}_create_kernel",
                      (_LW, Buf("oct_bits", "uint", "r"), Buf("oct_ranks", "uint", "r"),
                       Buf(f"{layout}_nodes", "uint", "w")), OCT_UNIFORMS)


CREATE_SVO = create_spec("svo")
CREATE_ESVO = create_spec("esvo")  # 32-bit descriptors of `esvo` (esvo.py, esvo.h)

# What every octree traversal reads: its nodes, then the leaves and their candidate lists.
LEAF_LISTS = (Buf("leaves", "uint2", "t"), Buf("voxel_tris", "uint", "t"))
TRACE_SVO = trace_spec("trace_svo", ("octree.h", "svo.h"), "trace_svo_kernel",
                       (Buf("svo_nodes", "uint", "t"),) + LEAF_LISTS, GRID_UNIFORMS)

# Per layout: nodes buffer name, bytes per internal node, create kernel.
LAYOUTS = {"svo": ("svo_nodes", 32, CREATE_SVO), "esvo": ("esvo_nodes", 4, CREATE_ESVO)}

ESVO_POINTER_LIMIT = 2 ** 24  # 24-bit child pointer of the esvo descriptor (Listing 2)


def octree_depth(resolution) -> int:
    """L for a cubic power-of-two resolution (R, R, R) = (2^L, ...); ValueError otherwise."""
    res = tuple(int(r) for r in resolution)
    r = res[0]
    if len(res) != 3 or not res[0] == res[1] == res[2]:
        raise ValueError(f"octrees need a cubic resolution (R, R, R), got {'x'.join(map(str, res))}")
    if r < 2 or r & (r - 1):
        raise ValueError(f"octree resolution must be a power of two >= 2, got {r}")
    depth = r.bit_length() - 1
    if depth > MAX_DEPTH:
        raise ValueError(f"octree resolution {r} is over the supported 2^{MAX_DEPTH} "
                         "(32-bit Morton codes)")
    return depth


def level_words(depth: int) -> np.ndarray:
    """First word of each level in the bit pyramid (depth + 2 entries, the last is the total)."""
    words = [max(1, 8 ** level // 32) for level in range(depth + 1)]
    return np.concatenate([[0], np.cumsum(words)]).astype(np.uint32)


def predicted_bytes(layout: str, nodes: int, leaves: int, references: int) -> dict[str, int]:
    """The bytes of each buffer build_octree returns for `layout`, from the non-empty cells per
    level (nodes: levels 0..depth-1, leaves: the last level) and the leaf level's references
    (lsbench/model/bytes.py): exact, as allocated below."""
    nodes_name, node_bytes, _ = LAYOUTS[layout]
    return {nodes_name: node_bytes * max(nodes, 1), "leaves": 8 * max(leaves, 1),
            "voxel_tris": max(4 * references, 4)}


def prepare(device: Device) -> None:
    """Compile the build kernels (the trace kernel depends on the depth and compiles on its
    first launch, before any timed one)."""
    grid.prepare(device)
    for spec in (FLAG_LEAVES, FLAG_UP, POPCOUNT, LEVEL_COUNTS, LINK_LEAVES, CREATE_SVO):
        device.compile(spec)


def build_octree(device: Device, scene_buffers: dict, n_tris: int, geometry: GridGeometry,
                 layout: str, leaf_hook=None) -> tuple[dict[str, DeviceBuffer], dict]:
    """Voxel lists -> bit pyramid -> ranks -> nodes + leaves (module docstring). Returns the
    structure's buffers (nodes, leaves, voxel_tris) and stats.

    leaf_hook(pyramid, leaves, n_leaves): called once the leaves are linked, while the bit
    pyramid still exists (pyramid: dict with the level_words, oct_bits and oct_ranks buffers,
    the build's uniforms and leaf_cells, the work items of a kernel per leaf-level cell);
    svo-ls / esvo-ls find their leaves' voxels there (octree_ls.py)."""
    depth = octree_depth((geometry.cube,) * 3)
    nodes_name, node_bytes, create = LAYOUTS[layout]
    vox, vstats = grid.build_voxel_lists(device, scene_buffers, n_tris, geometry)
    offsets, tris = vox["voxel_offsets"], vox["voxel_tris"]
    temps = [offsets]  # released at the end, whatever happens
    made: list[DeviceBuffer] = []  # released only if the build fails
    try:
        lw = level_words(depth)
        total_words = int(lw[-1])
        uniforms = dict(geometry.uniforms(), oct_depth=depth, oct_level=0)
        lw_buf = device.upload("level_words", lw)
        temps.append(lw_buf)
        bits = device.alloc("oct_bits", 4 * total_words, zero=False)  # every word is written
        temps.append(bits)
        # 1. flag: leaf level from the voxel lists, then each level from the one below.
        device.dispatch(FLAG_LEAVES, int(lw[depth + 1] - lw[depth]),
                        {"voxel_offsets": offsets, "level_words": lw_buf, "oct_bits": bits}, uniforms)
        for level in range(depth - 1, -1, -1):
            device.dispatch(FLAG_UP, int(lw[level + 1] - lw[level]), {"level_words": lw_buf, "oct_bits": bits},
                            dict(uniforms, oct_level=level))
        # 2. count: ranks of the flagged bits, and the rank at each level's start.
        counts = device.alloc("oct_counts", 4 * total_words, zero=False)
        temps.append(counts)
        device.dispatch(POPCOUNT, total_words, {"oct_bits": bits, "oct_counts": counts}, uniforms)
        ranks, _ = device.exclusive_scan(counts, total_words, "oct_ranks")
        temps.append(ranks)
        temps.remove(counts)
        device.release(counts)
        starts_buf = device.alloc("oct_level_counts", 4 * (depth + 2), zero=False)
        temps.append(starts_buf)
        device.dispatch(LEVEL_COUNTS, depth + 2,
                        {"level_words": lw_buf, "oct_ranks": ranks, "oct_level_counts": starts_buf}, uniforms)
        starts = device.read(starts_buf, np.uint32, depth + 2).astype(np.int64)
        per_level = np.diff(starts)  # nodes on levels 0..depth-1, leaves on level depth
        n_nodes, n_leaves = int(starts[depth]), int(per_level[depth])
        if layout == "esvo":
            for what, n in (("internal nodes", n_nodes), ("leaves", n_leaves)):
                if n > ESVO_POINTER_LIMIT:
                    raise DeviceLimitError(
                        f"esvo: {n} {what} at {geometry.cube}^3 overflow the 24-bit child "
                        f"pointer of the 32-bit descriptor (limit {ESVO_POINTER_LIMIT}, thesis Listing 2)")
        # 3. create nodes and 4. link leaves, into buffers of exactly the counted size.
        nodes = device.alloc(nodes_name, node_bytes * max(n_nodes, 1))  # zero: an empty scene's root
        made.append(nodes)
        nodes.used_bytes = node_bytes * n_nodes
        leaves = device.alloc("leaves", 8 * max(n_leaves, 1), zero=False)
        made.append(leaves)
        leaves.used_bytes = 8 * n_leaves
        # One work item per pyramid bit (cell) of levels 0..depth-1, then of the leaf level.
        device.dispatch(create, 32 * int(lw[depth]),
                        {"level_words": lw_buf, "oct_bits": bits, "oct_ranks": ranks, nodes_name: nodes},
                        uniforms)
        leaf_cells = 32 * int(lw[depth + 1] - lw[depth])
        device.dispatch(LINK_LEAVES, leaf_cells,
                        {"level_words": lw_buf, "oct_bits": bits, "oct_ranks": ranks,
                         "voxel_offsets": offsets, "leaves": leaves}, uniforms)
        if leaf_hook is not None:
            leaf_hook({"level_words": lw_buf, "oct_bits": bits, "oct_ranks": ranks, "uniforms": uniforms,
                       "leaf_cells": leaf_cells}, leaves, n_leaves)
        device.finish()
    except BaseException:
        for b in made + [tris]:
            device.release(b)
        raise
    finally:
        temp_bytes = sum(b.nbytes for b in temps)
        for b in temps:
            device.release(b)
    tris.used_bytes = 4 * vstats["references"]
    voxels = geometry.voxel_count
    stats = dict(vstats)
    stats.update({
        "depth": depth,
        "nodes_per_level": [int(n) for n in per_level[:depth]],
        "nodes": n_nodes,
        "leaves": n_leaves,
        "empty_fraction": 1.0 - n_leaves / voxels,  # of the scene's box (the cube's rest is empty)
        "cube_voxels": geometry.cube ** 3,
        "temp_bytes": int(temp_bytes),
    })
    return {nodes_name: nodes, "leaves": leaves, "voxel_tris": tris}, stats


def walk(spec: KernelSpec, depth: int, device: Device) -> KernelSpec:
    """An octree walk's trace kernel (svo, esvo and their Line Space twins) for a tree of `depth`
    levels on `device`: where it runs work items in SIMD lanes (Device.serial_work_items false:
    llvmpipe, GPUs) the walk's stack is read and written through selects (octree.h:
    OCT_SELECT_STACK), which PoCL indexes as memory."""
    spec = spec.with_defines(OCT_DEPTH=depth)
    return spec if device.serial_work_items else spec.with_defines(OCT_SELECT_STACK=1)


def build(device: Device, scene_buffers: dict, n_tris: int, geometry: GridGeometry,
          params: BuildParams) -> BuildResult:
    octree_depth(params.resolution)  # ValueError before any work
    buffers, stats = build_octree(device, scene_buffers, n_tris, geometry, "svo")
    spec = walk(TRACE_SVO, stats["depth"], device)
    return BuildResult(buffers, geometry.uniforms(), spec, stats)
