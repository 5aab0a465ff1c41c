"""The cost model: the work per ray of each structure at a setting, its device time per ray, and the
cheapest setting that fits a device-memory budget (issue 17).

Work, predicted from the scene's statistics (model/stats.py) and a sample of the case's own rays
cut at Embree's closest hit (the walk of every traversal ends in the cell of the closest hit,
shaders/common/trace.h: trace_done), walked on the host through the cells that the 3D-DDA of
Amanatides & Woo (1987) visits in the counted grids (`crossings`; the model's arithmetic, not a
structure: nothing here builds or traces):
- grid (thesis 3.3.1): one iteration per voxel the ray crosses, the voxel's candidates tested;
- svo / esvo (3.3.2, 5.2): one iteration per cell, on every level, that the ray crosses inside a
  non-empty parent (both walks visit exactly those, front to back), the leaves' candidates tested;
- a Line Space (3.3.3, 4): in a cell with more than K candidates one shaft lookup and that shaft's
  candidates: count x the sample's candidates per reference of each shaft, weighted by how often the
  sampled rays' chords through such cells take that shaft (an estimate: the sampled cells stand for
  all); other cells test their list.

Time per ray = launch / rays + ray + step[structure] x iterations + test x candidate tests + lookup x
lookups (rays: the set's, one launch), the constants per device (model/constants.py: measured by
`lsbench fit`, or documented defaults), the iterations and tests as the device's SIMD groups issue
them: a group of lanes in lock step runs each loop as often as its busiest lane (profile/simd.py),
so on llvmpipe (8 lanes) a test that one ray of eight makes costs the group as much as eight
(BMW, esvo 256³ -> 512³: 2.7 -> 1.0 tests per ray, 7.0 -> 2.5 issued, measured 253 -> 199 ns per
ray; fitted on the means, the model put the two within 1 ns). On a device of one lane per group
(PoCL's CPU device) issued = mean.

Settings tried for "auto" (Ize, Shirley & Parker 2007: a uniform grid wants cells ~ lambda x
triangles, per axis in proportion to the scene's extents): grids at lambda in GRID_LAMBDAS, non-cubic;
octrees the cubic powers of two 2^OCTREE_LEVELS (thesis 6.3: they force the bounding cube; here only
its cells over the scene's box are counted and walked, GridGeometry.over_bounds); N in
AUTO_NS; K in AUTO_KS. The cheapest predicted time that fits the budget wins; `choose` returns every
option with its prediction (the record keeps the runners-up).
"""
from __future__ import annotations

import functools
import math
import time
from dataclasses import asdict, dataclass, field

import numpy as np

from lsbench.backends.structures import STRUCTURES
from lsbench.backends.structures.base import GridGeometry
from lsbench.backends.structures.linespace import ListSizes, offset_entries, shafts_per_cell
from lsbench.model.bytes import BytesPrediction, predict_bytes
from lsbench.model.constants import load_constants
from lsbench.model.stats import LineSpaceSample, VoxelCounts
from lsbench.profile.simd import issued_per_ray, simd_lanes

GRID_LAMBDAS = (0.25, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0)
OCTREE_LEVELS = tuple(range(3, 10))  # 8^3 .. 512^3, those whose box has at most the voxels allowed
LS_MAX_VOXELS = 2**23  # Line Space settings tried: at most 8 M cells in the box (15 N^4 shafts each)
# Grid and octree settings tried: at most this many voxels in the scene's box, and no more than
# the device's largest buffer holds as the build's dense offsets (4 bytes per voxel, grid.h).
GRID_MAX_VOXELS = 2**26
AUTO_NS = (1, 2, 3, 4)
AUTO_KS = (0, 2, 4, 8, 16, 32, 64)
AUTO_REBUILDS = 2  # an auto Line Space built over the budget is rebuilt at most this often (Choice)
# Rays of the case walked per setting, drawn per counted grid (draw): the candidate tests per ray
# have a heavy tail (on BMW, 512² default camera, 0.1 % of the rays make 57-80 % of the tests of
# esvo 256³ / 512³ and grid 134 x 40 x 148, up to 20,735 tests by one ray), so the rays are drawn
# with probabilities that follow the candidates of their hit voxel; 8192 such rays put the mean
# and issued tests within 6-11 % rms of every ray's (docs/fit.md).
RAY_SAMPLE = 8192
RUNNERS_UP = 5  # options kept in the record besides the chosen one


@dataclass(frozen=True)
class Work:
    """Mean work per ray, as the profiling counters count it (iterations_per_ray, ...), and the
    lane-slots per ray that SIMD groups of the sample's width issue for the walk and the tests
    (each group runs every loop as often as its busiest lane: profile/simd.py; at width 1 they
    are the means)."""
    iterations: float
    tests: float
    lookups: float
    issued_iterations: float
    issued_tests: float


@dataclass(frozen=True, eq=False)  # compared and hashed by identity: a key of VoxelCounts.walks
class RaySample:
    """The case's rays in launch order (backends.launch_order), each walked from tmin to t_end (its
    closest hit, else its tmax), and how many of them predict_work walks: `size` rays in groups of
    `width` consecutive ones that the device runs in lock step (simd_lanes), drawn per counted grid
    (draw). Every ray when that is all of them."""
    origins: np.ndarray  # (n, 3) float64
    directions: np.ndarray
    tmin: float
    t_end: np.ndarray
    hit: np.ndarray  # bool: Embree found a hit (t_end is it)
    width: int = 1
    size: int = RAY_SAMPLE
    seed: int | None = None  # of the draws (None: from the set's size, so a set draws the same rays)

    @property
    def rays(self) -> int:
        """The rays of the set: one launch (each shares its fixed cost)."""
        return len(self.t_end)

    @functools.cached_property
    def hit_points(self) -> np.ndarray:
        """Each ray's closest hit (its origin where it misses): draw locates them in every grid."""
        return self.origins + self.directions * np.where(self.hit, self.t_end, 0.0)[:, None]


@dataclass(frozen=True, eq=False)
class Drawn:
    """The rays of a RaySample that one counted grid's predictions walk: rows in groups of `width`
    (each group whole, the last one of the set short), each row with the weight of its group (the
    inverse of its probability of being drawn; one where every ray is walked)."""
    origins: np.ndarray
    directions: np.ndarray
    tmin: np.ndarray
    t_end: np.ndarray
    weights: np.ndarray
    width: int


def ray_sample(rays, hit_t: np.ndarray, size: int = RAY_SAMPLE, width: int = 1, seed: int | None = None) -> RaySample:
    """The rays of the set in launch order, cut at Embree's closest hit `hit_t` (inf = miss), of
    which `size` in groups of `width` (simd_lanes: lanes in lock step; 1: rays on their own) are
    walked per counted grid (draw)."""
    from lsbench.backends import launch_order

    order = launch_order(rays)
    idx = np.arange(rays.count) if order is None else order
    hit_t = np.asarray(hit_t, np.float64)[idx]
    t_end = np.minimum(hit_t, np.asarray(rays.tmax_array, np.float64)[idx])
    return RaySample(np.asarray(rays.origins, np.float64)[idx], np.asarray(rays.directions, np.float64)[idx],
                     float(rays.tmin), t_end, np.isfinite(hit_t), max(int(width), 1), int(size), seed)


def draw(sample: RaySample, counts: VoxelCounts) -> Drawn:
    """About sample.size rays of `sample` as whole groups of sample.width, drawn for the grid of
    `counts` (once per grid: counts.walks). A group is drawn with probability proportional to
    sqrt(c) + mean sqrt(c), c the most candidates in a hit voxel of its rays (0 where none hits),
    and weighs the inverse of that probability: the rays whose tests dominate the mean are drawn
    more often, every group keeps at least half the uniform chance, and the weighted means stay
    unbiased (importance sampling by a quantity known for every ray: Kahn & Marshall 1953). The
    draw is systematic over the launch order (one jittered draw per equal share of the
    probability), so the groups spread over the image as well.

    Measured on BMW (512² default camera; esvo 256³ and 512³, grid 134 x 40 x 148; 300 draws of
    1024 of the 32,768 groups of 8, each group drawn independently): the mean tests per ray within
    8-9 % rms of every ray's and the issued within 9-11 %, where 8192 rays drawn uniformly put the
    mean 29-36 % off, and their mean times the issued-to-mean ratio of 1024 uniform groups the
    issued 46-53 %. Drawn in proportion to c itself the issued were 7-14 % off, to its root 9-10 %."""
    key = ("draw", sample)  # the object, not its id: a sample freed and another made may share an id
    if key in counts.walks:
        return counts.walks[key]
    n, width = len(sample.t_end), sample.width
    starts = np.arange(0, n, width)
    take = max(sample.size // width, 1)
    if take >= len(starts):
        rows, weights = np.arange(n), np.ones(n)
    else:
        g = counts.geometry
        res = np.asarray(g.resolution)
        voxel = np.clip(np.floor((sample.hit_points - np.asarray(g.origin)) / np.asarray(g.voxel_size)),
                        0, res - 1).astype(np.int64)
        flat = voxel[:, 0] + res[0] * (voxel[:, 1] + res[1] * voxel[:, 2])
        listed = np.where(sample.hit, counts.at(flat), 0)
        root = np.sqrt(np.maximum.reduceat(listed.astype(np.float64), starts))
        q = root + root.mean() if root.any() else np.ones(len(starts))
        q /= q.sum()
        rng = np.random.default_rng(n + width if sample.seed is None else sample.seed)
        picked = np.searchsorted(np.cumsum(q), (np.arange(take) + rng.random(take)) / take, side="right")
        groups, times = np.unique(np.minimum(picked, len(starts) - 1), return_counts=True)
        ends = np.minimum(starts[groups] + width, n)
        lane = np.arange(width)
        rows = (starts[groups][:, None] + lane)[lane < (ends - starts[groups])[:, None]]  # each group's rows, in order
        weights = np.repeat(times / q[groups], ends - starts[groups])
    out = Drawn(sample.origins[rows], sample.directions[rows], np.full(len(rows), sample.tmin), sample.t_end[rows],
                weights, width)
    counts.walks[key] = out
    return out


def box_span(o: np.ndarray, d: np.ndarray, t0: np.ndarray, t1: np.ndarray, res):
    """(enter, leave, 1/d) of each ray in the box [0, res] within [t0, t1] (enter > leave: it misses)."""
    res = np.asarray(res, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.where(d != 0, 1.0 / np.where(d != 0, d, 1.0), np.inf)
        ta, tb = -o * inv, (res - o) * inv
        inside = (o >= 0) & (o <= res)
        lo = np.where(d != 0, np.minimum(ta, tb), np.where(inside, -np.inf, np.inf))
        hi = np.where(d != 0, np.maximum(ta, tb), np.where(inside, np.inf, -np.inf))
    return np.maximum(t0, lo.max(axis=1)), np.minimum(t1, hi.min(axis=1)), inv


def crossings(o: np.ndarray, d: np.ndarray, t0, t1, res):
    """The cells of the grid [0, res] that each ray crosses between t0 and t1 as (ray, x, y, z),
    int32 arrays: the cell where the ray enters the grid, then one cell per grid plane it crosses.
    These are the cells the 3D-DDA of Amanatides & Woo (1987) steps through, one per crossing, but
    found for all crossings at once instead of one step of every ray at a time (a numpy loop of as
    many steps as the longest ray's, which took most of the choice). The crossing at a plane of one
    axis puts the ray in the cell of the other two axes that holds the crossing point, clamped to the
    cells its own span covers; where two planes are crossed at one point either order is taken (the
    DDA's order there is its rounding's). t0 and t1: scalars or one per ray."""
    rows, oc, dc, inv, first, low, high, count = _plane_counts(o, d, t0, t1, res)
    totals = [int(n.sum()) for n in count]
    out = np.empty((4, len(rows) + sum(totals)), np.int32)  # ray, x, y, z: the entries, then each axis'
    out[0, : len(rows)] = rows
    out[1:4, : len(rows)] = first
    at = len(rows)
    for a in range(3):
        n, total = count[a], totals[a]
        if total == 0:
            continue
        part = slice(at, at + total)
        at += total
        who = np.repeat(np.arange(len(rows)), n)
        j = np.arange(1, total + 1) - np.repeat(np.cumsum(n) - n, n)  # the ray's j-th crossing of this axis
        sign = np.sign(dc[a])[who]
        cell = first[a][who] + sign * j
        plane = np.where(sign > 0, cell, cell + 1)
        t = (plane - oc[a][who]) * inv[a][who]
        out[0, part] = rows[who]
        out[1 + a, part] = cell
        for b in range(3):
            if b != a:
                out[1 + b, part] = np.clip(np.floor(oc[b][who] + dc[b][who] * t), low[b][who], high[b][who])
    return out[0], out[1], out[2], out[3]


def octant_crossings(o: np.ndarray, d: np.ndarray, t0, t1):
    """crossings(o, d, t0, t1, (2, 2, 2)), the octree walk's step to a cell's children, without
    its machinery for many planes: each axis has one inner plane, crossed when the ray's ends are
    on its two sides, so the cells are the entry cell, then one more per plane crossed in the order
    of their t, each the last with that axis' bit flipped. A third of the numpy calls, on the
    octree walk's many small arrays (spheres esvo's choice: 0.26-0.31 s in crossings)."""
    enter, leave, inv = box_span(o, d, t0, t1, (2.0, 2.0, 2.0))
    rows = np.flatnonzero(enter <= leave)
    o, d, inv = o[rows], d[rows], inv[rows]
    first = np.clip(np.floor(o + d * enter[rows, None]), 0, 1).astype(np.int64)
    with np.errstate(invalid="ignore"):
        p = o + d * leave[rows, None]  # where the ray leaves: a plane strictly before it is crossed
        crossed = np.where(d > 0, (first == 0) & (p > 1), (d < 0) & (first == 1) & (p < 1))
        t = np.where(crossed, (1.0 - o) * inv, np.inf)
    order = np.argsort(t, axis=1)
    each = np.arange(len(rows))
    cells, kept = [first], [np.ones(len(rows), bool)]
    for k in range(3):
        axis = order[:, k]
        step = crossed[each, axis]  # the k-th crossing, where there is one (the uncrossed sort last)
        cell = cells[-1].copy()
        cell[each[step], axis[step]] ^= 1
        cells.append(cell)
        kept.append(step)
    kept = np.stack(kept)
    cell = np.stack(cells)[kept]
    return np.broadcast_to(rows, kept.shape)[kept], cell[:, 0], cell[:, 1], cell[:, 2]


def _plane_counts(o: np.ndarray, d: np.ndarray, t0, t1, res):
    """The rays that meet the box [0, res] between t0 and t1 (rows), their origins, directions and
    1/d per axis, and per axis the cell each enters in, the lowest and highest cell it reaches and
    how many planes of that axis it crosses (crossings)."""
    resf = np.asarray(res, np.float64)
    enter, leave, inv = box_span(o, d, t0, t1, resf)
    rows = np.flatnonzero(enter <= leave)
    r = [int(v) for v in res]
    enter, leave = enter[rows], leave[rows]
    oc = [o[rows, a] for a in range(3)]
    dc = [d[rows, a] for a in range(3)]
    first, low, high, count = [], [], [], []
    for a in range(3):
        f = np.clip(np.floor(oc[a] + dc[a] * enter), 0, r[a] - 1)
        with np.errstate(invalid="ignore"):
            p = oc[a] + dc[a] * leave  # where the ray leaves: planes strictly before it are crossed
            up = np.where(dc[a] > 0, np.maximum(np.minimum(np.ceil(p) - 1, r[a] - 1) - f, 0), 0)
            down = np.where(dc[a] < 0, np.maximum(f - np.maximum(np.floor(p) + 1, 1) + 1, 0), 0)
        first.append(f)
        low.append(f - down)
        high.append(f + up)
        count.append((up + down).astype(np.int64))
    return rows, oc, dc, [inv[rows, a] for a in range(3)], first, low, high, count


def cells_crossed(o: np.ndarray, d: np.ndarray, t0, t1, res) -> np.ndarray:
    """How many cells of the grid [0, res] each ray crosses between t0 and t1 (crossings' count per
    ray, without listing them)."""
    rows, *_, count = _plane_counts(o, d, t0, t1, res)
    out = np.zeros(len(o), np.int64)
    out[rows] = 1 + count[0] + count[1] + count[2]
    return out


def _in_grid(sample: Drawn, geometry: GridGeometry, scale: float = 1.0):
    """The sample in grid space of `geometry` (cell edge `scale` voxels); t is unchanged."""
    size = np.asarray(geometry.voxel_size, np.float64) * scale
    return (sample.origins - np.asarray(geometry.origin)) / size, sample.directions / size


def predict_work(structure: str, counts: VoxelCounts, sample: RaySample, k: int = 0,
                 ls: LineSpaceSample | None = None) -> Work:
    """Mean iterations, candidate tests and Line Space lookups per ray (module docstring), and the
    iterations and tests that the device's SIMD groups issue per ray (Work), over the rays drawn
    for this grid (draw), weighted."""
    drawn = draw(sample, counts)
    iterations, tests, lookups = _work_per_ray(structure, counts, drawn, k, ls)
    w = drawn.weights
    total = max(float(w.sum()), 1e-300)
    return Work(float(iterations @ w) / total, float(tests @ w) / total, float(lookups @ w) / total,
                issued_per_ray(iterations, drawn.width, w), issued_per_ray(tests, drawn.width, w))


def _work_per_ray(structure: str, counts: VoxelCounts, drawn: Drawn, k: int,
                  ls: LineSpaceSample | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each drawn ray's iterations, candidate tests and Line Space lookups."""
    info = STRUCTURES[structure]
    n_rays = len(drawn.t_end)
    ray_ids, cells, iterations = _walk(counts, drawn, info.cubic_power_of_two)
    listed = counts.at(cells).astype(np.float64)
    lookups = np.zeros(n_rays)
    if info.line_space:
        with_ls = listed > k
        per_reference = _shaft_tests_per_reference(counts, drawn, ray_ids[with_ls], cells[with_ls], k, ls)
        listed = np.where(with_ls, listed * per_reference, listed)  # a ray's tests in a Line Space cell
        lookups = np.bincount(ray_ids[with_ls], minlength=n_rays).astype(np.float64)
    tests = np.bincount(ray_ids, weights=listed, minlength=n_rays)
    return iterations.astype(np.float64), tests, lookups


def _shaft_tests_per_reference(counts: VoxelCounts, drawn: Drawn, ray_ids: np.ndarray, cells: np.ndarray,
                               k: int, ls: LineSpaceSample | None) -> float:
    """Candidates a ray tests in a Line Space cell, per reference of the cell: the sampled cells'
    candidates per reference of each shaft (cells over K), weighted by how often the drawn rays
    (by their weights) take that shaft in the Line Space cells they cross (their chords' shafts,
    linespace.h)."""
    if ls is None or len(ls.cell_counts) == 0 or len(cells) == 0:
        return 0.0
    per_shaft = ls.shaft_candidates_per_reference(k)
    if per_shaft is None:
        return 0.0
    o, d = _in_grid(drawn, counts.geometry)
    w = drawn.weights[ray_ids]
    used = np.bincount(chord_shafts(o[ray_ids], d[ray_ids], cells, counts.geometry.resolution, ls.n),
                       weights=w, minlength=len(per_shaft))
    return float(used @ per_shaft) / float(w.sum())


def chord_shafts(o: np.ndarray, d: np.ndarray, cells: np.ndarray, res, n: int) -> np.ndarray:
    """The shaft id (Listing 1: N^4 block(fs, fe) + N^2 patch_s + patch_e, fs < fe) of each ray's
    chord through its cell (flat id), as ls_chord in shaders/common/linespace.h computes it."""
    rx, ry, _ = (int(v) for v in res)
    lo = np.stack([cells % rx, (cells // rx) % ry, cells // (rx * ry)], axis=1).astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.where(d != 0, 1.0 / np.where(d != 0, d, 1.0), np.inf)
        t_enter = np.where(d != 0, (lo + (d <= 0) - o) * inv, -np.inf)
        t_exit = np.where(d != 0, (lo + (d > 0) - o) * inv, np.inf)
    rows = np.arange(len(cells))
    axis_in, axis_out = np.argmax(t_enter, axis=1), np.argmin(t_exit, axis=1)
    t_in, t_out = t_enter[rows, axis_in], t_exit[rows, axis_out]
    face_in = 2 * axis_in + (d[rows, axis_in] <= 0)
    face_out = 2 * axis_out + (d[rows, axis_out] > 0)

    def patch(t, axis):
        q = o + d * t[:, None] - lo
        u, v = q[rows, (axis + 1) % 3], q[rows, (axis + 2) % 3]
        ui = np.clip(np.floor(u * n), 0, n - 1).astype(np.int64)
        vi = np.clip(np.floor(v * n), 0, n - 1).astype(np.int64)
        return n * vi + ui

    p_in, p_out = patch(t_in, axis_in), patch(t_out, axis_out)
    fs, fe = np.minimum(face_in, face_out), np.maximum(face_in, face_out)
    ps, pe = np.where(face_in <= face_out, p_in, p_out), np.where(face_in <= face_out, p_out, p_in)
    block = fs * (11 - fs) // 2 + (fe - fs - 1)
    # a chord that enters and leaves through one face (grazing its plane) has no shaft: clamped
    return np.clip(n**4 * block + n * n * ps + pe, 0, shafts_per_cell(n) - 1)


def _walk(counts: VoxelCounts, sample: Drawn, octree: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(ray, voxel) pairs of the voxels the drawn rays cross, each once: every non-empty one, and
    the empty ones only where a walk passes them (they hold no candidates); and each ray's
    iterations: a grid's every voxel crossed, an octree's cells of all levels inside a non-empty
    parent. Once per (counts, drawn), whatever N and K. Both walks go top down, crossing only the
    children of non-empty cells, so their work is the cells that matter, not every voxel crossed
    (measured on 8192 rays, the same cells and iterations for every ray as listing every
    crossing: spheres esvo 512³ 0.13 s against 0.83 s, 446 k cells against 3.4 M crossings;
    atrium grid 256³ 0.075 s against 0.21 s)."""
    key = (sample, octree)
    if key not in counts.walks:
        counts.walks[key] = (_octree_walk if octree else _grid_walk)(counts, sample)
    return counts.walks[key]


# Voxels per block edge of a grid's walk (_grid_walk): 4 walked fastest on atrium at 64³..256³
# (0.037-0.075 s against 0.037-0.10 s for 2 and 0.05-0.08 s for 8).
GRID_WALK_BLOCK = 4


def _grid_walk(counts: VoxelCounts, sample: Drawn) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A grid's walk (_walk): the blocks of GRID_WALK_BLOCK³ voxels each ray crosses, then the
    voxels it crosses in the non-empty ones; its iterations are every voxel it crosses, counted
    without listing them (cells_crossed)."""
    g = counts.geometry
    res = tuple(int(v) for v in g.resolution)
    o, d = _in_grid(sample, g)
    enter, leave, _ = box_span(o, d, sample.tmin, sample.t_end, res)
    blocks = counts.coarse(GRID_WALK_BLOCK.bit_length() - 1)
    b = float(GRID_WALK_BLOCK)
    rays, x, y, z = crossings(o / b, d / b, enter, leave, blocks.shape[::-1])
    keep = blocks[z, y, x]
    rays, cell = _children(o, d, enter, leave, rays[keep], np.stack([x, y, z])[:, keep].astype(np.int64),
                           GRID_WALK_BLOCK, 1.0, res)
    return rays, cell[0] + res[0] * (cell[1] + res[1] * cell[2]), cells_crossed(o, d, enter, leave, res)


def _octree_walk(counts: VoxelCounts, sample: Drawn) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """An octree's walk (_walk), from the root to the leaves: a ray's cells of level l + 1 are the
    children it crosses of its non-empty cells of level l, and they are that level's iterations.
    Both octree walks cover the scene's box only (svo.h, esvo.h), so each ray is cut to the box."""
    levels = counts.occupancy  # (z, y, x) per level over the box, root first, leaves' parents last
    depth = len(levels)
    n_rays = len(sample.t_end)
    o, d = _in_grid(sample, counts.geometry)
    enter, leave, _ = box_span(o, d, sample.tmin, sample.t_end, counts.geometry.resolution)
    rays = np.flatnonzero(enter <= leave)
    cell = np.zeros((3, len(rays)), np.int64)  # (x, y, z) of each ray's cell at the level walked: the root
    iterations = np.zeros(n_rays, np.int64)
    for level in range(1, depth + 1):
        keep = levels[level - 1][cell[2], cell[1], cell[0]]
        box = levels[level].shape[::-1] if level < depth else counts.geometry.resolution
        rays, cell = _children(o, d, enter, leave, rays[keep], cell[:, keep], 2, 2.0 ** (depth - level), box)
        iterations += np.bincount(rays, minlength=n_rays)
    rx, ry, _ = (int(v) for v in counts.geometry.resolution)
    return rays, cell[0] + rx * (cell[1] + ry * cell[2]), iterations


def _children(o, d, enter, leave, rays: np.ndarray, cell: np.ndarray, branch: int, size: float, box):
    """(rays, cells) of the children that each ray crosses of its cell (x, y, z rows of `cell`),
    a cell being branch³ children of `size` voxels: the crossings of a branch³ grid in the cell's
    own frame (exact: the scalings are powers of two or one). `box`: the children over the grid's
    box (x, y, z); a child past it (a box's far cells are cut by it) is touched at most at the
    box's face, where the ray was cut (enter, leave: the rays' spans in the box), so it is dropped."""
    local = (o[rays] / size - branch * cell.T, d[rays] / size, enter[rays], leave[rays])
    pair, x, y, z = octant_crossings(*local) if branch == 2 else crossings(*local, (branch,) * 3)
    rays, cell = rays[pair], branch * cell[:, pair] + np.stack([x, y, z])
    inside = (cell[0] < box[0]) & (cell[1] < box[1]) & (cell[2] < box[2])
    return rays[inside], cell[:, inside]


def seconds_per_ray(structure: str, work: Work, constants, rays: int) -> float:
    """Predicted device time of one ray of a launch of `rays` (constants: model/constants.Constants):
    its share of the launch, the walk and the tests as the SIMD groups issue them (Work; `lsbench
    fit` fits the constants on the same)."""
    return (constants.launch / max(rays, 1) + constants.ray + constants.step[structure] * work.issued_iterations
            + constants.test * work.issued_tests + constants.lookup * work.lookups)


# ---- settings tried, and the choice ---------------------------------------------------------
def grid_resolutions(lo, hi, triangles: int, max_voxels: int) -> list[tuple[int, int, int]]:
    """Non-cubic grids of about lambda x triangles cells, per axis in proportion to the extents
    (Ize, Shirley & Parker 2007), for each lambda of GRID_LAMBDAS (duplicates and grids over
    max_voxels left out)."""
    extent = np.maximum(np.asarray(hi, np.float64) - np.asarray(lo, np.float64), 1e-9)
    extent = np.maximum(extent, 1e-3 * float(np.linalg.norm(extent)))  # flat axes: GridGeometry's rule
    out: list[tuple[int, int, int]] = []
    for lam in GRID_LAMBDAS:
        per_unit = (lam * max(triangles, 1) / float(np.prod(extent))) ** (1 / 3)
        res = tuple(int(max(1, round(e * per_unit))) for e in extent)
        if res not in out and math.prod(res) <= max_voxels:
            out.append(res)
    return out


def cubic_count_resolutions(max_voxels: int) -> list[tuple[int, int, int]]:
    """R x R x R cells over the scene's box for R in 2^OCTREE_LEVELS (the thesis' grids, 3.3.1):
    on a non-cubic scene their cells are stretched along its long axes, which can cross fewer cells
    per ray than the cubic cells of grid_resolutions (Sponza from inside: 128^3 took 51 steps and
    54 tests per ray, 206 x 86 x 126 cubic cells 60 and 58)."""
    return [(2**level,) * 3 for level in OCTREE_LEVELS if 8**level <= max_voxels]


def octree_resolutions(lo, hi, max_voxels: int) -> list[tuple[int, int, int]]:
    """The octree resolutions 2^OCTREE_LEVELS whose voxels over the scene's box [lo, hi] (what the
    count pass and the build cover) are at most max_voxels."""
    return [(2**level,) * 3 for level in OCTREE_LEVELS
            if GridGeometry.over_bounds(lo, hi, (2**level,) * 3, cubic=True).voxel_count <= max_voxels]


@dataclass(frozen=True)
class Option:
    """One setting with its prediction."""
    resolution: tuple[int, int, int]
    ls_n: int
    ls_min_candidates: int
    bytes: BytesPrediction
    work: Work
    seconds_per_ray: float
    fits: bool
    limit: str = ""  # a device limit that rules the setting out (its Line Space sample met it)

    def summary(self) -> dict:
        out = {"resolution": "x".join(map(str, self.resolution)), "ls_n": self.ls_n,
               "ls_min_candidates": self.ls_min_candidates, "predicted_bytes": self.bytes.total,
               "bytes_exact": self.bytes.exact, "predicted_rays_per_second": _rate(self.seconds_per_ray),
               "predicted_work": asdict(self.work), "fits_budget": self.fits}
        if self.limit:
            out["limit"] = self.limit
        return out


def _rate(seconds: float) -> float | None:
    """Rays per second; None where nothing is predicted (a setting ruled out before its walk)."""
    return 1.0 / seconds if 0 < seconds < math.inf else None


@dataclass
class Choice:
    structure: str
    chosen: Option | None  # None: no option fits the budget
    options: list[Option]
    budget_bytes: int | None
    seconds: float  # time spent choosing (count passes, Line Space samples, walks)
    constants_source: str
    requested: dict = field(default_factory=dict)
    counts_of: dict = field(default_factory=dict, repr=False)  # resolution -> VoxelCounts of every one visited
    rebuilt: list = field(default_factory=list)  # chosen options whose built structure was over the budget

    def next_after_overshoot(self, built_bytes: int, build_seconds: float) -> bool:
        """The chosen Line Space setting was built over the budget (its shaft lists are estimated
        from a sample: tens of percent off): take the cheapest other option that fits once its
        estimated part (the lists' ids) is scaled by the same error. False when there is none, or after
        AUTO_REBUILDS such rebuilds (the case then fails over the budget, naming them)."""
        failed = self.chosen
        self.rebuilt.append(dict(failed.summary(), built_bytes=int(built_bytes), build_seconds=build_seconds))
        if self.budget_bytes is None or len(self.rebuilt) > AUTO_REBUILDS:
            return False
        # What the sample estimates is mostly the lists' ids (ls_shaft_tris; the sets' offsets are a
        # word per set); where a prediction names no estimated part, the whole of it is scaled.
        def uncertain(o: Option) -> int:
            return o.bytes.estimated_bytes if failed.bytes.estimated_bytes > 0 else o.bytes.total

        scale = (built_bytes - (failed.bytes.total - uncertain(failed))) / max(uncertain(failed), 1)
        tried = {(r["resolution"], r["ls_n"], r["ls_min_candidates"]) for r in self.rebuilt}
        left = [o for o in self.options
                if o.fits and o.bytes.total + uncertain(o) * (max(scale, 1.0) - 1.0) <= self.budget_bytes
                and (o.summary()["resolution"], o.ls_n, o.ls_min_candidates) not in tried]
        if not left:
            return False
        self.chosen = min(left, key=lambda o: o.seconds_per_ray)
        return True

    @property
    def chosen_counts(self) -> VoxelCounts | None:
        """The chosen resolution's statistics (what makes its bytes exact once built)."""
        return self.counts_of.get(self.chosen.resolution) if self.chosen else None

    def no_fit_reason(self, budget_mib: float | None) -> str:
        """Why nothing was chosen: the budget (as given, in MiB) and the smallest option tried, or
        the device limit that ruled the options out."""
        sized = [o for o in self.options if o.bytes.buffers and not o.limit]
        smallest = min(sized, key=lambda o: o.bytes.total) if sized and budget_mib else None
        if smallest is None:
            limit = next((o.limit for o in self.options if o.limit), "more buffers than the driver allows")
            return f"auto {self.structure}: none of the {len(self.options)} settings tried can be built here ({limit})"
        setting = smallest.summary()["resolution"] + (f", N={smallest.ls_n}, K={smallest.ls_min_candidates}"
                                                      if smallest.ls_n else "")
        return (f"auto {self.structure}: no setting fits the device-memory budget of {budget_mib:g} MiB; the "
                f"smallest of the {len(self.options)} settings tried ({setting}) needs "
                f"{smallest.bytes.total / 2**20:.1f} MiB")

    def params(self):
        from lsbench.backends.structures.base import BuildParams

        c = self.chosen
        return BuildParams(resolution=c.resolution, ls_n=c.ls_n, ls_min_candidates=c.ls_min_candidates)

    def predicted(self, device, built) -> dict:
        """The chosen option's prediction beside what `built` measured: the record's `predicted`
        (the Line Space candidates counted by the build make memory_bytes_once_built exact)."""
        c = self.chosen
        exact = c.bytes.total
        if STRUCTURES[self.structure].line_space and self.chosen_counts is not None:
            exact = predict_bytes(device, self.structure, self.chosen_counts, c.ls_n, c.ls_min_candidates,
                                  lists=ListSizes.of(built.stats)).total
        return {"memory_bytes": c.bytes.total, "memory_bytes_exact": c.bytes.exact,
                "memory_bytes_once_built": exact, "rays_per_second": _rate(c.seconds_per_ray),
                "iterations_per_ray": c.work.iterations, "candidate_tests_per_ray": c.work.tests,
                "linespace_lookups_per_ray": c.work.lookups}

    def record(self) -> dict:
        """What the record's `auto` field holds (docs/record.md)."""
        ranked = sorted(self.options, key=lambda o: (not o.fits, bool(o.limit), o.seconds_per_ray))
        runners = [o.summary() for o in ranked if o is not self.chosen][:RUNNERS_UP]
        return {"requested": self.requested, "budget_bytes": self.budget_bytes,
                "chosen": self.chosen.summary() if self.chosen else None,
                "runners_up": runners, "options": len(self.options),
                "options_over_budget": sum(not o.fits and not o.limit for o in self.options),
                "options_over_device_limits": sum(bool(o.limit) for o in self.options),
                "choose_seconds": self.seconds, "constants": self.constants_source,
                "rebuilt_over_budget": self.rebuilt}


def resolution_walk(count: int, seconds, exhaustive: bool = False) -> list[int]:
    """The indices of the resolutions (ascending) whose options were predicted, in the order
    visited; seconds(i) predicts them and gives the cheapest fitting time at i (inf: none fits).

    The predicted time of a structure is unimodal in its resolution (finer cells: more steps,
    fewer tests; Ize, Shirley & Parker 2007), and bytes only grow with it. So the walk starts in
    the middle and goes the way the time falls (down where nothing fits) until it rises again:
    the cheapest is found with a few count passes instead of one per resolution. exhaustive:
    every index (what tests compare the walk with)."""
    visited: list[int] = []

    def at(i: int) -> float:
        visited.append(i)
        return seconds(i)

    if exhaustive or count <= 2:
        for i in range(count):
            at(i)
        return visited
    i = count // 2
    best, t_up = at(i), at(i + 1)
    if t_up < best:  # finer is cheaper: up while the time falls
        best, i = t_up, i + 1
        while i + 1 < count and (t := at(i + 1)) < best:
            best, i = t, i + 1
        return visited
    while i > 0:  # coarser: down while the time falls, or until one fits
        t = at(i - 1)
        if math.isfinite(best) and not t < best:
            break
        best, i = min(best, t), i - 1
    return visited


def choose(device, structure: str, scene, sample: RaySample, resolution="auto", ls_n="auto",
           ls_min_candidates="auto", budget_bytes: int | None = None, constants=None,
           exhaustive: bool = False) -> Choice:
    """The cheapest setting of `structure` on `scene` that fits `budget_bytes` (None: no budget),
    each "auto" parameter tried over its candidates, the others as given. Statistics are measured
    on `device` (count passes, Line Space samples), the scene uploaded once for them. The
    resolutions are walked from the middle of the list (resolution_walk); exhaustive: all of them."""
    from lsbench import backends
    from lsbench.backends.structures.base import BuildParams, parse_resolution
    from lsbench.model.stats import line_space_samples, voxel_counts

    t_start = time.perf_counter()
    info = STRUCTURES[structure]
    constants = constants or load_constants(device)
    limit = LS_MAX_VOXELS if info.line_space else min(GRID_MAX_VOXELS, device.max_buffer_bytes // 4 - 1)
    lo, hi = scene.bounds
    if resolution == "auto":
        families = [octree_resolutions(lo, hi, limit) if info.cubic_power_of_two
                    else grid_resolutions(lo, hi, scene.triangle_count, limit)]
        if not info.cubic_power_of_two and not info.line_space:
            # A grid's setting costs one count pass to predict: the stretched R^3 grids are walked too.
            # (A Line Space's costs its sample builds as well, so grid-ls keeps the cubic cells only.)
            families.append(cubic_count_resolutions(limit))
    else:
        families = [[parse_resolution(resolution)]]
    ns = (AUTO_NS if ls_n == "auto" else (int(ls_n) or 1,)) if info.line_space else (0,)
    ks = (AUTO_KS if ls_min_candidates == "auto" else (int(ls_min_candidates),)) if info.line_space else (0,)
    bufs = {"vertices": device.upload("model_vertices", np.ascontiguousarray(scene.vertices, np.float32).ravel()),
            "faces": device.upload("model_faces", np.ascontiguousarray(scene.faces, np.uint32).ravel())}
    options: list[Option] = []
    counts_of: dict = {}

    def options_at(res) -> list[Option]:
        geometry = backends.geometry_for(structure, scene, BuildParams(resolution=res), bounds=(lo, hi))
        if budget_bytes is not None and not info.cubic_power_of_two:
            # Over the budget before any triangle is counted (the counts only add bytes): the
            # count pass is skipped (BMW grid 256^3 at 64 MiB: 0.44-0.54 s of a 1.3 s choice).
            # Octrees are not asked: none of their bytes is per voxel.
            floors = {n: _bytes_whatever_the_counts(device, structure, geometry, n) for n in ns}
            if all(f.total > budget_bytes for f in floors.values()):
                return [Option(res, n, ks[0], f, Work(0.0, 0.0, 0.0, 0.0, 0.0), math.inf, False)
                        for n, f in floors.items()]
        counts = voxel_counts(device, bufs, scene, geometry)
        counts_of[res] = counts
        if not info.line_space:
            return [_option(device, structure, counts, sample, res, 0, 0, None, budget_bytes, constants)]
        # Line Space samples only for the N whose offsets alone (at the largest K) may fit.
        wanted = [n for n in ns if budget_bytes is None or _offsets_bytes(counts, n, max(ks)) <= budget_bytes]
        samples = line_space_samples(device, bufs, scene.triangle_count, geometry, counts, wanted) if wanted else {}
        densest = counts.densest
        out = []
        for n in ns:
            # Every K at or over the densest cell's count builds no Line Space at all: one of them is tried.
            tried = [k for k in ks if k < densest] + [k for k in ks if k >= densest][:1]
            for k in tried:
                out.append(_option(device, structure, counts, sample, res, n, k, samples.get(n), budget_bytes,
                                   constants))
        return out

    per_resolution: dict = {}

    def seconds_at(res) -> float:
        """The cheapest fitting predicted time at `res` (inf: none fits), predicted once."""
        if res not in per_resolution:
            per_resolution[res] = options_at(res)
            options.extend(per_resolution[res])
        return min((o.seconds_per_ray for o in per_resolution[res] if o.fits), default=math.inf)

    try:
        for resolutions in families:  # each ordered from coarse to fine: resolution_walk's premise
            resolution_walk(len(resolutions), lambda i: seconds_at(resolutions[i]), exhaustive)
    finally:
        for b in bufs.values():
            device.release(b)
    fitting = [o for o in options if o.fits]
    chosen = min(fitting, key=lambda o: o.seconds_per_ray) if fitting else None
    requested = {"resolution": resolution, "ls_n": ls_n, "ls_min_candidates": ls_min_candidates}
    return Choice(structure, chosen, options, budget_bytes, time.perf_counter() - t_start,
                  constants.source, requested, counts_of)


def resolve_case(case, device, scene, rays, hit_t, budget_bytes: int | None):
    """The BuildParams of `case` and, for a case with "auto" parameters, the Choice that picked
    them (execute.py calls this once, before the build); (None, choice) when no option fits the
    budget (choice.no_fit_reason(budget_mib) says why)."""
    if not case.auto:
        return case.build_params(), None
    choice = choose(device, case.structure, scene, ray_sample(rays, hit_t, width=simd_lanes(device)),
                    case.resolution, case.ls_n,
                    case.ls_min_candidates, budget_bytes)
    return (choice.params() if choice.chosen else None), choice


def _bytes_whatever_the_counts(device, structure: str, geometry: GridGeometry, n: int) -> BytesPrediction:
    """The bytes of `structure` at `geometry` (N = n) that do not depend on the counts: the
    recipe's own prediction (predict_bytes) for a grid with no triangle, a lower bound (exact =
    False) of its bytes at any counts (a grid's offsets, 4 bytes per voxel; grid-ls's voxel ->
    Line Space index too)."""
    empty = VoxelCounts(geometry, None, (np.zeros(0, np.int64), np.zeros(0, np.uint32)))
    return BytesPrediction(predict_bytes(device, structure, empty, n, 0, lists=ListSizes(0, 0)).buffers, False)


def _offsets_bytes(counts: VoxelCounts, n: int, k: int) -> int:
    """The Line Spaces' per-cell part of ls_shaft_offsets (a lower bound of their bytes)."""
    return 4 * offset_entries(counts.above(k)[0], n, 0)


def _option(device, structure, counts, sample, res, n, k, ls, budget_bytes, constants) -> Option:
    from lsbench.backends.device import DeviceLimitError

    line_space = STRUCTURES[structure].line_space
    no_cells = line_space and counts.above(k)[0] == 0  # K over every cell: no Line Space is built
    if ls is not None and ls.limit and not no_cells:  # the device cannot build this N here
        return Option(res, n, k, BytesPrediction({}, False), Work(0.0, 0.0, 0.0, 0.0, 0.0), math.inf, False, ls.limit)
    work = predict_work(structure, counts, sample, k, None if no_cells else ls)
    if line_space and ls is None and not no_cells:  # pruned: the offsets alone are over the budget
        b = BytesPrediction({"ls_shaft_offsets": _offsets_bytes(counts, n, k)}, False)
        return Option(res, n, k, b, work, seconds_per_ray(structure, work, constants, sample.rays), False)
    try:
        b = predict_bytes(device, structure, counts, n, k, sample=None if no_cells else ls,
                          lists=ListSizes(0, 0) if no_cells else None)
        over_device = False
    except DeviceLimitError:  # more buffers than the driver allows: never fits
        b, over_device = BytesPrediction({}, False), True
    fits = not over_device and (budget_bytes is None or b.total <= budget_bytes)
    return Option(res, n, k, b, work, seconds_per_ray(structure, work, constants, sample.rays), fits)


def bytes_at_least(device, structure: str, scene, params) -> tuple[int, bool]:
    """Before a build of `params`: the bytes it will allocate at least, from one count pass on the
    device, and whether that is exact (grid, svo, esvo: yes; a Line Space: all but its shaft
    candidates, which are not known before its count pass). execute.py fails a case over its
    budget with this instead of building it."""
    from lsbench import backends
    from lsbench.backends.structures import svo
    from lsbench.model.stats import voxel_counts

    info = STRUCTURES[structure]
    if info.cubic_power_of_two:
        svo.octree_depth(params.resolution)  # the recipe's own ValueError for a resolution it cannot build
    geometry = backends.geometry_for(structure, scene, params)
    bufs = {"vertices": device.upload("model_vertices", np.ascontiguousarray(scene.vertices, np.float32).ravel()),
            "faces": device.upload("model_faces", np.ascontiguousarray(scene.faces, np.uint32).ravel())}
    try:
        counts = voxel_counts(device, bufs, scene, geometry)
    finally:
        for b in bufs.values():
            device.release(b)
    n = (params.ls_n or 1) if info.line_space else 0
    return predict_bytes(device, structure, counts, n, params.ls_min_candidates, lists=ListSizes(0, 0)).total, \
        not info.line_space
