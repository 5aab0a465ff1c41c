"""Plain data shared by every structure: grid geometry, build parameters, a recipe's build result,
built structure, hits."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from ..device import Device, DeviceBuffer, as_float4, as_int4
from ..kernels import ORDER_BUFFER, PACKET_UNIFORM, SLICE_BUFFER, SLICE_UNIFORMS, WORK_BUFFER, KernelSpec

# Overlap epsilon of the conservative voxelization, in voxel units: a triangle within this
# distance of a voxel counts as overlapping it, so float32 rounding never drops a pair.
BOX_EPS = 1e-3


def parse_resolution(value) -> tuple[int, int, int]:
    """64 -> (64, 64, 64); "64x32x16" or (64, 32, 16) -> non-cubic."""
    if isinstance(value, (tuple, list)):
        res = tuple(int(v) for v in value)
    elif isinstance(value, str) and "x" in value.lower():
        res = tuple(int(v) for v in value.lower().split("x"))
    else:
        res = (int(value),) * 3
    if len(res) != 3 or min(res) < 1:
        raise ValueError(f"resolution must be a positive integer or RxRyRz, got {value!r}")
    return res  # type: ignore[return-value]


def format_resolution(res: tuple[int, int, int]) -> str:
    return str(res[0]) if res[0] == res[1] == res[2] else "x".join(map(str, res))


@dataclass(frozen=True)
class GridGeometry:
    """Axis-aligned grid over the scene: voxel (i,j,k) covers origin + [i,i+1]x.. * voxel_size.

    An octree's geometry (cube > 0) has cubic voxels of its bounding cube's leaf level, 2^L = cube
    per edge, but `resolution` covers only the scene's box: the cube is anchored at `origin` and its
    cells past `resolution` on the short axes are empty by construction, so neither the voxelization
    nor the walk pays for them (Delgado Krämer 2019, 6.3 and 7: the cube wastes space on
    non-cubic scenes)."""
    origin: tuple[float, float, float]
    voxel_size: tuple[float, float, float]
    resolution: tuple[int, int, int]
    cube: int = 0  # octrees: the cube's edge in voxels (2^L, >= every resolution); 0 for a grid

    @staticmethod
    def over_bounds(lo, hi, resolution, cubic: bool = False) -> "GridGeometry":
        """Grid over [lo, hi], padded by a hair so no triangle lies on the outer boundary.
        A flat axis (zero extent) gets a small extent so voxels never have zero size.
        cubic (octrees; resolution (R, R, R)): cubic voxels, R along the longest axis, and on the
        others the fewest that cover the scene, centred on it (`cube` = R)."""
        lo = np.asarray(lo, np.float64)
        hi = np.asarray(hi, np.float64)
        diag = float(np.linalg.norm(hi - lo)) or 1.0
        extent = np.maximum(hi - lo, 1e-3 * diag)
        centre = 0.5 * (lo + hi)
        extent = extent * (1 + 2e-5) + 1e-6 * diag + 1e-30
        res = np.asarray(resolution, np.float64)
        cube = 0
        if cubic:
            cube = int(resolution[0])
            edge = extent.max() / cube
            # The padding above keeps every triangle off the box's faces on the short axes too.
            res = np.minimum(np.ceil(extent / edge), cube)
            extent = res * edge
        origin = centre - 0.5 * extent
        return GridGeometry(tuple(origin.tolist()), tuple((extent / res).tolist()),
                            tuple(int(r) for r in res), cube)

    @property
    def voxel_count(self) -> int:
        rx, ry, rz = self.resolution
        return rx * ry * rz

    def uniforms(self) -> dict:
        return {
            "grid_origin": as_float4(self.origin),
            "grid_inv_voxel": as_float4(1.0 / np.asarray(self.voxel_size)),
            "grid_res": as_int4(self.resolution),
            "box_eps": BOX_EPS,
            "loop_probe": 2,  # shaders/common/geometry.h: loops_intact
        }


@dataclass
class BuildParams:
    resolution: tuple[int, int, int]
    ls_n: int = 0  # Line Space patches per face edge (0 = no Line Space)
    ls_min_candidates: int = 0  # build Line Spaces only in voxels with more candidates than this
    bounding_cube: bool = False  # a grid on an octree's geometry (GridGeometry.over_bounds cubic): compare with octrees
    leaf_size: int = 0  # bvh, bvh-ls: most triangles per leaf (0 = the structure's default; bvh.LEAF_SIZES)
    options: dict = field(default_factory=dict)
    # Not part of the setting: the device-memory budget of the structure. A build that learns it
    # would take more stops there with OverBudgetError (a Line Space after its count pass, before
    # its lists are filled: on llvmpipe that halved such a case, docs/fit.md). None: no budget.
    budget_bytes: int | None = None


@dataclass
class BuildResult:
    """What a structure recipe's build(device, scene_buffers, n_tris, geometry, params) returns."""
    buffers: dict[str, DeviceBuffer]  # the structure's own buffers (what memory_bytes counts)
    uniforms: dict  # the trace kernel's uniforms
    trace_spec: KernelSpec  # the closest-hit kernel of this build (its defines: depth, splits ...)
    stats: dict = field(default_factory=dict)  # counts of the build (voxels, references, nodes, ...)
    # Whether the walk can stop at a loop budget and resume in the next launch (trace.h: SLICED);
    # a walk that cannot (bvh, bvh-ls: their state is a stack) runs its rays whole in one launch.
    suspends: bool = True


@dataclass
class Built:
    structure: str
    device: Device
    params: BuildParams
    geometry: GridGeometry
    scene_buffers: dict[str, DeviceBuffer]
    buffers: dict[str, DeviceBuffer]  # the structure's own buffers (what memory_bytes counts)
    uniforms: dict
    trace_spec: KernelSpec
    build_seconds: float = 0.0
    stats: dict = field(default_factory=dict)
    suspends: bool = True  # BuildResult.suspends
    # The ray order measured for each ray set traced on this structure (backends.trace_order):
    # (rays' hash, query, slice budget, rays per work item refilled) -> (order, {order: probe seconds})
    ray_orders: dict = field(default_factory=dict)
    # The ray sets (rays' hash, query) whose refilled trace (backends.refill_rays) the driver's loop
    # budget cut: they are traced one ray per work item from then on.
    refill_cut: set = field(default_factory=set)

    def memory(self) -> dict[str, dict[str, int]]:
        return {name: {"allocated": b.nbytes, "used": b.used} for name, b in self.buffers.items()}

    @property
    def memory_bytes(self) -> int:
        return sum(b.nbytes for b in self.buffers.values())

    def release(self) -> None:
        for b in list(self.buffers.values()) + list(self.scene_buffers.values()):
            self.device.release(b)


@dataclass
class Hits:
    prim_ids: np.ndarray  # int32, -1 = miss
    distances: np.ndarray  # float32, inf for a miss
    work: np.ndarray | None = None  # (N, 4) uint32 counters of a profiling trace, WORK_CHANNELS
    slices: int = 1  # launches the trace took (more than 1: traversal in bounded slices)
    slice_budget: int | None = None  # loop iterations per ray and launch it started with (None: unbounded)
    packet: int = 1  # rays per work item (backends.packet_width: more than 1, the packet traversal)
    refill: int = 1  # rays per work item, one after the other in a lane (backends.refill_rays)
    order: str = "given"  # the order the rays were traced in (backends.trace_order)
    order_probe: dict | None = None  # where the order was measured: device seconds of each order


QUERIES = ("closest", "any")


def for_query(spec: KernelSpec, query: str) -> KernelSpec:
    """The traversal kernel that answers `query` (the same KERNEL_<name>, the same walk):
    "closest" is the kernel as built, "any" compiles QUERY_ANY in (shaders/common/trace.h: the
    first hit in [tmin, tmax) ends the candidate loop and the walk)."""
    if query not in QUERIES:
        raise ValueError(f"unknown query {query!r}; choose one of {', '.join(QUERIES)}")
    return spec.with_defines(QUERY_ANY=1) if query == "any" else spec


# The columns of Hits.work, in the order the COUNT_WORK kernels write them (shaders/common/trace.h).
WORK_CHANNELS = ("iterations", "candidate_tests", "linespace_lookups", "clock")


def with_work_counters(spec: KernelSpec, device: Device | None = None) -> KernelSpec:
    """The profiling variant of a traversal kernel (the same KERNEL_<name>): COUNT_WORK compiled
    in, a work buffer added, and the device clock where `device` has one (Device.clock_defines;
    without a device the clock field stays 0)."""
    clock = device.clock_defines() if device is not None else ()
    return dataclasses.replace(spec, buffers=spec.buffers + (WORK_BUFFER,),
                               defines=spec.defines + (("COUNT_WORK", "1"),) + clock)


def packeted(spec: KernelSpec, width: int) -> KernelSpec:
    """The packet variant of a traversal kernel (the same KERNEL_<name>, the same tests per ray):
    BVH_PACKET = width rays per work item, packet_rays the ray count (work item g traces rays
    g * width .. g * width + width - 1; shaders/common/bvh.h)."""
    return dataclasses.replace(spec, uniforms=spec.uniforms + (PACKET_UNIFORM,),
                               defines=spec.defines + (("BVH_PACKET", str(int(width))),))


def refilled(spec: KernelSpec, rays: int) -> KernelSpec:
    """The variant of a single-ray traversal kernel whose work item g traces up to `rays` rays,
    g, g + n_items, ..., each lane starting its next ray where the last one ended (the same
    KERNEL_<name>, the same walk per ray; BVH_REFILL, shaders/common/bvh.h); packet_rays the
    ray count."""
    return dataclasses.replace(spec, uniforms=spec.uniforms + (PACKET_UNIFORM,),
                               defines=spec.defines + (("BVH_REFILL", str(int(rays))),))


def ordered(spec: KernelSpec) -> KernelSpec:
    """The variant of a traversal kernel whose work item g traces ray order_ids[g] (the same
    KERNEL_<name>, the same walk; ORDERED_RAYS, shaders/common/trace.h; backends/ray_order.py)."""
    return dataclasses.replace(spec, buffers=spec.buffers + (ORDER_BUFFER,),
                               defines=spec.defines + (("ORDERED_RAYS", "1"),))


def sliced(spec: KernelSpec) -> KernelSpec:
    """The variant of a traversal kernel that runs in bounded slices (the same KERNEL_<name>, the
    same walk): SLICED compiled in, the slice state buffer and the budget bound
    (shaders/common/trace.h; backends/__init__.py: trace)."""
    return dataclasses.replace(spec, buffers=spec.buffers + (SLICE_BUFFER,), uniforms=spec.uniforms + SLICE_UNIFORMS,
                               defines=spec.defines + (("SLICED", "1"),))
