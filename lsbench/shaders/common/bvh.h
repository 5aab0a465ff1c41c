// `bvh` and `bvh-ls`: a BVH built on the device (a top-down binned SAH tree, Wald 2007, or a
// linear BVH: Morton codes of the triangles' centroids, a radix sort, the hierarchy of Karras 2012,
// "Maximizing parallelism in the construction of BVHs, octrees, and k-d trees"; then a bottom-up
// box fit with atomics, an SAH leaf
// collapse, treelet restructuring after Karras & Aila 2013), made 4- or 8-wide, and its stack
// traversal (the children's boxes in the parent as Aila & Laine 2009, "Understanding the efficiency
// of ray traversal on GPUs", 4 or 8 of them as Embree's BVH4 and BVH8; nearest child first).
// bvh-ls gives the large leaves a Line Space (linespace.h), looked up as the octree leaves do
// (octree_ls.h, Algorithm 3). Needs geometry.h; the kernels that read triangles (Morton codes, box fit, node
// writer, Line Space cells, traversal) also scene.h, the traversal trace.h (and for bvh-ls
// linespace.h and octree_ls.h). The host side: backends/structures/bvh.py.
//
// The finished structure is wide (builds 7-8): 4-wide, the binary tree with every odd level
// dropped, or 8-wide, two levels of three dropped. A record holds the boxes of up to 4 children
// (slots) side by side, so one float4 operation tests a plane of all four (the layout of Embree's
// BVH4 and tinybvh's BVH4_GPU); a node is BVH_NODE_RECORDS records (record r of node n is
// BVH_NODE_RECORDS * n + r), in one of three layouts (bvh.py picks one per device and structure):
// float, 128 bytes per record, one record per node (bvh-ls where work items run one after the
// other: PoCL), or float8, two per node, 256 bytes (bvh there):
//   bvh_nodes  6 float4 per record: lo.x of slots 0..3, hi.x, lo.y, hi.y, lo.z, hi.z    96 bytes
//   bvh_links  2 uint4 per record: ref of slots 0..3, then count of slots 0..3. count 0: the slot
//              is node ref; count > 0: a leaf whose triangles are voxel_tris[ref .. ref + count);
//              ref BVH_NONE: an unused slot                                             32 bytes
// quantized (BVH_QUANTIZED), 64 bytes per node (devices that run work items in SIMD lanes: llvmpipe,
// GPUs), the children's boxes in 8 bits per plane on a grid of the node's own (Mahovsky 2005;
// Ylitie, Karras & Laine 2017 quantize the same way to power-of-two steps):
//   bvh_qnodes 4 uint4 per node: (origin.x, .y, .z as float bits, the biased float exponents
//              e_x | e_y << 8 | e_z << 16 of the steps 2^(e - 127)); (lo.x, hi.x, lo.y, hi.y) of
//              slots 0..3 in the bytes of each word (slot k in byte k); (lo.z, hi.z, the slots'
//              counts in bytes, 0); the slots' refs (as bvh_links)                  64 bytes
//              A slot's plane is origin + q * step, exactly so in float32 (q * step is exact:
//              8 bits times a power of two; the sum rounds once, the same in the build and the
//              traversal), and the build picks q so that the box holds the child's exact one.
//              Leaves hold at most 255 triangles (bvh.py LEAF_SIZES).
//   voxel_tris the triangle ids in the tree's order (every leaf a contiguous range of it; trace.h
//              tests a cell's plain list from this buffer, whatever the structure)
// Node 0 is the root. A scene of at most leaf-size triangles has one node whose slot 0 is a leaf
// of all of them.

#define BVH_NONE 0xffffffffu
#define BVH_PRIM 0x80000000u  // Karras child code: a primitive (sorted position) instead of an inner node
#ifndef BVH_STACK
#define BVH_STACK 64  // the traversal's stack: the build compiles it with the tree's depth (bvh.py)
#endif
#define BVH_FLT_MAX 3.4028235e38f
// 4-slot records per node: 1 (4-wide nodes) or 2 (8-wide, the float8 layout: slots 0..3 in record
// 2 * node, 4..7 in record 2 * node + 1). A node at a depth that BVH_LEVELS divides opens its kept
// descendants of the next BVH_LEVELS - 1 levels (bvh_wide_flags_kernel, bvh_write_kernel).
#ifndef BVH_NODE_RECORDS
#define BVH_NODE_RECORDS 1
#endif
#define BVH_LEVELS (BVH_NODE_RECORDS + 1)

#ifdef LANG_GLSL
#define BVH_CLZ(x) (31 - findMSB(x))
#else
#define BVH_CLZ(x) I32(clz(x))
#endif

STRUCT(Box) { float3 lo; float3 hi; };

#ifdef BVH_QUANTIZED
// The step of a quantized node's biased exponent e (1..254): 2^(e - 127).
INLINE float bvh_q_step(uint e) { return as_float(e << 23); }
#endif

INLINE Box box_union(Box a, Box b) {
    Box u;
    u.lo = min(a.lo, b.lo);
    u.hi = max(a.hi, b.hi);
    return u;
}

INLINE float box_area(Box b) {
    float3 e = max(b.hi - b.lo, make_float3(0.0f, 0.0f, 0.0f));
    return 2.0f * (e.x * e.y + e.y * e.z + e.z * e.x);
}

#ifdef KERNEL_bvh_morton
// ---- Build 1: a 30-bit Morton code per triangle centroid (10 bits per axis over the bounds) ----
// grid space over the scene's bounds (scene.h), divided by grid_res: [0, 1)^3.
INLINE uint bvh_spread10(uint x) {  // 10 bits -> every third bit
    x &= 0x3ffu;
    x = (x | (x << 16)) & 0x030000ffu;
    x = (x | (x << 8)) & 0x0300f00fu;
    x = (x | (x << 4)) & 0x030c30c3u;
    x = (x | (x << 2)) & 0x09249249u;
    return x;
}

INLINE void bvh_morton_kernel(CTX_PARAM uint tri) {
    Triangle t = load_grid_triangle(CTX_ARG tri);
    float3 res = make_float3(F32(V(grid_res).x), F32(V(grid_res).y), F32(V(grid_res).z));
    float3 c = (t.a + t.b + t.c) * (1.0f / 3.0f) / res * 1024.0f;
    uint x = U32(clamp(c.x, 0.0f, 1023.0f));
    uint y = U32(clamp(c.y, 0.0f, 1023.0f));
    uint z = U32(clamp(c.z, 0.0f, 1023.0f));
    V(sort_keys)[tri] = bvh_spread10(x) | (bvh_spread10(y) << 1) | (bvh_spread10(z) << 2);
    V(sort_ids)[tri] = tri;
}
#endif

#if defined(KERNEL_bvh_sort_count) || defined(KERNEL_bvh_sort_scatter)
// ---- Build 2: LSD radix sort of (code, triangle id), BVH_RADIX bits per pass -----------------
// Each work item owns a chunk of sort_chunk consecutive keys. Count: the chunk's histogram of the
// pass's digit into sort_counts[digit * chunks + chunk] (the item owns those entries: no atomics);
// Device.exclusive_scan of that digit-major array gives every (digit, chunk) its first output
// slot; scatter: the item walks its chunk in order and writes each key to its digit's next slot.
// Equal digits keep their order (stable), so the passes from the low to the high digit sort.
#define BVH_RADIX 5
#define BVH_DIGITS 32u
INLINE uint bvh_digit(CTX_PARAM uint key) { return (key >> V(sort_shift)) & (BVH_DIGITS - 1u); }
#endif

#ifdef KERNEL_bvh_sort_count
INLINE void bvh_sort_count_kernel(CTX_PARAM uint chunk) {
    uint chunks = V(sort_chunks);
    for (uint d = 0u; d < BVH_DIGITS; ++d) V(sort_counts)[d * chunks + chunk] = 0u;
    uint begin = chunk * V(sort_chunk);
    uint end = min(begin + V(sort_chunk), V(bvh_n));
    for (uint i = begin; i < end; ++i) V(sort_counts)[bvh_digit(CTX_ARG V(sort_keys)[i]) * chunks + chunk] += 1u;
}
#endif

#ifdef KERNEL_bvh_sort_scatter
INLINE void bvh_sort_scatter_kernel(CTX_PARAM uint chunk) {
    uint chunks = V(sort_chunks);
    uint begin = chunk * V(sort_chunk);
    uint end = min(begin + V(sort_chunk), V(bvh_n));
    for (uint i = begin; i < end; ++i) {
        uint key = V(sort_keys)[i];
        uint slot = bvh_digit(CTX_ARG key) * chunks + chunk;
        uint at = V(sort_counts)[slot];
        V(sort_counts)[slot] = at + 1u;
        V(sorted_keys)[at] = key;
        V(sorted_ids)[at] = V(sort_ids)[i];
    }
}
#endif

#ifdef KERNEL_bvh_emit
// ---- Build 3: the hierarchy (Karras 2012, Fig. 4), one work item per inner node i < n - 1 ----
// delta(i, j): the common prefix of the sorted codes i and j, the position breaking ties between
// equal codes (32 + common prefix of i and j), -1 outside [0, n). Node i covers [min(i, j),
// max(i, j)]; its split gamma is where the prefix of the range ends. Writes the two children
// (inner node id, or BVH_PRIM | sorted position), the range, and every node's parent
// (bvh_parents: inner nodes 0..n-2, then the primitives at n-1+k; the root's is BVH_NONE).
INLINE int bvh_delta(CTX_PARAM int i, int j) {
    int n = I32(V(bvh_n));
    if (j < 0 || j >= n) return -1;
    uint ki = V(bvh_keys)[i];
    uint kj = V(bvh_keys)[j];
    if (ki == kj) return 32 + BVH_CLZ(U32(i) ^ U32(j));
    return BVH_CLZ(ki ^ kj);
}

INLINE void bvh_emit_kernel(CTX_PARAM uint gid) {
    int i = I32(gid);
    int n = I32(V(bvh_n));
    int d = bvh_delta(CTX_ARG i, i + 1) - bvh_delta(CTX_ARG i, i - 1) > 0 ? 1 : -1;
    int dmin = bvh_delta(CTX_ARG i, i - d);
    int lmax = 2;
    while (bvh_delta(CTX_ARG i, i + lmax * d) > dmin) lmax *= 2;
    int l = 0;
    for (int t = lmax / 2; t >= 1; t /= 2)
        if (bvh_delta(CTX_ARG i, i + (l + t) * d) > dmin) l += t;
    int j = i + l * d;
    int dnode = bvh_delta(CTX_ARG i, j);
    int s = 0;
    for (int div = 2; ; div *= 2) {
        int t = (l + div - 1) / div;
        if (bvh_delta(CTX_ARG i, i + (s + t) * d) > dnode) s += t;
        if (t <= 1) break;
    }
    int gamma = i + s * d + min(d, 0);
    int first = min(i, j);
    int last = max(i, j);
    uint left = first == gamma ? (BVH_PRIM | U32(gamma)) : U32(gamma);
    uint right = last == gamma + 1 ? (BVH_PRIM | U32(gamma + 1)) : U32(gamma + 1);
    V(bvh_children)[2u * gid] = left;
    V(bvh_children)[2u * gid + 1u] = right;
    V(bvh_ranges)[2u * gid] = U32(first);
    V(bvh_ranges)[2u * gid + 1u] = U32(last);
    uint up = U32(n - 1);
    V(bvh_parents)[(left & BVH_PRIM) != 0u ? up + (left & ~BVH_PRIM) : left] = gid;
    V(bvh_parents)[(right & BVH_PRIM) != 0u ? up + (right & ~BVH_PRIM) : right] = gid;
    if (gid == 0u) V(bvh_parents)[0] = BVH_NONE;
}
#endif

#if defined(KERNEL_bvh_fit) || defined(KERNEL_bvh_write) || defined(KERNEL_bvh_restructure) || \
    defined(KERNEL_bvh_restructure_wave) || defined(KERNEL_bvh_sah_centroids) || defined(KERNEL_bvh_sah_bin) || \
    defined(KERNEL_bvh_sah_flags) || defined(KERNEL_bvh_sah_small)
// The box of triangle `tri` (world space).
INLINE Box triangle_box(CTX_PARAM uint tri) {
    Triangle t = load_triangle(CTX_ARG tri);
    Box b;
    b.lo = min(t.a, min(t.b, t.c));
    b.hi = max(t.a, max(t.b, t.c));
    return b;
}
#endif

#if defined(KERNEL_bvh_fit) || defined(KERNEL_bvh_write) || defined(KERNEL_bvh_restructure) || defined(KERNEL_bvh_restructure_wave)

// The box of Karras child code `c`: a primitive's triangle box, or an inner node's fitted box.
INLINE Box bvh_child_box(CTX_PARAM uint c) {
    if ((c & BVH_PRIM) != 0u) return triangle_box(CTX_ARG V(voxel_tris)[c & ~BVH_PRIM]);
    Box b;
    b.lo = V(bvh_fit_boxes)[2u * c].xyz;
    b.hi = V(bvh_fit_boxes)[2u * c + 1u].xyz;
    return b;
}
#endif

#if defined(KERNEL_bvh_sah_centroids) || defined(KERNEL_bvh_sah_bin) || defined(KERNEL_bvh_sah_choose) || \
    defined(KERNEL_bvh_sah_flags) || defined(KERNEL_bvh_sah_emit) || defined(KERNEL_bvh_sah_partition) || \
    defined(KERNEL_bvh_sah_small)
// ---- Build 3 (bvh's default hierarchy, bvh.py HIERARCHIES "binned"): a top-down binned SAH tree ----
// Wald 2007, "On fast construction of SAH-based bounding volume hierarchies": a node's triangles
// go into bins of equal width along each axis of their centroids' extent, and the node splits at
// the bin boundary of least SA(L) n_L + SA(R) n_R, down to single triangles (the fit's SAH collapse
// and the treelets then work on it as on the Karras tree). PoCL, 256²: Sponza's incoherent rays
// took 0.74 of the device time of the Morton tree's (8.59 -> 7.01 node visits per ray), its
// primary rays 0.91, BMW's incoherent rays 0.74 (docs/profiles.md, section 22): the Morton curve
// puts a large triangle in the cell of its centroid, and the tree's boxes then overlap more.
// Nodes of at least BVH_SAH_LARGE triangles split level by level, a work item per triangle
// position and per node (the centroids' bounds and the bins by atomics, the choice per node, the
// sides, an exclusive scan of them, then a stable partition into the other order buffer); the
// smaller ones (fewer than BVH_SAH_LARGE) are built whole by one work item each, in place
// (bvh_sah_small_kernel). Every node covers a range of voxel_tris, as a Karras node does, and is
// named as Karras names them: by the position of its split (the last position of its left child),
// except the root, which is node 0 and gives its own split's name to the node whose split is at 0.
// So the buffers the fit reads (children, ranges, parents) are the same as EMIT's, and every
// atomic here is order-free (counts, maxima): the tree is the same on every run.
#define BVH_SAH_BINS 32u        // bins per axis, nodes of at least BVH_SAH_LARGE triangles
#define BVH_SAH_SMALL_BINS 16u  // bins per axis, the nodes each work item builds whole
#define BVH_SAH_LARGE 64u       // must match bvh.py SAH_LARGE
#define BVH_SAH_STACK 8         // the smaller child is split first: at most log2(BVH_SAH_LARGE) + 2 held
#define BVH_SAH_MEDIAN 3u       // a node's axis where no bin boundary separates its centroids: split at half
#define BVH_SAH_BIN_WORDS 7u    // a bin: its count, then its triangles' box (lo complemented, bvh_ordered)

// floats as uints in the same order, for the atomic maxima (atomics on floats are core in neither
// language); a minimum is kept as the maximum of the complement, so every word starts at 0.
INLINE uint bvh_ordered(float f) {
    uint b = as_uint(f);
    return (b & 0x80000000u) != 0u ? ~b : (b | 0x80000000u);
}
INLINE float bvh_unordered(uint k) { return as_float((k & 0x80000000u) != 0u ? (k & 0x7fffffffu) : ~k); }
// An atomic maximum only where a plain read shows it could raise the word (the words only grow, so
// a stale read errs towards the atomic): once a node's bounds settle, most triangles leave its
// cache lines unwritten (Sponza's top nodes: every triangle's 21 atomics on the same 96 bins).
#define BVH_RAISE(lvalue, v) if ((lvalue) < (v)) ATOMIC_MAX(lvalue, v);
// A box kept in words w .. w + 5 of buffer BUF (lo complemented, then hi) grown to hold lo..hi;
// bvh_ordered_box reads it back.
#define BVH_RAISE_BOX(BUF, w, lo, hi)                                                              \
    BVH_RAISE(V(BUF)[(w)], ~bvh_ordered((lo).x)) BVH_RAISE(V(BUF)[(w) + 1u], ~bvh_ordered((lo).y))   \
    BVH_RAISE(V(BUF)[(w) + 2u], ~bvh_ordered((lo).z)) BVH_RAISE(V(BUF)[(w) + 3u], bvh_ordered((hi).x)) \
    BVH_RAISE(V(BUF)[(w) + 4u], bvh_ordered((hi).y)) BVH_RAISE(V(BUF)[(w) + 5u], bvh_ordered((hi).z))
INLINE Box bvh_ordered_box(uint lx, uint ly, uint lz, uint hx, uint hy, uint hz) {
    Box b;
    b.lo = make_float3(bvh_unordered(~lx), bvh_unordered(~ly), bvh_unordered(~lz));
    b.hi = make_float3(bvh_unordered(hx), bvh_unordered(hy), bvh_unordered(hz));
    return b;
}
#define BVH_LOAD_BOX(BUF, w) bvh_ordered_box(V(BUF)[(w)], V(BUF)[(w) + 1u], V(BUF)[(w) + 2u], \
                                             V(BUF)[(w) + 3u], V(BUF)[(w) + 4u], V(BUF)[(w) + 5u])

INLINE float bvh_axis(float3 v, uint a) { return a == 0u ? v.x : (a == 1u ? v.y : v.z); }

INLINE Box bvh_empty_box() {
    Box b;
    b.lo = make_float3(BVH_FLT_MAX, BVH_FLT_MAX, BVH_FLT_MAX);
    b.hi = make_float3(-BVH_FLT_MAX, -BVH_FLT_MAX, -BVH_FLT_MAX);
    return b;
}

// A triangle's centroid: its box's centre.
INLINE float3 bvh_sah_centroid(Box b) { return (b.lo + b.hi) * 0.5f; }

// Bins per unit along an axis whose centroids span [lo, hi]: 0 where they do not (all in bin 0).
INLINE float bvh_sah_scale(float lo, float hi, uint bins) {
    float e = hi - lo;
    return e > 0.0f && F32(bins) / e < BVH_FLT_MAX ? F32(bins) / e : 0.0f;
}

// The bin of centroid coordinate x. The choice and the partition call this one function on the same
// floats, so a triangle's side is the side its bin was counted on.
INLINE uint bvh_sah_bin(float x, float lo, float scale, uint bins) {
    return U32(min(max((x - lo) * scale, 0.0f), F32(bins - 1u)));
}

// The least-cost split of a node's bins (BVH_SAH_BIN_WORDS words each) of one axis: a sweep from
// the right keeps the area and count right of each boundary, one from the left prices them.
#define BVH_SAH_SWEEP(BINS, COUNT, BOX, AXIS)                                                        \
    {                                                                                              \
        float right_area[BINS];                                                                    \
        uint right_count[BINS];                                                                    \
        Box acc = bvh_empty_box();                                                                 \
        uint n = 0u;                                                                               \
        for (uint i = BINS - 1u; i >= 1u; --i) {                                                   \
            if (COUNT(i) != 0u) { acc = box_union(acc, BOX(i)); n += COUNT(i); }                   \
            right_area[i] = box_area(acc);                                                         \
            right_count[i] = n;                                                                    \
        }                                                                                          \
        acc = bvh_empty_box();                                                                     \
        n = 0u;                                                                                    \
        for (uint i = 0u; i + 1u < BINS; ++i) {                                                    \
            if (COUNT(i) != 0u) { acc = box_union(acc, BOX(i)); n += COUNT(i); }                   \
            if (n != 0u && right_count[i + 1u] != 0u) {                                            \
                float cost = box_area(acc) * F32(n) + right_area[i + 1u] * F32(right_count[i + 1u]); \
                if (cost < best) { best = cost; best_axis = AXIS; best_bin = i; }                  \
            }                                                                                      \
        }                                                                                          \
    }
#endif

#if defined(KERNEL_bvh_sah_centroids) || defined(KERNEL_bvh_sah_bin) || defined(KERNEL_bvh_sah_flags) || \
    defined(KERNEL_bvh_sah_small)
// The box of the triangle at position p of the current order.
INLINE Box bvh_sah_tri_box(CTX_PARAM uint p) { return triangle_box(CTX_ARG V(voxel_tris)[p]); }
#endif

#if defined(KERNEL_bvh_sah_emit) || defined(KERNEL_bvh_sah_small)
// Karras' name of the node at positions node.x..node.y (parent node.z, its child node.w) that
// splits after position `split`; writes its range, its parent and its parent's link to it.
INLINE uint bvh_sah_node(CTX_PARAM uint4 node, uint split) {
    uint name = split;
    if (node.z == BVH_NONE) {
        V(sah_root)[0] = split;  // read by the node whose split is at 0, in a later dispatch or later here
        name = 0u;
    } else {
        if (split == 0u) name = V(sah_root)[0];
        V(bvh_children)[2u * node.z + node.w] = name;
    }
    V(bvh_parents)[name] = node.z;
    V(bvh_ranges)[2u * name] = node.x;
    V(bvh_ranges)[2u * name + 1u] = node.y;
    return name;
}

// A child of one triangle: the leaf at its position.
INLINE void bvh_sah_leaf(CTX_PARAM uint position, uint parent, uint side) {
    V(bvh_children)[2u * parent + side] = BVH_PRIM | position;
    V(bvh_parents)[V(bvh_n) - 1u + position] = parent;
}
#endif

#if defined(KERNEL_bvh_sah_centroids) || defined(KERNEL_bvh_sah_bin)
// The slot in this batch of the node that position p belongs to, or BVH_NONE (a position of a
// node already split, or of a node of another batch: bvh.py splits a level's nodes in batches that
// fit the bins' buffer).
INLINE uint bvh_sah_batch_slot(CTX_PARAM uint p) {
    uint k = V(sah_pos_node)[p];
    return k != BVH_NONE && k >= V(sah_node_base) && k - V(sah_node_base) < V(sah_node_count)
        ? k - V(sah_node_base) : BVH_NONE;
}
#endif

#if defined(KERNEL_bvh_sah_bin) || defined(KERNEL_bvh_sah_choose)
// The centroids' bounds of the node in batch slot j (bvh_sah_centroids_kernel).
INLINE Box bvh_sah_centroid_bounds(CTX_PARAM uint j) { return BVH_LOAD_BOX(sah_cbounds, 6u * j); }
#endif

#ifdef KERNEL_bvh_sah_centroids
// Per position of a large node: its centroid into the node's bounds.
INLINE void bvh_sah_centroids_kernel(CTX_PARAM uint p) {
    uint j = bvh_sah_batch_slot(CTX_ARG p);
    if (j == BVH_NONE) return;
    float3 c = bvh_sah_centroid(bvh_sah_tri_box(CTX_ARG p));
    BVH_RAISE_BOX(sah_cbounds, 6u * j, c, c)
}
#endif

#ifdef KERNEL_bvh_sah_bin
// Per position of a large node: its triangle counted, and its box merged, in its bin on each axis.
INLINE void bvh_sah_bin_kernel(CTX_PARAM uint p) {
    uint j = bvh_sah_batch_slot(CTX_ARG p);
    if (j == BVH_NONE) return;
    Box t = bvh_sah_tri_box(CTX_ARG p);
    float3 c = bvh_sah_centroid(t);
    Box cb = bvh_sah_centroid_bounds(CTX_ARG j);
    for (uint a = 0u; a < 3u; ++a) {
        float lo = bvh_axis(cb.lo, a);
        uint i = bvh_sah_bin(bvh_axis(c, a), lo, bvh_sah_scale(lo, bvh_axis(cb.hi, a), BVH_SAH_BINS), BVH_SAH_BINS);
        uint w = ((3u * j + a) * BVH_SAH_BINS + i) * BVH_SAH_BIN_WORDS;
        ATOMIC_ADD(V(sah_bins)[w], 1u);
        BVH_RAISE_BOX(sah_bins, w + 1u, t.lo, t.hi)
    }
}
#endif

#ifdef KERNEL_bvh_sah_choose
// Per large node of the batch: the split of least cost over the three axes' bins (ties: the lower
// axis, then the lower bin), kept with the axis' bin origin and scale for the sides' kernel.
INLINE void bvh_sah_choose_kernel(CTX_PARAM uint j) {
    Box cb = bvh_sah_centroid_bounds(CTX_ARG j);
    float best = INF_F;
    uint best_axis = BVH_SAH_MEDIAN;
    uint best_bin = 0u;
    for (uint a = 0u; a < 3u; ++a) {
        uint base = 3u * j + a;
#define BVH_SAH_BIN_COUNT(i) V(sah_bins)[(base * BVH_SAH_BINS + (i)) * BVH_SAH_BIN_WORDS]
#define BVH_SAH_BIN_BOX(i) BVH_LOAD_BOX(sah_bins, (base * BVH_SAH_BINS + (i)) * BVH_SAH_BIN_WORDS + 1u)
        BVH_SAH_SWEEP(BVH_SAH_BINS, BVH_SAH_BIN_COUNT, BVH_SAH_BIN_BOX, a)
#undef BVH_SAH_BIN_COUNT
#undef BVH_SAH_BIN_BOX
    }
    float lo = best_axis == BVH_SAH_MEDIAN ? 0.0f : bvh_axis(cb.lo, best_axis);
    float scale = best_axis == BVH_SAH_MEDIAN ? 0.0f
        : bvh_sah_scale(lo, bvh_axis(cb.hi, best_axis), BVH_SAH_BINS);
    V(sah_split)[2u * (V(sah_node_base) + j)] = make_uint4(best_axis, best_bin, as_uint(lo), as_uint(scale));
}
#endif

#ifdef KERNEL_bvh_sah_flags
// Per position (and one past the last, 0): 1 where the triangle goes to its large node's left child.
INLINE void bvh_sah_flags_kernel(CTX_PARAM uint p) {
    uint left = 0u;
    uint k = p < V(bvh_n) ? V(sah_pos_node)[p] : BVH_NONE;
    if (k != BVH_NONE) {
        uint4 s = V(sah_split)[2u * k];
        if (s.x != BVH_SAH_MEDIAN) {
            float x = bvh_axis(bvh_sah_centroid(bvh_sah_tri_box(CTX_ARG p)), s.x);
            left = bvh_sah_bin(x, as_float(s.z), as_float(s.w), BVH_SAH_BINS) <= s.y ? 1u : 0u;
        }
    }
    V(sah_scan)[p] = left;
}
#endif

#ifdef KERNEL_bvh_sah_emit
// Per large node, after the exclusive scan of the sides: its left count, its name and links, and
// its children queued: a leaf linked, a large child to the next level's list, a smaller one to the
// list bvh_sah_small_kernel builds. A split that leaves a side empty (only where no boundary
// separates the centroids) splits at half instead, the positions as they are.
INLINE void bvh_sah_emit_kernel(CTX_PARAM uint k) {
    uint4 node = V(sah_active)[k];
    uint4 s = V(sah_split)[2u * k];
    uint count = node.y - node.x + 1u;
    uint left = V(sah_scan)[node.y + 1u] - V(sah_scan)[node.x];
    if (s.x == BVH_SAH_MEDIAN || left == 0u || left == count) {
        s.x = BVH_SAH_MEDIAN;
        left = count / 2u;
        V(sah_split)[2u * k] = s;
    }
    uint split = node.x + left - 1u;
    uint name = bvh_sah_node(CTX_ARG node, split);
    uint next[2];
    for (uint side = 0u; side < 2u; ++side) {
        uint first = side == 0u ? node.x : split + 1u;
        uint last = side == 0u ? split : node.y;
        next[side] = BVH_NONE;
        if (first == last) {
            bvh_sah_leaf(CTX_ARG first, name, side);
        } else if (last - first + 1u >= BVH_SAH_LARGE) {
            next[side] = ATOMIC_ADD(V(sah_counts)[0], 1u);
            V(sah_next)[next[side]] = make_uint4(first, last, name, side);
        } else {
            V(sah_small)[ATOMIC_ADD(V(sah_counts)[1], 1u)] = make_uint4(first, last, name, side);
        }
    }
    V(sah_split)[2u * k + 1u] = make_uint4(next[0], next[1], left, name);
}
#endif

#ifdef KERNEL_bvh_sah_partition
// Per position: the triangle moved to its place in the other order buffer (left side first, each
// side in its old order), with the index of its node in the next level's list (BVH_NONE: none).
INLINE void bvh_sah_partition_kernel(CTX_PARAM uint p) {
    uint k = V(sah_pos_node)[p];
    uint tri = V(voxel_tris)[p];
    uint dest = p;
    uint node_next = BVH_NONE;
    if (k != BVH_NONE) {
        uint first = V(sah_active)[k].x;
        uint4 s = V(sah_split)[2u * k];
        uint4 e = V(sah_split)[2u * k + 1u];  // left child's next index, right's, left count
        if (s.x != BVH_SAH_MEDIAN) {
            uint before = V(sah_scan)[p] - V(sah_scan)[first];  // left ones before p in its node
            dest = V(sah_scan)[p + 1u] != V(sah_scan)[p] ? first + before : first + e.z + (p - first - before);
        }
        node_next = dest < first + e.z ? e.x : e.y;
    }
    V(sah_order_out)[dest] = tri;
    V(sah_pos_node_out)[dest] = node_next;
}
#endif

#ifdef KERNEL_bvh_sah_small
// Per node of fewer than BVH_SAH_LARGE triangles: its whole subtree by one work item, in place in
// voxel_tris (a two-ended partition per split), the smaller child first so that the held ones stay
// within BVH_SAH_STACK; splits that the loop budget of llvmpipe cut count into bvh_cut.
INLINE void bvh_sah_small_kernel(CTX_PARAM uint gid) {
    uint4 held[BVH_SAH_STACK];
    uint top = 0u;
    uint4 node = V(sah_small)[gid];
    uint more = 1u;
    while (more != 0u) {
        uint count = node.y - node.x + 1u;
        Box cb = bvh_empty_box();
        for (uint p = node.x; p <= node.y; ++p) {
            float3 c = bvh_sah_centroid(bvh_sah_tri_box(CTX_ARG p));
            cb.lo = min(cb.lo, c);
            cb.hi = max(cb.hi, c);
        }
        float best = INF_F;
        uint best_axis = BVH_SAH_MEDIAN;
        uint best_bin = 0u;
        for (uint a = 0u; a < 3u; ++a) {
            float lo = bvh_axis(cb.lo, a);
            float scale = bvh_sah_scale(lo, bvh_axis(cb.hi, a), BVH_SAH_SMALL_BINS);
            if (scale == 0.0f) continue;
            uint counts[BVH_SAH_SMALL_BINS];
            Box boxes[BVH_SAH_SMALL_BINS];
            for (uint i = 0u; i < BVH_SAH_SMALL_BINS; ++i) {
                counts[i] = 0u;
                boxes[i] = bvh_empty_box();
            }
            for (uint p = node.x; p <= node.y; ++p) {
                Box t = bvh_sah_tri_box(CTX_ARG p);
                uint i = bvh_sah_bin(bvh_axis(bvh_sah_centroid(t), a), lo, scale, BVH_SAH_SMALL_BINS);
                counts[i] += 1u;
                boxes[i] = box_union(boxes[i], t);
            }
#define BVH_SAH_BIN_COUNT(i) counts[i]
#define BVH_SAH_BIN_BOX(i) boxes[i]
            BVH_SAH_SWEEP(BVH_SAH_SMALL_BINS, BVH_SAH_BIN_COUNT, BVH_SAH_BIN_BOX, a)
#undef BVH_SAH_BIN_COUNT
#undef BVH_SAH_BIN_BOX
        }
        uint left = count / 2u;
        if (best_axis != BVH_SAH_MEDIAN) {
            float lo = bvh_axis(cb.lo, best_axis);
            float scale = bvh_sah_scale(lo, bvh_axis(cb.hi, best_axis), BVH_SAH_SMALL_BINS);
            uint i = node.x;
            uint j = node.y + 1u;  // [node.x, i) go left, [j, node.y] right
            while (i < j) {
                uint tri = V(voxel_tris)[i];
                float x = bvh_axis(bvh_sah_centroid(triangle_box(CTX_ARG tri)), best_axis);
                if (bvh_sah_bin(x, lo, scale, BVH_SAH_SMALL_BINS) <= best_bin) {
                    ++i;
                } else {
                    --j;
                    V(voxel_tris)[i] = V(voxel_tris)[j];
                    V(voxel_tris)[j] = tri;
                }
            }
            if (i != node.x && i != node.y + 1u) left = i - node.x;
        }
        uint split = node.x + left - 1u;
        uint name = bvh_sah_node(CTX_ARG node, split);
        uint4 l = make_uint4(node.x, split, name, 0u);
        uint4 r = make_uint4(split + 1u, node.y, name, 1u);
        if (l.x == l.y) bvh_sah_leaf(CTX_ARG l.x, name, 0u);
        if (r.x == r.y) bvh_sah_leaf(CTX_ARG r.x, name, 1u);
        if (l.x != l.y && r.x != r.y) {  // both inner: the larger held, the smaller next
            uint left_smaller = l.y - l.x <= r.y - r.x ? 1u : 0u;
            if (top < U32(BVH_SAH_STACK)) held[top] = left_smaller != 0u ? r : l;
            else ATOMIC_ADD(V(bvh_cut)[0], 1u);  // cannot happen (the held halve): fail the build if it did
            top += 1u;
            node = left_smaller != 0u ? l : r;
        } else if (l.x != l.y) {
            node = l;
        } else if (r.x != r.y) {
            node = r;
        } else if (top > 0u) {
            top -= 1u;
            node = held[min(top, U32(BVH_SAH_STACK) - 1u)];
        } else {
            more = 0u;
        }
    }
    if (loops_intact(V(loop_probe)) == 0) ATOMIC_ADD(V(bvh_cut)[0], 1u);  // geometry.h: the driver cut loops
}
#endif

#if defined(KERNEL_bvh_fit) || defined(KERNEL_bvh_restructure) || defined(KERNEL_bvh_restructure_wave)
#define BVH_COST_NODE 1.2f
#define BVH_COST_TRI 1.0f

#ifdef LANG_GLSL
#define BVH_FENCE() memoryBarrierBuffer()
#else
#define BVH_FENCE() mem_fence(CLK_GLOBAL_MEM_FENCE)
#endif

// Cost of child c as decided (plain = 0) or in the plain LBVH (plain = 1).
INLINE float bvh_child_cost(CTX_PARAM uint c, uint plain) {
    if ((c & BVH_PRIM) != 0u) return BVH_COST_TRI * box_area(bvh_child_box(CTX_ARG c));
    return V(bvh_costs)[2u * c + plain];
}

// Triangles below child code c.
INLINE uint bvh_child_count(CTX_PARAM uint c) {
    return (c & BVH_PRIM) != 0u ? 1u : V(bvh_counts)[c];
}

// Where the parent of child code c is kept (inner nodes first, then the primitives).
INLINE uint bvh_parent_slot(CTX_PARAM uint c) {
    return (c & BVH_PRIM) != 0u ? V(bvh_n) - 1u + (c & ~BVH_PRIM) : c;
}
#endif

#ifdef KERNEL_bvh_fit
// ---- Build 4: bottom-up box fit (Karras 2012, 4), one work item per primitive ----------------
// Each item climbs from its primitive's parent; at every node the first of the two children's
// items to arrive (atomic counter 0 -> 1) stops, the second one finds both children finished and
// fits the node. The fence orders a node's box (and cost) before the counter its parent reads.
// The same pass decides the leaves, the quality pass of this build (bvh_sah = 1): a node of at most
// bvh_leaf_size triangles becomes a leaf where the surface-area heuristic (MacDonald & Booth 1990;
// the final step of Karras & Aila 2013) rates testing them all as cheaper than descending,
// SA(N) * C_i * n <= SA(N) * C_t + cost(L) + cost(R) (costs scaled by the area: cost(N) =
// SA(N) * expected cost below N; C_t = 1.2, C_i = 1 as Karras & Aila). bvh_sah = 0: every node of at
// most bvh_leaf_size triangles is a leaf (the plain LBVH). bvh_costs holds 2 floats per inner node,
// the cost of the tree below it as decided and that of the plain LBVH, so the root's two, divided by
// its area, are the SAH costs of the tree and of the tree without the quality pass (stats).
INLINE void bvh_fit_kernel(CTX_PARAM uint prim) {
    uint node = V(bvh_parents)[V(bvh_n) - 1u + prim];
    while (node != BVH_NONE) {
        BVH_FENCE();
        if (ATOMIC_ADD(V(bvh_arrivals)[node], 1u) == 0u) return;  // the sibling's item fits it
        BVH_FENCE();
        uint l = V(bvh_children)[2u * node];
        uint r = V(bvh_children)[2u * node + 1u];
        Box b = box_union(bvh_child_box(CTX_ARG l), bvh_child_box(CTX_ARG r));
        V(bvh_fit_boxes)[2u * node] = make_float4(b.lo.x, b.lo.y, b.lo.z, 0.0f);
        V(bvh_fit_boxes)[2u * node + 1u] = make_float4(b.hi.x, b.hi.y, b.hi.z, 0.0f);
        uint count = V(bvh_ranges)[2u * node + 1u] - V(bvh_ranges)[2u * node] + 1u;
        float area = box_area(b);
        float split = BVH_COST_NODE * area + bvh_child_cost(CTX_ARG l, 0u) + bvh_child_cost(CTX_ARG r, 0u);
        float plain_split = BVH_COST_NODE * area + bvh_child_cost(CTX_ARG l, 1u) + bvh_child_cost(CTX_ARG r, 1u);
        float leaf = BVH_COST_TRI * F32(count) * area;
        uint small = count <= V(bvh_leaf_size) ? 1u : 0u;
        uint collapse = small != 0u && (V(bvh_sah) == 0u || leaf <= split) ? 1u : 0u;
        V(bvh_collapse)[node] = collapse;
        V(bvh_counts)[node] = count;
        V(bvh_costs)[2u * node] = collapse != 0u ? leaf : split;
        V(bvh_costs)[2u * node + 1u] = small != 0u ? leaf : plain_split;
        node = V(bvh_parents)[node];
    }
}
#endif

#if defined(KERNEL_bvh_restructure_wave) || defined(KERNEL_bvh_wave_start)
// A wave's node counts its arrival at node_; the second to arrive queues node_ for the next wave
// (bvh_restructure_wave_kernel below).
#define BVH_WAVE_QUEUE(node_) if (ATOMIC_ADD(V(bvh_arrivals)[node_], 1u) == 1u) \
        V(bvh_wave_out)[ATOMIC_ADD(V(bvh_wave_count)[0], 1u)] = node_;
#endif

#ifdef KERNEL_bvh_wave_start
// The first wave of the restructuring in waves: the nodes both of whose children are primitives.
INLINE void bvh_wave_start_kernel(CTX_PARAM uint prim) {
    uint node = V(bvh_parents)[V(bvh_n) - 1u + prim];
    if (node != BVH_NONE) BVH_WAVE_QUEUE(node)  // BVH_NONE: a tree of one primitive
}
#endif

#if defined(KERNEL_bvh_restructure) || defined(KERNEL_bvh_restructure_wave)
// ---- Build 5: treelet restructuring (Karras & Aila 2013, "Fast parallel construction of high-
// quality bounding volume hierarchies"), one work item per primitive climbing as in the fit -----
// At every node N of more than bvh_leaf_size triangles, once both its subtrees are done (an
// arrival counter, as the fit): grow a treelet of up to BVH_TREELET leaves from N's children,
// always opening the leaf of largest area that is itself such a node; find the topology of those
// leaves with the least SAH cost by dynamic programming over their subsets (each subset: the best
// of its 2-part splits); if it is cheaper than the treelet as it is, rebuild the treelet in place
// with its own inner nodes (boxes, costs, counts, parents). Nodes of at most bvh_leaf_size
// triangles are never opened nor made, so every leaf the compaction makes is still a contiguous
// range of voxel_tris. 5 leaves (Karras & Aila use 7): 3^5 = 243 split tests per node keeps a
// climb to the root inside llvmpipe's loop budget; loops cut short count into bvh_cut.
#define BVH_TREELET 5
#define BVH_SUBSETS 32

INLINE Box bvh_subset_box(Box b0, Box b1, Box b2, Box b3, Box b4, uint s) {
    Box u;
    u.lo = make_float3(BVH_FLT_MAX, BVH_FLT_MAX, BVH_FLT_MAX);
    u.hi = make_float3(-BVH_FLT_MAX, -BVH_FLT_MAX, -BVH_FLT_MAX);
    if ((s & 1u) != 0u) u = box_union(u, b0);
    if ((s & 2u) != 0u) u = box_union(u, b1);
    if ((s & 4u) != 0u) u = box_union(u, b2);
    if ((s & 8u) != 0u) u = box_union(u, b3);
    if ((s & 16u) != 0u) u = box_union(u, b4);
    return u;
}

INLINE void bvh_restructure(CTX_PARAM uint root) {
    uint leaf_size = V(bvh_leaf_size);
    uint leaves[BVH_TREELET];
    uint inner[BVH_TREELET];
    leaves[0] = V(bvh_children)[2u * root];
    leaves[1] = V(bvh_children)[2u * root + 1u];
    inner[0] = root;
    uint m = 2u;
    while (m < U32(BVH_TREELET)) {
        int best = -1;
        float best_area = -1.0f;
        for (uint k = 0u; k < m; ++k) {
            uint c = leaves[k];
            if ((c & BVH_PRIM) != 0u || V(bvh_counts)[c] <= leaf_size) continue;
            float a = box_area(bvh_child_box(CTX_ARG c));
            if (a > best_area) { best_area = a; best = I32(k); }
        }
        if (best < 0) break;
        uint opened = leaves[best];
        inner[m - 1u] = opened;
        leaves[best] = V(bvh_children)[2u * opened];
        leaves[m] = V(bvh_children)[2u * opened + 1u];
        m += 1u;
    }
    if (m < 3u) return;  // two leaves have one topology
    Box b0 = bvh_child_box(CTX_ARG leaves[0]), b1 = bvh_child_box(CTX_ARG leaves[1]), b2 = bvh_child_box(CTX_ARG leaves[2]);
    Box b3 = m > 3u ? bvh_child_box(CTX_ARG leaves[3]) : b0;
    Box b4 = m > 4u ? bvh_child_box(CTX_ARG leaves[4]) : b0;
    float cost[BVH_SUBSETS];
    uint split[BVH_SUBSETS];
    uint full = (1u << m) - 1u;
    for (uint s = 1u; s <= full; ++s) {
        split[s] = 0u;
        if ((s & (s - 1u)) == 0u) {  // one leaf: its own cost
            uint k = U32(BVH_CLZ(1u)) - U32(BVH_CLZ(s));
            cost[s] = bvh_child_cost(CTX_ARG leaves[k], 0u);
            continue;
        }
        float best = BVH_FLT_MAX;
        for (uint p = (s - 1u) & s; p != 0u; p = (p - 1u) & s) {
            float c = cost[p] + cost[s ^ p];
            if (c < best) { best = c; split[s] = p; }
        }
        cost[s] = BVH_COST_NODE * box_area(bvh_subset_box(b0, b1, b2, b3, b4, s)) + best;
    }
    if (!(cost[full] < V(bvh_costs)[2u * root] * 0.9999f)) return;  // no better topology
    // Rebuild top-down from the root, handing out the treelet's inner nodes in order.
    uint todo_set[BVH_TREELET];
    uint todo_node[BVH_TREELET];
    int top = 0;
    todo_set[0] = full;
    todo_node[0] = root;
    uint next_inner = 1u;
    while (top >= 0) {
        uint s = todo_set[top];
        uint id = todo_node[top];
        top -= 1;
        uint parts[2];
        parts[0] = split[s];
        parts[1] = s ^ split[s];
        uint count = 0u;
        for (uint h = 0u; h < 2u; ++h) {
            uint q = parts[h];
            uint code;
            if ((q & (q - 1u)) == 0u) {
                code = leaves[U32(BVH_CLZ(1u)) - U32(BVH_CLZ(q))];
            } else {
                code = inner[next_inner];
                next_inner += 1u;
                top += 1;
                todo_set[top] = q;
                todo_node[top] = code;
            }
            V(bvh_children)[2u * id + h] = code;
            V(bvh_parents)[bvh_parent_slot(CTX_ARG code)] = id;
        }
        for (uint k = 0u; k < m; ++k)
            if (((s >> k) & 1u) != 0u) count += bvh_child_count(CTX_ARG leaves[k]);
        Box b = bvh_subset_box(b0, b1, b2, b3, b4, s);
        V(bvh_fit_boxes)[2u * id] = make_float4(b.lo.x, b.lo.y, b.lo.z, 0.0f);
        V(bvh_fit_boxes)[2u * id + 1u] = make_float4(b.hi.x, b.hi.y, b.hi.z, 0.0f);
        V(bvh_costs)[2u * id] = cost[s];
        V(bvh_counts)[id] = count;
    }
}

#ifdef KERNEL_bvh_restructure
INLINE void bvh_restructure_kernel(CTX_PARAM uint prim) {
    uint node = V(bvh_parents)[V(bvh_n) - 1u + prim];
    while (node != BVH_NONE) {
        BVH_FENCE();
        if (ATOMIC_ADD(V(bvh_arrivals)[node], 1u) == 0u) return;
        BVH_FENCE();
        if (V(bvh_counts)[node] > V(bvh_leaf_size)) bvh_restructure(CTX_ARG node);
        node = V(bvh_parents)[node];
    }
    if (loops_intact(V(loop_probe)) == 0) ATOMIC_ADD(V(bvh_cut)[0], 1u);  // geometry.h: the driver cut loops
}
#else
// The same climbs in waves, where the lanes run in SIMD (llvmpipe, GPUs; bvh.py): a wave is the
// nodes whose two subtrees are done, a work item each, which restructures its node and counts
// its arrival at the parent; the second to arrive queues the parent for the next wave (the first
// wave: the nodes both of whose children are primitives, bvh_wave_start_kernel). With one climb
// per primitive, half the lanes of a SIMD group stop at every level while the group runs, masked,
// as long as its longest climb, and llvmpipe runs the restructuring's loops once even where no
// lane restructures (docs/linespace-build.md): BMW bvh glsl, bvh_restructure took 7.1 s of the
// build's 7.6. The waves keep every lane on a node to restructure; the dispatch between two waves
// orders their writes (no fences). The same trees, bit for bit.
INLINE void bvh_restructure_wave_kernel(CTX_PARAM uint gid) {
    uint node = V(bvh_wave_in)[gid];
    if (V(bvh_counts)[node] > V(bvh_leaf_size)) bvh_restructure(CTX_ARG node);
    uint parent = V(bvh_parents)[node];
    if (parent != BVH_NONE) BVH_WAVE_QUEUE(parent)
    if (loops_intact(V(loop_probe)) == 0) ATOMIC_ADD(V(bvh_cut)[0], 1u);  // geometry.h: the driver cut loops
}
#endif
#endif

#ifdef KERNEL_bvh_keep
// ---- Build 6: which inner nodes stay nodes: not collapsed, no collapsed ancestor -------------
// Only nodes of at most bvh_leaf_size triangles collapse, so the climb ends at the first ancestor
// with more (counts grow towards the root).
INLINE void bvh_keep_kernel(CTX_PARAM uint node) {
    uint keep = V(bvh_collapse)[node] != 0u ? 0u : 1u;
    uint p = V(bvh_parents)[node];
    while (keep != 0u && p != BVH_NONE && V(bvh_counts)[p] <= V(bvh_leaf_size)) {
        if (V(bvh_collapse)[p] != 0u) keep = 0u;
        p = V(bvh_parents)[p];
    }
    V(bvh_keep)[node] = keep;
}
#endif

#ifdef KERNEL_bvh_wide_flags
// ---- Build 7: which kept nodes head a wide node: those at a depth that BVH_LEVELS divides ----
// The binary tree becomes 4-wide by dropping every odd level: a node at an even depth takes its
// children, and where a child is a kept inner node (odd depth) that child's two children instead
// (up to 4 slots); 8-wide (BVH_NODE_RECORDS 2) by dropping two levels of three (up to 8 slots).
// Depth: the kept ancestors (every ancestor of a kept node is kept); the deepest is ~bvh_depth[0]
// (the atomics have a min, not a max), for the traversal's stack size.
INLINE void bvh_wide_flags_kernel(CTX_PARAM uint node) {
    uint flag = 0u;
    if (V(bvh_keep)[node] != 0u) {
        uint depth = 0u;
        for (uint p = V(bvh_parents)[node]; p != BVH_NONE; p = V(bvh_parents)[p]) depth += 1u;
        ATOMIC_MIN(V(bvh_depth)[0], ~depth);
        flag = (depth % U32(BVH_LEVELS)) == 0u ? 1u : 0u;
    }
    V(bvh_wide_flags)[node] = flag;
}
#endif

#ifdef KERNEL_bvh_write
// ---- Build 8: the final wide nodes, one work item per inner node -----------------------------
// bvh_ids: exclusive scan of bvh_wide_flags (node i heads wide node bvh_ids[i] iff
// bvh_ids[i + 1] > bvh_ids[i]; the root stays 0). A slot holding a wide node links it by its id;
// any other child (a primitive, a collapsed node) becomes a leaf of its range in voxel_tris;
// unused slots hold ref BVH_NONE (and a zero box, never tested).
STRUCT(WideChild) { Box b; uint ref; uint count; };

INLINE WideChild bvh_leaf_or_node(CTX_PARAM uint c) {  // a slot's child: Karras code c, not expanded
    WideChild w;
    w.b = bvh_child_box(CTX_ARG c);
    if ((c & BVH_PRIM) != 0u) {
        w.ref = c & ~BVH_PRIM;
        w.count = 1u;
    } else if (V(bvh_keep)[c] != 0u) {
        w.ref = V(bvh_ids)[c];  // a kept node at a depth BVH_LEVELS divides: a wide node
        w.count = 0u;
    } else {
        w.ref = V(bvh_ranges)[2u * c];
        w.count = V(bvh_ranges)[2u * c + 1u] - w.ref + 1u;
    }
    return w;
}

#ifdef BVH_QUANTIZED
// The biased exponent of the smallest power-of-two step with org + 255 * step >= top in float32.
// ext / 255 has biased exponent b, so 2^(b + 1 - 127) exceeds it; the loop settles the float
// rounding of org + 255 * step (a step of 2^-126 at least: a flat axis quantizes to q = 0).
INLINE uint bvh_q_exponent(float org, float top) {
    float v = (top - org) * (1.0f / 255.0f);
    uint e = clamp((as_uint(v) >> 23) + 1u, 1u, 254u);
    while (e < 254u && org + 255.0f * bvh_q_step(e) < top) e += 1u;
    return e;
}

// The largest q in 0..255 with org + q * step <= lo, and the smallest with org + q * step >= hi,
// in the traversal's own float32 arithmetic (bvh_node_planes): the slot's box holds the child's.
INLINE uint bvh_q_below(float org, float step, float lo) {
    float q = clamp(floor((lo - org) / step), 0.0f, 255.0f);
    while (q > 0.0f && org + q * step > lo) q -= 1.0f;
    while (q < 255.0f && org + (q + 1.0f) * step <= lo) q += 1.0f;
    return U32(q);
}

INLINE uint bvh_q_above(float org, float step, float hi) {
    float q = clamp(ceil((hi - org) / step), 0.0f, 255.0f);
    while (q < 255.0f && org + q * step < hi) q += 1.0f;
    while (q > 0.0f && org + (q - 1.0f) * step >= hi) q -= 1.0f;
    return U32(q);
}

// The 4 slots' q of one plane (used slots only: an unused one is 0) in the bytes of a word.
#define BVH_Q_WORD(fn, org, step, f_)                                                          \
    ((a.ref != BVH_NONE ? fn(org, step, a.b.f_) : 0u) | ((b.ref != BVH_NONE ? fn(org, step, b.b.f_) : 0u) << 8) | \
     ((c.ref != BVH_NONE ? fn(org, step, c.b.f_) : 0u) << 16) | ((d.ref != BVH_NONE ? fn(org, step, d.b.f_) : 0u) << 24))

INLINE void bvh_store_node(CTX_PARAM uint id, WideChild a, WideChild b, WideChild c, WideChild d) {
    // The node's box: the union of its used slots (slot 0 is always used; unused ones are ignored).
    Box u = a.b;
    if (b.ref != BVH_NONE) u = box_union(u, b.b);
    if (c.ref != BVH_NONE) u = box_union(u, c.b);
    if (d.ref != BVH_NONE) u = box_union(u, d.b);
    uint ex = bvh_q_exponent(u.lo.x, u.hi.x), ey = bvh_q_exponent(u.lo.y, u.hi.y), ez = bvh_q_exponent(u.lo.z, u.hi.z);
    float sx = bvh_q_step(ex), sy = bvh_q_step(ey), sz = bvh_q_step(ez);
    V(bvh_qnodes)[4u * id] = make_uint4(as_uint(u.lo.x), as_uint(u.lo.y), as_uint(u.lo.z), ex | (ey << 8) | (ez << 16));
    V(bvh_qnodes)[4u * id + 1u] = make_uint4(BVH_Q_WORD(bvh_q_below, u.lo.x, sx, lo.x), BVH_Q_WORD(bvh_q_above, u.lo.x, sx, hi.x),
                                             BVH_Q_WORD(bvh_q_below, u.lo.y, sy, lo.y), BVH_Q_WORD(bvh_q_above, u.lo.y, sy, hi.y));
    V(bvh_qnodes)[4u * id + 2u] = make_uint4(BVH_Q_WORD(bvh_q_below, u.lo.z, sz, lo.z), BVH_Q_WORD(bvh_q_above, u.lo.z, sz, hi.z),
                                             a.count | (b.count << 8) | (c.count << 16) | (d.count << 24), 0u);
    V(bvh_qnodes)[4u * id + 3u] = make_uint4(a.ref, b.ref, c.ref, d.ref);
}
#else
INLINE void bvh_store_node(CTX_PARAM uint id, WideChild a, WideChild b, WideChild c, WideChild d) {
    V(bvh_nodes)[6u * id] = make_float4(a.b.lo.x, b.b.lo.x, c.b.lo.x, d.b.lo.x);
    V(bvh_nodes)[6u * id + 1u] = make_float4(a.b.hi.x, b.b.hi.x, c.b.hi.x, d.b.hi.x);
    V(bvh_nodes)[6u * id + 2u] = make_float4(a.b.lo.y, b.b.lo.y, c.b.lo.y, d.b.lo.y);
    V(bvh_nodes)[6u * id + 3u] = make_float4(a.b.hi.y, b.b.hi.y, c.b.hi.y, d.b.hi.y);
    V(bvh_nodes)[6u * id + 4u] = make_float4(a.b.lo.z, b.b.lo.z, c.b.lo.z, d.b.lo.z);
    V(bvh_nodes)[6u * id + 5u] = make_float4(a.b.hi.z, b.b.hi.z, c.b.hi.z, d.b.hi.z);
    V(bvh_links)[2u * id] = make_uint4(a.ref, b.ref, c.ref, d.ref);
    V(bvh_links)[2u * id + 1u] = make_uint4(a.count, b.count, c.count, d.count);
}
#endif

INLINE WideChild bvh_no_child(void) {
    WideChild w;
    w.b.lo = make_float3(0.0f, 0.0f, 0.0f);
    w.b.hi = w.b.lo;
    w.ref = BVH_NONE;
    w.count = 0u;
    return w;
}

INLINE void bvh_write_kernel(CTX_PARAM uint node) {
    if (V(bvh_node_count) == 0u) {
        // No node kept (n <= leaf size): one node, slot 0 a leaf of everything, the others none.
        WideChild all;
        all.b = V(bvh_n) == 1u ? bvh_child_box(CTX_ARG BVH_PRIM) : bvh_child_box(CTX_ARG 0u);
        all.ref = 0u;
        all.count = V(bvh_n);
        WideChild none = bvh_no_child();
        bvh_store_node(CTX_ARG 0u, all, none, none, none);
        for (uint r = 1u; r < U32(BVH_NODE_RECORDS); ++r) bvh_store_node(CTX_ARG r, none, none, none, none);
        return;
    }
    uint id = V(bvh_ids)[node];
    if (V(bvh_ids)[node + 1u] == id) return;
    // The slots: the node's two children, each kept inner one opened into its two, for the
    // BVH_LEVELS - 1 levels below (the next kept level heads nodes of its own), in tree order.
    uint slots[4 * BVH_NODE_RECORDS];
    uint opened[4 * BVH_NODE_RECORDS];
    uint n = 2u;
    slots[0] = V(bvh_children)[2u * node];
    slots[1] = V(bvh_children)[2u * node + 1u];
    for (uint level = 1u; level < U32(BVH_LEVELS); ++level) {
        uint m = 0u;
        for (uint i = 0u; i < n; ++i) {
            uint c = slots[i];
            if ((c & BVH_PRIM) == 0u && V(bvh_keep)[c] != 0u) {  // a kept inner node: opened
                opened[m] = V(bvh_children)[2u * c];
                opened[m + 1u] = V(bvh_children)[2u * c + 1u];
                m += 2u;
            } else {
                opened[m] = c;
                m += 1u;
            }
        }
        for (uint i = 0u; i < m; ++i) slots[i] = opened[i];
        n = m;
    }
    for (uint r = 0u; r < U32(BVH_NODE_RECORDS); ++r) {
        WideChild w[4];
        for (uint k = 0u; k < 4u; ++k)
            w[k] = 4u * r + k < n ? bvh_leaf_or_node(CTX_ARG slots[4u * r + k]) : bvh_no_child();
        bvh_store_node(CTX_ARG U32(BVH_NODE_RECORDS) * id + r, w[0], w[1], w[2], w[3]);
    }
}
#endif

#ifdef KERNEL_bvh_records
// ---- Build 9 (bvh only; bvh.py step 7): the triangle records in leaf order, one item per position
// bvh_records[3i .. 3i+2] = the scene's record (trace.h, tri_verts) of triangle voxel_tris[i]; the
// traversal binds it as its tri_verts and reads it with LIST_ORDER_RECORDS.
INLINE void bvh_records_kernel(CTX_PARAM uint i) {
    uint tri = V(voxel_tris)[i];
    V(bvh_records)[3u * i] = V(tri_verts)[3u * tri];
    V(bvh_records)[3u * i + 1u] = V(tri_verts)[3u * tri + 1u];
    V(bvh_records)[3u * i + 2u] = V(tri_verts)[3u * tri + 2u];
}
#endif

#if defined(KERNEL_bvh_ls_flags) || defined(KERNEL_bvh_ls_cells) || defined(KERNEL_trace_bvh) || defined(KERNEL_trace_bvh_ls)
INLINE uint comp4u(uint4 v, uint k) { return k == 0u ? v.x : (k == 1u ? v.y : (k == 2u ? v.z : v.w)); }
INLINE float comp4(float4 v, uint k) { return k == 0u ? v.x : (k == 1u ? v.y : (k == 2u ? v.z : v.w)); }

// A record's slots in either layout (top of this file): the refs, the counts, and the 6 planes of
// the 4 boxes side by side (lo.x of slots 0..3, hi.x, ...), as the slab tests take them.
STRUCT(BvhPlanes) { float4 lx; float4 hx; float4 ly; float4 hy; float4 lz; float4 hz; };
// The trace kernels bind the node buffers as "t" (bvh.py: BVH_TRACE_BUFFERS) and read texels;
// bvh-ls's build kernels bind them as storage buffers.
#if defined(KERNEL_trace_bvh) || defined(KERNEL_trace_bvh_ls)
#define BVH_QNODE(i) LD_U4(bvh_qnodes, i)
#define BVH_NODE(i) LD_F4(bvh_nodes, i)
#define BVH_LINK(i) LD_U4(bvh_links, i)
#else
#define BVH_QNODE(i) V(bvh_qnodes)[i]
#define BVH_NODE(i) V(bvh_nodes)[i]
#define BVH_LINK(i) V(bvh_links)[i]
#endif
#ifdef BVH_QUANTIZED
INLINE uint4 bvh_slot_refs(CTX_PARAM uint record) { return BVH_QNODE(4u * record + 3u); }
INLINE uint4 bvh_slot_counts(CTX_PARAM uint record) {
    uint c = BVH_QNODE(4u * record + 2u).z;
    return make_uint4(c & 0xffu, (c >> 8) & 0xffu, (c >> 16) & 0xffu, c >> 24);
}
INLINE float4 bvh_q_bytes(uint w) {  // the 4 bytes of a word as floats, slot k from byte k
    return make_float4(F32(w & 0xffu), F32((w >> 8) & 0xffu), F32((w >> 16) & 0xffu), F32(w >> 24));
}
// origin + q * step, as the build checked it (PRECISE: no compiler may reorder it with the slab
// test's subtraction of the ray origin, which would round differently).
INLINE float4 bvh_q_plane(float org, uint e, uint w) {
    PRECISE float4 p = make_float4(org, org, org, org) + bvh_q_bytes(w) * bvh_q_step(e);
    return p;
}
INLINE BvhPlanes bvh_node_planes(CTX_PARAM uint record) {
    uint4 h = BVH_QNODE(4u * record);
    uint4 xy = BVH_QNODE(4u * record + 1u);
    uint4 z = BVH_QNODE(4u * record + 2u);
    float ox = as_float(h.x), oy = as_float(h.y), oz = as_float(h.z);
    uint ex = h.w & 0xffu, ey = (h.w >> 8) & 0xffu, ez = (h.w >> 16) & 0xffu;
    BvhPlanes p;
    p.lx = bvh_q_plane(ox, ex, xy.x);
    p.hx = bvh_q_plane(ox, ex, xy.y);
    p.ly = bvh_q_plane(oy, ey, xy.z);
    p.hy = bvh_q_plane(oy, ey, xy.w);
    p.lz = bvh_q_plane(oz, ez, z.x);
    p.hz = bvh_q_plane(oz, ez, z.y);
    return p;
}
#else
INLINE uint4 bvh_slot_refs(CTX_PARAM uint record) { return BVH_LINK(2u * record); }
INLINE uint4 bvh_slot_counts(CTX_PARAM uint record) { return BVH_LINK(2u * record + 1u); }
#ifndef KERNEL_bvh_ls_flags  // the flags read counts only: that kernel binds bvh_links alone
INLINE BvhPlanes bvh_node_planes(CTX_PARAM uint record) {
    BvhPlanes p;
    p.lx = BVH_NODE(6u * record);
    p.hx = BVH_NODE(6u * record + 1u);
    p.ly = BVH_NODE(6u * record + 2u);
    p.hy = BVH_NODE(6u * record + 3u);
    p.lz = BVH_NODE(6u * record + 4u);
    p.hz = BVH_NODE(6u * record + 5u);
    return p;
}
#endif
#endif
#endif

#if defined(KERNEL_bvh_ls_cells) || defined(KERNEL_trace_bvh_ls)
// ---- bvh-ls: a Line Space per large leaf ------------------------------------------------------
// Cells are the child slots, 4 per record (cell = 4 * record + slot): a slot that is a leaf of more
// than ls_min_count triangles gets a Line Space (ls_ids: exclusive scan of those flags, trace.h's
// cell_line_space). Its box, the leaf's box with every side at least BVH_LS_MIN_SIDE of its longest
// (a flat leaf, a wall, still has a cell-local space whose unit faces the float32 patch lookup can
// tell apart), is the cell the Line Space is built over (grid space) and the traversal looks the
// ray's chord up in (world space, the same box).
#define BVH_LS_MIN_SIDE 0.05f
INLINE Box bvh_ls_box(Box b) {
    float3 e = b.hi - b.lo;
    float m = max(e.x, max(e.y, e.z));
    float3 pad = max(make_float3(BVH_LS_MIN_SIDE * m, BVH_LS_MIN_SIDE * m, BVH_LS_MIN_SIDE * m) - e,
                     make_float3(0.0f, 0.0f, 0.0f)) * 0.5f;
    float3 tiny = make_float3(1e-30f, 1e-30f, 1e-30f) + 1e-6f * max(fabs(b.lo), fabs(b.hi));
    Box padded;
    padded.lo = b.lo - pad - tiny;
    padded.hi = b.hi + pad + tiny;
    return padded;
}

// The box of slot `slot` of record `record` (as the traversal's slab test sees it, in either layout).
INLINE Box bvh_slot_box(CTX_PARAM uint record, uint slot) {
    BvhPlanes p = bvh_node_planes(CTX_ARG record);
    Box b;
    b.lo = make_float3(comp4(p.lx, slot), comp4(p.ly, slot), comp4(p.lz, slot));
    b.hi = make_float3(comp4(p.hx, slot), comp4(p.hy, slot), comp4(p.hz, slot));
    return b;
}
#endif

#ifdef KERNEL_bvh_ls_flags
INLINE void bvh_ls_flags_kernel(CTX_PARAM uint cell) {
    uint count = comp4u(bvh_slot_counts(CTX_ARG cell >> 2), cell & 3u);
    V(ls_flags)[cell] = count > V(ls_min_count) ? 1u : 0u;
}
#endif

#ifdef KERNEL_bvh_ls_cells
INLINE void bvh_ls_cells_kernel(CTX_PARAM uint cell) {
    uint c = V(ls_ids)[cell];
    if (V(ls_ids)[cell + 1u] == c) return;
    uint record = cell >> 2;
    uint slot = cell & 3u;
    uint first = comp4u(bvh_slot_refs(CTX_ARG record), slot);
    uint count = comp4u(bvh_slot_counts(CTX_ARG record), slot);
    Box b = bvh_ls_box(bvh_slot_box(CTX_ARG record, slot));
    float3 lo = to_grid(CTX_ARG b.lo);
    float3 hi = to_grid(CTX_ARG b.hi);
    V(ls_cell_boxes)[2u * c] = make_float4(lo.x, lo.y, lo.z, 0.0f);
    V(ls_cell_boxes)[2u * c + 1u] = make_float4(hi.x, hi.y, hi.z, 0.0f);
    V(ls_cell_ranges)[2u * c] = first;
    V(ls_cell_ranges)[2u * c + 1u] = first + count;
}
#endif

#if defined(KERNEL_trace_bvh) || defined(KERNEL_trace_bvh_ls)
// ---- Traversal ----------------------------------------------------------------------------------
// World space. The slab test of a record's 4 slots at once (float4 lanes, the layout's point); a
// zero direction component gets 1/d = FLT_MAX instead of infinity (0 * inf would be NaN for an
// origin in a slab's plane; the build's boxes are exact float min/max, so only a ray in a
// triangle's own plane meets a plane exactly, and then it grazes). t_far is widened by 2 gamma(3)
// (Ize 2013, pbrt's robust slab test), so float rounding never loses a box the ray touches.
STRUCT(BvhRay) { float3 o; float3 inv; };

INLINE float bvh_rcp(float x) {
    if (x == 0.0f) return BVH_FLT_MAX;
    float r = 1.0f / x;
    return clamp(r, -BVH_FLT_MAX, BVH_FLT_MAX);
}

#define BVH_WIDEN 1.0000007f
#define BVH_LEAF 0x80000000u  // a stack entry: a leaf (BVH_LEAF_ENTRY), else a node

// A leaf's stack entry, BVH_LEAF | leaf: its cell (4 * record + slot), whose links give its range of
// voxel_tris, or with BVH_LEAF_RANGE_BITS = b (bvh: its leaves need nothing but their range; bvh.py
// traversal, where the triangle count leaves 31 - b bits for the first) the range itself,
// first << b | count, so that a popped leaf's record loads wait for no load of its node's links
// (a line the walk may have left long before). Sponza 256² incoherent rays, PoCL: 0.956 of the
// device time (25 alternated pairs), 512² primary rays in packets 0.985, BMW 512² incoherent 0.975;
// llvmpipe 0.927 and 0.979 (Sponza 256² incoherent, primary); hits identical
// (docs/profiles.md, section 20).
#ifdef BVH_LEAF_RANGE_BITS
#ifdef LEAF_LINE_SPACE
#error "a leaf with a Line Space is found by its cell: BVH_LEAF_RANGE_BITS is for leaves without one"
#endif
#define BVH_LEAF_ENTRY(cell_, ref_, count_) (BVH_LEAF | ((ref_) << BVH_LEAF_RANGE_BITS) | (count_))
INLINE uint2 bvh_leaf_range(CTX_PARAM uint leaf) {
    uint first = leaf >> BVH_LEAF_RANGE_BITS;
    return make_uint2(first, first + (leaf & ((1u << BVH_LEAF_RANGE_BITS) - 1u)));
}
#else
#define BVH_LEAF_ENTRY(cell_, ref_, count_) (BVH_LEAF | (cell_))
INLINE uint2 bvh_leaf_range(CTX_PARAM uint cell) {
    uint first = comp4u(bvh_slot_refs(CTX_ARG cell >> 2), cell & 3u);
    return make_uint2(first, first + comp4u(bvh_slot_counts(CTX_ARG cell >> 2), cell & 3u));
}
#endif

// The candidates of leaf `cell`: its range of voxel_tris, or for bvh-ls, where the leaf has a Line
// Space, the shaft of the ray's chord through the leaf's (padded) box: the ray in the box's own
// unit-cube space (an affine map keeps t) is given to octree_ls.h's ols_leaf_shaft as a leaf at
// cell (0, 0, 0), the lookup the octree leaves make (Algorithm 3).
#ifdef LEAF_LINE_SPACE
INLINE Candidates ols_leaf_shaft(CTX_PARAM Candidates list, GridRay g, uint leaf, int3 cell, float2 t_leaf);  // octree_ls.h
#endif

#ifdef LEAF_LINE_SPACE
// The stretch of `ray` from tmin in the box of leaf `leaf` (the walk's slab test without its bound,
// widened as there): empty (x > y) when the ray misses the box.
INLINE float2 bvh_leaf_span(Ray ray, float tmin, Box leaf) {
    float3 inv = make_float3(bvh_rcp(ray.d.x), bvh_rcp(ray.d.y), bvh_rcp(ray.d.z));
    float3 a = (leaf.lo - ray.o) * inv;
    float3 b = (leaf.hi - ray.o) * inv;
    float3 n = min(a, b);
    float3 f = max(a, b);
    return make_float2(max(max(n.x, n.y), max(n.z, tmin)), min(min(f.x, f.y), f.z) * BVH_WIDEN);
}

// The leaf of cell `cell` (box `leaf`, the ray's stretch in it `span`) through its Line Space.
INLINE Trace bvh_test_ls_leaf(CTX_PARAM Trace tr, Ray ray, uint cell, Box leaf, float2 span) {
    uint2 range = bvh_leaf_range(CTX_ARG cell);
    Box box = bvh_ls_box(leaf);
    float3 scale = box.hi - box.lo;
    GridRay g;
    g.o = (ray.o - box.lo) / scale;
    g.d = ray.d / scale;
    g.inv = make_float3(safe_rcp(g.d.x), safe_rcp(g.d.y), safe_rcp(g.d.z));
    g.voxel_t = 1.0f / max(fabs(g.d.x), max(fabs(g.d.y), fabs(g.d.z)));
    g.t_base = 0.0f;  // t here is the ray's own (trace.h: GridRay)
    g.span = span;
    Candidates c = ols_leaf_shaft(CTX_ARG plain_list(range.x, range.y), g, cell, make_int3(0, 0, 0), span);
    return test_candidates(CTX_ARG tr, c);
}
#endif

INLINE Trace bvh_test_leaf(CTX_PARAM Trace tr, Ray ray, uint cell) {
#ifdef LEAF_LINE_SPACE
    Box leaf = bvh_slot_box(CTX_ARG cell >> 2, cell & 3u);
    return bvh_test_ls_leaf(CTX_ARG tr, ray, cell, leaf, bvh_leaf_span(ray, tr.tmin, leaf));
#else
    uint2 range = bvh_leaf_range(CTX_ARG cell);
    return test_candidates(CTX_ARG tr, plain_list(range.x, range.y));
#endif
}

// Push a hit slot (entry e at entry distance t) among the ones this node pushed so far, kept in
// decreasing t from `base` up, so the nearest is popped first.
#define BVH_PUSH(e_, t_) {                                                   \
        int j_ = sp;                                                         \
        while (j_ > base && stack_t[j_ - 1] < (t_)) {                        \
            stack[j_] = stack[j_ - 1];                                       \
            stack_t[j_] = stack_t[j_ - 1];                                   \
            j_ -= 1;                                                         \
        }                                                                    \
        stack[j_] = (e_);                                                    \
        stack_t[j_] = (t_);                                                  \
        sp += 1;                                                             \
    }
// A pushed entry's data is prefetched (PREFETCH: CPUs only), so that its loads meet the cache when
// it is popped: a node's two lines of bvh_nodes (96 bytes at 96 * ref) and its line of bvh_links
// (a quantized node: its one line of bvh_qnodes), a leaf's records (LIST_ORDER_RECORDS: their first and last line; both lines of a leaf of 2) or
// its list. PoCL, Sponza 512² incoherent rays, with the records in list order: 0.87 of the device
// time (docs/profiles.md, section 9).
#ifdef LIST_ORDER_RECORDS
#define BVH_PREFETCH_LEAF(ref_, count_) {                                     \
        PREFETCH(&V(tri_verts)[3u * (ref_)]);                                \
        PREFETCH(&V(tri_verts)[3u * ((ref_) + (count_)) - 1u]);             \
    }
#else
#define BVH_PREFETCH_LEAF(ref_, count_) PREFETCH(&V(voxel_tris)[ref_]);
#endif
#ifdef BVH_QUANTIZED
#define BVH_PREFETCH_NODE(ref_) PREFETCH(&V(bvh_qnodes)[4u * (ref_)]);
#else
#if BVH_NODE_RECORDS == 2
#define BVH_PREFETCH_NODE(ref_) {                                             \
        PREFETCH(&V(bvh_nodes)[12u * (ref_)]);                                \
        PREFETCH(&V(bvh_nodes)[12u * (ref_) + 4u]);                           \
        PREFETCH(&V(bvh_nodes)[12u * (ref_) + 8u]);                           \
        PREFETCH(&V(bvh_links)[4u * (ref_)]);                                 \
    }
#else
#define BVH_PREFETCH_NODE(ref_) {                                             \
        PREFETCH(&V(bvh_nodes)[6u * (ref_)]);                                 \
        PREFETCH(&V(bvh_nodes)[6u * (ref_) + 5u]);                            \
        PREFETCH(&V(bvh_links)[2u * (ref_)]);                                 \
    }
#endif
#endif
#define BVH_PREFETCH_ENTRY(ref_, count_) {                                    \
        if ((count_) == 0u) BVH_PREFETCH_NODE(ref_)                           \
        else BVH_PREFETCH_LEAF(ref_, count_)                                  \
    }
// The stack entry of the slot in cell cell_ (4 * record + slot): its child node, or the leaf
// (BVH_LEAF_ENTRY); BVH_ENTRY: of slot k_ of `record` (the node's record being visited).
#define BVH_CELL_ENTRY(cell_, ref_, count_) ((count_) > 0u ? BVH_LEAF_ENTRY(cell_, ref_, count_) : (ref_))
#define BVH_ENTRY(k_, ref_, count_) BVH_CELL_ENTRY(4u * record + (k_), ref_, count_)
// A hit slot pushed at entry distance t_: its data prefetched, then its entry by BVH_PUSH.
#define BVH_PUSH_SLOT(cell_, ref_, count_, t_) {                             \
        BVH_PREFETCH_ENTRY(ref_, count_)                                     \
        uint entry_ = BVH_CELL_ENTRY(cell_, ref_, count_);                   \
        float entry_t_ = (t_);                                               \
        BVH_PUSH(entry_, entry_t_)                                           \
    }
#define BVH_SLOT(k_, tn_, tf_, ref_, count_)                                 \
    if ((ref_) != BVH_NONE && (tn_) <= (tf_)) BVH_PUSH_SLOT(4u * record + (k_), ref_, count_, tn_)

// A single ray's hit slots onto the stack, nearest on top. BVH_SORT_SLOTS (bvh.py: where the
// driver runs work items in SIMD lanes, Device.serial_work_items false: llvmpipe, GPUs): the four
// slots are sorted in registers first (a 5-comparator network on (entry, stack entry), a missed
// slot BVH_NONE at distance inf) and the hit ones pushed farthest first, because there a private
// array indexed by each lane's own stack pointer is a gather or a per-lane scatter, and the
// insertion sort's loop made four of them per shifted entry (llvmpipe, Sponza 256² primary:
// 0.54 of the device time, incoherent 0.67). Where work items run one at a time (PoCL) the stack is
// plain memory in cache and the insertion sort stays: the network measured 1.07 there (incoherent).
// Both orders push the same slots nearest first; slots at equal entry may swap, so a coplanar twin
// may be found instead at the same distance (a tie for the check, as the packets' note in
// trace_bvh_kernel says).
#define BVH_SLOT_KEY(k_, tn_, tf_, ref_, count_, t_, e_)                             \
    float t_ = INF_F;                                                                \
    uint e_ = BVH_NONE;                                                              \
    if ((ref_) != BVH_NONE && (tn_) <= (tf_)) {                                      \
        BVH_PREFETCH_ENTRY(ref_, count_)                                             \
        t_ = (tn_);                                                                  \
        e_ = BVH_ENTRY(k_, ref_, count_);                                            \
    }
#define BVH_ORDER(ta_, ea_, tb_, eb_) {                                              \
        bool swap_ = (tb_) < (ta_);                                                  \
        float t_ = swap_ ? (tb_) : (ta_);                                            \
        uint e_ = swap_ ? (eb_) : (ea_);                                             \
        tb_ = swap_ ? (ta_) : (tb_);                                                 \
        eb_ = swap_ ? (ea_) : (eb_);                                                 \
        ta_ = t_;                                                                    \
        ea_ = e_;                                                                    \
    }
#define BVH_PUSH_HIT(e_, t_) if ((e_) != BVH_NONE) { stack[sp] = (e_); stack_t[sp] = (t_); sp += 1; }
#ifdef BVH_SORT_SLOTS
#define BVH_SLOTS(tn, tf, refs, counts)                                              \
    BVH_SLOT_KEY(0u, tn.x, tf.x, refs.x, counts.x, slot_t0, slot_e0)                 \
    BVH_SLOT_KEY(1u, tn.y, tf.y, refs.y, counts.y, slot_t1, slot_e1)                 \
    BVH_SLOT_KEY(2u, tn.z, tf.z, refs.z, counts.z, slot_t2, slot_e2)                 \
    BVH_SLOT_KEY(3u, tn.w, tf.w, refs.w, counts.w, slot_t3, slot_e3)                 \
    BVH_ORDER(slot_t0, slot_e0, slot_t1, slot_e1)                                    \
    BVH_ORDER(slot_t2, slot_e2, slot_t3, slot_e3)                                    \
    BVH_ORDER(slot_t0, slot_e0, slot_t2, slot_e2)                                    \
    BVH_ORDER(slot_t1, slot_e1, slot_t3, slot_e3)                                    \
    BVH_ORDER(slot_t1, slot_e1, slot_t2, slot_e2)                                    \
    BVH_PUSH_HIT(slot_e3, slot_t3) BVH_PUSH_HIT(slot_e2, slot_t2)                    \
    BVH_PUSH_HIT(slot_e1, slot_t1) BVH_PUSH_HIT(slot_e0, slot_t0)
#else
#define BVH_SLOTS(tn, tf, refs, counts)                                              \
    BVH_SLOT(0u, tn.x, tf.x, refs.x, counts.x)                                       \
    BVH_SLOT(1u, tn.y, tf.y, refs.y, counts.y)                                       \
    BVH_SLOT(2u, tn.z, tf.z, refs.z, counts.z)                                       \
    BVH_SLOT(3u, tn.w, tf.w, refs.w, counts.w)
#endif

// Stack-based walk, nearest first, written once for the single-ray, the refilled and the packet
// traversal, the work injected (as madmann91/bvh's traverse_top_down takes its leaf and node
// callbacks):
//   VISIT  a node visit (one `iterations` step): tests the 4 slots' boxes of `node` against
//          [tmin, the closest hit so far] and pushes the hit ones, nodes and leaves alike, with
//          BVH_PUSH in order of entry distance;
//   BOUND  the entry distance past which a popped entry is dropped (the closest hit by then);
//   LEAF   tests the leaf of stack entry `e` (trace.h's candidate loop);
//   DONE   after a leaf: whether the walk ends (QUERY_ANY: a hit);
//   END    at the walk's end: `done = 1;`, or (BVH_REFILL) the next ray's walk set up from the
//          root (sp = 0, node = 0) in the same loop.
// Then entries are popped, nearest first; the nearest hit slot, when a node, is visited next
// without the pop loop's checks (its entry lies before the closest hit: tn <= tf <= best; PoCL,
// Sponza 512² primary: 0.949 and 0.977 of the device time, medians of 20 alternated pairs of
// lsbench.profile.ab; incoherent rays and llvmpipe unchanged, 1.005 and 1.002). Stack: at most
// width - 1 entries per node of the path plus one node's width (BVH_STACK, from the tree's
// depth: bvh.py).
// BVH_NEAREST_NEXT, after a visit that pushed from `base` on: the nearest hit slot, when a node,
// popped and visited next (`continue`: the walk's loop that holds it); else node = BVH_NONE.
#define BVH_NEAREST_NEXT                                                               \
    node = BVH_NONE;                                                                   \
    if (sp > base && (stack[sp - 1] & BVH_LEAF) == 0u) {                               \
        sp -= 1;                                                                       \
        node = stack[sp];                                                              \
        continue;                                                                      \
    }
#define BVH_WALK(VISIT, BOUND, LEAF, DONE, END)                                        \
    uint stack[BVH_STACK];                                                             \
    float stack_t[BVH_STACK];                                                          \
    int sp = 0;                                                                        \
    uint node = 0u;                                                                    \
    int done = 0;                                                                      \
    while (done == 0) {                                                                \
        int base = sp;                                                                 \
        VISIT                                                                          \
        BVH_NEAREST_NEXT                                                               \
        while (sp > 0) {                                                               \
            sp -= 1;                                                                   \
            uint e = stack[sp];                                                        \
            if (stack_t[sp] > (BOUND)) continue;                                       \
            if ((e & BVH_LEAF) == 0u) { node = e; break; }                             \
            LEAF                                                                       \
            if (DONE) break;                                                           \
        }                                                                              \
        if (node == BVH_NONE) { END }                                                  \
    }

#ifdef BVH_WHILE_WHILE
// The same walk with the leaves tested in an outer loop and the node visits and pops in an inner one
// until the next entry is a leaf (the "while-while" loops of Aila & Laine 2009; the order of visits
// and tests is the one above, so are the hits). Where a loop's body costs its time even when no
// lane runs it (llvmpipe), the one loop paid a leaf's Line Space lookup and a candidate test once
// per node visit: bvh-ls sets it there (bvh_ls.py; bvh's leaves of 2 gained nothing).
#undef BVH_WALK
#define BVH_WALK(VISIT, BOUND, LEAF, DONE, END)                                        \
    uint stack[BVH_STACK];                                                             \
    float stack_t[BVH_STACK];                                                          \
    int sp = 0;                                                                        \
    uint node = 0u;                                                                    \
    int done = 0;                                                                      \
    while (done == 0) {                                                                \
        uint e = BVH_NONE;                                                             \
        for (;;) {                                                                     \
            if (node != BVH_NONE) {                                                    \
                int base = sp;                                                         \
                VISIT                                                                  \
                BVH_NEAREST_NEXT                                                       \
            }                                                                          \
            e = BVH_NONE;                                                              \
            while (sp > 0) {                                                           \
                sp -= 1;                                                               \
                if (stack_t[sp] <= (BOUND)) { e = stack[sp]; break; }                  \
            }                                                                          \
            if (e == BVH_NONE || (e & BVH_LEAF) != 0u) break;                          \
            node = e;                                                                  \
        }                                                                              \
        if (e != BVH_NONE) {                                                           \
            LEAF                                                                       \
            if (!(DONE)) continue;                                                     \
        }                                                                              \
        END                                                                            \
    }
#endif

// A node's records, each given to M (BVH_NODE_RECORDS of them: the node's slots 0..3, then 4..7).
#if BVH_NODE_RECORDS == 2
#define BVH_EACH_RECORD(M) M(2u * node) M(2u * node + 1u)
#else
#define BVH_EACH_RECORD(M) M(node)
#endif
// The hit slots of `record_` among its 4 entry and exit distances onto the stack (BVH_SLOTS).
#define BVH_RECORD_SLOTS(record_, tn_, tf_) {                                          \
        uint record = (record_);                                                       \
        uint4 refs = bvh_slot_refs(CTX_ARG record);                                    \
        uint4 counts = bvh_slot_counts(CTX_ARG record);                                \
        float4 tn = (tn_), tf = (tf_);                                                 \
        BVH_SLOTS(tn, tf, refs, counts)                                                \
    }
// The single ray's node visit: the slab test of each record's 4 slots at once in float4 lanes.
#define BVH_VISIT_RECORD(record_) {                                                     \
        BvhPlanes pl = bvh_node_planes(CTX_ARG (record_));                             \
        float4 ax = (pl.lx - ox) * inv.x;                                              \
        float4 bx = (pl.hx - ox) * inv.x;                                              \
        float4 ay = (pl.ly - oy) * inv.y;                                              \
        float4 by = (pl.hy - oy) * inv.y;                                              \
        float4 az = (pl.lz - oz) * inv.z;                                              \
        float4 bz = (pl.hz - oz) * inv.z;                                              \
        float best = tr.best.t;                                                        \
        BVH_RECORD_SLOTS(record_, max(max(min(ax, bx), min(ay, by)), max(min(az, bz), t0)), \
                         min(min(min(max(ax, bx), max(ay, by)), max(az, bz)) * BVH_WIDEN,   \
                             make_float4(best, best, best, best)))                    \
    }
#if BVH_NODE_RECORDS == 2 && defined(LANG_OPENCL)
// OpenCL: the 8 slots' slab test in float8 lanes (one operation per plane for both records, as
// Embree's BVH8), the same arithmetic lane by lane as BVH_VISIT_RECORD, so the same hits; GLSL has
// no 8-wide vectors. PoCL, 9-11 pairs of lsbench.profile.ab against two float4 tests: Sponza 256²
// and 512² incoherent 0.959 and 0.968, BMW 512² incoherent 0.984, Sponza 512² diffuse 0.980.
// The hit slots are then pushed by a mask (BVH_PUSH_MASK8), not tested slot by slot.
#define BVH_SLAB8 1
#define BVH_PLANE8(k_) ((float8)(BVH_NODE(12u * node + (k_)), BVH_NODE(12u * node + 6u + (k_))))
#define BVH_VISIT_RAY {                                                                 \
        tr = trace_tick(tr);                                                           \
        float8 ax = (BVH_PLANE8(0u) - ox8) * ix8;                                      \
        float8 bx = (BVH_PLANE8(1u) - ox8) * ix8;                                      \
        float8 ay = (BVH_PLANE8(2u) - oy8) * iy8;                                      \
        float8 by = (BVH_PLANE8(3u) - oy8) * iy8;                                      \
        float8 az = (BVH_PLANE8(4u) - oz8) * iz8;                                      \
        float8 bz = (BVH_PLANE8(5u) - oz8) * iz8;                                      \
        float8 tn8 = max(max(min(ax, bx), min(ay, by)), max(min(az, bz), t08));        \
        float8 tf8 = min(min(min(max(ax, bx), max(ay, by)), max(az, bz)) * BVH_WIDEN,  \
                         (float8)(tr.best.t));                                         \
        BVH_PUSH_MASK8(tn8, tf8)                                                       \
    }
// The 8 slots' hits as one bit mask (a slot hit: a child, ref not BVH_NONE, and tn <= tf; one vector
// compare), then only the hit slots pushed, lowest slot first, each by BVH_PUSH as BVH_SLOT does:
// the same stack, so the same walk and hits. Testing the 8 slots one by one took two data-dependent
// branches per slot, which incoherent rays mispredict (the walk's cost is its instructions and
// branches more than its misses: docs/profiles.md, section 19); here one loop runs once per hit.
// PoCL, medians of alternated launches in one process (docs/profiles.md, section 20), hits
// identical: Sponza incoherent 0.959 (256², 41 pairs) and 0.955 (512²), diffuse 0.90; shadow 1.00,
// AO 0.99. Primary rays go in packets there (their visit is BVH_VISIT_PACKET).
// A record's links (bvh_links, 32 bytes: refs then counts) are read as 8 uints each: the node's
// 16 at 16 * node.
#define BVH_PUSH_MASK8(tn8, tf8) {                                                     \
        __global const uint* links_ = (__global const uint*)V(bvh_links) + 16u * node; \
        uint8 refs8 = (uint8)(vload4(0, links_), vload4(2, links_));                   \
        int8 bits8 = ((tn8 <= tf8) & (refs8 != (uint8)(BVH_NONE)))                     \
                     & (int8)(1, 2, 4, 8, 16, 32, 64, 128);                            \
        int4 bits4 = bits8.lo | bits8.hi;                                              \
        uint mask = U32(bits4.x | bits4.y | bits4.z | bits4.w);                        \
        float slot_t[8];                                                               \
        vstore8(tn8, 0, slot_t);                                                       \
        while (mask != 0u) {                                                           \
            uint k = LOWEST_BIT(mask);                                                 \
            mask &= mask - 1u;                                                         \
            uint at = 8u * (k >> 2) + (k & 3u);  /* record k / 4, slot k % 4 */        \
            /* a leaf's cell: 4 * record + slot = 8 * node + k */                      \
            BVH_PUSH_SLOT(8u * node + k, links_[at], links_[at + 4u], slot_t[k])       \
        }                                                                              \
    }
#else
#define BVH_VISIT_RAY { tr = trace_tick(tr); BVH_EACH_RECORD(BVH_VISIT_RECORD) }
#endif

#ifdef QUERY_ANY
#define BVH_RAY_DONE (tr.best.prim >= 0)
#else
#define BVH_RAY_DONE (0 != 0)
#endif

// The ray's values that a node visit (BVH_VISIT_RAY) reads, declared, then set for ray r_ and its
// walk state tr: origin, 1 / direction (bvh_rcp) and tmin broadcast to the slots' lanes.
#ifdef BVH_SLAB8
#define BVH_RAY_VALUES float8 ox8, oy8, oz8, ix8, iy8, iz8, t08;
#define BVH_SET_RAY(r_) {                                                               \
        ox8 = (float8)((r_).o.x); oy8 = (float8)((r_).o.y); oz8 = (float8)((r_).o.z);  \
        ix8 = (float8)(bvh_rcp((r_).d.x)); iy8 = (float8)(bvh_rcp((r_).d.y));          \
        iz8 = (float8)(bvh_rcp((r_).d.z)); t08 = (float8)(tr.tmin);                    \
    }
#else
#define BVH_RAY_VALUES float3 inv; float4 ox; float4 oy; float4 oz; float4 t0;
#define BVH_SET_RAY(r_) {                                                               \
        inv = make_float3(bvh_rcp((r_).d.x), bvh_rcp((r_).d.y), bvh_rcp((r_).d.z));    \
        ox = make_float4((r_).o.x, (r_).o.x, (r_).o.x, (r_).o.x);                      \
        oy = make_float4((r_).o.y, (r_).o.y, (r_).o.y, (r_).o.y);                      \
        oz = make_float4((r_).o.z, (r_).o.z, (r_).o.z, (r_).o.z);                      \
        t0 = make_float4(tr.tmin, tr.tmin, tr.tmin, tr.tmin);                          \
    }
#endif

INLINE Hit trace_bvh(CTX_PARAM Ray ray, uint id) {
    // Bounded slices (trace.h, SLICED) need a walk that saves its state in 8 words; this walk's
    // state is its stack, so it does not suspend: the host traces its rays whole in one launch on
    // every device (BuildResult.suspends). A ray whose loops llvmpipe still cuts fails the case
    // naming the limit (trace_finish's loop probe); a restart trail (Laine 2010) would let it resume.
    Trace tr = trace_start(CTX_ARG ray, id);
    BVH_RAY_VALUES
    BVH_SET_RAY(ray)
    BVH_WALK(BVH_VISIT_RAY, tr.best.t, tr = bvh_test_leaf(CTX_ARG tr, ray, e & ~BVH_LEAF);, BVH_RAY_DONE, done = 1;)
    return trace_finish(CTX_ARG tr, id);
}

#ifdef BVH_PACKET
// ---- Packet traversal (BVH_PACKET rays per work item) -----------------------------------------
// A CPU OpenCL device (PoCL) runs one work item after the other: a divergent single-ray walk gets
// no SIMD but the float4 of one node's slots (docs/profiles.md, section 1). Coherent rays (primary,
// shadow rays to a light) are traced here as packets (Wald, Slusallek, Benthin & Wagner 2001,
// "Interactive rendering with coherent ray tracing"): the work item carries BVH_PACKET rays in the
// lanes of a vector, tests each slot's box against all of them at once, enters a slot that any
// lane's ray hits (nearest first by the smallest lane entry), and tests a leaf's triangles against
// all lanes, the watertight test's edge functions in the lanes and, for the lanes that may hit, the
// scalar ray_triangle_wt for the distance. The host picks packets by the rays' coherence
// (backends.packet_width). OpenCL: float8 / float16 lanes. GLSL (vec4, 4 rays): for llvmpipe, whose
// SIMD lanes each load their own node lane by lane (docs/profiles.md, section 10), so that a lane's
// node loads and loop steps serve 4 rays.
// The vector dialect the packet code is written in (the preludes have none: only this code compares
// vectors): PK_* compare to lane masks (intP), combine and pick by them; HREDUCE folds the lanes.
#if defined(LANG_OPENCL)
#if BVH_PACKET == 8
typedef float8 floatP;
typedef int8 intP;
#define VLOADP vload8
#define VSTOREP vstore8
#define HREDUCE(op, v) op(op(op((v).lo.lo, (v).lo.hi), op((v).hi.lo, (v).hi.hi)).x, \
                          op(op((v).lo.lo, (v).lo.hi), op((v).hi.lo, (v).hi.hi)).y)
#elif BVH_PACKET == 16
typedef float16 floatP;
typedef int16 intP;
#define VLOADP vload16
#define VSTOREP vstore16
#define HREDUCE4(op, v) op(op((v).lo.lo, (v).lo.hi), op((v).hi.lo, (v).hi.hi))
#define HREDUCE(op, v) op(op(HREDUCE4(op, (v).lo), HREDUCE4(op, (v).hi)).x, \
                          op(HREDUCE4(op, (v).lo), HREDUCE4(op, (v).hi)).y)
#else
#error "BVH_PACKET must be 8 or 16 in OpenCL C"
#endif
#define VLOADI VLOADP
#define PK_SPLAT(x) ((floatP)(x))
#define PK_LT(a, b) ((a) < (b))
#define PK_GT(a, b) ((a) > (b))
#define PK_LE(a, b) ((a) <= (b))
#define PK_EQ(a, b) ((a) == (b))
#define PK_IEQ(a, k) ((a) == (k))
#define PK_OR(a, b) ((a) | (b))
#define PK_AND(a, b) ((a) & (b))
#define PK_NOT(a) (~(a))
#define PK_SELECT(a, b, m) select(a, b, m)  // b where the mask is set, else a
#define PK_STORE_MASK(m, a) { VSTOREP(m, 0, a); }
#else
#if BVH_PACKET != 4
#error "BVH_PACKET must be 4 in GLSL (vec4 lanes)"
#endif
#define floatP vec4
#define intP bvec4
#define VLOADP(o_, a_) vec4(a_[0], a_[1], a_[2], a_[3])
#define VLOADI(o_, a_) ivec4(a_[0], a_[1], a_[2], a_[3])
#define HREDUCE(op, v) op(op((v).x, (v).y), op((v).z, (v).w))
#define PK_SPLAT(x) vec4(x)
#define PK_LT(a, b) lessThan(a, b)
#define PK_GT(a, b) greaterThan(a, b)
#define PK_LE(a, b) lessThanEqual(a, b)
#define PK_EQ(a, b) equal(a, b)
#define PK_IEQ(a, k) equal(a, ivec4(k))
#define PK_OR(a, b) notEqual(uvec4(a) | uvec4(b), uvec4(0u))
#define PK_AND(a, b) notEqual(uvec4(a) & uvec4(b), uvec4(0u))
#define PK_NOT(a) not(a)
#define PK_SELECT(a, b, m) mix(a, b, m)
#define PK_STORE_MASK(m, a) { a[0] = int((m).x); a[1] = int((m).y); a[2] = int((m).z); a[3] = int((m).w); }
#endif

// The packet's rays: lane l is ray gid * BVH_PACKET + l (launch order: rows of the 8 x 8 tiles).
// Each lane runs the single-ray walk's operations (the same slab test per box against its own
// closest hit, the watertight test with its own ray's axes), and a box is entered when any lane's
// ray hits it, so a lane tests the triangles its own walk would and maybe more: the same closest
// distance as trace_bvh. The triangle can differ at a tie only: where the single walk dropped a
// box whose entry, rounded, lay past an equally near hit (the box of a coplanar twin), a packet may
// still enter it for another lane and find the twin (closer(): the smaller id at equal t). PoCL,
// Sponza 512²: all 262,144 primary rays the same; 21 of 262,144 incoherent rays a twin at the same
// t (or one float step nearer), every one a tie for Embree's check (tests/test_bvh.py).
// The packet's rays in lanes: origin, 1 / direction (bvh_rcp) and tmin for the slab tests; the
// watertight test's per-ray shear (make_wray) with its axes as lane masks (k?0: the axis is x,
// k?1: y); `lanes` rays are real, the others (past the ray count) meet nothing.
STRUCT(Packet) {
    floatP ox; floatP oy; floatP oz; floatP ix; floatP iy; floatP iz; floatP t0; floatP sx; floatP sy; floatP sz;
    intP kx0; intP kx1; intP ky0; intP ky1; intP kz0; intP kz1; int lanes;
};

// Component k (0 x, 1 y, 2 z) of each lane, picked by the lane masks of k.
#define BVH_PICK(x_, y_, z_, k0_, k1_) PK_SELECT(PK_SELECT(z_, y_, k1_), x_, k0_)

// A leaf (stack entry e_) against every lane of packet pk: the sheared vertices (wray_vertex) and
// the edge functions of ray_triangle_wt in the lanes; a lane that the edge values and det do not
// rule out runs ray_triangle_wt itself for its distance, so a lane hits exactly what its own test
// hits. prune[l]: lane l's bound of the walk (its closest hit; QUERY_ANY: -inf once it has a hit).
// (A macro over the kernel's tr, prune and pk: GLSL has no pointers to pass them by.) The whole
// test in the lanes instead, each lane's own call only for triangle_plane_t, was slower on
// llvmpipe (Sponza 256² primary rays: 1.03 of the one-ray kernel's time against 0.78).
#ifdef COUNT_WORK
#define BVH_PACKET_COUNT_TEST for (int l = 0; l < BVH_PACKET; ++l) tr[l].tests += 1u;
#else
#define BVH_PACKET_COUNT_TEST
#endif
#ifdef QUERY_ANY
#define BVH_PACKET_PRUNE(l_) prune[l_] = tr[l_].best.prim >= 0 ? -INF_F : tr[l_].best.t;
#else
#define BVH_PACKET_PRUNE(l_) prune[l_] = tr[l_].best.t;
#endif
#ifdef LIST_ORDER_RECORDS
#define BVH_PACKET_RECORD_AT(i_, tri_) load_candidate(CTX_ARG i_)
#else
#define BVH_PACKET_RECORD_AT(i_, tri_) load_candidate(CTX_ARG tri_)
#endif
#ifdef LEAF_LINE_SPACE
// bvh-ls: a leaf's Line Space gives each lane the shaft of its own ray's chord, so the leaf is
// tested lane by lane, each lane whose ray meets the leaf's box before its bound (the single walk's
// slab test for that box) through bvh_test_ls_leaf as its single walk would; `lane_ray` holds the
// lanes' rays. (The packet test of bvh below would test the leaf's whole list in every lane.)
#define BVH_PACKET_LEAF(e_) {                                                                   \
    uint cell_ = (e_) & ~BVH_LEAF;                                                              \
    Box leaf_ = bvh_slot_box(CTX_ARG cell_ >> 2, cell_ & 3u);                                   \
    for (int l = 0; l < BVH_PACKET; ++l) {                                                      \
        if (l >= pk.lanes) continue;                                                            \
        float2 span_ = bvh_leaf_span(lane_ray[l], tr[l].tmin, leaf_);                           \
        if (span_.x > min(span_.y, prune[l])) continue;                                         \
        tr[l] = bvh_test_ls_leaf(CTX_ARG tr[l], lane_ray[l], cell_, leaf_, span_);              \
        BVH_PACKET_PRUNE(l)                                                                     \
    }                                                                                           \
}
#else
#define BVH_PACKET_LEAF(e_) {                                                                   \
    uint2 range = bvh_leaf_range(CTX_ARG (e_) & ~BVH_LEAF);                                     \
    for (uint i = range.x; i < range.y; ++i) {                                                  \
        uint tri = LD_U(voxel_tris, i);                                                         \
        TriRecord T = BVH_PACKET_RECORD_AT(i, tri);                                             \
        floatP pxa = T.a.x - pk.ox, pya = T.a.y - pk.oy, pza = T.a.z - pk.oz;                   \
        floatP pxb = T.b.x - pk.ox, pyb = T.b.y - pk.oy, pzb = T.b.z - pk.oz;                   \
        floatP pxc = T.c.x - pk.ox, pyc = T.c.y - pk.oy, pzc = T.c.z - pk.oz;                   \
        floatP za = BVH_PICK(pxa, pya, pza, pk.kz0, pk.kz1);                                    \
        floatP zb = BVH_PICK(pxb, pyb, pzb, pk.kz0, pk.kz1);                                    \
        floatP zc = BVH_PICK(pxc, pyc, pzc, pk.kz0, pk.kz1);                                    \
        floatP ax = BVH_PICK(pxa, pya, pza, pk.kx0, pk.kx1) - pk.sx * za;                       \
        floatP ay = BVH_PICK(pxa, pya, pza, pk.ky0, pk.ky1) - pk.sy * za;                       \
        floatP bx = BVH_PICK(pxb, pyb, pzb, pk.kx0, pk.kx1) - pk.sx * zb;                       \
        floatP by = BVH_PICK(pxb, pyb, pzb, pk.ky0, pk.ky1) - pk.sy * zb;                       \
        floatP cx = BVH_PICK(pxc, pyc, pzc, pk.kx0, pk.kx1) - pk.sx * zc;                       \
        floatP cy = BVH_PICK(pxc, pyc, pzc, pk.ky0, pk.ky1) - pk.sy * zc;                       \
        /* ray_triangle_wt's misses, lane by lane: edge values of both signs, or det zero (the  */ \
        /* edge values PRECISE as there, so that no lane is ruled out that its own test keeps)  */ \
        PRECISE floatP u = cx * by - cy * bx;                                                   \
        PRECISE floatP v = ax * cy - ay * cx;                                                   \
        PRECISE floatP w = bx * ay - by * ax;                                                   \
        floatP zero_ = PK_SPLAT(0.0f);                                                          \
        intP mixed = PK_AND(PK_OR(PK_OR(PK_LT(u, zero_), PK_LT(v, zero_)), PK_LT(w, zero_)),    \
                            PK_OR(PK_OR(PK_GT(u, zero_), PK_GT(v, zero_)), PK_GT(w, zero_)));   \
        intP maybe = PK_AND(PK_NOT(mixed), PK_NOT(PK_EQ(u + v + w, zero_)));                    \
        BVH_PACKET_COUNT_TEST                                                                   \
        if (!any(maybe)) continue;                                                              \
        int m_[BVH_PACKET];                                                                     \
        PK_STORE_MASK(maybe, m_)                                                                \
        for (int l = 0; l < BVH_PACKET; ++l) {                                                  \
            if (l >= pk.lanes || m_[l] == 0) continue;                                          \
            tr[l].best = closer(tr[l].best, ray_triangle_wt(tr[l].wr, T.a, T.b, T.c, T.n), I32(tri), tr[l].tmin); \
            BVH_PACKET_PRUNE(l)                                                                 \
        }                                                                                       \
    }                                                                                           \
}

#endif

// The packet's node visit: each slot's box against every lane (the single ray's slab test, lane
// by lane); a slot is pushed when some lane's ray hits it, at the smallest entry of those lanes, and
// its data prefetched as the single ray's (Sponza 512² primary: 0.91-0.93 of the device time).
// BVH_PACKET_SLOT(c_, ON_HIT): slot c_'s test, ON_HIT run with its `entry` when some lane hits it.
#define BVH_PACKET_SLOT(c_, ON_HIT)                                                             \
    if (refs.c_ != BVH_NONE) {                                                                  \
        floatP ax = (lx.c_ - pk.ox) * pk.ix, bx = (hx.c_ - pk.ox) * pk.ix;                      \
        floatP ay = (ly.c_ - pk.oy) * pk.iy, by = (hy.c_ - pk.oy) * pk.iy;                      \
        floatP az = (lz.c_ - pk.oz) * pk.iz, bz = (hz.c_ - pk.oz) * pk.iz;                      \
        floatP tn = max(max(min(ax, bx), min(ay, by)), max(min(az, bz), pk.t0));                \
        floatP tf = min(min(min(max(ax, bx), max(ay, by)), max(az, bz)) * BVH_WIDEN, best);     \
        intP hit = PK_LE(tn, tf);                                                               \
        if (any(hit)) {                                                                         \
            float entry = HREDUCE(min, PK_SELECT(PK_SPLAT(INF_F), tn, hit));                    \
            ON_HIT                                                                              \
        }                                                                                       \
    }
#ifdef COUNT_WORK
#define BVH_PACKET_TICK for (int l = 0; l < BVH_PACKET; ++l) tr[l].iterations += 1u;
#else
#define BVH_PACKET_TICK
#endif
#ifdef BVH_SORT_SLOTS
// Where the stack is written lane by lane (BVH_SORT_SLOTS: llvmpipe), the record's slot entries are
// gathered first (a slot no lane hits at inf, against -inf) and pushed through the single ray's
// sorting network: with BVH_PUSH's insertion the packets took 1.08 of the one-ray time there
// instead of 0.81 (Sponza 256² primary rays; docs/profiles.md, section 26).
#define BVH_PACKET_SLOTS                                                                        \
    float4 slot_tn = make_float4(INF_F, INF_F, INF_F, INF_F);                                   \
    float4 slot_tf = make_float4(-INF_F, -INF_F, -INF_F, -INF_F);                               \
    BVH_PACKET_SLOT(x, slot_tn.x = entry; slot_tf.x = INF_F;)                                   \
    BVH_PACKET_SLOT(y, slot_tn.y = entry; slot_tf.y = INF_F;)                                   \
    BVH_PACKET_SLOT(z, slot_tn.z = entry; slot_tf.z = INF_F;)                                   \
    BVH_PACKET_SLOT(w, slot_tn.w = entry; slot_tf.w = INF_F;)                                   \
    BVH_SLOTS(slot_tn, slot_tf, refs, counts)
#else
#define BVH_PACKET_SLOTS                                                                        \
    BVH_PACKET_SLOT(x, BVH_PUSH_SLOT(4u * record, refs.x, counts.x, entry))                     \
    BVH_PACKET_SLOT(y, BVH_PUSH_SLOT(4u * record + 1u, refs.y, counts.y, entry))                \
    BVH_PACKET_SLOT(z, BVH_PUSH_SLOT(4u * record + 2u, refs.z, counts.z, entry))                \
    BVH_PACKET_SLOT(w, BVH_PUSH_SLOT(4u * record + 3u, refs.w, counts.w, entry))
#endif
#define BVH_PACKET_RECORD(record_) {                                                            \
        uint record = (record_);                                                                \
        BvhPlanes pl = bvh_node_planes(CTX_ARG record);                                         \
        float4 lx = pl.lx, hx = pl.hx, ly = pl.ly, hy = pl.hy, lz = pl.lz, hz = pl.hz;          \
        uint4 refs = bvh_slot_refs(CTX_ARG record);                                             \
        uint4 counts = bvh_slot_counts(CTX_ARG record);                                         \
        BVH_PACKET_SLOTS                                                                        \
    }
#define BVH_VISIT_PACKET {                                                                      \
        BVH_PACKET_TICK                                                                         \
        floatP best = VLOADP(0, prune);                                                         \
        BVH_EACH_RECORD(BVH_PACKET_RECORD)                                                      \
    }
#ifdef QUERY_ANY
#define BVH_PACKET_DONE (HREDUCE(max, VLOADP(0, prune)) == -INF_F)
#else
#define BVH_PACKET_DONE (0 != 0)
#endif

INLINE void trace_bvh_kernel(CTX_PARAM uint gid) {
    uint first = gid * U32(BVH_PACKET);
    float ox_[BVH_PACKET], oy_[BVH_PACKET], oz_[BVH_PACKET], ix_[BVH_PACKET], iy_[BVH_PACKET], iz_[BVH_PACKET];
    float t0_[BVH_PACKET], sx_[BVH_PACKET], sy_[BVH_PACKET], sz_[BVH_PACKET], prune[BVH_PACKET];
    int kx_[BVH_PACKET], ky_[BVH_PACKET], kz_[BVH_PACKET];
    Trace tr[BVH_PACKET];
#ifdef LEAF_LINE_SPACE
    Ray lane_ray[BVH_PACKET];
#endif
    Packet pk;
    pk.lanes = 0;
    for (int l = 0; l < BVH_PACKET; ++l) {
        uint ray = first + U32(l);
        Ray r;
        if (ray < V(packet_rays)) {
            r = load_ray(CTX_ARG ray);
            pk.lanes = l + 1;
        } else {  // past the last ray: a ray that meets nothing (tmin = inf)
            r.o = make_float3(0.0f, 0.0f, 0.0f);
            r.d = make_float3(1.0f, 0.0f, 0.0f);
            r.tmin = INF_F;
            r.tmax = INF_F;
        }
        tr[l] = trace_start(CTX_ARG r, ray);
#ifdef LEAF_LINE_SPACE
        lane_ray[l] = r;
#endif
        ox_[l] = r.o.x; oy_[l] = r.o.y; oz_[l] = r.o.z;
        ix_[l] = bvh_rcp(r.d.x); iy_[l] = bvh_rcp(r.d.y); iz_[l] = bvh_rcp(r.d.z);
        t0_[l] = r.tmin;
        prune[l] = tr[l].best.t;
        kx_[l] = tr[l].wr.kx; ky_[l] = tr[l].wr.ky; kz_[l] = tr[l].wr.kz;
        sx_[l] = tr[l].wr.sx; sy_[l] = tr[l].wr.sy; sz_[l] = tr[l].wr.sz;
    }
    pk.ox = VLOADP(0, ox_); pk.oy = VLOADP(0, oy_); pk.oz = VLOADP(0, oz_);
    pk.ix = VLOADP(0, ix_); pk.iy = VLOADP(0, iy_); pk.iz = VLOADP(0, iz_);
    pk.t0 = VLOADP(0, t0_); pk.sx = VLOADP(0, sx_); pk.sy = VLOADP(0, sy_); pk.sz = VLOADP(0, sz_);
    pk.kx0 = PK_IEQ(VLOADI(0, kx_), 0); pk.kx1 = PK_IEQ(VLOADI(0, kx_), 1);
    pk.ky0 = PK_IEQ(VLOADI(0, ky_), 0); pk.ky1 = PK_IEQ(VLOADI(0, ky_), 1);
    pk.kz0 = PK_IEQ(VLOADI(0, kz_), 0); pk.kz1 = PK_IEQ(VLOADI(0, kz_), 1);
    BVH_WALK(BVH_VISIT_PACKET, HREDUCE(max, VLOADP(0, prune)), BVH_PACKET_LEAF(e), BVH_PACKET_DONE, done = 1;)
    for (int l = 0; l < BVH_PACKET; ++l) {
        if (l < pk.lanes) store_hit(CTX_ARG first + U32(l), trace_finish(CTX_ARG tr[l], first + U32(l)));
    }
}
#elif defined(BVH_REFILL)
// ---- Refilled lanes (BVH_REFILL rays per work item) -----------------------------------------
// Where work items run in SIMD lanes (llvmpipe, GPUs) a group runs until its longest walk ends,
// the lanes whose rays ended idle under the mask: rays without locality (the incoherent set) kept
// 46 % of llvmpipe's lanes busy (Sponza 256², bvh, node visits and tests of 8 consecutive rays,
// mean over max). Here a lane whose ray ends stores its hit and starts the next of its rays in the
// same loop (Aila & Laine 2009, "Understanding the efficiency of ray traversal on GPUs": replacing
// terminated rays), so a group waits for its longest walk once per BVH_REFILL rays. Work item g
// traces the rays at g, g + n_items, ... (at most BVH_REFILL of them, below packet_rays, the
// count): the host launches ceil(count / BVH_REFILL) items (backends.refill_rays, for ray sets
// without locality; coherent ones, whose lanes finish together, lost 2-33 % to the refill's setup:
// docs/profiles.md, section 21).
// Each ray's walk, hits and counters are those of trace_bvh. llvmpipe's loop budget (65535 per
// SIMD group) is shared by a lane's rays: the ray it cuts is stored as LOOP_CUT_PRIM (trace.h:
// cut_hit), and the lane's rays after it are never started (every loop then runs its body once and
// ends), so the host fills the hit ids with LOOP_CUT_PRIM before the launch; a cut ray traces the
// set again one ray per work item (backends.trace).
INLINE void trace_bvh_kernel(CTX_PARAM uint gid) {
    uint slot = gid;
    uint taken = 1u;
    uint id;
    Ray ray;
    Trace tr;
    BVH_RAY_VALUES
    // the ray of launch slot `slot` set up for its walk (the walk's own sp and node: the root)
#define BVH_REFILL_START {                                                                \
        id = trace_ray(CTX_ARG slot);                                                     \
        ray = load_ray(CTX_ARG id);                                                       \
        tr = trace_start(CTX_ARG ray, id);                                                \
        BVH_SET_RAY(ray)                                                                  \
    }
    BVH_REFILL_START
#define BVH_REFILL_NEXT                                                                   \
    store_hit(CTX_ARG id, trace_finish(CTX_ARG tr, id));                                  \
    slot += V(n_items);                                                                   \
    if (taken == U32(BVH_REFILL) || slot >= V(packet_rays)) {                             \
        done = 1;                                                                         \
    } else {                                                                              \
        taken += 1u;                                                                      \
        BVH_REFILL_START                                                                  \
        sp = 0;                                                                           \
        node = 0u;                                                                        \
    }
    BVH_WALK(BVH_VISIT_RAY, tr.best.t, tr = bvh_test_leaf(CTX_ARG tr, ray, e & ~BVH_LEAF);, BVH_RAY_DONE,
             BVH_REFILL_NEXT)
}
#else
INLINE void trace_bvh_kernel(CTX_PARAM uint gid) {
    uint ray = trace_ray(CTX_ARG gid);
    store_hit(CTX_ARG ray, trace_bvh(CTX_ARG load_ray(CTX_ARG ray), ray));
}
#endif
#endif  // traversal
