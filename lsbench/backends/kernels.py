"""Kernel specifications: one description per kernel, turned into GLSL or OpenCL C.

A kernel's algorithm lives once, in `shaders/common/*.h`, as a function
`void body(CTX_PARAM uint gid)` written in the small C dialect of the preludes. The spec below
names the buffers and scalar arguments it reads; each backend generates the declarations its
language needs (GLSL: std430 SSBOs + uniforms; OpenCL: kernel parameters gathered into a `Ctx`
struct) and a tiny entry point that bounds-checks `gid` against `n_items` and calls the body (for
a spec with `item_loop`, on PoCL: a loop over a work group's items in one work item).

Which code of the headers compiles is chosen explicitly, never by the buffers a spec binds:
`#define KERNEL_<name>` (the spec's name) guards the kernel's body and the helpers only it uses,
and the spec's `defines` set the features a header section is optional for (LEAF_LINE_SPACE:
cells with a Line Space; COUNT_WORK: profiling counters; OCT_DEPTH, LS_CLIP_SH, ...).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from lsbench.paths import SHADER_ROOT


# Scalar/vector types usable in buffers and uniforms, with numpy dtype and element size.
# std430 and OpenCL agree on these layouts (no 3-component types in buffers on purpose).
TYPE_BYTES = {"float": 4, "uint": 4, "int": 4, "float4": 16, "uint4": 16, "int4": 16, "uint2": 8}


@dataclass(frozen=True)
class Buf:
    name: str
    type: str  # element type, a key of TYPE_BYTES
    # "r", "w" or "rw"; "t": read-only, and where the backend binds such buffers as textures (GLSL:
    # a buffer texture) fetched as texels: the shared code reads it with LD_U / LD_U2 / LD_U4 / LD_F / LD_F4
    # (preludes) only, never V(name)[i]. llvmpipe loads an SSBO element lane by lane, each behind
    # a bounds check and a branch, and a texel as one gather: random uvec4 loads took 2.1-2.6x as
    # long from an SSBO (docs/profiles.md, section 17).
    access: str = "rw"


@dataclass(frozen=True)
class Uniform:
    name: str
    type: str  # "float", "uint", "int", "float4", "int4", "uint4"


@dataclass(frozen=True)
class KernelSpec:
    name: str
    headers: tuple[str, ...]  # files under shaders/common, concatenated in order
    body: str  # void body(CTX_PARAM uint gid)
    buffers: tuple[Buf, ...]
    uniforms: tuple[Uniform, ...] = ()
    defines: tuple[tuple[str, str], ...] = ()
    local_size: int = 64
    # Where the device runs a work group's items one after the other (Device.serial_work_items:
    # PoCL's CPU device), run them as a loop of one work item instead: OpenCL launches work groups
    # of 1 whose entry point calls the body for local_size consecutive items (opencl.py
    # kernel_source). PoCL's own loop over a group's work items keeps every private array of the
    # body (a walk's stack) once per work item, addressed by the item's index (a multiply and a
    # reload at each stack access); in one item's loop it is one plain array. Trace kernels set it
    # (trace_spec): bvh 0.95-0.97 of the device time (Sponza and BMW, incoherent and primary rays),
    # the cell walks (grid, esvo, grid-ls) unchanged; the build kernels gained nothing, so they keep
    # PoCL's group loop (docs/profiles.md, section 20).
    item_loop: bool = False

    def with_defines(self, **defines: object) -> "KernelSpec":
        extra = tuple((k, str(v)) for k, v in sorted(defines.items()))
        return dataclasses.replace(self, defines=self.defines + extra)

    @property
    def key(self) -> tuple:
        return (self.name, self.headers, self.body, self.buffers, self.uniforms, self.defines,
                self.local_size, self.item_loop)


def read_common(headers: tuple[str, ...]) -> str:
    parts = []
    for h in headers:
        path = SHADER_ROOT / "common" / h
        parts.append(f"// ---- common/{h}\n" + path.read_text())
    return "\n".join(parts)


def define_lines(defines: tuple[tuple[str, str], ...]) -> str:
    return "".join(f"#define {k} {v}\n" for k, v in defines)


def kernel_defines(spec: "KernelSpec") -> str:
    """The lines both backends put before the headers: KERNEL_<name>, then the spec's defines."""
    return f"#define KERNEL_{spec.name} 1\n" + define_lines(spec.defines)


def numbered(source: str) -> str:
    """Source with line numbers, for compiler error messages."""
    return "\n".join(f"{i + 1:5d}  {line}" for i, line in enumerate(source.splitlines()))


# --- Specs shared by every structure -------------------------------------------------------
SCENE_BUFFERS = (Buf("vertices", "float", "r"), Buf("faces", "uint", "r"))
# Traversal kernels also read tri_verts: each triangle's three vertices as float4 (w: its unit
# normal) at 3 * tri .. 3 * tri + 2, gathered through the faces once at upload
# (backends.triangle_records). A
# candidate test then loads one 48-byte record instead of 3 face indices and 3 scattered vertices
# (docs/profiles.md, primary rays per CPU-second: +5-7 % on PoCL, +35-42 % on llvmpipe; incoherent rays:
# no difference resolved); builds keep vertices/faces. The traversals bind tri_verts only
# (TRIANGLE_RECORDS: scene.h leaves out the indexed loads), so the records cost no storage-buffer
# binding of the 16 GLSL allows (a Line Space split over 4 + 4 buffers, slices and counters).
TRACE_SCENE_BUFFERS = (Buf("tri_verts", "float4", "t"),)
RAY_BUFFERS = (Buf("rays", "float4", "r"), Buf("hit_prim", "int", "w"), Buf("hit_t", "float", "w"))
# What every traversal kernel reads besides its structure: trace.h (rays, hits, the candidate loop
# over voxel_tris) after the scene and, for Line Space kernels, linespace.h.
TRACE_HEADERS = ("geometry.h", "scene.h", "trace.h")
LS_TRACE_HEADERS = ("geometry.h", "scene.h", "linespace.h", "trace.h")
# loop_probe = 2: the driver loop-limit probe of every traversal (cut_hit, shaders/common/trace.h).
GRID_UNIFORMS = (Uniform("grid_origin", "float4"), Uniform("grid_inv_voxel", "float4"),
                 Uniform("grid_res", "int4"), Uniform("box_eps", "float"), Uniform("loop_probe", "uint"))
# Per-ray work counters (iterations, candidate tests, Line Space lookups, clock) for profiling
# builds only: the plain kernels are compiled without COUNT_WORK and never touch this buffer.
WORK_BUFFER = Buf("work", "uint4", "w")
# Traversal in bounded slices (SLICED, shaders/common/trace.h): one buffer holds every ray's state
# (SLICE_WORDS uints each) and, from slice_list_base on, the slice's compacted ray ids (one buffer,
# not two: llvmpipe binds at most 16 storage buffers and a split Line Space trace needs 16 already);
# slice_budget is the loop iterations a ray may run in one launch.
SLICE_WORDS = 16  # must match shaders/common/trace.h
SLICE_BUFFER = Buf("slice_state", "uint", "rw")
# A trace of rays in another order than given (backends/ray_order.py): work item g traces ray
# order_ids[g] (ORDERED_RAYS, shaders/common/trace.h); only unsliced kernels bind it (a sliced one
# takes its order from the slice's ray list), so it costs no binding over a sliced kernel's 16.
ORDER_BUFFER = Buf("order_ids", "uint", "r")
SLICE_UNIFORMS = (Uniform("slice_budget", "uint"), Uniform("slice_list_base", "uint"))
# The ray count of a packet traversal (BVH_PACKET rays per work item; shaders/common/bvh.h): the last
# packet's lanes past it trace nothing.
PACKET_UNIFORM = Uniform("packet_rays", "uint")


def trace_spec(name: str, headers: tuple[str, ...], body: str, structure_buffers: tuple[Buf, ...],
               uniforms: tuple[Uniform, ...], line_space: bool = False) -> KernelSpec:
    """A traversal kernel: the scene, the structure's buffers and the rays bound; `headers` are
    the structure's own, after TRACE_HEADERS (or LS_TRACE_HEADERS with LEAF_LINE_SPACE: its
    cells may hold a Line Space)."""
    common = LS_TRACE_HEADERS if line_space else TRACE_HEADERS
    defines = (("TRIANGLE_RECORDS", "1"),) + ((("LEAF_LINE_SPACE", "1"),) if line_space else ())
    return KernelSpec(name, common + headers, body, TRACE_SCENE_BUFFERS + structure_buffers + RAY_BUFFERS,
                      uniforms, defines, item_loop=True)
