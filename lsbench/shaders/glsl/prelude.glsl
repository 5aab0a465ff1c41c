// GLSL side of the shared kernel dialect (shaders/common/*.h are written against these names).
// The common code is a C subset: no pointers, no out-params, no vector compares, casts via U32()/F32().
#define float2 vec2
#define float3 vec3
#define float4 vec4
#define int2 ivec2
#define int3 ivec3
#define int4 ivec4
#define uint2 uvec2
#define uint3 uvec3
#define uint4 uvec4
// Double precision (core since GL 4.0; llvmpipe and NVIDIA run it): used only where float32 cannot
// place a point, once per ray (common/trace.h: make_grid_ray).
#define double3 dvec3
#define F64(x) double(x)
#define F64_3(v) dvec3(v)
#define F32_3(v) vec3(v)
#define make_float2(x, y) vec2(x, y)
#define make_float3(x, y, z) vec3(x, y, z)
#define make_float4(x, y, z, w) vec4(x, y, z, w)
#define make_int3(x, y, z) ivec3(x, y, z)
#define make_uint4(x, y, z, w) uvec4(x, y, z, w)
#define make_uint2(x, y) uvec2(x, y)
#define make_uint3(x, y, z) uvec3(x, y, z)
#define U32(x) uint(x)
#define I32(x) int(x)
#define F32(x) float(x)
#define as_uint(x) floatBitsToUint(x)
#define as_int(x) floatBitsToInt(x)
#define as_float(x) uintBitsToFloat(x)
#define fabs(x) abs(x)
#define fmin(a, b) min(a, b)
#define fmax(a, b) max(a, b)
#define INLINE
// `precise` keeps the compiler from fusing or reordering (the watertight test needs exact edges).
#define PRECISE precise
#define STRUCT(name) struct name
#define INF_F uintBitsToFloat(0x7f800000u)
// Buffer access: SSBOs are globals in GLSL, so the context parameter is empty.
#define V(name) name
// Reads of a buffer bound as "t" (kernels.py: Buf): a buffer texture of the same name, one texel
// per element (glsl.py: TEXEL_FORMATS); llvmpipe fetches a texel as one gather, where an SSBO
// element is loaded lane by lane behind a bounds check.
#define LD_U(name, i) texelFetch(name, int(i)).x
#define LD_F(name, i) texelFetch(name, int(i)).x
#define LD_U2(name, i) texelFetch(name, int(i)).xy
#define LD_U4(name, i) texelFetch(name, int(i))
#define LD_F4(name, i) texelFetch(name, int(i))
#define CTX_PARAM
#define CTX_ARG
#define ATOMIC_ADD(lvalue, v) atomicAdd(lvalue, v)
#define ATOMIC_MIN(lvalue, v) atomicMin(lvalue, v)
#define ATOMIC_MAX(lvalue, v) atomicMax(lvalue, v)
#define ATOMIC_OR(lvalue, v) atomicOr(lvalue, v)
#define ATOMIC_XCHG(lvalue, v) atomicExchange(lvalue, v)
#define ATOMIC_CAS(lvalue, expected, v) atomicCompSwap(lvalue, expected, v)
#define POPCOUNT(x) U32(bitCount(x))  // set bits of a uint, as a uint
#define LOWEST_BIT(x) uint(findLSB(x))  // the index of the lowest set bit of a non-zero uint
// The high word of the 64-bit product of two uints (a * b / 2^32: maps a hash onto [0, b) without a division)
uint mul_hi_u32(uint a, uint b) { uint hi, lo; umulExtended(a, b, hi, lo); return hi; }
#define MUL_HI(a, b) mul_hi_u32(a, b)
#define LANG_GLSL 1
#define PREFETCH(p)  // GLSL has no prefetch (opencl/prelude.cl: only CPUs need it)
// Device clock for the profiling counters (COUNT_WORK builds; Delgado Kraemer 2019, 6.3, Fig. 20b):
// `uint c0 = CLOCK_START(); ... CLOCK_ELAPSED(c0)` gives uint ticks, a 32-bit difference that
// stays right across one wrap of the low word. The tick source CLOCK_NOW() is picked in
// common/trace.h, after the kernel's defines: clock2x32ARB().x where USE_CLOCK is set (the
// driver has GL_ARB_shader_clock; llvmpipe: nanoseconds, 8 lanes share a value), else 0.
#define CLOCK_START() CLOCK_NOW()
#define CLOCK_ELAPSED(start) (CLOCK_NOW() - (start))
