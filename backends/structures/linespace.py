"""Candidate-list Line Spaces for a set of cells (thesis 3.3.3, 4, 5.1), built on the device.

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
    ls.buffers -> {"ls_shaft_offsets": CSR offsets, cells * 15 N^4 + 1 entries,
                   "ls_shaft_tris": candidate ids}
    ls.stats   -> shafts, non_empty_shafts, candidate_references, ...

Shaft s of cell c has candidates ls_shaft_tris[ls_shaft_offsets[c * 15N^4 + s] .. [.. + 1]];
the traversal finds s with ls_shaft_id() of shaders/common/linespace.h (Listing 1) from the
ray's entry and exit face and patch in cell-local coordinates.

Build: (1) the shaft volumes (convex hull of the two patches) as facet planes, once per N;
(2) count: one work item per (cell, shaft) clips each of the cell's triangles against the
shaft (Sutherland-Hodgman, conservative margin LS_EPS); (3) exclusive scan; (4) fill, same test,
writing in list order. Offsets are 32-bit: any case past 2^32 - 1 candidates or shafts raises
DeviceLimitError naming the limit (thesis 6.3 saw such cases fail), never truncates.

Candidate lists past the driver's per-buffer limit (llvmpipe: 128 MiB per SSBO; PoCL: 2 GiB per
buffer) are split over up to LS_MAX_TRI_CHUNKS buffers of a power-of-two number of entries
(`ls_shaft_tris`, `ls_shaft_tris1`, ...; shaders/common/linespace.h: ls_candidate), so such a case
runs wherever the device's memory holds it; `with_tri_chunks` gives a kernel spec the extra
buffers. The offsets stay one buffer: a case whose offsets alone pass the limit still fails,
naming it.
"""
from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass, field

import numpy as np

from ..device import Device, DeviceBuffer, DeviceLimitError
from ..kernels import GRID_UNIFORMS, SCENE_BUFFERS, Buf, KernelSpec, Uniform
from .base import GridGeometry

LS_HEADERS = ("geometry.h", "scene.h", "grid.h", "linespace.h")
# Kernels that bind no scene buffers leave scene.h out (it reads vertices/faces).
LS_HEADERS_NO_SCENE = ("geometry.h", "grid.h", "linespace.h")
LS_UNIFORMS = GRID_UNIFORMS + (Uniform("ls_n", "uint"), Uniform("ls_shafts", "uint"),
                               Uniform("ls_eps", "float"))
LS_MAX_PLANES = 8  # must match shaders/common/linespace.h
# Conservative margin of the shaft planes, in cell-local units (the cell is the unit cube): covers
# float rounding of the build's world -> cell mapping and of the traversal's entry/exit points.
LS_EPS = 1e-3
UINT32_MAX = 2**32 - 1
# Most buffers one candidate list is split over. llvmpipe allows 16 storage buffers per shader:
# the svo-ls trace binds 12 with the work counters, which leaves room for 3 more.
LS_MAX_TRI_CHUNKS = 4

LS_PLANES = KernelSpec(
    "ls_planes", LS_HEADERS_NO_SCENE, "ls_planes_kernel", (Buf("ls_planes", "float4", "w"),), LS_UNIFORMS,
    defines=(("LS_PLANES_KERNEL", "1"),))
_CELL_BUFFERS = (Buf("ls_planes", "float4", "r"), Buf("ls_cell_boxes", "float4", "r"),
                 Buf("ls_cell_ranges", "uint", "r"), Buf("ls_cell_tris", "uint", "r"))
LS_COUNT = KernelSpec(
    "ls_count", LS_HEADERS, "ls_shaft_kernel",
    SCENE_BUFFERS + _CELL_BUFFERS + (Buf("ls_shaft_counts", "uint", "w"), Buf("ls_stats", "uint", "rw")),
    LS_UNIFORMS)
LS_FILL = KernelSpec(
    "ls_fill", LS_HEADERS, "ls_shaft_kernel",
    SCENE_BUFFERS + _CELL_BUFFERS + (Buf("ls_shaft_offsets", "uint", "r"), Buf("ls_shaft_tris", "uint", "w")),
    LS_UNIFORMS, defines=(("LS_FILL", "1"),))
LS_CHECK = KernelSpec(
    "ls_check", LS_HEADERS_NO_SCENE, "ls_check_kernel",
    (Buf("ls_check_offsets", "uint", "r"), Buf("ls_check_flag", "uint", "rw")), LS_UNIFORMS)

BUILD_SPECS = (LS_PLANES, LS_COUNT, LS_FILL, LS_CHECK)

# The undecided triangle/shaft pairs (the facet planes neither separate nor contain the triangle)
# get an exact test: Sutherland-Hodgman clipping against the facet planes (thesis 3.3.3) or the
# equivalent separating-axis test. Both are conservative with the same margin and give the same
# candidates up to that margin; each backend uses the one its driver runs faster: llvmpipe spends
# 10x more time on the clipper's variable-indexed polygon arrays, PoCL runs the clipper about 2x
# faster than the 57-axis SAT. Override with LSBENCH_LS_TEST=clip|sat.
EXACT_TEST = {"glsl": "sat", "opencl": "clip"}


def exact_test(device: Device) -> str:
    choice = os.environ.get("LSBENCH_LS_TEST") or EXACT_TEST.get(device.backend, "sat")
    if choice not in ("clip", "sat"):
        raise ValueError(f"LSBENCH_LS_TEST must be 'clip' or 'sat', got {choice!r}")
    return choice


def _with_test(device: Device, spec: KernelSpec) -> KernelSpec:
    return spec.with_defines(LS_CLIP_SH=1) if exact_test(device) == "clip" else spec


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


@dataclass
class LineSpaces:
    n: int
    shafts_per_cell: int
    buffers: dict[str, DeviceBuffer]
    stats: dict = field(default_factory=dict)
    tri_chunks: int = 1  # buffers the candidate list is split over (with_tri_chunks)
    tri_shift: int = 32  # log2 of the entries per chunk

    def trace_spec(self, spec: KernelSpec) -> KernelSpec:
        return with_tri_chunks(spec, self.tri_chunks, self.tri_shift)


def tri_chunk_names(n_chunks: int) -> list[str]:
    return ["ls_shaft_tris"] + [f"ls_shaft_tris{i}" for i in range(1, n_chunks)]


def with_tri_chunks(spec: KernelSpec, n_chunks: int, shift: int) -> KernelSpec:
    """`spec` reading (or, in the fill, writing) a candidate list split over n_chunks buffers of
    2^shift entries each; unchanged for one chunk."""
    if n_chunks <= 1:
        return spec
    access = next(b.access for b in spec.buffers if b.name == "ls_shaft_tris")
    extra = tuple(Buf(name, "uint", access) for name in tri_chunk_names(n_chunks)[1:])
    return dataclasses.replace(spec, buffers=spec.buffers + extra).with_defines(
        LS_TRI_CHUNKS=n_chunks, LS_TRI_SHIFT=shift)


def _tri_chunking(device: Device, total: int) -> tuple[int, int]:
    """(chunks, log2 entries per chunk) for `total` candidates: one chunk while the list fits
    one buffer, else the fewest power-of-two chunks under the per-buffer limit."""
    limit = device.max_buffer_bytes
    if 4 * max(total, 1) <= limit:
        return 1, 32
    shift = (limit // 4).bit_length() - 1  # 2^shift entries fit one buffer
    chunks = -(-total // (1 << shift))
    if chunks > LS_MAX_TRI_CHUNKS:
        raise DeviceLimitError(
            f"buffer 'ls_shaft_tris' needs {4 * total / 2**20:.1f} MiB: more than {LS_MAX_TRI_CHUNKS} "
            f"buffers of the {device.backend} driver's per-buffer limit of {limit / 2**20:.0f} MiB "
            f"({device.limit_name})")
    return chunks, shift


def uniforms(geometry: GridGeometry, n: int) -> dict:
    return dict(geometry.uniforms(), ls_n=int(n), ls_shafts=shafts_per_cell(n), ls_eps=float(LS_EPS))


def prepare(device: Device) -> None:
    for spec in BUILD_SPECS:
        spec = _with_test(device, spec)
        device.program(spec) if device.backend == "glsl" else device.kernel(spec)


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
    cells with candidates (voxels, octree leaves), how many got no Line Space, and the shaft
    offsets they do not need (their candidates are not counted here: compare memory_bytes with
    a K = 0 build for the whole saving)."""
    skipped = candidate_cells - ls.stats["linespace_cells"]
    return {"candidate_cells": candidate_cells, "linespace_skipped_cells": skipped,
            "ls_min_candidates": k, "ls_offsets_bytes_saved": 4 * skipped * ls.shafts_per_cell}


def build_linespaces(device: Device, scene_buffers: dict, geometry: GridGeometry, cells: Cells,
                     n: int) -> LineSpaces:
    """Line Spaces of all cells: count -> scan -> fill, all on the device."""
    n = check_n(n)
    per_cell = shafts_per_cell(n)
    n_shafts = cells.count * per_cell
    if n_shafts + 1 > UINT32_MAX:
        raise DeviceLimitError(
            f"{cells.count} Line Spaces x {per_cell} shafts = {n_shafts} shafts overflow 32-bit "
            "shaft indices (uint, 2^32 - 1)")
    u = uniforms(geometry, n)
    if n_shafts == 0:  # no cell gets a Line Space (e.g. ls_min_candidates above every list)
        offsets = device.alloc("ls_shaft_offsets", 4)
        tris = device.alloc("ls_shaft_tris", 4)
        tris.used_bytes = 0
        stats = {"ls_n": n, "shafts_per_cell": per_cell, "linespace_cells": 0, "shafts": 0,
                 "non_empty_shafts": 0, "candidate_references": 0, "ls_bytes": 8,
                 "ls_exact_test": exact_test(device), "ls_tri_buffers": 1}
        return LineSpaces(n, per_cell, {"ls_shaft_offsets": offsets, "ls_shaft_tris": tris}, stats)
    # Fail before the long count pass when the offsets alone cannot fit.
    device.check_size("ls_shaft_offsets", 4 * (n_shafts + 1))
    temps: list[DeviceBuffer] = []  # released however the build ends
    kept: list[DeviceBuffer] = []  # released only if it fails
    try:
        planes = device.alloc("ls_planes", 16 * LS_MAX_PLANES * per_cell, zero=False)
        temps.append(planes)
        device.dispatch(LS_PLANES, per_cell, {"ls_planes": planes}, u)
        stats_buf = device.alloc("ls_stats", 16)
        temps.append(stats_buf)
        cell_bufs = dict(scene_buffers, ls_planes=planes, ls_cell_boxes=cells.boxes,
                         ls_cell_ranges=cells.ranges, ls_cell_tris=cells.tris)
        counts = device.alloc("ls_shaft_counts", 4 * n_shafts)
        temps.append(counts)
        device.dispatch(_with_test(device, LS_COUNT), n_shafts,
                        dict(cell_bufs, ls_shaft_counts=counts, ls_stats=stats_buf), u)
        offsets, total = device.exclusive_scan(counts, n_shafts, "ls_shaft_offsets")
        kept.append(offsets)
        temps.remove(counts)
        device.release(counts)
        # A 32-bit prefix sum wraps silently: whenever the candidates could pass 2^32 - 1, look
        # for the wrap (a decreasing offset) on the device before trusting `total`.
        if per_cell * cells.references > UINT32_MAX or total >= UINT32_MAX:
            flag = device.alloc("ls_check_flag", 4)
            temps.append(flag)
            device.dispatch(LS_CHECK, n_shafts, {"ls_check_offsets": offsets, "ls_check_flag": flag}, u)
            if int(device.read(flag, np.uint32, 1)[0]) or total >= UINT32_MAX:
                raise DeviceLimitError(
                    f"Line Space candidate lists (N={n}, {cells.count} cells) pass 2^32 - 1 "
                    "references: over the 32-bit candidate offsets")
        chunks, shift = _tri_chunking(device, total)
        tris_bufs = {}
        for i, name in enumerate(tri_chunk_names(chunks)):
            entries = min(max(total, 1), (i + 1) << shift) - (i << shift)
            tris_bufs[name] = device.alloc(name, 4 * entries, zero=False)
            kept.append(tris_bufs[name])
        fill = with_tri_chunks(_with_test(device, LS_FILL), chunks, shift)
        device.dispatch(fill, n_shafts, dict(cell_bufs, ls_shaft_offsets=offsets, **tris_bufs), u)
        non_empty, cut = (int(v) for v in device.read(stats_buf, np.uint32, 2))
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
    for b in tris_bufs.values():
        b.used_bytes = b.nbytes
    if total == 0:
        tris_bufs["ls_shaft_tris"].used_bytes = 0
    stats = {
        "ls_n": n,
        "shafts_per_cell": per_cell,
        "linespace_cells": cells.count,
        "shafts": n_shafts,
        "non_empty_shafts": non_empty,
        "candidate_references": total,
        "ls_bytes": offsets.nbytes + sum(b.nbytes for b in tris_bufs.values()),
        "ls_exact_test": exact_test(device),
        "ls_tri_buffers": chunks,
    }
    return LineSpaces(n, per_cell, dict(ls_shaft_offsets=offsets, **tris_bufs), stats, chunks, shift)
