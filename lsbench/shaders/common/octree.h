// Sparse voxel octrees over the voxel lists of grid.h: the build both octrees share (Delgado Kraemer 2019,
// 3.3.2, 5.2.1) and the leaf handling both traversals share. svo.h (node pool, Algorithm 1) and
// esvo.h (Laine & Karras descriptors, 5.2) each write their nodes and walk them; octree_ls.h adds
// the Line Space of a leaf (svo-ls, esvo-ls). Needs geometry.h; the leaf handling also scene.h and
// trace.h, and for LEAF_LINE_SPACE kernels linespace.h and octree_ls.h after this file.
//
// The octree covers the bounding cube, resolution R = 2^L (L = OCT_DEPTH levels below the
// root), anchored at grid_origin; the voxel lists (grid.h) cover only the scene's box in the
// cube's voxels, grid_res (<= R per axis): a leaf-level cell outside it is empty. Level l has 8^l cells; cell c of level l is the Morton code of its coordinates
// (bit 3i = x, 3i+1 = y, 3i+2 = z), so its 8 children are cells 8c..8c+7 of level l+1 and
// the child slot is x + 2y + 4z, as in Algorithm 1 line 12.
//
// Build (all on the device, see backends/structures/svo.py):
//   oct_bits   one bit per cell and level (a bit pyramid, levels one after another, each level
//              starting on a word boundary: level_words[l] is its first word). Leaf level:
//              "voxel non-empty"; level l: "some child flagged" (the thesis' flagging step).
//   oct_ranks  exclusive prefix sum of the words' popcounts. The rank of a flagged bit in the
//              whole pyramid is its node id: levels 0..L-1 give the internal nodes in level
//              order (root = 0), level L gives leaf index + oct_ranks[level_words[L]].
//              Ranks are what Listing 2 computes serially (accumOffset), in parallel.
//   nodes      the internal nodes in the layout of svo.h (svo_nodes) or esvo.h (esvo_nodes).
//   leaves     2 uints per leaf: (first, count) of its candidates in voxel_tris (the thesis'
//              candidate helper buffer), so the dense voxel_offsets can be dropped.

#ifndef OCT_DEPTH
#define OCT_DEPTH 10
#endif

// The walks' stacks (one entry per level, svo.h and esvo.h): OCT_STACK_SET(a, k, v) writes entry k,
// OCT_STACK_GET(dst, a, k) reads it. Where work items run in SIMD lanes (svo.py `walk`: llvmpipe,
// GPUs) OCT_SELECT_STACK makes each access a loop over the OCT_DEPTH entries that the compiler
// unrolls into one compare and select per entry: llvmpipe writes an array indexed per lane lane by
// lane and reads it with a gather (docs/profiles.md, section 10); the selects took the octree walks
// to 0.84-0.97 of their device time (section 18). PoCL, whose stack is plain memory in cache,
// indexes it (the selects measured 1.03-1.06 there).
#ifdef OCT_SELECT_STACK
#define OCT_STACK_SET(a_, k_, v_) for (int i_ = 0; i_ < OCT_DEPTH; ++i_) { if (i_ == (k_)) a_[i_] = (v_); }
#define OCT_STACK_GET(dst_, a_, k_) for (int i_ = 0; i_ < OCT_DEPTH; ++i_) { if (i_ == (k_)) dst_ = a_[i_]; }
#else
#define OCT_STACK_SET(a_, k_, v_) a_[k_] = (v_);
#define OCT_STACK_GET(dst_, a_, k_) dst_ = a_[k_];
#endif

// Morton code -> coordinate: every third bit (x = compact3(m), y = compact3(m >> 1), ...).
INLINE uint oct_compact3(uint x) {
    x &= 0x09249249u;
    x = (x ^ (x >> 2)) & 0x030c30c3u;
    x = (x ^ (x >> 4)) & 0x0300f00fu;
    x = (x ^ (x >> 8)) & 0xff0000ffu;
    x = (x ^ (x >> 16)) & 0x000003ffu;
    return x;
}

// Cell coordinates of Morton code m (bit 3i = x, 3i+1 = y, 3i+2 = z).
INLINE int3 oct_cell(uint m) {
    return make_int3(I32(oct_compact3(m)), I32(oct_compact3(m >> 1)), I32(oct_compact3(m >> 2)));
}

// Linear voxel index in the scene's box (x fastest, as grid.h) of the leaf-level cell with Morton
// code m; OCT_OUTSIDE for a cell of the cube outside the box.
#define OCT_OUTSIDE 0xffffffffu
INLINE uint oct_voxel(CTX_PARAM uint m) {
    int3 c = oct_cell(m);
    int3 r = V(grid_res).xyz;
    if (c.x >= r.x || c.y >= r.y || c.z >= r.z) return OCT_OUTSIDE;
    return U32(c.x) + U32(r.x) * (U32(c.y) + U32(r.y) * U32(c.z));
}

#ifdef KERNEL_oct_flag_leaves
// ---- Build 1: flag the leaf level, one work item per word (32 cells, no atomics) ----------
INLINE void oct_flag_leaves_kernel(CTX_PARAM uint gid) {
    uint depth = V(oct_depth);
    uint cells = 1u << (3u * depth);
    uint bits = 0u;
    for (uint b = 0u; b < 32u; ++b) {
        uint m = 32u * gid + b;
        if (m >= cells) break;
        uint v = oct_voxel(CTX_ARG m);
        if (v != OCT_OUTSIDE && V(voxel_offsets)[v + 1u] > V(voxel_offsets)[v]) bits |= 1u << b;
    }
    V(oct_bits)[V(level_words)[depth] + gid] = bits;
}
#endif

#ifdef KERNEL_oct_flag_up
// ---- Build 2: flag level oct_level from the level below (a cell is needed if a child is) ---
INLINE void oct_flag_up_kernel(CTX_PARAM uint gid) {
    uint l = V(oct_level);
    uint cells = 1u << (3u * l);
    uint below = V(level_words)[l + 1u];
    uint bits = 0u;
    for (uint b = 0u; b < 32u; ++b) {
        uint c = 32u * gid + b;
        if (c >= cells) break;
        uint w = V(oct_bits)[below + ((8u * c) >> 5)];
        if (((w >> ((8u * c) & 31u)) & 0xffu) != 0u) bits |= 1u << b;
    }
    V(oct_bits)[V(level_words)[l] + gid] = bits;
}
#endif

#ifdef KERNEL_oct_popcount
// ---- Build 3: popcount per word (then Device.exclusive_scan, on the device) ---------------
INLINE void oct_popcount_kernel(CTX_PARAM uint gid) {
    V(oct_counts)[gid] = POPCOUNT(V(oct_bits)[gid]);
}
#endif

#ifdef KERNEL_oct_level_counts
// ---- Build 4: the rank at each level's first word = nodes above that level ----------------
INLINE void oct_level_counts_kernel(CTX_PARAM uint gid) {
    V(oct_level_counts)[gid] = V(oct_ranks)[V(level_words)[gid]];
}
#endif

#if defined(KERNEL_svo_create) || defined(KERNEL_esvo_create)
// ---- Build 5: the internal nodes, one work item per cell (pyramid bit) of levels 0..L-1 ------
// Every flagged cell becomes the node with its rank; its children are the flagged bits of the
// byte 8c..8c+7 one level down, and the rank of that byte's first bit is the first child's id,
// so the children of a node are contiguous and in slot order (the esvo layout needs exactly
// that: child k lives at first + popcount(mask below k)). svo_create_kernel (svo.h) and
// esvo_create_kernel (esvo.h) write the node in their layout.
STRUCT(OctNode) { uint flagged; uint id; uint first; uint mask; uint to_leaves; };

// Node of pyramid bit `gid`: flagged or not, its id, and its children: the first child's index
// (a leaf index when the children are leaves: to_leaves = 1) and the 8-bit valid mask.
INLINE OctNode oct_internal_node(CTX_PARAM uint gid) {
    uint depth = V(oct_depth);
    uint word = gid >> 5;
    uint b = gid & 31u;
    uint bits = V(oct_bits)[word];
    OctNode n;
    n.flagged = (bits >> b) & 1u;
    if (n.flagged == 0u) return n;  // also the padding bits of levels 0 and 1 (fewer than 32 cells)
    uint l = 0u;
    while (V(level_words)[l + 1u] <= word) l += 1u;
    n.id = V(oct_ranks)[word] + rank_in_word(bits, b);
    uint c = 32u * (word - V(level_words)[l]) + b;
    uint cw = V(level_words)[l + 1u] + ((8u * c) >> 5);
    uint shift = (8u * c) & 31u;
    uint cword = V(oct_bits)[cw];
    n.mask = (cword >> shift) & 0xffu;
    n.first = V(oct_ranks)[cw] + rank_in_word(cword, shift);
    n.to_leaves = l + 1u == depth ? 1u : 0u;
    if (n.to_leaves != 0u) n.first -= V(oct_ranks)[V(level_words)[depth]];  // index into `leaves`
    return n;
}
#endif

#if defined(KERNEL_oct_leaves) || defined(KERNEL_oct_ls_cells)
// Cell m of the leaf level (its Morton code, one work item per pyramid bit of that level):
// flagged (the voxel is non-empty) and its leaf index, the rank of its bit from the leaf level's
// start. The kernels that visit every leaf (oct_leaves_kernel, oct_ls_cells_kernel in
// octree_ls.h) start with it.
STRUCT(OctLeaf) { uint flagged; uint id; };

INLINE OctLeaf oct_leaf(CTX_PARAM uint m) {
    uint start = V(level_words)[V(oct_depth)];
    uint bits = V(oct_bits)[start + (m >> 5)];
    OctLeaf lf;
    lf.flagged = (bits >> (m & 31u)) & 1u;
    lf.id = V(oct_ranks)[start + (m >> 5)] - V(oct_ranks)[start] + rank_in_word(bits, m & 31u);
    return lf;
}
#endif

#ifdef KERNEL_oct_leaves
// ---- Build 6: link every leaf to its candidate list -----------------------------------------
INLINE void oct_leaves_kernel(CTX_PARAM uint m) {
    OctLeaf lf = oct_leaf(CTX_ARG m);
    if (lf.flagged == 0u) return;
    uint v = oct_voxel(CTX_ARG m);  // flagged: inside the box
    uint begin = V(voxel_offsets)[v];
    V(leaves)[2u * lf.id] = begin;
    V(leaves)[2u * lf.id + 1u] = V(voxel_offsets)[v + 1u] - begin;
}
#endif

#if defined(KERNEL_trace_svo) || defined(KERNEL_trace_svo_ls) || defined(KERNEL_trace_esvo) || defined(KERNEL_trace_esvo_ls)
// ---- Leaf handling shared by both traversals ---------------------------------------------
// The candidates of leaf `leaf` (voxel `cell`) are its plain list, or for svo-ls / esvo-ls
// (LEAF_LINE_SPACE) the shaft of its Line Space that holds the ray's chord through the leaf
// (octree_ls.h: ols_leaf_shaft, Algorithm 3), tested by trace.h's one candidate loop.
// t_leaf: the stretch of the ray the traversal gives this leaf (world t).
#ifdef LEAF_LINE_SPACE
INLINE Candidates ols_leaf_shaft(CTX_PARAM Candidates list, GridRay g, uint leaf, int3 cell, float2 t_leaf);  // octree_ls.h
#endif

INLINE Trace oct_test_leaf(CTX_PARAM Trace tr, GridRay g, uint leaf, int3 cell, float2 t_leaf) {
    uint2 list = LD_U2(leaves, leaf);  // (first, count): the trace binds `leaves` as uint2 (svo.py: LEAF_LISTS)
    Candidates c = plain_list(list.x, list.x + list.y);
#ifdef LEAF_LINE_SPACE
    c = ols_leaf_shaft(CTX_ARG c, g, leaf, cell, t_leaf);
#endif
    return test_candidates(CTX_ARG tr, c);
}
#endif  // leaf handling
