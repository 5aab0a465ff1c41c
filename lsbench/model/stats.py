"""The scene statistics the model predicts from, measured on the device with the structures' own
kernels (never a host voxelizer): the triangles per voxel of the conservative voxelization's count
pass (grid.h, Delgado Krämer 2019, 3.4) at a candidate resolution, the non-empty cells per octree
level derived from them (the octree build's flag pyramid, svo.py: a cell is needed when a child
is), and, for the Line Space, the candidates per shaft of a sample of cells (the real Line Space
build, linespace.build_linespaces, run on those cells only).

    counts = voxel_counts(device, scene_buffers, scene, geometry)      # VoxelCounts
    counts.references, counts.non_empty, counts.level_cells()          # per octree level
    samples = line_space_samples(device, scene_buffers, n_tris, geometry, counts, (1, 2))
    samples[2].candidates_per_reference(k)   # shaft candidates per reference in cells with > k
"""
from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np

from lsbench.backends.device import Device, DeviceLimitError
from lsbench.backends.structures import grid, linespace
from lsbench.backends.structures.base import GridGeometry

# Cells of the Line Space sample: spread evenly over the voxel references of the non-empty cells
# sorted by their count (each reference equally likely: a cell in proportion to its count), so the
# cells over a threshold K, which hold most references, are most of the sample (sample_cells); fewer
# (at least LS_SAMPLE_MIN) where the sample's triangle/shaft tests would pass LS_SAMPLE_PAIRS (coarse
# grids of dense scenes: 32 cells of 5000 triangles at N = 4 are 600 M tests, half a minute on PoCL here).
LS_SAMPLE_CELLS = 32
LS_SAMPLE_MIN = 4
LS_SAMPLE_PAIRS = 2**24


# A count pass over more voxels than this is read in slabs of z layers of at most COUNT_SLAB_VOXELS
# voxels, one buffer reused, keeping the non-empty voxels only (voxel_counts): spheres' 512^3 octree
# box is 512 x 224 x 512 voxels, a 235 MB buffer whose first touch alone took 0.2-0.9 s on this
# VM, and the occupancy pyramid halved all of it again (docs/fit.md).
COUNT_DENSE_VOXELS = 2**23
COUNT_SLAB_VOXELS = 2**22


@dataclass
class VoxelCounts:
    """Triangles per voxel of one grid geometry (the count pass): either whole, as a (z, y, x)
    array (`counts`; voxel (x, y, z) is x + Rx * (y + Ry * z) as on the device, grid.h), or, for a
    grid over COUNT_DENSE_VOXELS, only the non-empty voxels: their flat ids, ascending, and their
    counts (`listed`). Everything the model asks of the counts goes through the methods below,
    which answer alike for both."""
    geometry: GridGeometry
    counts: np.ndarray | None  # uint32, shape (Rz, Ry, Rx); None: only the non-empty voxels are held
    sparse: tuple[np.ndarray, np.ndarray] | None = field(default=None, repr=False)  # (int64 ids, uint32 counts)
    walks: dict = field(default_factory=dict, repr=False)  # model/cost.py's ray walks, per ray sample

    @functools.cached_property
    def listed(self) -> tuple[np.ndarray, np.ndarray]:
        """(flat ids ascending, counts) of the non-empty voxels."""
        if self.sparse is not None:
            return self.sparse
        flat = self.counts.ravel()
        ids = np.flatnonzero(flat != 0)
        return ids, flat[ids]

    @property
    def voxels(self) -> int:
        return int(self.geometry.voxel_count)

    @property
    def references(self) -> int:
        return int(self.listed[1].sum(dtype=np.int64))

    @property
    def non_empty(self) -> int:
        return int(len(self.listed[0]))

    @property
    def densest(self) -> int:
        """The most candidates in one voxel (0: none)."""
        return int(self.listed[1].max(initial=0))

    def above(self, k: int) -> tuple[int, int]:
        """(cells, references) of the voxels with more than k candidates (those that get a Line
        Space at ls_min_candidates = k)."""
        values = self.listed[1]
        keep = values > k
        return int(np.count_nonzero(keep)), int(values[keep].sum(dtype=np.int64))

    def at(self, flat: np.ndarray) -> np.ndarray:
        """The counts of the voxels of flat ids `flat` (0 where empty)."""
        if self.counts is not None:
            return self.counts.ravel()[flat]
        ids, values = self.sparse
        if len(ids) == 0:
            return np.zeros(np.shape(flat), np.uint32)
        i = np.minimum(np.searchsorted(ids, flat), len(ids) - 1)
        return np.where(ids[i] == flat, values[i], 0).astype(np.uint32)

    def coarse(self, steps: int) -> np.ndarray:
        """Non-zero where non-empty, for the cells of 2^steps x 2^steps x 2^steps voxels (the last
        cell of an axis whose voxels do not divide evenly covers the rest), as a (z, y, x) array:
        the counts themselves for steps = 0 when held whole (not copied), else booleans."""
        if self.counts is not None:
            occ = self.counts
            for _ in range(steps):
                occ = halved(occ)
            return occ
        rx, ry, rz = (int(v) for v in self.geometry.resolution)
        shape = tuple(-(-r >> steps) for r in (rz, ry, rx))
        ids = self.sparse[0]
        x, y, z = ids % rx >> steps, ids // rx % ry >> steps, ids // (rx * ry) >> steps
        occ = np.zeros(shape, bool)
        occ[z, y, x] = True
        return occ

    @functools.cached_property
    def occupancy(self) -> list[np.ndarray]:
        """Octrees (cubic power-of-two resolution): the non-empty cells of levels 0..depth - 1 (root
        first, the leaves' parents last) as (z, y, x) arrays of booleans: a cell is non-empty when
        one of its 8 children is (svo.py's flag pyramid). The counts cover the scene's box
        (GridGeometry.over_bounds, cubic), so level l holds only the cells of its 2^l per axis over
        the box, ceil(box / 2^(depth - l)); the cube's cells past them are empty. The leaves are
        the counts themselves (at, listed)."""
        cube = self.geometry.cube or self.geometry.resolution[0]
        depth = cube.bit_length() - 1
        if depth == 0:
            return []
        levels = [self.coarse(1)]
        for _ in range(depth - 1):
            levels.append(halved(levels[-1]))
        return levels[::-1]

    def level_cells(self) -> list[int]:
        """Non-empty cells per octree level 0..depth (the nodes of each level, leaves last)."""
        return [int(np.count_nonzero(level)) for level in self.occupancy] + [self.non_empty]


def halved(occ: np.ndarray) -> np.ndarray:
    """The occupancy (booleans) of the grid of cells twice as large as those of `occ` (booleans or
    counts: non-zero where non-empty): a cell is non-empty when one of its 2 x 2 x 2 is, those past
    the array (an odd extent: the box's far cells) empty. Pairs or-ed axis by axis: far faster
    than .any over three axes, and no padded copy."""
    for axis in range(3):
        occ = _pairs_or(occ, axis)
    return occ


def _pairs_or(occ: np.ndarray, axis: int) -> np.ndarray:
    """Cells 2i and 2i + 1 or-ed along one axis, a last odd cell on its own."""
    def along(sl: slice) -> tuple:  # the index of `sl` on `axis`
        return (slice(None),) * axis + (sl,)

    n = occ.shape[axis]
    half = n // 2
    out = np.empty(occ.shape[:axis] + (-(-n // 2),) + occ.shape[axis + 1:], bool)
    np.logical_or(occ[along(slice(0, 2 * half, 2))], occ[along(slice(1, 2 * half, 2))], out=out[along(slice(0, half))])
    if n % 2:
        out[along(slice(half, None))] = occ[along(slice(n - 1, None))]
    return out


def voxel_counts(device: Device, scene_buffers: dict, scene, geometry: GridGeometry) -> VoxelCounts:
    """The voxelization's count pass of `scene` (uploaded as `scene_buffers`) at `geometry` on the
    device (the same kernel every grid and octree build runs first), read back: whole up to
    COUNT_DENSE_VOXELS voxels, past that slab by slab (grid.h: VOXEL_SLAB), keeping the non-empty
    voxels only. Compiles only the pass it runs (not the build's fill pass: the build compiles that
    in its own prepare)."""
    rx, ry, rz = geometry.resolution
    if geometry.voxel_count <= COUNT_DENSE_VOXELS:
        device.compile_voxelizer(grid.VOXELIZE_COUNT)
        buf = device.alloc_readable("model_voxel_counts", 4 * geometry.voxel_count)
        try:
            device.voxelize(grid.VOXELIZE_COUNT, scene.triangle_count, dict(scene_buffers, voxel_counts=buf),
                            geometry.uniforms(), geometry.resolution)
            device.finish()
            counts = device.read_readable(buf, np.uint32, geometry.voxel_count)
        finally:
            device.release(buf)
        return VoxelCounts(geometry, counts.reshape(rz, ry, rx))  # an array of its own (read_readable)
    device.compile_voxelizer(grid.VOXELIZE_COUNT_SLAB)
    layer = rx * ry
    layers = max(1, COUNT_SLAB_VOXELS // layer)
    # Each slab's pass gets only the triangles whose z cells, widened by one each side (the
    # kernel's eps and float32 rounding are far less), meet its layers; the kernel still cuts them
    # exactly (a count pass ignores the triangle ids). Over every triangle, each slab cost a full
    # launch: on llvmpipe 60-70 ms per slab on BMW's 793 k triangles.
    z = (np.asarray(scene.vertices, np.float64)[:, 2] - geometry.origin[2]) / geometry.voxel_size[2]
    tri_z = z[np.asarray(scene.faces)]
    first, last = np.floor(tri_z.min(axis=1)) - 1, np.floor(tri_z.max(axis=1)) + 1
    faces = np.ascontiguousarray(scene.faces, np.uint32)
    buf = device.alloc_readable("model_voxel_counts", 4 * layer * min(layers, rz))
    ids, values = [], []
    try:
        for z0 in range(0, rz, layers):
            z1 = min(z0 + layers, rz)
            meeting = np.flatnonzero((last >= z0) & (first < z1))
            if len(meeting) == 0:
                continue
            if ids:
                device.fill_zero(buf)
            slab_faces = device.upload("model_slab_faces", faces[meeting].ravel())
            try:
                device.voxelize(grid.VOXELIZE_COUNT_SLAB, len(meeting),
                                dict(scene_buffers, faces=slab_faces, voxel_counts=buf),
                                dict(geometry.uniforms(), voxel_slab=(z0, z1, 0, 0)), geometry.resolution)
                device.finish()
            finally:
                device.release(slab_faces)
            slab = device.read_readable(buf, np.uint32, layer * (z1 - z0))
            listed = np.flatnonzero(slab != 0)  # 3-4x faster than of the uint32 array itself
            ids.append(listed + z0 * layer)
            values.append(slab[listed])  # copies: the next slab reuses the buffer
    finally:
        device.release(buf)
    if not ids:
        return VoxelCounts(geometry, None, (np.zeros(0, np.int64), np.zeros(0, np.uint32)))
    return VoxelCounts(geometry, None, (np.concatenate(ids).astype(np.int64), np.concatenate(values)))


@dataclass
class LineSpaceSample:
    """Shaft candidates of a sample of cells at one geometry and N, from the real build."""
    n: int
    cell_counts: np.ndarray  # int64: each sampled cell's candidates (its voxel list length)
    shaft_candidates: np.ndarray  # int64 (cells, 15 N^4): each sampled cell's candidates per shaft
    limit: str = ""  # the device limit the sample's build met (that N cannot be built here), else ""
    # Each sampled cell's distinct candidate sets and their triangle ids (what its lists store).
    cell_sets: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    cell_set_references: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    # Each sampled cell's weight in the ratio estimators: times drawn / its count (sample_cells).
    weights: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def _ratio(self, per_cell: np.ndarray, k: int):
        """Per voxel reference of the cells with more than k candidates: sum w x per_cell / sum w x
        count over the sampled ones (Hansen & Hurwitz 1943 for cells drawn in proportion to their
        count: the mean of per_cell / count over the draws); None when none is sampled."""
        keep = self.cell_counts > k
        refs = float(self.weights[keep] @ self.cell_counts[keep])
        return (np.tensordot(self.weights[keep], per_cell[keep], axes=1) / refs) if refs else None

    @property
    def cell_candidates(self) -> np.ndarray:
        """The candidates of all of each sampled cell's shafts together."""
        return self.shaft_candidates.sum(axis=1)

    def lists_per_reference(self, k: int) -> tuple[float, float]:
        """Distinct sets and their triangle ids per voxel reference in the cells with more than k
        candidates (those that get a Line Space at K = k), estimated from the sample (_ratio);
        (0, 0) when none is sampled."""
        sets, ids = self._ratio(self.cell_sets, k), self._ratio(self.cell_set_references, k)
        return (0.0, 0.0) if sets is None else (float(sets), float(ids))

    def candidates_per_reference(self, k: int) -> float:
        """Shaft candidates per voxel reference in the cells with more than k candidates (_ratio);
        0 when none is sampled."""
        ratio = self._ratio(self.cell_candidates, k)
        return 0.0 if ratio is None else float(ratio)

    def shaft_candidates_per_reference(self, k: int) -> np.ndarray | None:
        """Each shaft's candidates per voxel reference in the cells with more than k candidates
        (_ratio; model/cost.py weights them by the shafts the rays take); None when none is sampled."""
        return self._ratio(self.shaft_candidates, k)


def sample_cells(counts: VoxelCounts, size: int = LS_SAMPLE_CELLS, shafts: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The sample's flat voxel ids and each one's weight (times drawn / its count): `size` draws
    evenly spaced over the voxel references of the non-empty voxels in count order (systematic
    sampling in proportion to the count), fewer when the cells drawn x `shafts` pass LS_SAMPLE_PAIRS.
    Drawn evenly over the cells instead, the few dense cells that a threshold K keeps were 1-3 of 32
    and their stored sets came out 0.72-0.80 of the truth; drawn this way, 0.96-0.98 (Sponza, svo-ls
    128^3 N=3, K = 16-64: docs/fit.md)."""
    non_empty, listed = counts.listed
    by_count = np.argsort(listed, kind="stable")
    order = non_empty[by_count]
    cumulative = np.cumsum(listed[by_count], dtype=np.float64)

    def draw(k: int) -> tuple[np.ndarray, np.ndarray]:
        at = np.searchsorted(cumulative, (np.arange(k) + 0.5) * (cumulative[-1] / k), side="right")
        cells, times = np.unique(order[np.minimum(at, len(order) - 1)], return_counts=True)
        return cells, times / counts.at(cells)

    if len(order) == 0:
        return np.zeros(0, np.int64), np.zeros(0)
    cells, weights = draw(size)
    pairs = int(counts.at(cells).sum(dtype=np.int64)) * shafts
    if pairs > LS_SAMPLE_PAIRS:
        cells, weights = draw(max(LS_SAMPLE_MIN, int(size * LS_SAMPLE_PAIRS / pairs)))
    return cells, weights


def line_space_samples(device: Device, scene_buffers: dict, n_tris: int, geometry: GridGeometry,
                       counts: VoxelCounts, ns, size: int = LS_SAMPLE_CELLS) -> dict[int, LineSpaceSample]:
    """The Line Spaces of a sample of non-empty voxels for each N in `ns`, built on the device by
    the build every Line Space structure runs (linespace.build_linespaces on the grid's voxel lists,
    built once for all N), and each sampled cell's shaft candidates read from its offsets."""
    linespace.prepare(device)
    if counts.non_empty == 0:
        return {n: LineSpaceSample(n, np.zeros(0, np.int64), np.zeros((0, linespace.shafts_per_cell(n)), np.int64))
                for n in ns}
    try:
        lists, _ = grid.build_voxel_lists(device, scene_buffers, n_tris, geometry)
    except DeviceLimitError as exc:
        return {n: _limited(n, exc) for n in ns}
    try:
        offsets = device.read(lists["voxel_offsets"], np.uint32, geometry.voxel_count + 1).astype(np.int64)
        out = {}
        for n in ns:
            try:
                out[n] = _sample(device, scene_buffers, geometry, lists["voxel_tris"], offsets,
                                 *sample_cells(counts, size, linespace.shafts_per_cell(n)), n)
            except DeviceLimitError as exc:  # e.g. llvmpipe's loop budget in the densest cell (sampled)
                out[n] = _limited(n, exc)
        return out
    finally:
        for b in lists.values():
            device.release(b)


def _limited(n: int, exc: Exception) -> LineSpaceSample:
    return LineSpaceSample(n, np.zeros(0, np.int64), np.zeros((0, linespace.shafts_per_cell(n)), np.int64),
                           f"{type(exc).__name__}: {exc}".splitlines()[0][:300])


def _sample(device: Device, scene_buffers: dict, geometry: GridGeometry, voxel_tris, offsets: np.ndarray,
            cells: np.ndarray, weights: np.ndarray, n: int) -> LineSpaceSample:
    """The Line Spaces of `cells` (flat voxel ids, with their weights: sample_cells) at N = n,
    and each one's shaft candidates."""
    rx, ry, _ = geometry.resolution
    x, y, z = cells % rx, (cells // rx) % ry, cells // (rx * ry)
    lo = np.stack([x, y, z], axis=1).astype(np.float32)
    boxes = np.zeros((len(cells), 2, 4), np.float32)  # (lo.xyz, 0), (hi.xyz, 0) in grid space
    boxes[:, 0, :3], boxes[:, 1, :3] = lo, lo + 1
    ranges = np.stack([offsets[cells], offsets[cells + 1]], axis=1).astype(np.uint32)
    made = [device.upload("model_ls_boxes", boxes.ravel()), device.upload("model_ls_ranges", ranges.ravel())]
    try:
        cell_counts = ranges[:, 1].astype(np.int64) - ranges[:, 0]
        sample = linespace.Cells(len(cells), made[0], made[1], voxel_tris, int(cell_counts.sum()))
        ls = linespace.build_linespaces(device, scene_buffers, geometry, sample, n)
        made += list(ls.buffers.values())
        words = linespace.read_array(device, ls.buffers, "ls_shaft_offsets")
        begin, end = linespace.shaft_ranges(words, ls.shafts_per_cell)
        sets, set_refs = linespace.cell_set_sizes(words, ls.shafts_per_cell)
        return LineSpaceSample(n, cell_counts, (end - begin).reshape(len(cells), ls.shafts_per_cell),
                               cell_sets=sets, cell_set_references=set_refs, weights=np.asarray(weights, np.float64))
    finally:
        for b in made:
            device.release(b)


def line_space_sample(device: Device, scene_buffers: dict, n_tris: int, geometry: GridGeometry,
                      counts: VoxelCounts, n: int, size: int = LS_SAMPLE_CELLS) -> LineSpaceSample:
    """line_space_samples for one N."""
    return line_space_samples(device, scene_buffers, n_tris, geometry, counts, (n,), size)[n]
