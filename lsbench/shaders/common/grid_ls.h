// `grid-ls`: uniform grid whose non-empty voxels hold a candidate-list Line Space (Delgado Kraemer 2019, 3.3.3,
// 5.1, Algorithm 2): the build steps that pick the voxels and describe them as Line Space cells,
// and the lookup the grid walk (grid.h) makes in such a voxel. The trace kernel is grid.h's
// trace_grid_kernel with LEAF_LINE_SPACE; it needs geometry.h, scene.h, linespace.h, trace.h and
// grid.h before this file.
//
// Buffers: voxel_offsets / voxel_tris (the grid's CSR lists), ls_ids (exclusive scan of the
// "has a Line Space" flags, voxels + 1 entries: trace.h, cell_line_space), ls_shaft_offsets /
// ls_shaft_tris (linespace.h).
// Uniform ls_min_count: only voxels with more candidates than this get a Line Space; the others
// keep their plain list (thesis 6.3: Line Spaces only where they pay).

#ifdef KERNEL_gls_flags
// ---- Build: which voxels get a Line Space -----------------------------------------------------
INLINE void gls_flags_kernel(CTX_PARAM uint vox) {
    uint count = V(voxel_offsets)[vox + 1u] - V(voxel_offsets)[vox];
    V(ls_flags)[vox] = count > V(ls_min_count) ? 1u : 0u;
}
#endif

#ifdef KERNEL_gls_cells
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

#ifdef KERNEL_trace_grid_ls
// ---- Traversal: the voxel's shaft (Algorithm 2) -------------------------------------------------
// In a voxel with a Line Space the ray's entry face and patch and its exit face and patch (from
// the walk's step, grid.h) select one shaft; only its candidates are tested, and an empty shaft
// skips the voxel without a triangle test. The patch coordinates of the entry are those the
// previous voxel's exit had: the step changes only the cell coordinate of the crossed axis, which
// the face's (u, v) leave out. A voxel without a Line Space keeps its plain list.
INLINE Candidates gls_voxel_shaft(CTX_PARAM Candidates list, uint vox, GridRay g, GridStep s) {
    uint ls = cell_line_space(CTX_ARG vox);
    if (ls == LS_NONE) return list;
    float3 cf = make_float3(F32(s.cell.x), F32(s.cell.y), F32(s.cell.z));
    // Face 2a + side: the ray enters an axis it runs up through side 0 and leaves it through side 1.
    int face_in = 2 * s.axis_in + (comp3(g.d, s.axis_in) > 0.0f ? 0 : 1);
    int face_out = 2 * s.axis_out + (comp3(g.d, s.axis_out) > 0.0f ? 1 : 0);
    float2 uv_in = ls_face_uv(g.o + g.d * s.t_in - cf, s.axis_in);
    float2 uv_out = ls_face_uv(g.o + g.d * s.t_exit - cf, s.axis_out);
    return shaft_list(CTX_ARG ls, ls_shaft_id(V(ls_n), face_in, uv_in, face_out, uv_out), list);
}
#endif
