// `svo`: the node-pool octree (Delgado Kraemer 2019, 3.3.2, Algorithm 1): 8 uints per internal node, written by
// the shared build of octree.h, and its stack traversal. Needs geometry.h and octree.h; the
// traversal also scene.h and trace.h before octree.h (svo-ls: linespace.h too, octree_ls.h after).
//
//   svo_nodes  8 uints per internal node: child node id, or on the last internal level leaf
//              index + 1; 0 = empty (the root is never anyone's child).

#ifdef KERNEL_svo_create
// ---- Build 5 (octree.h) in the node-pool layout --------------------------------------------
INLINE void svo_create_kernel(CTX_PARAM uint gid) {
    OctNode n = oct_internal_node(CTX_ARG gid);
    if (n.flagged == 0u) return;
    for (uint k = 0u; k < 8u; ++k) {
        // A leaf child is stored as leaf index + 1, so 0 stays "empty".
        uint child = ((n.mask >> k) & 1u) != 0u ? n.first + rank_in_word(n.mask, k) + n.to_leaves : 0u;
        V(svo_nodes)[8u * n.id + k] = child;
    }
}
#endif

#if defined(KERNEL_trace_svo) || defined(KERNEL_trace_svo_ls)
// ---- svo traversal (thesis Algorithm 1) ---------------------------------------------------
// Grid space (scene.h: voxel = unit cube, t unchanged). The stack holds node ids only
// (stack[l] = node whose children are being walked at depth l+1), the current cell is kept
// as integer coordinates at its depth. A child is entered where the ray enters it (the
// child whose octant contains the entry point: "intersect middle planes"); after a cell the
// ray steps to the neighbour across its exit face (front to back from the direction signs),
// and goes up while that neighbour lies outside the parent (lines 23-31: the parent is left
// through the same face, so the step repeats one level up). Ends at the first hit that lies
// inside the current leaf, or when the ray leaves the root.
// The walk's loop state in the slice words (trace.h): the depth and the cell's coordinates at that
// depth. The stack need not be saved: stack[l] is always the node of the cell's ancestor at
// depth l, so the resumed walk descends to it again along the cell's bits (integer, exact).
INLINE Trace svo_suspend(Trace tr, int level, int3 cell) {
    tr.wa = make_uint4(U32(level), U32(cell.x), U32(cell.y), U32(cell.z));
    return tr;
}

INLINE Hit trace_svo(CTX_PARAM Ray ray, uint id) {
    Trace tr = trace_start(CTX_ARG ray, id);
    GridRay gr = make_grid_ray(CTX_ARG ray);  // t below: from gr.t_base (trace.h)
    float3 og = gr.o;
    float3 dg = gr.d;
    float3 inv = gr.inv;
    int res = 1 << OCT_DEPTH;  // the cube's edge in voxels
    // The walk covers the scene's box only (octree.h: the cube's cells past grid_res are empty).
    float t0 = gr.span.x;
    float t1 = gr.span.y;
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
        if (tr.resumed != 0) {  // an earlier slice stopped here (svo_suspend)
            level = I32(tr.wa.x);
            cell = make_int3(I32(tr.wa.y), I32(tr.wa.z), I32(tr.wa.w));
            size = res >> level;
            for (int l = 1; l < level; ++l) {
                int up = level - l;  // the ancestor at depth l and its slot in stack[l - 1]
                uint slot = U32((cell.x >> up) & 1) | (U32((cell.y >> up) & 1) << 1) | (U32((cell.z >> up) & 1) << 2);
                uint above = 0u;
                OCT_STACK_GET(above, stack, l - 1)
                OCT_STACK_SET(stack, l, LD_U(svo_nodes, 8u * above + slot))
            }
        }
        // The steps that test no candidates (descents, empty children, advances) run in the inner
        // loop and a leaf's candidates in the outer one (esvo.h says why): after the leaf the inner
        // loop takes the same cell again (leaf_done) without counting a step, and advances past it.
        int leaf_done = 0;
        for (;;) {
            int at_leaf = 0;
            uint leaf = 0u;
            float leaf_exit = 0.0f;
            for (;;) {
                if (leaf_done == 0) {  // (the leaf just tested was counted when the walk reached it)
                    tr = trace_tick(tr);
                    if (TRACE_SUSPENDED(tr)) { tr = svo_suspend(tr, level, cell); break; }
                }
                float fs = F32(size);
                // Exit distance of the cell on each axis (an axis the ray does not move along never wins).
                float nx = dg.x == 0.0f ? INF_F : (F32(cell.x + (sx > 0 ? 1 : 0)) * fs - og.x) * inv.x;
                float ny = dg.y == 0.0f ? INF_F : (F32(cell.y + (sy > 0 ? 1 : 0)) * fs - og.y) * inv.y;
                float nz = dg.z == 0.0f ? INF_F : (F32(cell.z + (sz > 0 ? 1 : 0)) * fs - og.z) * inv.z;
                float t_exit = min(nx, min(ny, nz));
                uint slot = U32(cell.x & 1) | (U32(cell.y & 1) << 1) | (U32(cell.z & 1) << 2);
                uint parent = 0u;
                OCT_STACK_GET(parent, stack, level - 1)
                uint child = LD_U(svo_nodes, 8u * parent + slot);
                if (child != 0u) {
                    if (level == OCT_DEPTH) {
                        if (leaf_done == 0) {  // to the outer loop, which tests it
                            at_leaf = 1;
                            leaf = child - 1u;
                            leaf_exit = t_exit;
                            tr = trace_revisit(tr, 2u);  // the outer loop and the inner loop's return
                            if (TRACE_SUSPENDED(tr)) tr = svo_suspend(tr, level, cell);
                            break;
                        }
                    } else {
                        // Descend (lines 11-18): enter the child octant that holds the entry point.
                        float ex = dg.x == 0.0f ? -INF_F : (F32(cell.x + (sx > 0 ? 0 : 1)) * fs - og.x) * inv.x;
                        float ey = dg.y == 0.0f ? -INF_F : (F32(cell.y + (sy > 0 ? 0 : 1)) * fs - og.y) * inv.y;
                        float ez = dg.z == 0.0f ? -INF_F : (F32(cell.z + (sz > 0 ? 0 : 1)) * fs - og.z) * inv.z;
                        float t_in = max(t0, max(ex, max(ey, ez)));
                        OCT_STACK_SET(stack, level, child)
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
                leaf_done = 0;
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
            if (TRACE_SUSPENDED(tr) || at_leaf == 0) break;
            // At the last level `cell` is the leaf's voxel, and the walk's stretch in it ends at the
            // chord's own exit (the same arithmetic): leaf_exit stands for both ends.
            tr = oct_test_leaf(CTX_ARG tr, gr, leaf, cell, make_float2(leaf_exit, leaf_exit));
            if (TRACE_SUSPENDED(tr)) { tr = svo_suspend(tr, level, cell); break; }
            if (trace_done(tr, gr.t_base + leaf_exit) != 0) break;
            leaf_done = 1;
        }
    }
    return trace_finish(CTX_ARG tr, id);
}

INLINE void trace_svo_kernel(CTX_PARAM uint gid) {
    uint ray = trace_ray(CTX_ARG gid);
    store_hit(CTX_ARG ray, trace_svo(CTX_ARG load_ray(CTX_ARG ray), ray));
}
#endif  // svo traversal
