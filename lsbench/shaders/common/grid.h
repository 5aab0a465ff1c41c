// Uniform grid (thesis 3.3.1): conservative voxelization (3.4) and 3D-DDA traversal
// (Amanatides & Woo 1987). Needs geometry.h and scene.h.
//
// Grid space: p' = (p - grid_origin) * grid_inv_voxel, so voxel (i,j,k) is the unit cube
// [i,i+1]x[j,j+1]x[k,k+1] and voxel index = i + rx*(j + ry*k). Affine maps keep the ray
// parameter, so a t found in grid space is the world distance along the unit direction.
// Uniforms: grid_origin, grid_inv_voxel (float4), grid_res (int4), box_eps (grid units).
// Buffers: voxel_offsets (uint, rx*ry*rz+1, CSR), voxel_tris (uint).

INLINE float3 to_grid(CTX_PARAM float3 p) {
    return (p - V(grid_origin).xyz) * V(grid_inv_voxel).xyz;
}

#ifdef HAS_faces
// A triangle's corners in grid space (voxel (i,j,k) = unit cube at (i,j,k)).
INLINE Triangle load_grid_triangle(CTX_PARAM uint tri) {
    Triangle t = load_triangle(CTX_ARG tri);
    t.a = to_grid(CTX_ARG t.a);
    t.b = to_grid(CTX_ARG t.b);
    t.c = to_grid(CTX_ARG t.c);
    return t;
}
#endif

INLINE uint voxel_index(CTX_PARAM int3 c) {
    int3 r = V(grid_res).xyz;
    return U32(c.x) + U32(r.x) * (U32(c.y) + U32(r.y) * U32(c.z));
}

#if defined(HAS_voxel_counts) || defined(HAS_voxel_cursor)
// ---- Voxelization: count pass (VOXELIZE_FILL undefined) and fill pass --------------------
// Both passes run the same overlap tests, so pass 2 writes exactly the counts of pass 1.
INLINE void emit_voxel(CTX_PARAM uint voxel, uint tri) {
#ifdef VOXELIZE_FILL
    uint slot = ATOMIC_ADD(V(voxel_cursor)[voxel], 1u);
    V(voxel_tris)[V(voxel_offsets)[voxel] + slot] = tri;
#else
    ATOMIC_ADD(V(voxel_counts)[voxel], 1u);
#endif
}

INLINE int overlaps_voxel(float3 a, float3 b, float3 c, int3 cell, float eps) {
    float3 centre = make_float3(F32(cell.x) + 0.5f, F32(cell.y) + 0.5f, F32(cell.z) + 0.5f);
    float h = 0.5f + eps;  // eps-expanded box: conservative despite float rounding
    return tri_box_overlap(centre, make_float3(h, h, h), a, b, c);
}

// Compute-kernel voxelizer (OpenCL): one work item per triangle walks its clamped bounds.
INLINE void voxelize_triangle(CTX_PARAM uint tri) {
    Triangle t = load_grid_triangle(CTX_ARG tri);
    float3 a = t.a;
    float3 b = t.b;
    float3 c = t.c;
    float eps = V(box_eps);
    int3 r = V(grid_res).xyz;
    float3 lo = min(a, min(b, c)) - make_float3(eps, eps, eps);
    float3 hi = max(a, max(b, c)) + make_float3(eps, eps, eps);
    int x0 = max(I32(floor(lo.x)), 0), x1 = min(I32(floor(hi.x)), r.x - 1);
    int y0 = max(I32(floor(lo.y)), 0), y1 = min(I32(floor(hi.y)), r.y - 1);
    int z0 = max(I32(floor(lo.z)), 0), z1 = min(I32(floor(hi.z)), r.z - 1);
    for (int z = z0; z <= z1; ++z)
        for (int y = y0; y <= y1; ++y)
            for (int x = x0; x <= x1; ++x) {
                int3 cell = make_int3(x, y, z);
                if (overlaps_voxel(a, b, c, cell, eps) != 0) emit_voxel(CTX_ARG voxel_index(CTX_ARG cell), tri);
            }
}

INLINE void voxelize_kernel(CTX_PARAM uint gid) { voxelize_triangle(CTX_ARG gid); }

// Raster voxelizer column (GLSL fragment shader): the triangle was projected along its
// dominant axis w; this fragment is column (cu, cv) of the other two axes. Only the depth
// neighbours the triangle's plane can reach over the column are tested (at most a few voxels,
// since |n_w| is the largest normal component), each with the same exact overlap test.
INLINE void voxelize_column(CTX_PARAM uint tri, int w, int cu, int cv) {
    Triangle t = load_grid_triangle(CTX_ARG tri);
    float3 a = t.a;
    float3 b = t.b;
    float3 c = t.c;
    float eps = V(box_eps);
    int3 r = V(grid_res).xyz;
    int u = (w + 1) % 3;
    int v = (w + 2) % 3;
    if (cu < 0 || cv < 0 || cu >= icomp3(r, u) || cv >= icomp3(r, v)) return;
    float dlo = min(comp3(a, w), min(comp3(b, w), comp3(c, w)));
    float dhi = max(comp3(a, w), max(comp3(b, w), comp3(c, w)));
    float3 n = cross(b - a, c - a);
    float nw = comp3(n, w);
    float nu = comp3(n, u);
    float nv = comp3(n, v);
    if (fabs(nw) > 1e-20f && fabs(nw) >= fabs(nu) && fabs(nw) >= fabs(nv)) {
        // Plane depth over the column's corners: w = (n.a - nu*u - nv*v) / nw.
        float k = dot(n, a);
        float u0 = F32(cu), u1 = F32(cu + 1), v0 = F32(cv), v1 = F32(cv + 1);
        float d00 = (k - nu * u0 - nv * v0) / nw;
        float d01 = (k - nu * u0 - nv * v1) / nw;
        float d10 = (k - nu * u1 - nv * v0) / nw;
        float d11 = (k - nu * u1 - nv * v1) / nw;
        // The eps-expanded box widens the reachable depth by at most 2 eps (|nu|,|nv| <= |nw|);
        // the extra margin only adds voxels for the exact test to reject.
        float margin = 3.0f * eps + 1e-3f * (1.0f + fabs(dhi));
        dlo = max(dlo, min(min(d00, d01), min(d10, d11)) - margin);
        dhi = min(dhi, max(max(d00, d01), max(d10, d11)) + margin);
    }
    int w0 = max(I32(floor(dlo - eps)), 0);
    int w1 = min(I32(floor(dhi + eps)), icomp3(r, w) - 1);
    for (int d = w0; d <= w1; ++d) {
        int3 cell = w == 0 ? make_int3(d, cu, cv) : (w == 1 ? make_int3(cv, d, cu) : make_int3(cu, cv, d));
        if (overlaps_voxel(a, b, c, cell, eps) != 0) emit_voxel(CTX_ARG voxel_index(CTX_ARG cell), tri);
    }
}

#endif  // voxelization

#ifdef HAS_rays
// ---- Traversal ------------------------------------------------------------------------------
// Closest hit by 3D-DDA. Every candidate's hit is kept (closer() keeps the nearest), but the walk
// ends only once that hit lies before the current voxel's exit: a farther hit of a triangle that
// spans several voxels is then beaten by any nearer one in the voxels still to come. (A hit past
// the exit used to be thrown away, so a triangle listed in no later voxel was lost when float
// rounding put its t a hair beyond the exit: strips in the grid's boundary planes, issue 13 item 1.)
INLINE Hit trace_grid(CTX_PARAM float3 o, float3 d, float tmin, float tmax, uint ray) {
#ifdef COUNT_WORK
    uint clock0 = CLOCK_START();
#endif
    Hit best = no_hit(tmax);
    WRay wr = make_wray(o, d);
    float3 og = to_grid(CTX_ARG o);
    float3 dg = d * V(grid_inv_voxel).xyz;
    float3 inv = make_float3(safe_rcp(dg.x), safe_rcp(dg.y), safe_rcp(dg.z));
    int3 r = V(grid_res).xyz;
    float2 span = ray_box(og, inv, dg, make_float3(0.0f, 0.0f, 0.0f), make_float3(F32(r.x), F32(r.y), F32(r.z)));
    float t0 = max(span.x, tmin);
    float t1 = min(span.y, tmax);
    uint iterations = 0u;
    uint tests = 0u;
    if (t0 <= t1) {
        float3 p = og + dg * t0;
        int3 cell = clamp(make_int3(I32(floor(p.x)), I32(floor(p.y)), I32(floor(p.z))),
                          make_int3(0, 0, 0), r - make_int3(1, 1, 1));
        int sx = dg.x > 0.0f ? 1 : -1, sy = dg.y > 0.0f ? 1 : -1, sz = dg.z > 0.0f ? 1 : -1;
        // Parameter of the next boundary on each axis; an axis the ray does not move along never wins.
        float nx = dg.x == 0.0f ? INF_F : (F32(cell.x + (sx > 0 ? 1 : 0)) - og.x) * inv.x;
        float ny = dg.y == 0.0f ? INF_F : (F32(cell.y + (sy > 0 ? 1 : 0)) - og.y) * inv.y;
        float nz = dg.z == 0.0f ? INF_F : (F32(cell.z + (sz > 0 ? 1 : 0)) - og.z) * inv.z;
        float dx = fabs(inv.x), dy = fabs(inv.y), dz = fabs(inv.z);
        for (;;) {
            iterations += 1u;
            uint vox = voxel_index(CTX_ARG cell);
            float t_exit = min(nx, min(ny, nz));
            uint begin = V(voxel_offsets)[vox];
            uint end = V(voxel_offsets)[vox + 1u];
            for (uint i = begin; i < end; ++i) {
                uint tri = V(voxel_tris)[i];
                Triangle T = load_triangle(CTX_ARG tri);
                float t = ray_triangle_wt(wr, T.a, T.b, T.c);
                tests += 1u;
                best = closer(best, t, I32(tri), tmin);
            }
            if (best.prim >= 0 && best.t <= t_exit) break;
            if (t_exit >= t1) break;
            if (nx <= ny && nx <= nz) {
                cell.x += sx; nx += dx;
                if (cell.x < 0 || cell.x >= r.x) break;
            } else if (ny <= nz) {
                cell.y += sy; ny += dy;
                if (cell.y < 0 || cell.y >= r.y) break;
            } else {
                cell.z += sz; nz += dz;
                if (cell.z < 0 || cell.z >= r.z) break;
            }
        }
    }
#ifdef COUNT_WORK
    V(work)[ray] = make_uint4(iterations, tests, 0u, CLOCK_ELAPSED(clock0));
#endif
    return cut_hit(CTX_ARG best);
}

INLINE void trace_grid_kernel(CTX_PARAM uint ray) {
    Ray r = load_ray(CTX_ARG ray);
    store_hit(CTX_ARG ray, trace_grid(CTX_ARG r.o, r.d, r.tmin, r.tmax, ray));
}
#endif  // traversal
