// No fused multiply-add contraction: the watertight triangle test needs its edge functions
// evaluated exactly as written (antisymmetric across a shared edge).
#pragma OPENCL FP_CONTRACT OFF
#define PRECISE
// OpenCL C side of the shared kernel dialect (shaders/common/*.h are written against these names).
#define make_float2(x, y) ((float2)((x), (y)))
#define make_float3(x, y, z) ((float3)((x), (y), (z)))
#define make_float4(x, y, z, w) ((float4)((x), (y), (z), (w)))
#define make_int3(x, y, z) ((int3)((x), (y), (z)))
#define make_uint4(x, y, z, w) ((uint4)((x), (y), (z), (w)))
#define make_uint2(x, y) ((uint2)((x), (y)))
#define make_uint3(x, y, z) ((uint3)((x), (y), (z)))
#define U32(x) ((uint)(x))
#define I32(x) ((int)(x))
#define F32(x) ((float)(x))
// Double precision, used only where float32 cannot place a point, once per ray (common/trace.h:
// make_grid_ray). A device without cl_khr_fp64 places that point in float: a far ray's walk then
// starts up to float32's step at the origin's distance off its line (0.25 voxels at 1e4 scene
// diagonals, 128³), though its t values stay small (untested: PoCL and NVIDIA have fp64).
#ifdef cl_khr_fp64
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#define F64(x) ((double)(x))
#define F64_3(v) convert_double3(v)
#else
#define double3 float3
#define F64(x) ((float)(x))
#define F64_3(v) (v)
#endif
#define F32_3(v) convert_float3(v)
// Every shared function inlined: PoCL's LLVM left ray_triangle_wt, test_candidates and the walks as
// calls that pass the Trace struct by value through the stack, and `perf record` put 40 % of the
// grid walk's samples and 30 % of the candidate loop's on those struct copies (store-forwarding
// stalls). Inlined, × Embree rose 0.20 -> 0.33 (grid 128³), 0.20 -> 0.35 (grid-ls 64³ N=2) and
// 0.33 -> 0.39 (esvo 512³) on Sponza 256² (docs/profiles.md).
#define INLINE inline __attribute__((always_inline))
#define STRUCT(name) typedef struct name name; struct name
#define INF_F INFINITY
// Buffer access: every kernel gets a generated `Ctx` struct holding its __global pointers and
// scalar arguments; common code reaches them through V(name) and passes the context along.
#define V(name) (C->name)
// Reads of a buffer bound read-only as "t" (kernels.py: Buf): plain loads here; GLSL fetches texels.
#define LD_U(name, i) (V(name)[i])
#define LD_F(name, i) (V(name)[i])
#define LD_U2(name, i) (V(name)[i])
#define LD_U4(name, i) (V(name)[i])
#define LD_F4(name, i) (V(name)[i])
#define CTX_PARAM const Ctx* C,
#define CTX_ARG C,
#define ATOMIC_ADD(lvalue, v) atomic_add(&(lvalue), v)
#define ATOMIC_MIN(lvalue, v) atomic_min(&(lvalue), v)
#define ATOMIC_MAX(lvalue, v) atomic_max(&(lvalue), v)
#define ATOMIC_OR(lvalue, v) atomic_or(&(lvalue), v)
#define ATOMIC_XCHG(lvalue, v) atomic_xchg(&(lvalue), v)
#define ATOMIC_CAS(lvalue, expected, v) atomic_cmpxchg(&(lvalue), expected, v)
#define POPCOUNT(x) popcount(x)  // set bits of a uint, as a uint
#define LOWEST_BIT(x) ctz(x)  // the index of the lowest set bit of a non-zero uint, as a uint
#define MUL_HI(a, b) mul_hi(a, b)  // the high word of the 64-bit product of two uints
#define LANG_OPENCL 1
// A software prefetch of the cache line at address p, where the kernel runs on a CPU: PoCL compiles
// for the host with clang, and its OpenCL prefetch() is a no-op there. A walk prefetches the nodes
// and leaves it pushes, so their loads meet the cache when popped (bvh.h, BVH_SLOT). GPUs hide the
// latency with other warps: there (and in GLSL) it expands to nothing.
#if defined(__clang__) && (defined(__x86_64__) || defined(__aarch64__))
#define PREFETCH(p) __builtin_prefetch(p)
#else
#define PREFETCH(p)
#endif
// Device clock for the profiling counters (COUNT_WORK builds): `uint c0 = CLOCK_START(); ...
// CLOCK_ELAPSED(c0)` gives uint ticks (32-bit difference). OpenCL C has no clock builtin; the
// tick source CLOCK_NOW() is picked in common/trace.h, after the kernel's defines: NVIDIA's
// %clock register through inline PTX where CLOCK_PTX is set (vendor NVIDIA), else 0 (PoCL's
// CPU device has no device clock).
#define CLOCK_START() CLOCK_NOW()
#define CLOCK_ELAPSED(start) (CLOCK_NOW() - (start))
