"""GLSL backend: moderngl compute shaders (plus the raster pipeline for voxelization) on a
standalone EGL context, `#version 450` so the same sources run on Mesa llvmpipe and NVIDIA."""
from __future__ import annotations

import ctypes
import ctypes.util
import dataclasses
import math
import time

import numpy as np

from .device import (Device, DeviceBuffer, DeviceError, DeviceLimitError, Timing, check_item_count,
                     start_failure_hint)
from .kernels import SHADER_ROOT, TYPE_BYTES, Buf, KernelSpec, kernel_defines, numbered, read_common

MAX_GROUPS = 65535  # per dispatch dimension, GL minimum and llvmpipe's value
# Loop iterations per ray in one traversal launch on llvmpipe (Device.loop_budget): its limit of
# 65535 (LP_MAX_TGSI_LOOP_ITERATIONS, shaders/common/geometry.h) counts every loop of an invocation
# and is shared by a SIMD group of lanes (8 with AVX2, 16 with AVX-512), whose loops run while any
# lane runs (the candidate loops of diverging lanes add up), so a lane gets a 16th of it, which
# also leaves room for what the walks run besides steps and tests (the stack restore, the probe).
# A group that still passes the limit is rerun from its saved state with half the budget
# (backends/__init__.py: trace). Smaller slices were also faster here: BMW 32^3, 20,000 incoherent
# rays, svo 1.91 / 1.53 / 1.27 / 1.03 s and grid 0.94 / 0.68 / 0.52 / 0.36 s at B = 16000 / 8000 /
# 4000 / 2000 (13-98 launches): the first launch ends every ray at B instead of waiting for a
# group's longest, and the long rays then share SIMD groups. 4000 keeps the launches few.
LLVMPIPE_LOOP_BUDGET = 4000
# llvmpipe's raster voxelizer costs ~0.6 us of the two threads per triangle (its geometry shader),
# its compute voxelizer ~0.05 us (BMW, 792,746 triangles at 134 x 40 x 148: count pass 0.40-0.55
# against 0.04-0.12 s), but the compute kernel's loops over a triangle's bounds meet the loop
# budget (65535 iterations, every loop of an invocation, shared by a SIMD group of up to 16
# lanes). Bounds of at most 1024 voxels take at most 3 x 1024 loop iterations (the z, y and x
# loops), 16 lanes of them 49,152: within it. The raster pipeline takes the larger ones.
LLVMPIPE_COMPUTE_VOXEL_CELLS = 1024
# Rays per work item of the BVH's packet traversal on llvmpipe (bvh.h: BVH_PACKET, vec4 lanes), for
# coherent ray sets (backends.packet_width): each SIMD lane loads its own node lane by lane
# (docs/profiles.md, section 10), so a packet of 4 rays per lane shares one node load and one loop
# step among 4 rays: Sponza 256² primary rays 0.78-0.80 of the one-ray kernel's device time, BMW
# 256² and 512² 0.83-0.84, the same hits (section 26). Closest hits only (Device.packet_queries).
LLVMPIPE_PACKET_WIDTH = 4
HOST_CLOCK = "host clock around glFinish"
SCAN_BLOCK = 256  # invocations per work group in the prefix-sum kernels (shaders/glsl/scan.comp)
SCAN_CHUNK = 16  # consecutive items each invocation scans serially


def _prelude() -> str:
    return (SHADER_ROOT / "glsl" / "prelude.glsl").read_text()


# Buffers bound as "t" (kernels.Buf): the sampler type a kernel declares and the texel format of the
# buffer texture over the buffer's store, one texel per element (GL 4.5 core: glTexBuffer).
TEXEL_FORMATS = {"uint": ("usamplerBuffer", 0x8236), "uint2": ("usamplerBuffer", 0x823C),  # R32UI, RG32UI
                 "uint4": ("usamplerBuffer", 0x8D70), "float4": ("samplerBuffer", 0x8814),  # RGBA32UI, RGBA32F
                 "float": ("samplerBuffer", 0x822E)}  # R32F
GL_TEXTURE_BUFFER = 0x8C2A
GL_TEXTURE0 = 0x84C0
GL_MAX_TEXTURE_BUFFER_SIZE = 0x8C2B


class _BufferTextures:
    """Buffer textures over moderngl buffers (moderngl has no API for them): the GL entry points
    through eglGetProcAddress, one texture per buffer and format, made on first use and deleted
    with the buffer."""

    def __init__(self):
        egl = ctypes.CDLL(ctypes.util.find_library("EGL") or "libEGL.so.1")
        egl.eglGetProcAddress.restype = ctypes.c_void_p
        egl.eglGetProcAddress.argtypes = [ctypes.c_char_p]

        def gl(name, restype, *args):
            address = egl.eglGetProcAddress(name.encode())
            if not address:
                raise DeviceError(f"the GL driver has no {name}")
            return ctypes.CFUNCTYPE(restype, *args)(address)
        u, i, p = ctypes.c_uint, ctypes.c_int, ctypes.POINTER(ctypes.c_uint)
        self.gen = gl("glGenTextures", None, i, p)
        self.delete = gl("glDeleteTextures", None, i, p)
        self.bind = gl("glBindTexture", None, u, u)
        self.tex_buffer = gl("glTexBuffer", None, u, u, u)
        self.active = gl("glActiveTexture", None, u)
        self.location = gl("glGetUniformLocation", i, u, ctypes.c_char_p)
        self.uniform = gl("glProgramUniform1i", None, u, i, i)
        get_integer = gl("glGetIntegerv", None, u, ctypes.POINTER(i))
        value = i(0)
        get_integer(GL_MAX_TEXTURE_BUFFER_SIZE, ctypes.byref(value))
        self.max_texels = int(value.value)
        self.textures: dict = {}  # (buffer glo, format) -> texture name
        self.locations: dict = {}  # (program glo, name) -> uniform location

    def bind_buffer(self, unit: int, prog, buf: DeviceBuffer, b: Buf) -> None:
        fmt = TEXEL_FORMATS[b.type][1]
        texels = buf.nbytes // TYPE_BYTES[b.type]
        if texels > self.max_texels:
            raise DeviceLimitError(f"buffer '{b.name}' holds {texels} texels, over the driver's {self.max_texels} "
                                   "per buffer texture (GL_MAX_TEXTURE_BUFFER_SIZE)")
        key = (buf.handle.glo, fmt)
        tex = self.textures.get(key)
        self.active(GL_TEXTURE0 + unit)  # before a new texture's first bind, which binds it to the active unit
        if tex is None:
            name = ctypes.c_uint(0)
            self.gen(1, ctypes.byref(name))
            tex = self.textures[key] = name.value
            self.bind(GL_TEXTURE_BUFFER, tex)
            self.tex_buffer(GL_TEXTURE_BUFFER, fmt, buf.handle.glo)
        self.bind(GL_TEXTURE_BUFFER, tex)
        loc = self.locations.get((prog.glo, b.name))
        if loc is None:
            loc = self.locations[(prog.glo, b.name)] = self.location(prog.glo, b.name.encode())
        if loc >= 0:  # the compiler drops an unused sampler
            self.uniform(prog.glo, loc, unit)

    def forget(self, buf: DeviceBuffer) -> None:
        for key in [k for k in self.textures if k[0] == buf.handle.glo]:
            name = ctypes.c_uint(self.textures.pop(key))
            self.delete(1, ctypes.byref(name))


def declarations(spec: KernelSpec) -> str:
    """std430 SSBOs (binding = position in spec.buffers), buffer textures for "t" buffers (a
    sampler of the buffer's name, bound to a texture unit by _bind) and plain uniforms."""
    lines = []
    for binding, b in enumerate(spec.buffers):
        if b.access == "t":
            lines.append(f"uniform {TEXEL_FORMATS[b.type][0]} {b.name};")
            continue
        qual = {"r": "readonly ", "w": "writeonly ", "rw": ""}[b.access]
        lines.append(f"layout(std430, binding = {binding}) {qual}buffer B_{b.name} "
                     f"{{ {b.type} {b.name}[]; }};")
    for u in spec.uniforms:
        lines.append(f"uniform {u.type} {u.name};")
    lines.append("uniform uint n_items;")
    return "\n".join(lines) + "\n"


def compute_source(spec: KernelSpec) -> str:
    return (
        "#version 450\n"
        + ("#extension GL_ARB_shader_clock : require\n" if ("USE_CLOCK", "1") in spec.defines else "")
        + f"layout(local_size_x = {spec.local_size}) in;\n"
        + _prelude() + kernel_defines(spec) + declarations(spec) + read_common(spec.headers)
        + "\nvoid main() {\n"
        # Two-dimensional dispatch: more than 65 535 groups spill into y.
        f"    uint gid = (gl_WorkGroupID.y * gl_NumWorkGroups.x + gl_WorkGroupID.x) * {spec.local_size}u"
        " + gl_LocalInvocationID.x;\n"
        "    if (gid >= n_items) return;\n"
        f"    {spec.body}(CTX_ARG gid);\n"
        "}\n")


class GLSLDevice(Device):
    backend = "glsl"
    line_space_test = "edges"  # llvmpipe: count 1.8x faster than the SAT, clipper 10x slower (docs/linespace-build.md)

    def __init__(self):
        import moderngl

        self.mgl = moderngl
        try:
            self.ctx = moderngl.create_context(standalone=True, backend="egl", require=450)
        except Exception as exc:  # no EGL / Mesa: name what is missing
            raise DeviceError(
                f"cannot create an OpenGL 4.5 context through EGL ({exc}); " + start_failure_hint(
                    "install the EGL and Mesa drivers, e.g. `apt-get install libegl1 libegl-mesa0 "
                    "libgl1-mesa-dri`")) from exc
        self._programs: dict = {}
        self._scan_programs: dict = {}
        self._textures = _BufferTextures()
        # Framebuffers by size, kept: releasing a bound framebuffer left the next draw failing
        # with GL_INVALID_OPERATION under moderngl 5.13 / llvmpipe.
        self._raster_targets: dict = {}
        self._max_ssbo = int(self.ctx.info["GL_MAX_SHADER_STORAGE_BLOCK_SIZE"])
        # A buffer a trace kernel reads as texels ("t") must fit a buffer texture: 4 bytes per texel
        # of a uint buffer (llvmpipe: 128 MiB of storage block against 512 MiB; a GPU's storage
        # blocks may pass it, and its Line Spaces then split over more buffers).
        self._max_buffer = min(self._max_ssbo, 4 * self._textures.max_texels)
        self._time_query = None  # one GL_TIME_ELAPSED query object, reused by every timed launch
        # The most voxels a triangle's bounds may hold for the compute voxelizer to take it
        # (voxelize); None: the raster pipeline takes every triangle.
        self.compute_voxel_cells = LLVMPIPE_COMPUTE_VOXEL_CELLS if self.is_llvmpipe else None
        # GPUs run a ray per lane: a packet in each lane would only multiply its registers.
        self.packet_width = LLVMPIPE_PACKET_WIDTH if self.is_llvmpipe else 1
        self.packet_queries = ("closest",)

    # --- information -----------------------------------------------------------------------
    def info(self) -> dict:
        i = self.ctx.info
        return {
            "backend": "glsl",
            "device": i["GL_RENDERER"],
            "driver": i["GL_VERSION"],
            "vendor": i["GL_VENDOR"],
            "backend_version": f"moderngl {self.mgl.__version__}",
            "max_buffer_bytes": self._max_buffer,
            "max_texture_buffer_texels": self._textures.max_texels,
            "shader_clock": "GL_ARB_shader_clock" in self.ctx.extensions,
            "int64": "GL_ARB_gpu_shader_int64" in self.ctx.extensions,
        }

    @property
    def max_buffer_bytes(self) -> int:
        return self._max_buffer

    @property
    def limit_name(self) -> str:
        if self._max_ssbo <= self._max_buffer:
            return "GL_MAX_SHADER_STORAGE_BLOCK_SIZE"
        return "GL_MAX_TEXTURE_BUFFER_SIZE, 4-byte texels"

    @property
    def is_llvmpipe(self) -> bool:
        return "llvmpipe" in self.ctx.info["GL_RENDERER"]

    @property
    def loop_budget(self) -> int | None:
        """llvmpipe's per-invocation loop limit (a share of it: LLVMPIPE_LOOP_BUDGET); other GL
        drivers have none."""
        return LLVMPIPE_LOOP_BUDGET if self.is_llvmpipe else None

    # --- errors ----------------------------------------------------------------------------
    def check_error(self, what: str) -> None:
        """moderngl raises nothing on GL errors (e.g. too many work groups): ask GL."""
        err = self.ctx.error
        if err != "GL_NO_ERROR":
            if err == "GL_OUT_OF_MEMORY":
                raise DeviceLimitError(f"{what}: GL_OUT_OF_MEMORY")
            raise DeviceError(f"{what}: {err}")

    # --- buffers ---------------------------------------------------------------------------
    def alloc(self, name, nbytes, zero=True):
        nbytes = max(int(nbytes), 4)
        self.check_size(name, nbytes)
        try:
            buf = self.ctx.buffer(reserve=nbytes)
        except Exception as exc:
            raise DeviceLimitError(f"allocating buffer '{name}' of {nbytes} bytes failed: {exc}") from exc
        self.check_error(f"allocating buffer '{name}'")
        if zero:
            buf.clear()
        return DeviceBuffer(name, nbytes, buf)

    def upload(self, name, array):
        data = np.ascontiguousarray(array)
        if data.nbytes == 0:
            return self.alloc(name, 4)
        self.check_size(name, data.nbytes)
        buf = self.ctx.buffer(data.tobytes())
        self.check_error(f"uploading buffer '{name}'")
        return DeviceBuffer(name, data.nbytes, buf)

    def read(self, buf, dtype, count=None):
        dtype = np.dtype(dtype)
        size = buf.nbytes if count is None else int(count) * dtype.itemsize
        out = np.empty(size // dtype.itemsize, dtype)
        buf.handle.read_into(out, size=size)  # one copy, not bytes and then an array of them
        return out

    def fill_zero(self, buf, nbytes=None):
        buf.handle.clear(size=-1 if nbytes is None else int(nbytes))

    def write(self, buf, array, offset=0):
        buf.handle.write(np.ascontiguousarray(array).tobytes(), offset=int(offset))

    def release(self, buf):
        self._textures.forget(buf)
        buf.handle.release()

    # --- device clock ----------------------------------------------------------------------
    def clock_defines(self):
        """GL_ARB_shader_clock where the driver has it (compute_source then adds the #extension
        line): CLOCK_NOW() = clock2x32ARB().x, shaders/common/trace.h."""
        return (("USE_CLOCK", "1"),) if "GL_ARB_shader_clock" in self.ctx.extensions else ()

    def clock_info(self):
        name = self.ctx.info["GL_RENDERER"]
        if not self.clock_defines():
            return {"available": False, "unit": None, "source": None,
                    "note": f"no device clock on {name}: the GL driver lacks GL_ARB_shader_clock"}
        if "llvmpipe" in name.lower():
            unit = "ns"
            note = (f"GL_ARB_shader_clock on {name}: clock2x32ARB() ticks in nanoseconds (wall time), only "
                    "the low 32 bits are valid, 8 SIMD lanes share one value (per-ray time of its 8-ray group)")
        else:
            unit = "shader clock ticks"
            note = f"GL_ARB_shader_clock (clock2x32ARB().x, low 32 bits) on {name}; GPU cycles on NVIDIA"
        return {"available": True, "unit": unit, "source": "clock2x32ARB", "note": note}

    # --- kernels ---------------------------------------------------------------------------
    def compile(self, spec: KernelSpec):
        prog = self._programs.get(spec.key)
        if prog is None:
            limit = int(self.ctx.info["GL_MAX_COMPUTE_SHADER_STORAGE_BLOCKS"])
            ssbos = sum(1 for b in spec.buffers if b.access != "t")
            if ssbos > limit:  # the link would fail with a bare driver message
                raise DeviceLimitError(
                    f"{spec.name} binds {ssbos} storage buffers, over the driver's {limit} "
                    "per compute shader (GL_MAX_COMPUTE_SHADER_STORAGE_BLOCKS)")
            src = compute_source(spec)
            try:
                prog = self.ctx.compute_shader(src)
            except Exception as exc:
                raise DeviceError(f"GLSL compile of {spec.name} failed:\n{exc}\n{numbered(src)}") from exc
            self._programs[spec.key] = prog
        return prog

    def _bind(self, prog, spec, n_items, buffers, uniforms):
        check_item_count(spec, n_items)
        unit = 0
        for binding, b in enumerate(spec.buffers):
            if b.name not in buffers:
                raise KeyError(f"{spec.name}: buffer '{b.name}' not given")
            if b.access == "t":
                self._textures.bind_buffer(unit, prog, buffers[b.name], b)
                unit += 1
            else:
                buffers[b.name].handle.bind_to_storage_buffer(binding)
        values = dict(uniforms or {})
        values["n_items"] = int(n_items)
        for name, value in values.items():
            if name in prog:  # the compiler drops unused uniforms
                prog[name].value = value

    def _groups(self, spec, n_items):
        groups = max(1, math.ceil(n_items / spec.local_size))
        gx = min(groups, MAX_GROUPS)
        gy = math.ceil(groups / gx)
        if gy > MAX_GROUPS:
            raise DeviceLimitError(
                f"{spec.name}: {n_items} items need {groups} work groups, over "
                f"{MAX_GROUPS}x{MAX_GROUPS} (GL_MAX_COMPUTE_WORK_GROUP_COUNT)")
        return gx, gy

    def dispatch(self, spec, n_items, buffers, uniforms=None):
        if n_items <= 0:
            return
        prog = self.compile(spec)
        self._bind(prog, spec, n_items, buffers, uniforms)
        gx, gy = self._groups(spec, n_items)
        prog.run(gx, gy, 1)
        self.ctx.memory_barrier()
        self.check_error(f"dispatch of {spec.name} ({gx}x{gy} groups)")

    def finish(self):
        self.ctx.finish()

    def time_dispatch(self, spec, n_items, buffers, uniforms, warmup, repeats, between=None):
        prog = self.compile(spec)
        self._bind(prog, spec, n_items, buffers, uniforms)
        gx, gy = self._groups(spec, n_items)
        for _ in range(max(warmup, 1)):
            prog.run(gx, gy, 1)
        self.ctx.finish()
        self.check_error(f"warm-up of {spec.name}")
        seconds, clocks = [], set()
        for _ in range(repeats):
            s, clock = self._timed_run(prog, gx, gy)
            seconds.append(s)
            clocks.add(clock)
            if between is not None:
                between()
        self.check_error(f"timed dispatch of {spec.name}")
        return Timing(seconds, "GL_TIME_ELAPSED" if "GL_TIME_ELAPSED" in clocks else HOST_CLOCK)

    def dispatch_timed(self, spec, n_items, buffers, uniforms=None):
        prog = self.compile(spec)
        self._bind(prog, spec, n_items, buffers, uniforms)
        gx, gy = self._groups(spec, n_items)
        seconds, clock = self._timed_run(prog, gx, gy)
        self.ctx.memory_barrier()
        self.check_error(f"timed dispatch of {spec.name} ({gx}x{gy} groups)")
        return seconds, clock

    def _timed_run(self, prog, gx, gy) -> tuple[float, str]:
        """One launch, finished. GL_TIME_ELAPSED is used where it reads non-zero and close to wall
        time; llvmpipe reads 0 for compute, so there the host clock around glFinish measures."""
        if self._time_query is None:
            self._time_query = self.ctx.query(time=True)
        query = self._time_query
        t0 = time.perf_counter()
        with query:
            prog.run(gx, gy, 1)
        self.ctx.finish()
        wall = time.perf_counter() - t0
        gpu = query.elapsed * 1e-9
        if gpu > 0 and 0.5 * wall <= gpu <= 1.05 * wall:
            return gpu, "GL_TIME_ELAPSED"
        return wall, HOST_CLOCK

    # --- prefix sum ------------------------------------------------------------------------
    def _scan_program(self, kind: str):
        prog = self._scan_programs.get(kind)
        if prog is None:
            src = (SHADER_ROOT / "glsl" / "scan.comp").read_text()
            src = src.replace("#version 450\n", f"#version 450\n#define {kind} 1\n#define BLOCK {SCAN_BLOCK}\n"
                              f"#define CHUNK {SCAN_CHUNK}\n", 1)
            try:
                prog = self.ctx.compute_shader(src)
            except Exception as exc:
                raise DeviceError(f"GLSL compile of scan ({kind}) failed:\n{exc}\n{numbered(src)}") from exc
            self._scan_programs[kind] = prog
        return prog

    def _scan_in_place(self, buf: DeviceBuffer, n: int) -> None:
        """Block scan (shaders/glsl/scan.comp): scan each block of SCAN_BLOCK x SCAN_CHUNK items,
        write block totals, scan those recursively, add them back."""
        blocks = math.ceil(n / (SCAN_BLOCK * SCAN_CHUNK))
        sums = self.alloc(f"{buf.name}.blocksums", 4 * blocks)
        prog = self._scan_program("SCAN_BLOCKS")
        buf.handle.bind_to_storage_buffer(0)
        sums.handle.bind_to_storage_buffer(1)
        prog["n_items"].value = n
        gx = min(blocks, MAX_GROUPS)
        prog.run(gx, math.ceil(blocks / gx), 1)
        self.ctx.memory_barrier()
        if blocks > 1:
            self._scan_in_place(sums, blocks)
            add = self._scan_program("ADD_BLOCKS")
            buf.handle.bind_to_storage_buffer(0)
            sums.handle.bind_to_storage_buffer(1)
            add["n_items"].value = n
            add.run(gx, math.ceil(blocks / gx), 1)
            self.ctx.memory_barrier()
        self.check_error("prefix sum")
        self.release(sums)

    def exclusive_scan(self, src, n, name):
        out = self.alloc(name, 4 * (n + 1), zero=True)
        self.ctx.copy_buffer(out.handle, src.handle, size=4 * n)
        self._scan_in_place(out, n + 1)  # the extra zero entry becomes the total
        return out, self.read_uint(out, n)

    def read_uint(self, buf, index):
        return int(np.frombuffer(buf.handle.read(size=4, offset=4 * int(index)), np.uint32)[0])

    # --- raster voxelization ---------------------------------------------------------------
    def _split_voxelizer(self, spec: KernelSpec) -> KernelSpec:
        """spec as the compute kernel that leaves the triangles of large bounds to the raster
        pipeline, listed in raster_tris (grid.h: VOXELIZE_MAX_CELLS); the raster program of this
        spec draws those."""
        return dataclasses.replace(
            spec, buffers=spec.buffers + (Buf("raster_tris", "uint", "rw"),),
            defines=spec.defines + (("VOXELIZE_MAX_CELLS", str(int(self.compute_voxel_cells))),))

    def compile_voxelizer(self, spec: KernelSpec):
        """Vertex + geometry + fragment program for the conservative voxelizer of Delgado Krämer 2019, 3.4:
        one point per triangle, the geometry shader projects along the dominant axis and emits
        the dilated footprint, each fragment tests its column's depth neighbours. Where the compute
        kernel takes the small triangles (compute_voxel_cells), it and the raster program of the
        rest are compiled too."""
        if self.compute_voxel_cells is not None and not any(k == "VOXELIZE_MAX_CELLS" for k, _ in spec.defines):
            split = self._split_voxelizer(spec)
            self.compile(split)
            self.compile_voxelizer(split)
        prog = self._programs.get(("raster",) + spec.key)
        if prog is None:
            head = "#version 450\n" + _prelude() + kernel_defines(spec) + declarations(spec) \
                + read_common(spec.headers) + "\n"
            stage = lambda f: head + (SHADER_ROOT / "glsl" / f).read_text()  # noqa: E731
            try:
                prog = self.ctx.program(
                    vertex_shader=stage("voxelize.vert"),
                    geometry_shader=stage("voxelize.geom"),
                    fragment_shader=stage("voxelize.frag"))
            except Exception as exc:
                raise DeviceError(f"GLSL compile of the raster voxelizer failed:\n{exc}") from exc
            self._programs[("raster",) + spec.key] = prog
        return prog

    def voxelize(self, spec, n_tris, buffers, uniforms, resolution):
        """The conservative voxelization of n_tris triangles (grid.h). Through the raster pipeline,
        except where compute_voxel_cells is set (llvmpipe): there the compute kernel takes the
        triangles whose bounds hold at most that many voxels, and the raster pipeline the others."""
        if self.compute_voxel_cells is None:
            self._raster(spec, n_tris, buffers, uniforms, resolution)
            return
        split = self._split_voxelizer(spec)
        left = self.alloc("raster_tris", 4 * (n_tris + 1))
        try:
            buffers = dict(buffers, raster_tris=left)
            self.dispatch(split, n_tris, buffers, uniforms)
            n_left = self.read_uint(left, 0)
            if n_left:
                self._raster(split, n_left, buffers, uniforms, resolution)
        finally:
            self.release(left)

    def _raster(self, spec, n_tris, buffers, uniforms, resolution):
        """Draw n_tris points through the raster voxelizer into a viewport of R x R pixels, R the
        largest grid side (one pixel = one voxel column of the projection axis)."""
        viewport = max(int(r) for r in resolution)
        uniforms = dict(uniforms, viewport_size=float(viewport))
        # Checked before any GL call: an incomplete framebuffer leaves a sticky GL error that
        # would fail the next, unrelated call on this context (found by tests/test_limits.py).
        limit = min(int(self.ctx.info["GL_MAX_RENDERBUFFER_SIZE"]), *map(int, self.ctx.info["GL_MAX_VIEWPORT_DIMS"]))
        if viewport > limit:
            raise DeviceLimitError(
                f"{spec.name}: raster voxelization needs a {viewport}x{viewport} viewport, over the "
                f"driver's {limit} (GL_MAX_VIEWPORT_DIMS / GL_MAX_RENDERBUFFER_SIZE)")
        prog = self.compile_voxelizer(spec)
        self._bind(prog, spec, n_tris, buffers, uniforms)
        # llvmpipe accepts a framebuffer without attachments, moderngl wants one: a 1-byte
        # renderbuffer of the viewport size with colour writes off costs viewport^2 bytes.
        fbo = self._raster_targets.get(viewport)
        if fbo is None:
            rb = self.ctx.renderbuffer((viewport, viewport), components=1, dtype="f1")
            fbo = self.ctx.framebuffer(color_attachments=[rb])
            fbo.color_mask = (False, False, False, False)
            self._raster_targets[viewport] = fbo
        fbo.use()
        fbo.viewport = (0, 0, viewport, viewport)
        self.ctx.disable(self.mgl.DEPTH_TEST | self.mgl.CULL_FACE | self.mgl.BLEND)
        vao = self.ctx.vertex_array(prog, [])
        vao.render(mode=self.mgl.POINTS, vertices=int(n_tris))
        self.ctx.memory_barrier()
        self.check_error("raster voxelization")
        vao.release()
