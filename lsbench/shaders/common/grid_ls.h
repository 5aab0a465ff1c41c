// `grid-ls`: uniform grid whose non-empty voxels hold a candidate-list Line Space (thesis 3.3.3,
// 5.1, Algorithm 2). Needs geometry.h, scene.h, grid.h, linespace.h.
//
// Buffers: voxel_offsets / voxel_tris (the grid's CSR lists), ls_ids (exclusive scan of the
// "has a Line Space" flags, voxels + 1 entries: voxel v has Line Space ls_ids[v] iff
// ls_ids[v + 1] > ls_ids[v]), ls_shaft_offsets / ls_shaft_tris (linespace.h).
// Uniform ls_min_count: only voxels with more candidates than this get a Line Space; the others
// keep their plain list (thesis 6.3: Line Spaces only where they pay).

#ifdef HAS_ls_flags
// ---- Build: which voxels get a Line Space -----------------------------------------------------
INLINE void gls_flags_kernel(CTX_PARAM uint vox) {
    uint count = V(voxel_offsets)[vox + 1u] - V(voxel_offsets)[vox];
    V(ls_flags)[vox] = count > V(ls_min_count) ? 1u : 0u;
}
#endif

#if defined(HAS_ls_cell_boxes) && defined(HAS_ls_ids)
// ---- Build: voxel -> Line Space cell (box in grid space + candidate range) -------------------
INLINE void gls_cells_kernel(CTX_PARAM uint vox) {
    uint c = V(ls_ids)[vox];
    if (V(ls_ids)[vox + 1u] == c) return;
    int3 r = V(grid_res).xyz;
    int x = I32(vox % U32(r.x));
    int y = I32((vox / U32(r.x)) % U32(r.y));
    int z = I32(vox / (U32(r.x) * U32(r.y)));
    V(ls_cell_boxes)[2u * c] = make_float4(F32(x), F32(y), F32(z), 0.0f);
    V(ls_cell_boxes)[2u * c + 1u] = make_float4(F32(x + 1), F32(y + 1), F32(z + 1), 0.0f);
    V(ls_cell_ranges)[2u * c] = V(voxel_offsets)[vox];
    V(ls_cell_ranges)[2u * c + 1u] = V(voxel_offsets)[vox + 1u];
}
#endif

#if defined(HAS_rays) && defined(HAS_ls_shaft_tris)
// ---- Traversal (Algorithm 2) --------------------------------------------------------------------
// 3D-DDA over the voxels as in trace_grid. In a voxel with a Line Space the ray's entry face and
// patch and its exit face and patch select one shaft; only its candidates are tested, and an empty
// shaft skips the voxel without a triangle test. The exit face/point of a voxel is the entry
// face/point of the next (the step crosses exactly that face, and the two tangential cell-local
// coordinates are the same on both sides), so each boundary is computed once (Alg. 2, lines 7,
// 12-13); it is computed only when a Line Space needs it, so empty voxels cost nothing extra.
// Every candidate's hit is kept and the walk ends once it lies before the voxel's exit, as in the plain grid.
INLINE Hit trace_grid_ls(CTX_PARAM float3 o, float3 d, float tmin, float tmax, uint ray) {
    uint clock0 = CLOCK_START();
    Hit best = no_hit(tmax);
    WRay wr = make_wray(o, d);
    float3 og = to_grid(CTX_ARG o);
    float3 dg = d * V(grid_inv_voxel).xyz;
    float3 inv = make_float3(safe_rcp(dg.x), safe_rcp(dg.y), safe_rcp(dg.z));
    int3 r = V(grid_res).xyz;
    float2 span = ray_box(og, inv, dg, make_float3(0.0f, 0.0f, 0.0f), make_float3(F32(r.x), F32(r.y), F32(r.z)));
    float t0 = max(span.x, tmin);
    float t1 = min(span.y, tmax);
    uint n = V(ls_n);
    uint shafts = V(ls_shafts);
    uint iterations = 0u;
    uint tests = 0u;
    uint lookups = 0u;
    if (t0 <= t1) {
        float3 p = og + dg * t0;
        int3 cell = clamp(make_int3(I32(floor(p.x)), I32(floor(p.y)), I32(floor(p.z))),
                          make_int3(0, 0, 0), r - make_int3(1, 1, 1));
        int sx = dg.x > 0.0f ? 1 : -1, sy = dg.y > 0.0f ? 1 : -1, sz = dg.z > 0.0f ? 1 : -1;
        int3 sgn = make_int3(sx, sy, sz);
        float nx = dg.x == 0.0f ? INF_F : (F32(cell.x + (sx > 0 ? 1 : 0)) - og.x) * inv.x;
        float ny = dg.y == 0.0f ? INF_F : (F32(cell.y + (sy > 0 ? 1 : 0)) - og.y) * inv.y;
        float nz = dg.z == 0.0f ? INF_F : (F32(cell.z + (sz > 0 ? 1 : 0)) - og.z) * inv.z;
        float dx = fabs(inv.x), dy = fabs(inv.y), dz = fabs(inv.z);
        // Entry of the first voxel: where the ray's line enters it, also when the origin lies
        // inside (the shaft of the whole chord holds the part the ray covers).
        float qx = dg.x == 0.0f ? -INF_F : (F32(cell.x + (sx > 0 ? 0 : 1)) - og.x) * inv.x;
        float qy = dg.y == 0.0f ? -INF_F : (F32(cell.y + (sy > 0 ? 0 : 1)) - og.y) * inv.y;
        float qz = dg.z == 0.0f ? -INF_F : (F32(cell.z + (sz > 0 ? 0 : 1)) - og.z) * inv.z;
        int axis_in = (qx >= qy && qx >= qz) ? 0 : (qy >= qz ? 1 : 2);
        float t_in = max(qx, max(qy, qz));
        int face_in = 2 * axis_in + (icomp3(sgn, axis_in) > 0 ? 0 : 1);
        float2 uv_in = make_float2(0.0f, 0.0f);
        int have_uv_in = 0;
        for (;;) {
            iterations += 1u;
            uint vox = voxel_index(CTX_ARG cell);
            float t_exit = min(nx, min(ny, nz));
            int axis_out = (nx <= ny && nx <= nz) ? 0 : (ny <= nz ? 1 : 2);
            int face_out = 2 * axis_out + (icomp3(sgn, axis_out) > 0 ? 1 : 0);
            float2 uv_out = make_float2(0.0f, 0.0f);
            int have_uv_out = 0;
            uint begin = V(voxel_offsets)[vox];
            uint end = V(voxel_offsets)[vox + 1u];
            if (begin < end) {
                uint ls = V(ls_ids)[vox];
                if (V(ls_ids)[vox + 1u] > ls) {
                    float3 cf = make_float3(F32(cell.x), F32(cell.y), F32(cell.z));
                    if (have_uv_in == 0) uv_in = ls_face_uv(og + dg * t_in - cf, axis_in);
                    uv_out = ls_face_uv(og + dg * t_exit - cf, axis_out);
                    have_uv_out = 1;
                    uint sid = ls * shafts + ls_shaft_id(n, face_in, uv_in, face_out, uv_out);
                    lookups += 1u;
                    uint cb = LS_OFFSET(sid);
                    uint ce = LS_OFFSET(sid + 1u);
                    for (uint i = cb; i < ce; ++i) {
                        uint tri = LS_CANDIDATE(i);
                        Triangle T = load_triangle(CTX_ARG tri);
                        float t = ray_triangle_wt(wr, T.a, T.b, T.c);
                        tests += 1u;
                        best = closer(best, t, I32(tri), tmin);
                    }
                } else {
                    for (uint i = begin; i < end; ++i) {
                        uint tri = V(voxel_tris)[i];
                        Triangle T = load_triangle(CTX_ARG tri);
                        float t = ray_triangle_wt(wr, T.a, T.b, T.c);
                        tests += 1u;
                        best = closer(best, t, I32(tri), tmin);
                    }
                }
            }
            if (best.prim >= 0 && best.t <= t_exit) break;
            if (t_exit >= t1) break;
            if (axis_out == 0) {
                cell.x += sx; nx += dx;
                if (cell.x < 0 || cell.x >= r.x) break;
            } else if (axis_out == 1) {
                cell.y += sy; ny += dy;
                if (cell.y < 0 || cell.y >= r.y) break;
            } else {
                cell.z += sz; nz += dz;
                if (cell.z < 0 || cell.z >= r.z) break;
            }
            // The exit of this voxel is the entry of the next.
            axis_in = axis_out;
            face_in = face_out ^ 1;
            t_in = t_exit;
            uv_in = uv_out;
            have_uv_in = have_uv_out;
        }
    }
#ifdef COUNT_WORK
    V(work)[ray] = make_uint4(iterations, tests, lookups, CLOCK_ELAPSED(clock0));
#endif
    return cut_hit(CTX_ARG best);
}

INLINE void trace_grid_ls_kernel(CTX_PARAM uint ray) {
    Ray r = load_ray(CTX_ARG ray);
    store_hit(CTX_ARG ray, trace_grid_ls(CTX_ARG r.o, r.d, r.tmin, r.tmax, ray));
}
#endif  // traversal
