// Uniform grid (Delgado Kraemer 2019, 3.3.1): conservative voxelization (3.4) and the 3D-DDA walk (Amanatides &
// Woo 1987) that grid and grid-ls share. Needs geometry.h and scene.h (grid space); the traversal
// also trace.h, and for grid-ls linespace.h and grid_ls.h after this file.
//
// Uniforms: grid_origin, grid_inv_voxel (float4), grid_res (int4), box_eps (grid units).
// Buffers: voxel_offsets (uint, rx*ry*rz+1, CSR), voxel_tris (uint), voxel_bits (uint, one bit per
// voxel: its list is not empty; grid_occupancy below).

#if defined(KERNEL_voxelize_count) || defined(KERNEL_voxelize_fill)
// ---- Voxelization: count pass (voxelize_count) and fill pass (voxelize_fill) ----------------
// Both passes run the same overlap tests, so pass 2 writes exactly the counts of pass 1.
// VOXEL_SLAB (count pass only): count the voxels of z layers [voxel_slab.x, voxel_slab.y) alone,
// into a buffer of those layers. The cost model reads a large grid's counts slab by slab and keeps
// only the non-empty voxels (model/stats.py: voxel_counts), so it never holds, nor first touches,
// a buffer of the whole grid (235 MB at spheres' 512^3 octree). The overlap tests are the
// full pass's, so each voxel's count is the one the build's count pass finds.
INLINE void emit_voxel(CTX_PARAM uint voxel, uint tri) {
#ifdef KERNEL_voxelize_fill
    uint slot = ATOMIC_ADD(V(voxel_cursor)[voxel], 1u);
    V(voxel_tris)[V(voxel_offsets)[voxel] + slot] = tri;
#elif defined(VOXEL_SLAB)
    int3 r = V(grid_res).xyz;  // voxel_counts holds the slab's layers only
    ATOMIC_ADD(V(voxel_counts)[voxel - U32(V(voxel_slab).x) * U32(r.x) * U32(r.y)], 1u);
#else
    ATOMIC_ADD(V(voxel_counts)[voxel], 1u);
#endif
}

INLINE int overlaps_voxel(Triangle t, int3 cell, float eps) {
    float3 centre = make_float3(F32(cell.x) + 0.5f, F32(cell.y) + 0.5f, F32(cell.z) + 0.5f);
    float h = 0.5f + eps;  // eps-expanded box: conservative despite float rounding
    return tri_box_overlap(centre, make_float3(h, h, h), t.a, t.b, t.c);
}

// Compute-kernel voxelizer: one work item per triangle walks its clamped bounds (OpenCL; on
// llvmpipe the triangles of small bounds, see VOXELIZE_MAX_CELLS).
INLINE void voxelize_triangle(CTX_PARAM uint tri) {
    Triangle t = load_grid_triangle(CTX_ARG tri);
    float eps = V(box_eps);
    int3 r = V(grid_res).xyz;
    float3 lo = min(t.a, min(t.b, t.c)) - make_float3(eps, eps, eps);
    float3 hi = max(t.a, max(t.b, t.c)) + make_float3(eps, eps, eps);
    // Bounds (eps-widened) within one cell: the triangle lies inside that cell's box, 2 eps from
    // its faces, so no axis can separate them (|a.v| <= h.|a| for every vertex v) and the test
    // would only say so. Most triangles of a fitted grid are such (BMW at 134 x 40 x 148: 1.13
    // references per triangle).
    int one_cell = (floor(lo.x) == floor(hi.x) && floor(lo.y) == floor(hi.y) && floor(lo.z) == floor(hi.z)) ? 1 : 0;
    int x0 = max(I32(floor(lo.x)), 0), x1 = min(I32(floor(hi.x)), r.x - 1);
    int y0 = max(I32(floor(lo.y)), 0), y1 = min(I32(floor(hi.y)), r.y - 1);
    int z0 = max(I32(floor(lo.z)), 0), z1 = min(I32(floor(hi.z)), r.z - 1);
#ifdef VOXEL_SLAB
    z0 = max(z0, V(voxel_slab).x);
    z1 = min(z1, V(voxel_slab).y - 1);
#endif
#ifdef VOXELIZE_MAX_CELLS
    // A driver that ends an invocation's loops silently after a budget (llvmpipe: 65535, shared
    // by the lanes of a SIMD group) cannot walk large bounds here: such a triangle is listed in
    // raster_tris (its count in entry 0) for the raster voxelizer, which walks one column per
    // fragment (voxelize_column). Both passes split the triangles alike, so the fill writes
    // exactly what the count counted.
    if (z1 >= z0 && y1 >= y0 && x1 >= x0
        && (z1 - z0 + 1) * (y1 - y0 + 1) * (x1 - x0 + 1) > VOXELIZE_MAX_CELLS) {
        V(raster_tris)[1u + ATOMIC_ADD(V(raster_tris)[0], 1u)] = tri;
        return;
    }
#endif
    for (int z = z0; z <= z1; ++z)
        for (int y = y0; y <= y1; ++y)
            for (int x = x0; x <= x1; ++x) {
                int3 cell = make_int3(x, y, z);
                if (one_cell != 0 || overlaps_voxel(t, cell, eps) != 0) emit_voxel(CTX_ARG voxel_index(CTX_ARG cell), tri);
            }
}

INLINE void voxelize_kernel(CTX_PARAM uint gid) { voxelize_triangle(CTX_ARG gid); }

// Raster voxelizer column (GLSL fragment shader, shaders/glsl/voxelize.*): the triangle was
// projected along its dominant axis w; this fragment is column (cu, cv) of the other two axes.
// Only the depth neighbours the triangle's plane can reach over the column are tested (at most a
// few voxels, since |n_w| is the largest normal component), each with the same exact overlap test.
INLINE void voxelize_column(CTX_PARAM uint tri, int w, int cu, int cv) {
    Triangle t = load_grid_triangle(CTX_ARG tri);
    int3 r = V(grid_res).xyz;
    int u = (w + 1) % 3;
    int v = (w + 2) % 3;
    if (cu < 0 || cv < 0 || cu >= icomp3(r, u) || cv >= icomp3(r, v)) return;
    float eps = V(box_eps);
    float3 a = t.a;
    float dlo = min(comp3(a, w), min(comp3(t.b, w), comp3(t.c, w)));
    float dhi = max(comp3(a, w), max(comp3(t.b, w), comp3(t.c, w)));
    float3 n = cross(t.b - a, t.c - a);
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
#ifdef VOXEL_SLAB
    int4 slab = V(voxel_slab);  // z is the depth (w == 2) or one of the column's coordinates
    if (w == 2) {
        w0 = max(w0, slab.x);
        w1 = min(w1, slab.y - 1);
    } else if ((w == 0 ? cv : cu) < slab.x || (w == 0 ? cv : cu) >= slab.y) {
        return;
    }
#endif
    for (int d = w0; d <= w1; ++d) {
        int3 cell = w == 0 ? make_int3(d, cu, cv) : (w == 1 ? make_int3(cv, d, cu) : make_int3(cu, cv, d));
        if (overlaps_voxel(t, cell, eps) != 0) emit_voxel(CTX_ARG voxel_index(CTX_ARG cell), tri);
    }
}
#endif  // voxelization

#ifdef KERNEL_grid_occupancy
// ---- After the lists: one bit per voxel, set where its list is not empty --------------------
// Bit v & 31 of word v >> 5 (linear voxel order); one work item per word (no atomics). The walk
// crosses empty voxels reading this bit: 1/32 of the offsets' bytes (256 KiB at 128^3 against
// 8 MiB), so an incoherent ray's empty stretch stays in the cache, and one load, not two.
INLINE void grid_occupancy_kernel(CTX_PARAM uint w) {
    int3 r = V(grid_res).xyz;
    uint n = U32(r.x) * U32(r.y) * U32(r.z);
    uint bits = 0u;
    for (uint b = 0u; b < 32u; ++b) {
        uint v = 32u * w + b;
        if (v >= n) break;
        if (V(voxel_offsets)[v + 1u] > V(voxel_offsets)[v]) bits |= 1u << b;
    }
    V(voxel_bits)[w] = bits;
}
#endif

#if defined(KERNEL_trace_grid) || defined(KERNEL_trace_grid_ls)
// ---- Traversal: the 3D-DDA walk of grid and grid-ls -----------------------------------------
// The walk visits the voxels the ray crosses, front to back, and hands each to grid_voxel below:
// its plain list (grid), or for grid-ls (LEAF_LINE_SPACE) the shaft of its Line Space that the
// ray's entry and exit select (grid_ls.h: gls_voxel_shaft, thesis Algorithm 2). Per voxel the walk
// knows where the ray's line enters it (t_in, through a face of axis axis_in) and leaves it
// (t_exit, axis_out); the exit of one voxel is the entry of the next (the step crosses exactly
// that face), so each boundary is computed once (Alg. 2, lines 7, 12-13). The walk ends once the
// closest hit lies before the voxel's exit (trace.h: test_candidates, trace_done). `next`: the
// parameter of the next voxel boundary on each axis, stepped incrementally (Amanatides & Woo's tMax).
STRUCT(GridStep) { int3 cell; float t_in; int axis_in; float t_exit; int axis_out; float3 next; };

#ifdef LEAF_LINE_SPACE
INLINE Candidates gls_voxel_shaft(CTX_PARAM Candidates list, uint vox, GridRay g, GridStep s);  // grid_ls.h
#endif

INLINE Candidates grid_voxel(CTX_PARAM GridRay g, GridStep s) {
    uint vox = voxel_index(CTX_ARG s.cell);
    Candidates c = plain_list(V(voxel_offsets)[vox], V(voxel_offsets)[vox + 1u]);
#ifdef LEAF_LINE_SPACE
    if (c.begin < c.end) c = gls_voxel_shaft(CTX_ARG c, vox, g, s);  // an empty voxel has none
#endif
    return c;
}

// The voxel's exit: the nearest of the next boundaries (s.next, the parameter of the next face on
// each axis; an axis the ray does not move along holds INF_F and never wins).
INLINE GridStep grid_exit(GridStep s) {
    s.t_exit = min(s.next.x, min(s.next.y, s.next.z));
    s.axis_out = (s.next.x <= s.next.y && s.next.x <= s.next.z) ? 0 : (s.next.y <= s.next.z ? 1 : 2);
    return s;
}

// The step across the exit face (dir: +-1 per axis, dt: the parameter one voxel spans per axis):
// the exit becomes the next voxel's entry (grid_inside says whether the step left the grid).
INLINE GridStep grid_cross(GridStep s, int3 dir, float3 dt) {
    if (s.axis_out == 0) {
        s.cell.x += dir.x;
        s.next.x += dt.x;
    } else if (s.axis_out == 1) {
        s.cell.y += dir.y;
        s.next.y += dt.y;
    } else {
        s.cell.z += dir.z;
        s.next.z += dt.z;
    }
    s.axis_in = s.axis_out;
    s.t_in = s.t_exit;
    return s;
}

INLINE int grid_inside(int3 c, int3 r) {
    return (c.x >= 0 && c.y >= 0 && c.z >= 0 && c.x < r.x && c.y < r.y && c.z < r.z) ? 1 : 0;
}

// The walk's loop state in the slice words (trace.h): the voxel about to be visited, its entry,
// and the next boundary on each axis (the incremental values themselves, so the resumed walk
// steps exactly as one launch would).
INLINE Trace grid_suspend(Trace tr, GridStep s) {
    tr.wa = make_uint4(U32(s.cell.x), U32(s.cell.y), U32(s.cell.z), U32(s.axis_in));
    tr.wb = make_uint4(as_uint(s.t_in), as_uint(s.next.x), as_uint(s.next.y), as_uint(s.next.z));
    return tr;
}

INLINE Hit trace_grid(CTX_PARAM Ray ray, uint id) {
    Trace tr = trace_start(CTX_ARG ray, id);
    GridRay g = make_grid_ray(CTX_ARG ray);  // t below: from g.t_base (trace.h)
    int3 r = V(grid_res).xyz;
    float t1 = g.span.y;
    if (g.span.x <= t1) {
        float3 p = g.o + g.d * g.span.x;
        GridStep s;
        s.cell = clamp(make_int3(I32(floor(p.x)), I32(floor(p.y)), I32(floor(p.z))),
                       make_int3(0, 0, 0), r - make_int3(1, 1, 1));
        int sx = g.d.x > 0.0f ? 1 : -1, sy = g.d.y > 0.0f ? 1 : -1, sz = g.d.z > 0.0f ? 1 : -1;
        int3 dir = make_int3(sx, sy, sz);
        float3 dt = make_float3(fabs(g.inv.x), fabs(g.inv.y), fabs(g.inv.z));
        // Parameter of the next boundary on each axis; an axis the ray does not move along never wins.
        s.next.x = g.d.x == 0.0f ? INF_F : (F32(s.cell.x + (sx > 0 ? 1 : 0)) - g.o.x) * g.inv.x;
        s.next.y = g.d.y == 0.0f ? INF_F : (F32(s.cell.y + (sy > 0 ? 1 : 0)) - g.o.y) * g.inv.y;
        s.next.z = g.d.z == 0.0f ? INF_F : (F32(s.cell.z + (sz > 0 ? 1 : 0)) - g.o.z) * g.inv.z;
        // Entry of the first voxel: where the ray's line enters it, also when the origin lies
        // inside (a Line Space shaft of the whole chord holds the part the ray covers).
        float qx = g.d.x == 0.0f ? -INF_F : (F32(s.cell.x + (sx > 0 ? 0 : 1)) - g.o.x) * g.inv.x;
        float qy = g.d.y == 0.0f ? -INF_F : (F32(s.cell.y + (sy > 0 ? 0 : 1)) - g.o.y) * g.inv.y;
        float qz = g.d.z == 0.0f ? -INF_F : (F32(s.cell.z + (sz > 0 ? 0 : 1)) - g.o.z) * g.inv.z;
        s.axis_in = (qx >= qy && qx >= qz) ? 0 : (qy >= qz ? 1 : 2);
        s.t_in = max(qx, max(qy, qz));
        if (tr.resumed != 0) {  // an earlier slice stopped here (grid_suspend)
            s.cell = make_int3(I32(tr.wa.x), I32(tr.wa.y), I32(tr.wa.z));
            s.axis_in = I32(tr.wa.w);
            s.t_in = as_float(tr.wb.x);
            s.next = make_float3(as_float(tr.wb.y), as_float(tr.wb.z), as_float(tr.wb.w));
        }
        for (;;) {
            // Empty voxels are crossed in an inner loop, reading their occupancy bit (voxel_bits),
            // and a voxel's candidates tested in the outer one (the "while-while" loops of Aila &
            // Laine 2009). llvmpipe runs a loop's body once even where no lane iterates it, so a
            // candidate loop inside every step cost a triangle test per empty voxel (docs/profiles.md,
            // section 17). The bit instead of the two offsets took llvmpipe to 0.65-0.93 of the
            // device time; PoCL, which ran one loop over every voxel, to 0.90-1.03 (section 18).
            // The steps, their order and the hits are those of that one loop.
            int walking = 1;
            for (;;) {
                tr = trace_tick(tr);
                if (TRACE_SUSPENDED(tr)) break;
                s = grid_exit(s);
                uint vox = voxel_index(CTX_ARG s.cell);
                if (((LD_U(voxel_bits, vox >> 5) >> (vox & 31u)) & 1u) != 0u) {
                    tr = trace_revisit(tr, 1u);
                    break;
                }
                if (trace_done(tr, g.t_base + s.t_exit) != 0 || s.t_exit >= t1) { walking = 0; break; }
                s = grid_cross(s, dir, dt);
                if (grid_inside(s.cell, r) == 0) { walking = 0; break; }
            }
            if (TRACE_SUSPENDED(tr)) { tr = grid_suspend(tr, s); break; }
            if (walking == 0) break;
            tr = test_candidates(CTX_ARG tr, grid_voxel(CTX_ARG g, s));
            if (TRACE_SUSPENDED(tr)) { tr = grid_suspend(tr, s); break; }
            if (trace_done(tr, g.t_base + s.t_exit) != 0) break;
            if (s.t_exit >= t1) break;
            s = grid_cross(s, dir, dt);
            if (grid_inside(s.cell, r) == 0) break;
        }
    }
    return trace_finish(CTX_ARG tr, id);
}

INLINE void trace_grid_kernel(CTX_PARAM uint gid) {
    uint ray = trace_ray(CTX_ARG gid);
    store_hit(CTX_ARG ray, trace_grid(CTX_ARG load_ray(CTX_ARG ray), ray));
}
#endif  // traversal
