// Sparse voxel octrees over the voxel lists of grid.h: the build both octrees share and the
// node-pool traversal of `svo` (thesis 3.3.2, Algorithm 1). Needs geometry.h and scene.h;
// esvo.h adds the Laine & Karras layout and traversal on top of this file.
//
// The octree covers the bounding cube, resolution R = 2^L (L = OCT_DEPTH levels below the
// root). Level l has 8^l cells; cell c of level l is the Morton code of its coordinates
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
//   svo_nodes  8 uints per internal node: child node id, or on the last internal level leaf
//              index + 1; 0 = empty (the root is never anyone's child).
//   leaves     2 uints per leaf: (first, count) of its candidates in voxel_tris (the thesis'
//              candidate helper buffer), so the dense voxel_offsets can be dropped.

#ifndef OCT_DEPTH
#define OCT_DEPTH 10
#endif

#ifdef LANG_GLSL
#define OCT_POPCOUNT(x) U32(bitCount(x))
#else
#define OCT_POPCOUNT(x) popcount(x)
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

// Linear voxel index (x fastest, as grid.h) of the leaf-level cell with Morton code m.
INLINE uint oct_voxel(uint m, uint r) {
    int3 c = oct_cell(m);
    return U32(c.x) + r * (U32(c.y) + r * U32(c.z));
}

// Number of bits below `bit` that are set in `word`.
INLINE uint oct_rank_in_word(uint word, uint bit) {
    return bit == 0u ? 0u : OCT_POPCOUNT(word & ((1u << bit) - 1u));
}

#if defined(HAS_oct_bits) && defined(HAS_voxel_offsets) && !defined(HAS_leaves)
// ---- Build 1: flag the leaf level, one work item per word (32 cells, no atomics) ----------
INLINE void oct_flag_leaves_kernel(CTX_PARAM uint gid) {
    uint depth = V(oct_depth);
    uint cells = 1u << (3u * depth);
    uint r = U32(V(grid_res).x);
    uint bits = 0u;
    for (uint b = 0u; b < 32u; ++b) {
        uint m = 32u * gid + b;
        if (m >= cells) break;
        uint v = oct_voxel(m, r);
        if (V(voxel_offsets)[v + 1u] > V(voxel_offsets)[v]) bits |= 1u << b;
    }
    V(oct_bits)[V(level_words)[depth] + gid] = bits;
}
#endif

#if defined(HAS_oct_bits) && !defined(HAS_voxel_offsets) && !defined(HAS_oct_ranks) && !defined(HAS_oct_counts)
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

#ifdef HAS_oct_counts
// ---- Build 3: popcount per word (then Device.exclusive_scan, on the device) ---------------
INLINE void oct_popcount_kernel(CTX_PARAM uint gid) {
    V(oct_counts)[gid] = OCT_POPCOUNT(V(oct_bits)[gid]);
}
#endif

#ifdef HAS_oct_level_counts
// ---- Build 4: the rank at each level's first word = nodes above that level ----------------
INLINE void oct_level_counts_kernel(CTX_PARAM uint gid) {
    V(oct_level_counts)[gid] = V(oct_ranks)[V(level_words)[gid]];
}
#endif

#if defined(HAS_oct_ranks) && (defined(HAS_svo_nodes) || defined(HAS_esvo_nodes)) && !defined(HAS_rays)
// ---- Build 5: create the internal nodes, one work item per word of levels 0..L-1 ----------
// Every flagged cell becomes the node with its rank; its children are the flagged bits of the
// byte 8c..8c+7 one level down, and the rank of that byte's first bit is the first child's id,
// so the children of a node are contiguous and in slot order (the esvo layout needs exactly
// that: child k lives at first + popcount(mask below k)).
INLINE void oct_create_kernel(CTX_PARAM uint gid) {
    uint depth = V(oct_depth);
    uint l = 0u;
    while (V(level_words)[l + 1u] <= gid) l += 1u;
    uint word = V(oct_bits)[gid];
    if (word == 0u) return;
    uint node = V(oct_ranks)[gid];
    uint first_cell = 32u * (gid - V(level_words)[l]);
    uint below = V(level_words)[l + 1u];
    uint leaf_base = V(oct_ranks)[V(level_words)[depth]];
    for (uint b = 0u; b < 32u; ++b) {
        if (((word >> b) & 1u) == 0u) continue;
        uint c = first_cell + b;
        uint cw = below + ((8u * c) >> 5);
        uint shift = (8u * c) & 31u;
        uint cword = V(oct_bits)[cw];
        uint mask = (cword >> shift) & 0xffu;
        uint first = V(oct_ranks)[cw] + oct_rank_in_word(cword, shift);
        if (l + 1u == depth) first -= leaf_base;  // children are leaves: index into `leaves`
#ifdef HAS_esvo_nodes
        // Listing 2: 24-bit child pointer above the 8-bit valid mask (the build checks that
        // every pointer fits in 24 bits before it gets here).
        V(esvo_nodes)[node] = (first << 8) | mask;
#endif
#ifdef HAS_svo_nodes
        uint leafbias = l + 1u == depth ? 1u : 0u;  // leaf index + 1, so 0 stays "empty"
        for (uint k = 0u; k < 8u; ++k) {
            uint child = ((mask >> k) & 1u) != 0u ? first + oct_rank_in_word(mask, k) + leafbias : 0u;
            V(svo_nodes)[8u * node + k] = child;
        }
#endif
        node += 1u;
    }
}
#endif

#if defined(HAS_oct_bits) && defined(HAS_oct_ranks) && defined(HAS_level_words)
// Word gid of the pyramid's leaf level: its bits (bit b = Morton code 32 gid + b) and the index of
// the leaf of its lowest set bit (ranks count set bits from the pyramid's start, so subtract the
// leaf level's first rank). The kernels walking the leaves per word (oct_leaves_kernel,
// oct_ls_cells_kernel in octree_ls.h) number each set bit first_leaf, first_leaf + 1, ...
STRUCT(LeafWord) { uint bits; uint first_leaf; };

INLINE LeafWord oct_leaf_word(CTX_PARAM uint gid) {
    uint start = V(level_words)[V(oct_depth)];
    LeafWord lw;
    lw.bits = V(oct_bits)[start + gid];
    lw.first_leaf = V(oct_ranks)[start + gid] - V(oct_ranks)[start];
    return lw;
}
#endif

#if defined(HAS_leaves) && defined(HAS_voxel_offsets)
// ---- Build 6: link every leaf to its candidate list, one work item per leaf-level word ----
INLINE void oct_leaves_kernel(CTX_PARAM uint gid) {
    LeafWord lw = oct_leaf_word(CTX_ARG gid);
    uint word = lw.bits;
    if (word == 0u) return;
    uint leaf = lw.first_leaf;
    uint r = U32(V(grid_res).x);
    for (uint b = 0u; b < 32u; ++b) {
        if (((word >> b) & 1u) == 0u) continue;
        uint m = 32u * gid + b;
        uint v = oct_voxel(m, r);
        uint begin = V(voxel_offsets)[v];
        V(leaves)[2u * leaf] = begin;
        V(leaves)[2u * leaf + 1u] = V(voxel_offsets)[v + 1u] - begin;
        leaf += 1u;
    }
}
#endif

#if defined(HAS_rays) && defined(HAS_leaves)
// ---- Leaf handling shared by both traversals ---------------------------------------------
// Candidates of a leaf are tested against the original ray (the watertight test of
// geometry.h, so t is the world distance). Every hit is kept, wherever it lies: the walk ends
// only once the closest hit lies before the current leaf's exit, so a farther hit never wins,
// and a hit that float rounding puts just past the leaf (of a triangle no later leaf lists)
// is not lost (issue 13 item 1; this was a margin of 1/100 voxel past the exit).
STRUCT(LeafResult) { Hit best; uint tests; uint lookups; };

// The ray in grid space (voxel = unit cube), for the Line Space lookup of svo-ls / esvo-ls; the
// plain octrees never read it and their compilers drop it. voxel_t: one voxel edge along the
// ray's main axis, in t (the most t a chord through one voxel can span along that axis).
STRUCT(GridRay) { float3 o; float3 d; float3 inv; float voxel_t; };

INLINE GridRay make_grid_ray(CTX_PARAM float3 o, float3 d) {
    GridRay g;
    g.o = (o - V(grid_origin).xyz) * V(grid_inv_voxel).xyz;
    g.d = d * V(grid_inv_voxel).xyz;
    g.inv = make_float3(safe_rcp(g.d.x), safe_rcp(g.d.y), safe_rcp(g.d.z));
    g.voxel_t = 1.0f / max(fabs(g.d.x), max(fabs(g.d.y), fabs(g.d.z)));
    return g;
}

// Candidates of leaf `leaf` (voxel `cell`) against the ray. svo-ls / esvo-ls (HAS_ls_shaft_tris,
// Algorithm 3): a leaf with a Line Space (ls_ids, as in grid_ls.h) gives only the candidates of
// the shaft that holds the ray's chord through the leaf, looked up from the chord's entry and
// exit face and patch (linespace.h); an empty shaft skips the leaf with no triangle test. A leaf
// without one (at most ls_min_count candidates) tests its plain list.
//
// t_leaf: the stretch of the ray the traversal gives this leaf (world t). The shaft holds what
// the real line meets inside the leaf, so it serves only if the chord covers that stretch, up to
// half the build's margin (LS_EPS = 1e-3 cell units; a point t past the chord's end lies at most
// t / voxel_t cell units outside). svo's walk uses the chord's own arithmetic, so it always does;
// esvo walks a slightly different line (direction components below 2^-23 are raised to it, LK10),
// and a ray in a leaf's face plane can then be given a leaf its real line only touches: that leaf
// tests its plain list (tests/test_adversarial.py found such rays).
INLINE LeafResult oct_test_leaf(CTX_PARAM WRay wr, GridRay gr, uint leaf, int3 cell, float2 t_leaf,
                                float tmin, Hit best) {
    LeafResult res;
    uint begin = V(leaves)[2u * leaf];
    uint end = begin + V(leaves)[2u * leaf + 1u];
    int from_shaft = 0;
#ifdef HAS_ls_shaft_tris
    uint ls = V(ls_ids)[leaf];
    if (V(ls_ids)[leaf + 1u] > ls) {
        LsChord ch = ls_chord(V(ls_n), gr.o, gr.d, gr.inv, cell);
        float tol = 5e-4f * gr.voxel_t + 1e-6f * max(fabs(t_leaf.x), fabs(t_leaf.y));
        if (ch.t_in <= t_leaf.x + tol && ch.t_out >= t_leaf.y - tol) {
            uint sid = ls * V(ls_shafts) + ch.shaft;
            begin = LS_OFFSET(sid);
            end = LS_OFFSET(sid + 1u);
            from_shaft = 1;
        }
    }
#endif
    for (uint i = begin; i < end; ++i) {
#ifdef HAS_ls_shaft_tris
        uint tri = from_shaft != 0 ? LS_CANDIDATE(i) : V(voxel_tris)[i];
#else
        uint tri = V(voxel_tris)[i];
#endif
        Triangle T = load_triangle(CTX_ARG tri);
        float t = ray_triangle_wt(wr, T.a, T.b, T.c);
        best = closer(best, t, I32(tri), tmin);
    }
    res.best = best;
    res.tests = end - begin;
    res.lookups = U32(from_shaft);
    return res;
}

#endif

#if defined(HAS_rays) && defined(HAS_svo_nodes)
// ---- svo traversal (thesis Algorithm 1) ---------------------------------------------------
// Grid space as in grid.h (voxel = unit cube, t unchanged). The stack holds node ids only
// (stack[l] = node whose children are being walked at depth l+1), the current cell is kept
// as integer coordinates at its depth. A child is entered where the ray enters it (the
// child whose octant contains the entry point: "intersect middle planes"); after a cell the
// ray steps to the neighbour across its exit face (front to back from the direction signs),
// and goes up while that neighbour lies outside the parent (lines 23-31: the parent is left
// through the same face, so the step repeats one level up). Ends at the first hit that lies
// inside the current leaf, or when the ray leaves the root.
INLINE Hit trace_svo(CTX_PARAM float3 o, float3 d, float tmin, float tmax, uint ray) {
#ifdef COUNT_WORK
    uint clock0 = CLOCK_START();
#endif
    Hit best = no_hit(tmax);
    WRay wr = make_wray(o, d);
    GridRay gr = make_grid_ray(CTX_ARG o, d);
    float3 og = gr.o;
    float3 dg = gr.d;
    float3 inv = gr.inv;
    int res = V(grid_res).x;
    float fres = F32(res);
    float2 span = ray_box(og, inv, dg, make_float3(0.0f, 0.0f, 0.0f), make_float3(fres, fres, fres));
    float t0 = max(span.x, tmin);
    float t1 = min(span.y, tmax);
    uint iterations = 0u;
    uint tests = 0u;
    uint lookups = 0u;
    if (t0 <= t1) {
        uint stack[OCT_DEPTH];
        stack[0] = 0u;  // the root
        int level = 1;  // depth of `cell`
        int size = res >> 1;  // edge of a cell at this depth, in voxels
        int sx = dg.x > 0.0f ? 1 : -1, sy = dg.y > 0.0f ? 1 : -1, sz = dg.z > 0.0f ? 1 : -1;
        float3 p = og + dg * t0;
        float fs0 = F32(size);
        int3 cell = clamp(make_int3(I32(floor(p.x / fs0)), I32(floor(p.y / fs0)), I32(floor(p.z / fs0))),
                          make_int3(0, 0, 0), make_int3(1, 1, 1));
        for (;;) {
            iterations += 1u;
            float fs = F32(size);
            // Exit distance of the cell on each axis (an axis the ray does not move along never wins).
            float nx = dg.x == 0.0f ? INF_F : (F32(cell.x + (sx > 0 ? 1 : 0)) * fs - og.x) * inv.x;
            float ny = dg.y == 0.0f ? INF_F : (F32(cell.y + (sy > 0 ? 1 : 0)) * fs - og.y) * inv.y;
            float nz = dg.z == 0.0f ? INF_F : (F32(cell.z + (sz > 0 ? 1 : 0)) * fs - og.z) * inv.z;
            float t_exit = min(nx, min(ny, nz));
            uint slot = U32(cell.x & 1) | (U32(cell.y & 1) << 1) | (U32(cell.z & 1) << 2);
            uint child = V(svo_nodes)[8u * stack[level - 1] + slot];
            if (child != 0u) {
                if (level == OCT_DEPTH) {
                    // At the last level `cell` is the leaf's voxel, and the walk's stretch in it
                    // ends at the chord's own exit (the same arithmetic): t_exit stands for both ends.
                    LeafResult lr = oct_test_leaf(CTX_ARG wr, gr, child - 1u, cell, make_float2(t_exit, t_exit),
                                                  tmin, best);
                    best = lr.best;
                    tests += lr.tests;
                    lookups += lr.lookups;
                    if (best.prim >= 0 && best.t <= t_exit) break;
                } else {
                    // Descend (lines 11-18): enter the child octant that holds the entry point.
                    float ex = dg.x == 0.0f ? -INF_F : (F32(cell.x + (sx > 0 ? 0 : 1)) * fs - og.x) * inv.x;
                    float ey = dg.y == 0.0f ? -INF_F : (F32(cell.y + (sy > 0 ? 0 : 1)) * fs - og.y) * inv.y;
                    float ez = dg.z == 0.0f ? -INF_F : (F32(cell.z + (sz > 0 ? 0 : 1)) * fs - og.z) * inv.z;
                    float t_in = max(t0, max(ex, max(ey, ez)));
                    stack[level] = child;
                    level += 1;
                    size >>= 1;
                    float hs = F32(size);
                    float3 q = og + dg * t_in;
                    int3 base = make_int3(2 * cell.x, 2 * cell.y, 2 * cell.z);
                    int3 sub = make_int3(I32(floor(q.x / hs)), I32(floor(q.y / hs)), I32(floor(q.z / hs))) - base;
                    cell = base + clamp(sub, make_int3(0, 0, 0), make_int3(1, 1, 1));
                    continue;
                }
            }
            if (t_exit >= t1) break;
            // Advance to the neighbour across the exit face; go up while it is outside the parent.
            int axis = (nx <= ny && nx <= nz) ? 0 : (ny <= nz ? 1 : 2);
            int left_root = 0;
            for (;;) {
                int c = axis == 0 ? cell.x : (axis == 1 ? cell.y : cell.z);
                int s = axis == 0 ? sx : (axis == 1 ? sy : sz);
                int nc = c + s;
                if ((nc >> 1) == (c >> 1)) {
                    if (axis == 0) cell.x = nc; else if (axis == 1) cell.y = nc; else cell.z = nc;
                    break;
                }
                level -= 1;
                if (level == 0) { left_root = 1; break; }
                cell = make_int3(cell.x >> 1, cell.y >> 1, cell.z >> 1);
                size <<= 1;
            }
            if (left_root != 0) break;
        }
    }
#ifdef COUNT_WORK
    V(work)[ray] = make_uint4(iterations, tests, lookups, CLOCK_ELAPSED(clock0));
#endif
    return cut_hit(CTX_ARG best);
}

INLINE void trace_svo_kernel(CTX_PARAM uint ray) {
    Ray r = load_ray(CTX_ARG ray);
    store_hit(CTX_ARG ray, trace_svo(CTX_ARG r.o, r.d, r.tmin, r.tmax, ray));
}
#endif  // svo traversal
