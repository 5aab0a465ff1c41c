// Scene and ray access shared by all kernels.
// Buffers: vertices (float, xyz packed), faces (uint, 3 per triangle), rays (float4 pairs:
// origin.xyz + tmin, direction.xyz + tmax), hit_prim (int, -1 = miss), hit_t (float).

INLINE float3 load_vertex(CTX_PARAM uint i) {
    return make_float3(V(vertices)[3u * i], V(vertices)[3u * i + 1u], V(vertices)[3u * i + 2u]);
}

STRUCT(Triangle) { float3 a; float3 b; float3 c; };

INLINE Triangle load_triangle(CTX_PARAM uint tri) {
    Triangle t;
    t.a = load_vertex(CTX_ARG V(faces)[3u * tri]);
    t.b = load_vertex(CTX_ARG V(faces)[3u * tri + 1u]);
    t.c = load_vertex(CTX_ARG V(faces)[3u * tri + 2u]);
    return t;
}

STRUCT(Hit) { float t; int prim; };

// One ray of the `rays` buffer and where its hit goes: every traversal's entry kernel is
// store_hit(ray, trace_x(load_ray(ray)...)).
#ifdef HAS_rays
STRUCT(Ray) { float3 o; float tmin; float3 d; float tmax; };

INLINE Ray load_ray(CTX_PARAM uint ray) {
    float4 o = V(rays)[2u * ray];
    float4 d = V(rays)[2u * ray + 1u];
    Ray r;
    r.o = o.xyz;
    r.tmin = o.w;
    r.d = d.xyz;
    r.tmax = d.w;
    return r;
}
#endif

INLINE Hit no_hit(float tmax) { Hit h; h.t = tmax; h.prim = -1; return h; }

// llvmpipe (gallivm) ends every loop of a shader invocation, silently, once all its loops together
// have run 65535 iterations (LP_MAX_TGSI_LOOP_ITERATIONS, one budget per SIMD group of lanes);
// from then on every loop runs its body once. Dense scenes at low resolution pass that (BMW at
// 32^3: 58k triangles in one voxel). So every traversal ends with a probe: a loop of
// V(loop_probe) = 2 iterations (a uniform, so no compiler can count it). If it runs only once,
// the budget was spent and the walk may have been cut: the ray is stored as LOOP_CUT_PRIM, and
// backends.trace fails the case naming the limit instead of reporting misses. (A probe on the
// loops' own exit conditions does not work: the compiler folds them, knowing no other exit.)
// Drivers without such a limit always count 2.
#define LOOP_CUT_PRIM -2
INLINE int loops_intact(uint trips) {  // trips = V(loop_probe)
    uint runs = 0u;
    for (uint k = 0u; k < trips; ++k) runs += 1u;
    return runs == trips ? 1 : 0;
}

INLINE Hit cut_hit(CTX_PARAM Hit best) {
    if (loops_intact(V(loop_probe)) == 0) best.prim = LOOP_CUT_PRIM;
    return best;
}

// Closest-hit update with a deterministic tie-break (smaller id wins at equal t), so a run
// gives the same ids whatever order the candidates arrive in (fill order is not deterministic).
// Only a hit before tmax counts, so a miss (t = INF_F) never becomes one while best.t = tmax = inf.
INLINE Hit closer(Hit best, float t, int prim, float tmin) {
    if (t >= tmin && (t < best.t || (t == best.t && best.prim >= 0 && prim < best.prim))) {
        best.t = t;
        best.prim = prim;
    }
    return best;
}

// Tick source of CLOCK_START()/CLOCK_ELAPSED() (preludes). USE_CLOCK and CLOCK_PTX come from
// with_work_counters (backends/structures/base.py) only where the device has a clock; every
// other build reads 0, so the counters' clock field is 0 there.
#if defined(USE_CLOCK) && defined(LANG_GLSL)
#define CLOCK_NOW() clock2x32ARB().x
#elif defined(USE_CLOCK) && defined(CLOCK_PTX)
INLINE uint clock_now_ptx(void) {
    uint c;
    __asm__ __volatile__("mov.u32 %0, %%clock;" : "=r"(c));
    return c;
}
#define CLOCK_NOW() clock_now_ptx()
#else
#define CLOCK_NOW() 0u
#endif

#ifdef HAS_rays
INLINE void store_hit(CTX_PARAM uint ray, Hit h) {
    V(hit_prim)[ray] = h.prim;
    V(hit_t)[ray] = h.prim >= 0 ? h.t : INF_F;
}
#endif
