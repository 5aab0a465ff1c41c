"""What every backend provides: buffers, compiled kernels, dispatch, voxelization, scan, timing,
and the device clock of the profiling kernels.

Structures (backends/structures/*.py) are written once against this interface and never ask
which backend they run on; `glsl.py` and `opencl.py` implement it with moderngl and pyopencl.
Nothing here runs on the host in place of the device: every build and trace step is a kernel
launch.
"""
from __future__ import annotations

import abc
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from .kernels import KernelSpec


class DeviceLimitError(RuntimeError):
    """A case needs more than the driver allows (buffer size, work groups, memory, index width).
    The message names the limit; the harness records the case as failed and goes on."""


class OverBudgetError(DeviceLimitError):
    """A build given a device-memory budget (BuildParams.budget_bytes) stopped as soon as it knew
    the structure would take more: `needed_bytes`, exact (a Line Space build knows it after its
    count pass, before the fill)."""

    def __init__(self, needed_bytes: int, budget_bytes: int, when: str):
        self.needed_bytes, self.budget_bytes, self.when = int(needed_bytes), int(budget_bytes), when
        super().__init__(self.reason(budget_bytes / 2**20))

    def reason(self, budget_mib: float) -> str:
        """The one-line reason, the budget as the user gave it (MiB)."""
        return (f"the structure takes {self.needed_bytes / 2**20:.1f} MiB ({self.when}), over the device-memory "
                f"budget of {budget_mib:g} MiB (budget_mib, --budget)")


class DeviceError(RuntimeError):
    """The driver reported an error (compile failure, GL error after a dispatch, ...)."""


def start_failure_hint(install_hint: str) -> str:
    """What to suggest when a device does not start. Under an address-space limit (RLIMIT_AS:
    `lsbench run --memory-budget` sets one in each case worker, `ulimit -v` in a shell) the
    installed drivers fail to start for want of memory (PoCL: no platform, DEVICE_NOT_AVAILABLE or
    'cannot build kernels' at 200-600 MiB here; EGL: eglInitialize failed), so the limit is named
    as the likely cause instead of `install_hint`, which would send the user to install drivers
    that are there."""
    import resource

    soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    if soft == resource.RLIM_INFINITY:
        return install_hint
    return (f"an address-space limit of {soft / 2**20:.0f} MiB is in force (RLIMIT_AS, which "
            "--memory-budget sets): the likely cause; give the case more memory")


@dataclass
class DeviceBuffer:
    name: str
    nbytes: int  # allocated
    handle: object  # moderngl.Buffer or pyopencl.Buffer
    used_bytes: int | None = None  # bytes that hold data, when less than allocated

    @property
    def used(self) -> int:
        return self.nbytes if self.used_bytes is None else self.used_bytes


@dataclass
class Timing:
    seconds: list[float]  # one entry per repeat, device time of the measured launches
    clock: str  # which clock measured it


class Device(abc.ABC):
    backend: str  # "glsl" or "opencl"
    # The exact triangle/shaft test the Line Space build runs fastest on this backend's driver
    # (structures/linespace.py: "sat" separating axes, or "clip" Sutherland-Hodgman clipping).
    line_space_test: str

    @abc.abstractmethod
    def info(self) -> dict:
        """device, driver, backend_version and the limits that matter (max buffer bytes ...)."""

    @property
    @abc.abstractmethod
    def max_buffer_bytes(self) -> int: ...

    @abc.abstractmethod
    def alloc(self, name: str, nbytes: int, zero: bool = True) -> DeviceBuffer: ...

    @abc.abstractmethod
    def upload(self, name: str, array: np.ndarray) -> DeviceBuffer: ...

    @abc.abstractmethod
    def read(self, buf: DeviceBuffer, dtype, count: int | None = None) -> np.ndarray: ...

    @abc.abstractmethod
    def fill_zero(self, buf: DeviceBuffer, nbytes: int | None = None) -> None:
        """Zero the buffer's first `nbytes` (default: all of it)."""

    def alloc_readable(self, name: str, nbytes: int) -> DeviceBuffer:
        """A zeroed buffer that the host reads back whole once the kernels are done (read_readable):
        the model's count passes. Here a plain `alloc`; a backend whose device works in host memory
        lends it the host array itself (opencl.py), so reading back copies nothing."""
        return self.alloc(name, nbytes)

    def read_readable(self, buf: DeviceBuffer, dtype, count: int | None = None) -> np.ndarray:
        """An alloc_readable buffer's contents after the kernels, a host array of its own (valid
        after release)."""
        return self.read(buf, dtype, count)

    def write(self, buf: DeviceBuffer, array: np.ndarray, offset: int = 0) -> None:
        """Copy `array` into buf from byte `offset` on (the ray list of a trace slice)."""
        raise NotImplementedError(f"{self.backend}: write")

    # Loop iterations (walk steps + candidate tests) one traversal launch may run per ray before
    # the host re-dispatches the unfinished rays (traversal in bounded slices, shaders/common/trace.h);
    # None: unbounded, one launch runs whole rays. llvmpipe sets one (glsl.py); PoCL and NVIDIA none.
    loop_budget: int | None = None

    # Rays per work item of the packet traversals (shaders/common/bvh.h: BVH_PACKET), for coherent ray
    # sets (backends.packet_width): 8 on a CPU device whose work items run one at a time, so that the
    # kernel's vector types are its only SIMD (PoCL); 4 on llvmpipe, whose lanes load their nodes
    # one by one (glsl.py: LLVMPIPE_PACKET_WIDTH); 1 (a ray per work item) on GPUs.
    packet_width: int = 1
    # The queries whose coherent sets go in packets: both on PoCL (shadow rays to a light 0.75 of the
    # one-ray time, docs/profiles.md section 8); on llvmpipe closest hits only (any-hit shadow rays
    # took 1.19-1.24 of it there: a packet's walk ends when its last lane's does).
    packet_queries: tuple = ("closest", "any")
    # True where the work items of a work group run one after the other on one core (PoCL's CPU
    # device), False where the driver runs them in SIMD lanes (llvmpipe, GPUs): a loop that one work
    # item in 32 runs for its neighbours is cheap on the first and stalls the other lanes on the
    # second (linespace.h: ls_set_len_kernel).
    serial_work_items: bool = False

    @abc.abstractmethod
    def release(self, buf: DeviceBuffer) -> None:
        """Free buf's device memory now (the driver's handle is unusable afterwards)."""

    @abc.abstractmethod
    def compile(self, spec: KernelSpec) -> object:
        """Compile spec's kernel (cached by spec.key) and return the driver's handle; recipes call
        it in prepare() so that no build or trace timing includes a compile."""

    @abc.abstractmethod
    def compile_voxelizer(self, spec: KernelSpec) -> object:
        """Compile what `voxelize` runs for spec (cached), as `compile` does for dispatch."""

    @abc.abstractmethod
    def voxelize(self, spec: KernelSpec, n_tris: int, buffers: dict[str, DeviceBuffer],
                 uniforms: dict[str, object], resolution: tuple[int, int, int]) -> None:
        """Conservative voxelization of n_tris triangles into a grid of `resolution` (Delgado Krämer 2019, 3.4):
        spec's voxelize_column (shaders/common/grid.h) per raster fragment on GLSL (on llvmpipe
        only for the triangles of large bounds, the others through its body as a compute kernel),
        its body once per triangle as a compute kernel on OpenCL. Same voxel -> triangle sets
        either way."""

    @abc.abstractmethod
    def dispatch(self, spec: KernelSpec, n_items: int, buffers: dict[str, DeviceBuffer],
                 uniforms: dict[str, object] | None = None) -> None:
        """Run spec's body once per item 0..n_items-1."""

    @abc.abstractmethod
    def exclusive_scan(self, src: DeviceBuffer, n: int, name: str) -> tuple[DeviceBuffer, int]:
        """Exclusive prefix sum of n uint32 values into a new buffer of n+1 entries (the last
        one is the total, so buffer[i]..buffer[i+1] is item i's range); returns the total."""

    @abc.abstractmethod
    def _scan_in_place(self, buf: DeviceBuffer, n: int) -> None:
        """Exclusive prefix sum of the first n uint32 values of buf, in place."""

    @abc.abstractmethod
    def read_uint(self, buf: DeviceBuffer, index: int) -> int:
        """One uint32 entry of buf."""

    def scan_in_place(self, buf: DeviceBuffer, n: int) -> int:
        """Exclusive prefix sum of buf's first n uint32 values in place (no second buffer: for
        arrays near the memory limit); returns their sum modulo 2^32."""
        if n <= 0:
            return 0
        last = self.read_uint(buf, n - 1)
        self._scan_in_place(buf, n)
        return (self.read_uint(buf, n - 1) + last) & 0xFFFFFFFF

    @abc.abstractmethod
    def finish(self) -> None: ...

    # --- device time per kernel (where the build's time goes; `lsbench speedtest --work`) -------
    def start_kernel_log(self) -> None:
        """Record the device time of every dispatch from now on, per kernel name. A backend
        that cannot time one kernel (llvmpipe: GL_TIME_ELAPSED reads 0 for compute) records none."""

    def kernel_seconds(self) -> dict[str, float] | None:
        """Device seconds per kernel name of the dispatches since start_kernel_log (which ends the
        log), or None where the backend cannot time a kernel."""
        return None

    @abc.abstractmethod
    def time_dispatch(self, spec: KernelSpec, n_items: int, buffers: dict[str, DeviceBuffer],
                      uniforms: dict[str, object] | None, warmup: int, repeats: int,
                      between: Callable[[], object] | None = None) -> Timing:
        """Warm-up launches (not counted: compile, first launch), then `repeats` timed ones;
        `between` is called after each timed launch has finished, outside its timing (execute.py
        times Embree there, so the two figures of a ratio see the same load on a shared machine)."""

    def dispatch_timed(self, spec: KernelSpec, n_items: int, buffers: dict[str, DeviceBuffer],
                       uniforms: dict[str, object] | None = None) -> tuple[float, str]:
        """One launch (as dispatch), waited for; its device time and the clock that measured it
        (the slices of a timed trace, whose launches differ, are timed one by one and summed)."""
        raise NotImplementedError(f"{self.backend}: dispatch_timed")

    # --- device clock of the profiling kernels (COUNT_WORK, shaders/common/trace.h) --------------
    @abc.abstractmethod
    def clock_defines(self) -> tuple[tuple[str, str], ...]:
        """Defines that give the profiling kernels a device clock (CLOCK_START()/CLOCK_ELAPSED(),
        preludes + common/trace.h), only where the device has one; () elsewhere, and the counters'
        clock field then reads 0. `clock_info` describes the same choice."""

    @abc.abstractmethod
    def clock_info(self) -> dict:
        """What the clock field of the work counters holds: available, unit, source, and a note
        naming the device (and why there is no clock where there is none)."""

    def check_size(self, name: str, nbytes: int) -> None:
        limit = self.max_buffer_bytes
        if nbytes > limit:
            raise DeviceLimitError(
                f"buffer '{name}' needs {nbytes} bytes ({nbytes / 2**20:.1f} MiB), over the {self.backend} "
                f"driver's per-buffer limit of {limit} bytes ({limit / 2**20:.0f} MiB, {self.limit_name})")

    limit_name = "max buffer size"

    def check_memory(self, name: str, nbytes: int) -> None:
        """Fail early when `nbytes` (one array, possibly split over buffers) cannot fit the device
        memory next to what is allocated. Backends that know their memory override it."""

    def loop_limit_error(self, what: str) -> DeviceLimitError:
        """The driver cut a kernel's loops (the probe of shaders/common/geometry.h); `what` names the
        loops and why they ran long."""
        return DeviceLimitError(
            f"the {self.backend} driver cut short {what}; llvmpipe stops a shader invocation's loops "
            "after 65535 iterations in all (LP_MAX_TGSI_LOOP_ITERATIONS)")


def check_item_count(spec, n_items: int) -> None:
    """Kernels index items with a 32-bit gid and get n_items as a uint uniform."""
    if n_items > 0xFFFFFFFF:
        raise DeviceLimitError(f"{spec.name}: {n_items} items overflow the 32-bit item index (gid, n_items)")


def as_float4(v, w: float = 0.0) -> tuple[float, float, float, float]:
    return (float(v[0]), float(v[1]), float(v[2]), float(w))


def as_int4(v, w: int = 0) -> tuple[int, int, int, int]:
    return (int(v[0]), int(v[1]), int(v[2]), int(w))
