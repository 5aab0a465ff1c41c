"""OpenCL backend: pyopencl on a GPU device when there is one, else the CPU (PoCL here).
`LSBENCH_OPENCL_DEVICE=substring` picks a device by name."""
from __future__ import annotations

import os

import numpy as np

from .device import (Device, DeviceBuffer, DeviceError, DeviceLimitError, Timing, check_item_count,
                     start_failure_hint)
from .kernels import SHADER_ROOT, KernelSpec, kernel_defines, numbered, read_common

# Rays per work item of the packet traversals on a CPU device (bvh.h: BVH_PACKET, 8 or 16). PoCL,
# Sponza 512² primary rays: 8 and 16 both took 0.57-0.62 of the single-ray kernel's device time;
# on incoherent rays 8 lost less (1.54x against 1.84x), and coherence (backends.packet_width)
# keeps such sets on single rays anyway (docs/profiles.md, section 8).
CPU_PACKET_WIDTH = 8

CL_TYPES = {"float": "float", "uint": "uint", "int": "int", "float4": "float4", "uint4": "uint4",
            "int4": "int4", "uint2": "uint2"}


def _prelude() -> str:
    return (SHADER_ROOT / "opencl" / "prelude.cl").read_text()


def kernel_source(spec: KernelSpec, item_loop: bool = False) -> str:
    """Ctx struct with every buffer pointer and scalar, the shared code, and the entry point: one
    item per work item, or with `item_loop` (KernelSpec.item_loop on a device that runs work items
    one after the other) local_size consecutive items per work item, in a loop."""
    fields, params, assigns = [], [], []
    for b in spec.buffers:
        const = "const " if b.access in ("r", "t") else ""
        decl = f"__global {const}{CL_TYPES[b.type]}* {b.name}"
        fields.append(f"    {decl};")
        params.append(decl)
        assigns.append(f"    c.{b.name} = {b.name};")
    for name, type_name in [(u.name, u.type) for u in spec.uniforms] + [("n_items", "uint")]:
        fields.append(f"    {CL_TYPES[type_name]} {name};")
        params.append(f"{CL_TYPES[type_name]} {name}")
        assigns.append(f"    c.{name} = {name};")
    return (
        _prelude() + kernel_defines(spec)
        + "typedef struct {\n" + "\n".join(fields) + "\n} Ctx;\n"
        + read_common(spec.headers)
        + f"\n__kernel void k_{spec.name}(" + ", ".join(params) + ") {\n"
        + "    Ctx c;\n" + "\n".join(assigns) + "\n"
        + (f"    uint first = (uint)get_global_id(0) * {spec.local_size}u;\n"
           f"    uint end = min(first + {spec.local_size}u, n_items);\n"
           f"    for (uint gid = first; gid < end; ++gid) {spec.body}(&c, gid);\n}}\n" if item_loop else
           "    uint gid = (uint)get_global_id(0);\n    if (gid >= n_items) return;\n"
           f"    {spec.body}(&c, gid);\n}}\n"))


def _numpy_scalar(type_name: str, value):
    import pyopencl.cltypes as clt

    if type_name == "float":
        return np.float32(value)
    if type_name == "uint":
        return np.uint32(value)
    if type_name == "int":
        return np.int32(value)
    maker = {"float4": clt.make_float4, "uint4": clt.make_uint4, "int4": clt.make_int4}[type_name]
    return maker(*value)


class OpenCLDevice(Device):
    backend = "opencl"
    limit_name = "CL_DEVICE_MAX_MEM_ALLOC_SIZE"
    line_space_test = "edges"  # PoCL: as fast as the clipper (docs/linespace-build.md)

    def __init__(self):
        import pyopencl as cl

        self.cl = cl
        self.device = self._pick_device()
        self.ctx = cl.Context([self.device])
        self.queue = cl.CommandQueue(self.ctx, properties=cl.command_queue_properties.PROFILING_ENABLE)
        # PoCL runs a CPU device's work items one after the other (docs/profiles.md, section 1): a
        # packet of rays per work item puts them in the vector lanes (Device.packet_width).
        self.serial_work_items = bool(self.device.type & cl.device_type.CPU)
        self.packet_width = CPU_PACKET_WIDTH if self.serial_work_items else 1
        self._programs: dict = {}
        self._kernel_log: list | None = None  # (kernel name, event) while start_kernel_log is on
        self._scan = None
        # fill_zero's kernel, built here so that no timed build compiles it (33 ms from PoCL's cache)
        src = "__kernel void fill_zero(__global uint *a, uint n) { uint i = get_global_id(0); if (i < n) a[i] = 0u; }"
        self._zero_kernel = cl.Kernel(cl.Program(self.ctx, src).build(), "fill_zero")
        # Bytes of the live buffers: PoCL hands out buffers past CL_DEVICE_GLOBAL_MEM_SIZE and
        # fails (or swaps) later, so alloc checks the sum itself and names the limit.
        self._live: dict[int, int] = {}
        self._host_arrays: dict[int, np.ndarray] = {}  # alloc_readable's buffers: their host arrays

    def _pick_device(self):
        cl = self.cl
        try:
            platforms = cl.get_platforms()
        except cl.Error as exc:
            raise DeviceError(f"no OpenCL platform ({exc}); " + start_failure_hint(
                "install an ICD, e.g. `pip install pocl-binary-distribution` for the CPU")) from exc
        try:
            devices = [d for p in platforms for d in p.get_devices()]
        except cl.Error as exc:  # DEVICE_NOT_AVAILABLE, OUT_OF_HOST_MEMORY under a low RLIMIT_AS
            raise DeviceError(f"cannot list OpenCL devices ({exc}); " + start_failure_hint(
                "check the ICD's driver")) from exc
        if not devices:
            raise DeviceError("no OpenCL device found; " + start_failure_hint(
                "`pip install pocl-binary-distribution` gives a CPU one"))
        wanted = os.environ.get("LSBENCH_OPENCL_DEVICE")
        if wanted:
            devices = [d for d in devices if wanted.lower() in d.name.lower()]
            if not devices:
                raise DeviceError(f"LSBENCH_OPENCL_DEVICE={wanted!r} matches no OpenCL device")
        # GPUs first. A device whose compiler cannot build a trivial kernel is skipped: the
        # pip PoCL 3.0 (LLVM 14) reports CPU 'generic' on CPUs newer than LLVM 14 and then
        # rejects it, while Debian's PoCL 3.1 on the same machine works.
        devices.sort(key=lambda d: 0 if d.type & cl.device_type.GPU else 1)
        self.skipped_devices = []
        for d in devices:
            try:
                ctx = cl.Context([d])
                cl.Program(ctx, "__kernel void probe(__global int* a) { a[0] = 1; }").build()
                return d
            except cl.Error as exc:
                first = (str(exc).strip().splitlines() or ["?"])[0]
                self.skipped_devices.append(f"{d.name.strip()} ({d.platform.version.strip()}): "
                                            f"cannot build kernels ({first[:120]})")
        raise DeviceError("no OpenCL device can build kernels: " + "; ".join(self.skipped_devices)
                          + "; " + start_failure_hint("on Debian `apt-get install pocl-opencl-icd` "
                                                      "gives a working CPU device"))

    # --- information -----------------------------------------------------------------------
    def info(self) -> dict:
        d = self.device
        import pyopencl

        return {
            "backend": "opencl",
            "device": d.name.strip(),
            "driver": f"{d.platform.name.strip()} {d.platform.version.strip()}; driver {d.driver_version}",
            "vendor": d.vendor.strip(),
            "backend_version": f"pyopencl {pyopencl.VERSION_TEXT}",
            "max_buffer_bytes": int(d.max_mem_alloc_size),
            "global_mem_bytes": self.global_mem_bytes,
            "device_type": self.cl.device_type.to_string(d.type),
            "skipped_devices": self.skipped_devices,
        }

    @property
    def max_buffer_bytes(self) -> int:
        return int(self.device.max_mem_alloc_size)

    # --- buffers ---------------------------------------------------------------------------
    def _new_buffer(self, name: str, nbytes: int, make) -> DeviceBuffer:
        """The buffer that make() creates, after the per-buffer and device-memory checks; a driver
        error becomes a DeviceLimitError naming the buffer (alloc, upload, alloc_readable)."""
        self.check_size(name, nbytes)
        self.check_memory(name, nbytes)
        try:
            handle = make()
        except self.cl.Error as exc:
            raise DeviceLimitError(f"allocating buffer '{name}' of {nbytes} bytes failed: {exc}") from exc
        return self._track(DeviceBuffer(name, nbytes, handle))

    def alloc(self, name, nbytes, zero=True):
        cl = self.cl
        nbytes = max(int(nbytes), 4)

        buf = self._new_buffer(name, nbytes, lambda: cl.Buffer(self.ctx, cl.mem_flags.READ_WRITE, nbytes))
        if zero:
            self.fill_zero(buf)
        return buf

    @property
    def global_mem_bytes(self) -> int:
        return int(self.device.global_mem_size)

    def check_memory(self, name: str, nbytes: int) -> None:
        live = sum(self._live.values())
        limit = self.global_mem_bytes
        if live + nbytes > limit:
            raise DeviceLimitError(
                f"buffer '{name}' needs {nbytes / 2**20:.1f} MiB with {live / 2**20:.1f} MiB in use: over "
                f"the device's {limit / 2**20:.0f} MiB of global memory (CL_DEVICE_GLOBAL_MEM_SIZE)")

    def _track(self, buf: DeviceBuffer) -> DeviceBuffer:
        self._live[id(buf.handle)] = buf.nbytes
        return buf

    def upload(self, name, array):
        cl = self.cl
        data = np.ascontiguousarray(array)
        if data.nbytes == 0:
            return self.alloc(name, 4)
        return self._new_buffer(name, data.nbytes, lambda: cl.Buffer(
            self.ctx, cl.mem_flags.READ_WRITE | cl.mem_flags.COPY_HOST_PTR, hostbuf=data))

    def read(self, buf, dtype, count=None):
        dtype = np.dtype(dtype)
        n = buf.nbytes // dtype.itemsize if count is None else int(count)
        out = np.empty(n, dtype=dtype)
        self.cl.enqueue_copy(self.queue, out, buf.handle, is_blocking=True)
        return out

    def write(self, buf, array, offset=0):
        self.cl.enqueue_copy(self.queue, buf.handle, np.ascontiguousarray(array), dst_offset=int(offset),
                             is_blocking=True)

    def alloc_readable(self, name, nbytes):
        """The buffer over a zeroed host array (USE_HOST_PTR). PoCL's CPU device then works in that
        array: read_readable copies nothing, and the pages the kernels never write are never
        touched (np.zeros maps them on demand). Measured on spheres' 512 x 224 x 512 count pass
        (235 MB) in a fresh process, where this VM makes every first touch of a page dear:
        allocation and read-back 0.81-1.17 s with alloc + read (the fill and the copy each touch
        every page), 0.001 s this way, while the kernel, which now touches the pages it writes
        first, took 0.13-0.47 s against 0.11-0.18 s. A device with memory of its own copies the
        array in and out as the OpenCL spec says."""
        cl = self.cl
        nbytes = max(int(nbytes), 4)
        host = None

        def make():  # the host array only once the checks passed
            nonlocal host
            host = np.zeros(-(-nbytes // 4), np.uint32)
            return cl.Buffer(self.ctx, cl.mem_flags.READ_WRITE | cl.mem_flags.USE_HOST_PTR, hostbuf=host)

        buf = self._new_buffer(name, nbytes, make)
        self._host_arrays[id(buf.handle)] = host
        return buf

    def read_readable(self, buf, dtype, count=None):
        host = self._host_arrays.get(id(buf.handle))
        if host is None:
            return self.read(buf, dtype, count)
        dtype = np.dtype(dtype)
        n = buf.nbytes // dtype.itemsize if count is None else int(count)
        cl = self.cl
        # Mapping makes the host array hold the kernels' writes (a copy only where the device has
        # memory of its own); the map is released before the array is handed out.
        mapped, _ = cl.enqueue_map_buffer(self.queue, buf.handle, cl.map_flags.READ, 0, (n,), dtype,
                                          is_blocking=True)
        view = host.view(dtype)[:n]
        if mapped.__array_interface__["data"][0] != view.__array_interface__["data"][0]:
            view[:] = mapped
        mapped.base.release()
        return view

    def fill_zero(self, buf, nbytes=None):
        nbytes = buf.nbytes if nbytes is None else int(nbytes)
        if nbytes <= 0:
            return
        if self.serial_work_items and nbytes % 4 == 0:
            # PoCL clears a buffer (clEnqueueFillBuffer) on one core; a kernel's work items store on
            # all of them, and take the first touch of a fresh buffer's pages there too (120 MiB:
            # 5 against 10 ms warm, 0.17 against 0.35 s fresh on this machine's VM)
            words = nbytes // 4
            event = self._zero_kernel(self.queue, (-(-words // 256) * 256,), (256,), buf.handle, np.uint32(words))
            if self._kernel_log is not None:
                self._kernel_log.append(("fill_zero", event))
        else:
            self.cl.enqueue_fill_buffer(self.queue, buf.handle, np.uint32(0), 0, nbytes)

    def release(self, buf):
        self._live.pop(id(buf.handle), None)
        self._host_arrays.pop(id(buf.handle), None)  # read_readable's array lives on with its readers
        buf.handle.release()

    # --- device clock ----------------------------------------------------------------------
    @property
    def _is_nvidia(self) -> bool:
        return "nvidia" in self.device.vendor.strip().lower()

    def clock_defines(self):
        """OpenCL C has no clock builtin: NVIDIA's %clock register by inline PTX (CLOCK_PTX,
        shaders/common/trace.h); every other device (PoCL's CPU device) gets none."""
        return (("USE_CLOCK", "1"), ("CLOCK_PTX", "1")) if self._is_nvidia else ()

    def clock_info(self):
        name = self.device.name.strip()
        if self.clock_defines():
            return {"available": True, "unit": "SM clock cycles", "source": "PTX %clock",
                    "note": f"%clock register read by inline PTX on {name} (per-SM cycle counter, 32 bits)"}
        why = ("PoCL's CPU device has no kernel-readable clock and OpenCL C has no clock builtin"
               if "portable computing language" in self.device.platform.name.strip().lower()
               else "OpenCL C has no clock builtin and only NVIDIA devices get one (inline PTX %clock)")
        return {"available": False, "unit": None, "source": None, "note": f"no device clock on {name}: {why}"}

    # --- kernels ---------------------------------------------------------------------------
    def _item_loop(self, spec: KernelSpec) -> bool:
        return spec.item_loop and self.serial_work_items

    def compile(self, spec: KernelSpec):
        knl = self._programs.get(spec.key)
        if knl is None:
            src = kernel_source(spec, self._item_loop(spec))
            try:
                prog = self.cl.Program(self.ctx, src).build()
            except self.cl.Error as exc:
                raise DeviceError(f"OpenCL build of {spec.name} failed:\n{exc}\n{numbered(src)}") from exc
            knl = getattr(prog, "k_" + spec.name)
            self._programs[spec.key] = knl
        return knl

    def _args(self, spec, n_items, buffers, uniforms):
        check_item_count(spec, n_items)
        args = []
        for b in spec.buffers:
            if b.name not in buffers:
                raise KeyError(f"{spec.name}: buffer '{b.name}' not given")
            args.append(buffers[b.name].handle)
        uniforms = uniforms or {}
        for u in spec.uniforms:
            args.append(_numpy_scalar(u.type, uniforms[u.name]))
        args.append(np.uint32(n_items))
        return args

    def _launch(self, spec, n_items, args):
        knl = self.compile(spec)
        local = spec.local_size
        global_size = ((n_items + local - 1) // local) * local
        if self._item_loop(spec):  # work groups of one item that loops over `local` (kernel_source)
            global_size, local = global_size // local, 1
        try:
            event = knl(self.queue, (global_size,), (local,), *args)
        except self.cl.Error as exc:
            if "OUT_OF" in str(exc) or "MEM_OBJECT_ALLOCATION" in str(exc):
                raise DeviceLimitError(f"{spec.name}: {exc}") from exc
            raise DeviceError(f"{spec.name}: {exc}") from exc
        if self._kernel_log is not None:
            self._kernel_log.append((spec.name, event))
        return event

    def dispatch(self, spec, n_items, buffers, uniforms=None):
        if n_items <= 0:
            return None
        return self._launch(spec, n_items, self._args(spec, n_items, buffers, uniforms))

    def compile_voxelizer(self, spec):
        return self.compile(spec)

    def voxelize(self, spec, n_tris, buffers, uniforms, resolution):
        """The compute voxelizer: spec's body (grid.h: voxelize_kernel) once per triangle."""
        self.dispatch(spec, n_tris, buffers, uniforms)

    def finish(self):
        self.queue.finish()

    def start_kernel_log(self):
        self._kernel_log = []

    def kernel_seconds(self):
        """From the events of the profiling queue (PROFILING_ENABLE is on for time_dispatch):
        costs nothing extra. The prefix sums of pyopencl.scan are not dispatches, so not here."""
        log, self._kernel_log = self._kernel_log or [], None
        self.queue.finish()
        seconds: dict[str, float] = {}
        for name, event in log:
            seconds[name] = seconds.get(name, 0.0) + (event.profile.end - event.profile.start) * 1e-9
        return seconds

    def time_dispatch(self, spec, n_items, buffers, uniforms, warmup, repeats, between=None):
        args = self._args(spec, n_items, buffers, uniforms)
        for _ in range(max(warmup, 1)):
            self._launch(spec, n_items, args)
        self.queue.finish()
        seconds = []
        for _ in range(repeats):
            ev = self._launch(spec, n_items, args)
            ev.wait()
            seconds.append((ev.profile.end - ev.profile.start) * 1e-9)
            if between is not None:
                between()
        return Timing(seconds, "OpenCL event profiling")

    def dispatch_timed(self, spec, n_items, buffers, uniforms=None):
        event = self._launch(spec, n_items, self._args(spec, n_items, buffers, uniforms))
        event.wait()
        return (event.profile.end - event.profile.start) * 1e-9, "OpenCL event profiling"

    # --- prefix sum ------------------------------------------------------------------------
    def exclusive_scan(self, src, n, name):
        out = self.alloc(name, 4 * (n + 1), zero=True)
        self.cl.enqueue_copy(self.queue, out.handle, src.handle, byte_count=4 * n)
        self._scan_in_place(out, n + 1)  # the extra zero entry becomes the total
        return out, self.read_uint(out, n)

    def _scan_in_place(self, buf, n):
        import pyopencl.array as cla
        from pyopencl.scan import ExclusiveScanKernel

        if self._scan is None:
            self._scan = ExclusiveScanKernel(self.ctx, np.uint32, "a+b", "0")
        self._scan(cla.Array(self.queue, (n,), np.uint32, data=buf.handle), queue=self.queue)

    def read_uint(self, buf, index):
        out = np.empty(1, np.uint32)
        self.cl.enqueue_copy(self.queue, out, buf.handle, src_offset=4 * int(index), is_blocking=True)
        return int(out[0])
