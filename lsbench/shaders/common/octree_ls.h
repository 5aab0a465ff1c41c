// `svo-ls` / `esvo-ls`: the adaptive Line Space (Delgado Kraemer 2019, 4, 5.1, Algorithm 3): the octrees of
// svo.h / esvo.h with a candidate-list Line Space (linespace.h) in their leaves. This file holds
// the build steps between the octree and the Line Space build, and the lookup that octree.h's
// oct_test_leaf makes for every leaf either traversal meets. Needs geometry.h and octree.h; the
// lookup also scene.h, linespace.h and trace.h before octree.h. The trace kernels are svo.h's and
// esvo.h's with LEAF_LINE_SPACE.
//
// Buffers: leaves (2 uints per leaf: first, count in voxel_tris; octree.h), ls_ids (exclusive scan
// of the "has a Line Space" flags, leaves + 1 entries: leaf l has Line Space ls_ids[l] iff
// ls_ids[l + 1] > ls_ids[l], the convention of trace.h's cell_line_space).
// Uniform ls_min_count: only leaves with more candidates than this get a Line Space.

#ifdef KERNEL_oct_ls_flags
// ---- Build 1: which leaves get a Line Space, one work item per leaf -----------------------
INLINE void oct_ls_flags_kernel(CTX_PARAM uint leaf) {
    V(ls_flags)[leaf] = V(leaves)[2u * leaf + 1u] > V(ls_min_count) ? 1u : 0u;
}
#endif

#ifdef KERNEL_oct_ls_cells
// ---- Build 2: leaf -> Line Space cell (voxel box in grid space + candidate range) ---------
// One work item per cell of the leaf level (octree.h: oct_leaf): the Morton code is the leaf's
// voxel, the rank of its bit the leaf index, as in oct_leaves_kernel.
INLINE void oct_ls_cells_kernel(CTX_PARAM uint m) {
    OctLeaf lf = oct_leaf(CTX_ARG m);
    if (lf.flagged == 0u) return;
    uint c = V(ls_ids)[lf.id];
    if (V(ls_ids)[lf.id + 1u] == c) return;
    int3 v = oct_cell(m);
    float x = F32(v.x), y = F32(v.y), z = F32(v.z);
    V(ls_cell_boxes)[2u * c] = make_float4(x, y, z, 0.0f);
    V(ls_cell_boxes)[2u * c + 1u] = make_float4(x + 1.0f, y + 1.0f, z + 1.0f, 0.0f);
    uint begin = V(leaves)[2u * lf.id];
    V(ls_cell_ranges)[2u * c] = begin;
    V(ls_cell_ranges)[2u * c + 1u] = begin + V(leaves)[2u * lf.id + 1u];
}
#endif

#if defined(KERNEL_trace_svo_ls) || defined(KERNEL_trace_esvo_ls) || defined(KERNEL_trace_bvh_ls)
// ---- Traversal: the leaf's shaft (Algorithm 3) -----------------------------------------------
// A leaf with a Line Space gives only the candidates of the shaft that holds the ray's chord
// through the leaf, looked up from the chord's entry and exit face and patch (linespace.h:
// ls_chord); an empty shaft skips the leaf with no triangle test. A leaf without one (at most
// ls_min_count candidates) keeps its plain list.
//
// t_leaf: the stretch of the ray the traversal gives this leaf (world t). The shaft holds what
// the real line meets inside the leaf, so it serves only if the chord covers that stretch, up to
// half the build's margin (LS_EPS = 1e-3 cell units; a point t past the chord's end lies at most
// t / voxel_t cell units outside). svo's walk uses the chord's own arithmetic, so it always does;
// esvo walks a slightly different line (direction components below 2^-23 are raised to it, LK10),
// and a ray in a leaf's face plane can then be given a leaf its real line only touches: that leaf
// tests its plain list (tests/test_adversarial.py found such rays).
INLINE Candidates ols_leaf_shaft(CTX_PARAM Candidates list, GridRay g, uint leaf, int3 cell, float2 t_leaf) {
    uint ls = cell_line_space(CTX_ARG leaf);
    if (ls == LS_NONE) return list;
    LsChord ch = ls_chord(V(ls_n), g.o, g.d, g.inv, cell);
    float tol = 5e-4f * g.voxel_t + 1e-6f * max(fabs(t_leaf.x), fabs(t_leaf.y));
    if (ch.t_in <= t_leaf.x + tol && ch.t_out >= t_leaf.y - tol) return shaft_list(CTX_ARG ls, ch.shaft, list);
    return list;
}
#endif
