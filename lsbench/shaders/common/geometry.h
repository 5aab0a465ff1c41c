// Geometry shared by every structure and both languages (see shaders/*/prelude for the dialect).

// Component i of a float3 (OpenCL C does not portably index vectors with a variable).
INLINE float comp3(float3 v, int i) { return i == 0 ? v.x : (i == 1 ? v.y : v.z); }
INLINE int icomp3(int3 v, int i) { return i == 0 ? v.x : (i == 1 ? v.y : v.z); }

// Number of bits below `bit` (0..31) that are set in `word`: a node's child slot in its packed
// children (octree.h), a shaft's set among its cell's heads (linespace.h).
INLINE uint rank_in_word(uint word, uint bit) {
    return bit == 0u ? 0u : POPCOUNT(word & ((1u << bit) - 1u));
}

// 1/x that maps +0 and -0 to +/-infinity by sign bit, so axis-parallel rays never divide by
// zero and the slab test below sees an infinite slope instead of NaN.
// A non-zero |x| below ~2.9e-39 (a denormal direction component) would give 1/x = inf, and
// a ray starting exactly on a cell boundary then computes 0 * inf = NaN for its next boundary
// (svo lost such rays, tests/test_properties.py): the largest finite float keeps it ordered.
INLINE float safe_rcp(float x) {
    if (x == 0.0f) return (as_uint(x) & 0x80000000u) != 0u ? -INF_F : INF_F;
    float r = 1.0f / x;
    if (fabs(r) > 3.4028235e38f) return x < 0.0f ? -3.4028235e38f : 3.4028235e38f;
    return r;
}

// Ray/box slab test (Kay & Kajiya). Returns (t_enter, t_exit); the box is missed if t_enter > t_exit.
// A zero direction component gives +/-inf slopes: 0 * inf is avoided by testing the origin.
INLINE float2 ray_box(float3 o, float3 inv_d, float3 d, float3 lo, float3 hi) {
    float t0 = -INF_F;
    float t1 = INF_F;
    for (int a = 0; a < 3; ++a) {
        float oa = comp3(o, a);
        float da = comp3(d, a);
        float ia = comp3(inv_d, a);
        float la = comp3(lo, a);
        float ha = comp3(hi, a);
        if (da == 0.0f) {
            if (oa < la || oa > ha) { t0 = INF_F; t1 = -INF_F; }
        } else {
            float ta = (la - oa) * ia;
            float tb = (ha - oa) * ia;
            t0 = max(t0, min(ta, tb));
            t1 = min(t1, max(ta, tb));
        }
    }
    return make_float2(t0, t1);
}

// Watertight ray/triangle test (Woop, Benthin & Wald, JCGT 2013), the test Embree uses: the
// ray is sheared so it runs along +z, edge functions are evaluated in that 2D space, and a
// point on an edge shared by two triangles gives the same edge value (opposite sign) in
// both, so no ray slips through a shared edge (Moeller-Trumbore does, at box corners).
// The per-ray part (axis permutation and shear) is computed once per ray.
STRUCT(WRay) { float3 o; float3 d; int kx; int ky; int kz; float sx; float sy; float sz; };

// Direction components below 1e-30 (denormals included) count as signed zeros here: a ray in
// a triangle's plane whose off-plane component is 1.4e-45 otherwise gets tiny non-zero edge
// values and a "hit" at a meaningless t (tests/test_bad_input.py, flat scene). The ray moves
// < 1e-30 * t off its line, far below float32 resolution; GPUs that flush denormals agree.
INLINE float flush_tiny(float x) { return fabs(x) < 1e-30f ? x * 0.0f : x; }

INLINE WRay make_wray(float3 o, float3 d0) {
    float3 d = make_float3(flush_tiny(d0.x), flush_tiny(d0.y), flush_tiny(d0.z));
    WRay r;
    r.o = o;
    r.d = d;
    float ax = fabs(d.x), ay = fabs(d.y), az = fabs(d.z);
    r.kz = (ax >= ay && ax >= az) ? 0 : (ay >= az ? 1 : 2);
    r.kx = (r.kz + 1) % 3;
    r.ky = (r.kx + 1) % 3;
    float dz = comp3(d, r.kz);
    if (dz < 0.0f) { int t = r.kx; r.kx = r.ky; r.ky = t; }  // keep the winding
    r.sx = comp3(d, r.kx) / dz;
    r.sy = comp3(d, r.ky) / dz;
    r.sz = 1.0f / dz;
    return r;
}

INLINE float3 wray_vertex(WRay r, float3 v) {
    float3 p = v - r.o;
    float pz = comp3(p, r.kz);
    return make_float3(comp3(p, r.kx) - r.sx * pz, comp3(p, r.ky) - r.sy * pz, r.sz * pz);
}

// Distance of the hit once the edge test has said "inside": where the ray meets the triangle's
// plane (as Embree's Moeller-Trumbore computes t), not the barycentric mean of the sheared
// vertex depths, whose weights are differences of nearly equal products for a long thin
// triangle (a 5 m x 0.7 mm strip gave t off by 5e-5 relative, pushing hits past the cell exit;
// issue 13 item 1). n is the triangle's unit normal, computed once per scene in float64 on the
// host (backends.triangle_records: the records' w components). Computed here in float32, it was
// the largest part of the candidate test on llvmpipe, where a SIMD group runs the branch whenever
// one of its lanes hits (Sponza 256², precomputed against computed here: grid glsl 0.70 of the
// trace time on primary rays, esvo 0.73, grid-ls 0.81, bvh 0.85; PoCL 0.92-0.98; docs/profiles.md
// section 15). A well-conditioned float32 normal also needed the two shortest edges' cross product
// made perpendicular to the longest edge (issue 13 item 3: collinear triangles were hit up to
// 2.5e-3 off) and the edges scaled by a power of two (dot(n, n) was inf past edges of ~4e9 units,
// and dot(n, p - o) denormal in scenes of ~1e-13 units). A unit normal has neither limit, and its
// float32 rounding moves the hit by ~2^-24 of the triangle's extent. A zero normal (a zero-area
// triangle has no surface) or a ray in the plane to float precision is a miss; t stays inside the
// vertices' depth range [zlo, zhi] along the ray.
// A ray within about 0.06 degrees of the plane (|cos| < 1e-3) crosses it where rounding of the
// crossing is large and may lie far from where the edge test found the ray on the triangle: an
// adversarial Cornell box ray along a box face, within 1e-8 of one vertex (the edge test's "inside",
// at depth 0.911), crossed the face's plane 0.16 before it, off the triangle, and that was the
// distance reported (the BVH's packets found it: docs/profiles.md, section 8). There the edge
// test's own point is reported: t_edge, the depth Woop et al. interpolate from the sheared
// vertices (on the triangle, to rounding).
INLINE float triangle_plane_t(WRay r, float3 v0, float3 n, float zlo, float zhi, float t_edge) {
    float den = dot(n, r.d);
    // in the plane to float precision (|cos| <= 2^-23; also n = 0): the edge test's "inside" is
    // rounding, and no distance along the ray is meaningful
    if (fabs(den) <= 1.1920929e-7f) return INF_F;
    if (fabs(den) < 1e-3f) return clamp(t_edge, zlo, zhi);  // grazing the plane: the edge test's point
    return clamp(dot(n, v0 - r.o) / den, zlo, zhi);
}

// Returns t (distance along the unit direction), or INF_F for a miss. Edges and vertices
// count as inside, so a ray through a shared edge hits one of the two triangles (a tie).
// n: the triangle's unit normal (triangle_plane_t).
INLINE float ray_triangle_wt(WRay r, float3 v0, float3 v1, float3 v2, float3 n) {
    float3 a = wray_vertex(r, v0);
    float3 b = wray_vertex(r, v1);
    float3 c = wray_vertex(r, v2);
    // The ray is the point (0, 0) of the sheared plane: a triangle whose sheared bounds leave it out
    // is a miss, decided by comparisons alone. The edge functions below are differences of two
    // products of the sheared coordinates; for a triangle small against its distance from the ray
    // origin those products (~|v - o|^2) agree in all their leading bits, and the difference is
    // rounding: a 2e-3 triangle 6e3 units from the origin, its line passing 3e3 units away, got
    // (1, 0, 0) for edge values whose true signs were mixed (1.10, -0.28, -0.83), "inside", and a
    // hit reported thousands of units from the triangle (grid, svo, esvo and the Line Spaces, both
    // backends; tests/test_accuracy.py, mixed scales). Once (0, 0) lies within the bounds, every
    // vertex is within the triangle's own extent of it, so the products' rounding is relative to
    // the triangle's size. A point on a shared edge lies within both triangles' bounds (the
    // comparisons are exact), so the test stays watertight.
    if (min(a.x, min(b.x, c.x)) > 0.0f || max(a.x, max(b.x, c.x)) < 0.0f ||
        min(a.y, min(b.y, c.y)) > 0.0f || max(a.y, max(b.y, c.y)) < 0.0f) return INF_F;
    PRECISE float u = c.x * b.y - c.y * b.x;
    PRECISE float v = a.x * c.y - a.y * c.x;
    PRECISE float w = b.x * a.y - b.y * a.x;
    if ((u < 0.0f || v < 0.0f || w < 0.0f) && (u > 0.0f || v > 0.0f || w > 0.0f)) return INF_F;
    float det = u + v + w;
    if (det == 0.0f) return INF_F;  // ray in the triangle's plane, or a degenerate triangle
    float t_edge = (u * a.z + v * b.z + w * c.z) / det;  // Woop's depth: the edge test's point
    return triangle_plane_t(r, v0, n, min(a.z, min(b.z, c.z)), max(a.z, max(b.z, c.z)), t_edge);
}

// --- Akenine-Moeller triangle/box overlap (2001), separating axis theorem -------------------
// The box is centred at the origin with half extent h; the triangle is already translated.
// A zero axis (degenerate triangle, parallel edge) projects everything to 0 and never separates,
// so zero-area triangles are kept conservatively.
INLINE int separated_on_axis(float3 a, float3 v0, float3 v1, float3 v2, float3 h) {
    float p0 = dot(a, v0);
    float p1 = dot(a, v1);
    float p2 = dot(a, v2);
    float r = h.x * fabs(a.x) + h.y * fabs(a.y) + h.z * fabs(a.z);
    return (min(p0, min(p1, p2)) > r || max(p0, max(p1, p2)) < -r) ? 1 : 0;
}

INLINE int tri_box_overlap(float3 centre, float3 h, float3 a, float3 b, float3 c) {
    float3 v0 = a - centre;
    float3 v1 = b - centre;
    float3 v2 = c - centre;
    // 3 box normals: the triangle's bounds against the box.
    if (min(v0.x, min(v1.x, v2.x)) > h.x || max(v0.x, max(v1.x, v2.x)) < -h.x) return 0;
    if (min(v0.y, min(v1.y, v2.y)) > h.y || max(v0.y, max(v1.y, v2.y)) < -h.y) return 0;
    if (min(v0.z, min(v1.z, v2.z)) > h.z || max(v0.z, max(v1.z, v2.z)) < -h.z) return 0;
    float3 e0 = v1 - v0;
    float3 e1 = v2 - v1;
    float3 e2 = v0 - v2;
    // Triangle normal.
    if (separated_on_axis(cross(e0, e1), v0, v1, v2, h) != 0) return 0;
    // 9 edge x box-axis cross products: cross(e, X) = (0, e.z, -e.y) etc.
    if (separated_on_axis(make_float3(0.0f, e0.z, -e0.y), v0, v1, v2, h) != 0) return 0;
    if (separated_on_axis(make_float3(0.0f, e1.z, -e1.y), v0, v1, v2, h) != 0) return 0;
    if (separated_on_axis(make_float3(0.0f, e2.z, -e2.y), v0, v1, v2, h) != 0) return 0;
    if (separated_on_axis(make_float3(-e0.z, 0.0f, e0.x), v0, v1, v2, h) != 0) return 0;
    if (separated_on_axis(make_float3(-e1.z, 0.0f, e1.x), v0, v1, v2, h) != 0) return 0;
    if (separated_on_axis(make_float3(-e2.z, 0.0f, e2.x), v0, v1, v2, h) != 0) return 0;
    if (separated_on_axis(make_float3(e0.y, -e0.x, 0.0f), v0, v1, v2, h) != 0) return 0;
    if (separated_on_axis(make_float3(e1.y, -e1.x, 0.0f), v0, v1, v2, h) != 0) return 0;
    if (separated_on_axis(make_float3(e2.y, -e2.x, 0.0f), v0, v1, v2, h) != 0) return 0;
    return 1;
}

// ---- Driver loop budget ------------------------------------------------------------------------
// llvmpipe (gallivm) ends every loop of a shader invocation, silently, once all its loops together
// have run 65535 iterations (LP_MAX_TGSI_LOOP_ITERATIONS, one budget per SIMD group of lanes);
// from then on every loop runs its body once. Dense scenes at low resolution pass that (BMW at
// 32^3: 58k triangles in one voxel). So every long kernel ends with a probe: a loop of
// V(loop_probe) = 2 iterations (a uniform, so no compiler can count it). If it runs only once,
// the budget was spent and the kernel's loops may have been cut: a traversal stores the ray as
// LOOP_CUT_PRIM (trace.h: cut_hit), the Line Space build counts the shaft, and the host fails the
// case naming the limit instead of reporting misses. (A probe on the loops' own exit conditions
// does not work: the compiler folds them, knowing no other exit.) Drivers without such a limit
// always count 2.
INLINE int loops_intact(uint trips) {  // trips = V(loop_probe)
    uint runs = 0u;
    for (uint k = 0u; k < trips; ++k) runs += 1u;
    return runs == trips ? 1 : 0;
}
