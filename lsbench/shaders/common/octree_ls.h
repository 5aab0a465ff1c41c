// `svo-ls` / `esvo-ls`: the adaptive Line Space (thesis 4, 5.1, Algorithm 3): the octrees of
// svo.h / esvo.h with a candidate-list Line Space (linespace.h) in their leaves. This file holds
// the build steps between the octree and the Line Space build; the lookup itself is in
// oct_test_leaf (svo.h), which both traversals call for every leaf they meet. Needs geometry.h
// and svo.h.
//
// Buffers: leaves (2 uints per leaf: first, count in voxel_tris; svo.h), ls_ids (exclusive scan
// of the "has a Line Space" flags, leaves + 1 entries: leaf l has Line Space ls_ids[l] iff
// ls_ids[l + 1] > ls_ids[l], the same convention as grid_ls.h uses for voxels).
// Uniform ls_min_count: only leaves with more candidates than this get a Line Space.

#if defined(HAS_ls_flags) && defined(HAS_leaves)
// ---- Build 1: which leaves get a Line Space, one work item per leaf -----------------------
INLINE void oct_ls_flags_kernel(CTX_PARAM uint leaf) {
    V(ls_flags)[leaf] = V(leaves)[2u * leaf + 1u] > V(ls_min_count) ? 1u : 0u;
}
#endif

#if defined(HAS_ls_cell_boxes) && defined(HAS_leaves) && defined(HAS_oct_ranks)
// ---- Build 2: leaf -> Line Space cell (voxel box in grid space + candidate range) ---------
// One work item per word of the leaf level of the bit pyramid (svo.h: oct_leaf_word): the Morton
// code of a set bit is the leaf's voxel, its rank the leaf index, as in oct_leaves_kernel.
INLINE void oct_ls_cells_kernel(CTX_PARAM uint gid) {
    LeafWord lw = oct_leaf_word(CTX_ARG gid);
    uint word = lw.bits;
    if (word == 0u) return;
    uint leaf = lw.first_leaf;
    for (uint b = 0u; b < 32u; ++b) {
        if (((word >> b) & 1u) == 0u) continue;
        uint c = V(ls_ids)[leaf];
        if (V(ls_ids)[leaf + 1u] > c) {
            uint m = 32u * gid + b;
            int3 v = oct_cell(m);
            float x = F32(v.x), y = F32(v.y), z = F32(v.z);
            V(ls_cell_boxes)[2u * c] = make_float4(x, y, z, 0.0f);
            V(ls_cell_boxes)[2u * c + 1u] = make_float4(x + 1.0f, y + 1.0f, z + 1.0f, 0.0f);
            uint begin = V(leaves)[2u * leaf];
            V(ls_cell_ranges)[2u * c] = begin;
            V(ls_cell_ranges)[2u * c + 1u] = begin + V(leaves)[2u * leaf + 1u];
        }
        leaf += 1u;
    }
}
#endif
