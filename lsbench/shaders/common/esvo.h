// `esvo`: the octree of svo.h in the compact layout of Laine & Karras (2010) as simplified in
// Delgado Kraemer 2019, 5.2.1: one 32-bit child descriptor per internal node, a 24-bit pointer to its first
// child above an 8-bit valid mask (Listing 2; no far bit, no contours, no leaf mask: leaves
// exist only on the last level, so the level says what a child is). The children of a node
// are contiguous in slot order, child k at pointer + popcount(mask below k); on the last
// internal level the pointer indexes `leaves`. The descriptors are written by the shared build of
// octree.h (esvo_create_kernel below). Needs geometry.h and octree.h; the traversal also scene.h
// and trace.h before octree.h (esvo-ls: linespace.h too, octree_ls.h after).
//
// Traversal after Laine & Karras, "Efficient Sparse Voxel Octrees" (I3D 2010, appendix code),
// thesis 5.2.2 (Fig. 16-18): the bounding cube is mapped to [1,2]^3, axes are mirrored so
// the direction is negative on every axis, and the loop runs PUSH (descend), ADVANCE (next
// sibling) and POP (the scale of the common ancestor is the highest bit in which the
// position's float bits changed). Positions and scales are exact binary fractions in the
// mantissa, so depth is limited to ESVO_SMAX - 1 = 22 levels, far beyond what fits in memory.

#define ESVO_SMAX 23

#ifdef KERNEL_esvo_create
// ---- Build 5 (octree.h) in the descriptor layout -------------------------------------------
// Listing 2: 24-bit child pointer above the 8-bit valid mask (the build checks that every
// pointer fits in 24 bits before it gets here).
INLINE void esvo_create_kernel(CTX_PARAM uint gid) {
    OctNode n = oct_internal_node(CTX_ARG gid);
    if (n.flagged != 0u) V(esvo_nodes)[n.id] = (n.first << 8) | n.mask;
}
#endif

#if defined(KERNEL_trace_esvo) || defined(KERNEL_trace_esvo_ls)
// Voxel coordinates of the leaf whose mirrored min corner is `pos` (edge `edge`, octree space
// [1,2]^3): undo the mirroring (x -> 3 - x turns [pos, pos + edge] into [3 - pos - edge, 3 - pos]),
// then scale to the grid. Every value is an exact binary fraction; + 0.5 only guards the floor.
INLINE int3 esvo_leaf_cell(float3 pos, float edge, uint mirror, float res) {
    float x = (mirror & 1u) != 0u ? 3.0f - pos.x - edge : pos.x;
    float y = (mirror & 2u) != 0u ? 3.0f - pos.y - edge : pos.y;
    float z = (mirror & 4u) != 0u ? 3.0f - pos.z - edge : pos.z;
    return make_int3(I32(floor((x - 1.0f) * res + 0.5f)), I32(floor((y - 1.0f) * res + 0.5f)),
                     I32(floor((z - 1.0f) * res + 0.5f)));
}

// The walk's loop state in the slice words (trace.h): the parent's descriptor index, the cell's
// mirrored slot and scale, its mirrored corner and the walked stretch (t_min, t_max). The stack
// is not saved: the entry of scale S holds the node of the cell's ancestor at scale S + 1's
// children and the t_max the walk had at scale S, the ray's t_max cut by the exits of the
// ancestors above. The resumed walk computes both again from the root along the corner's bits with
// the walk's own arithmetic (corners are exact binary fractions), so it pops exactly as one launch.
INLINE Trace esvo_suspend(Trace tr, uint parent, uint idx, int scale, float3 pos, float t_min, float t_max) {
    tr.wa = make_uint4(parent, idx | (U32(scale) << 8), as_uint(pos.x), as_uint(pos.y));
    tr.wb = make_uint4(as_uint(pos.z), as_uint(t_min), as_uint(t_max), 0u);
    return tr;
}

INLINE Hit trace_esvo(CTX_PARAM Ray ray, uint id) {
    Trace tr = trace_start(CTX_ARG ray, id);
    // The ray in grid space from a point by the scene's box (trace.h: make_grid_ray), also for
    // esvo-ls' Line Space lookup; every t below is from gr.t_base.
    GridRay gr = make_grid_ray(CTX_ARG ray);
    // Octree space (thesis 5.2.2, "Implementierung"): origin moved to the cube's corner,
    // divided by the cube's edge, shifted by one; the direction divided by the edge and
    // normalized. t' = t * dlen, so every distance below is t' / dlen. (Grid space divided by
    // the cube's edge in voxels, a power of two: exact.)
    float res = F32(1 << OCT_DEPTH);  // the cube's edge in voxels
    float inv_edge = V(grid_inv_voxel).x / res;
    float3 p = gr.o / res + make_float3(1.0f, 1.0f, 1.0f);
    float3 dn = ray.d * inv_edge;
    float dlen = length(dn);
    float3 dd = dn / dlen;
    // Components too small for the reciprocal become +-2^-23 (LK10: keeps t finite).
    float eps = 1.1920929e-7f;
    if (fabs(dd.x) < eps) dd.x = (as_uint(dd.x) & 0x80000000u) != 0u ? -eps : eps;
    if (fabs(dd.y) < eps) dd.y = (as_uint(dd.y) & 0x80000000u) != 0u ? -eps : eps;
    if (fabs(dd.z) < eps) dd.z = (as_uint(dd.z) & 0x80000000u) != 0u ? -eps : eps;
    // t of the plane x = X is X * tx_coef - tx_bias (one multiply-add per plane).
    float tx_coef = 1.0f / -fabs(dd.x);
    float ty_coef = 1.0f / -fabs(dd.y);
    float tz_coef = 1.0f / -fabs(dd.z);
    float tx_bias = tx_coef * p.x;
    float ty_bias = ty_coef * p.y;
    float tz_bias = tz_coef * p.z;
    // Mirror the axes the ray runs up (x -> 3 - x): then it runs down on every axis, and the
    // real child slot of mirrored slot idx is idx ^ mirror.
    uint mirror = 0u;
    if (dd.x > 0.0f) { mirror ^= 1u; tx_bias = 3.0f * tx_coef - tx_bias; }
    if (dd.y > 0.0f) { mirror ^= 2u; ty_bias = 3.0f * ty_coef - ty_bias; }
    if (dd.z > 0.0f) { mirror ^= 4u; tz_bias = 3.0f * tz_coef - tz_bias; }
    float t_min = max(max(2.0f * tx_coef - tx_bias, 2.0f * ty_coef - ty_bias), 2.0f * tz_coef - tz_bias);
    float t_max = min(min(tx_coef - tx_bias, ty_coef - ty_bias), tz_coef - tz_bias);
    // The walk covers the scene's box only (octree.h: the cube's cells past grid_res are empty),
    // and the ray's [tmin, tmax); the first child is then the one that holds the point at t_min.
    t_min = max(t_min, gr.span.x * dlen);
    t_max = min(t_max, gr.span.y * dlen);
    float t_end = t_max;  // nothing past the ray's end can be hit: the walk stops there
    if (t_min <= t_max) {
        // Stack entry of scale s (s = leaf scale + 1 .. ESVO_SMAX - 1) at s - leaf_scale - 1:
        // one per level above the leaves, "sized to depth".
        uint stack_node[OCT_DEPTH];
        float stack_tmax[OCT_DEPTH];
        int leaf_scale = ESVO_SMAX - OCT_DEPTH;
        uint parent = 0u;  // descriptor index of the node whose children are walked
        uint desc = 0u;  // its descriptor; 0 = fetch again
        uint idx = 0u;  // mirrored slot of the current cell
        float3 pos = make_float3(1.0f, 1.0f, 1.0f);  // mirrored min corner of the current cell
        int scale = ESVO_SMAX - 1;
        float scale_exp2 = 0.5f;  // 2^(scale - ESVO_SMAX): the cell's edge
        if (1.5f * tx_coef - tx_bias > t_min) { idx ^= 1u; pos.x = 1.5f; }
        if (1.5f * ty_coef - ty_bias > t_min) { idx ^= 2u; pos.y = 1.5f; }
        if (1.5f * tz_coef - tz_bias > t_min) { idx ^= 4u; pos.z = 1.5f; }
        if (tr.resumed != 0) {  // an earlier slice stopped here (esvo_suspend)
            float t_top = t_max;  // the t_max of the root's children
            parent = tr.wa.x;
            idx = tr.wa.y & 0xffu;
            scale = I32(tr.wa.y >> 8);
            pos = make_float3(as_float(tr.wa.z), as_float(tr.wa.w), as_float(tr.wb.x));
            t_min = as_float(tr.wb.y);
            t_max = as_float(tr.wb.z);
            scale_exp2 = as_float(U32(scale - ESVO_SMAX + 127) << 23);
            uint node = 0u;
            for (int sc = ESVO_SMAX - 1; sc > scale; --sc) {
                OCT_STACK_SET(stack_node, sc - leaf_scale - 1, node)
                OCT_STACK_SET(stack_tmax, sc - leaf_scale - 1, t_top)
                // The ancestor at scale sc: the corner rounded down to that scale (as POP does).
                uint ax = as_uint(pos.x) >> U32(sc), ay = as_uint(pos.y) >> U32(sc), az = as_uint(pos.z) >> U32(sc);
                float cx = as_float(ax << U32(sc)) * tx_coef - tx_bias;
                float cy = as_float(ay << U32(sc)) * ty_coef - ty_bias;
                float cz = as_float(az << U32(sc)) * tz_coef - tz_bias;
                t_top = min(t_top, min(min(cx, cy), cz));
                uint d_anc = LD_U(esvo_nodes, node);
                uint a_slot = ((ax & 1u) | ((ay & 1u) << 1) | ((az & 1u) << 2)) ^ mirror;
                node = (d_anc >> 8) + rank_in_word(d_anc & 0xffu, a_slot);
            }
        }
        // The steps that test no candidates (PUSH, ADVANCE, POP, empty children) run in the inner
        // loop and a leaf's candidates in the outer one (the "while-while" loops of Aila & Laine
        // 2009): llvmpipe runs a loop's body once even where no lane iterates it, so a candidate
        // loop inside every step cost a triangle test per step (docs/profiles.md, section 17:
        // 0.66-0.80 of the device time; PoCL the same within 1 %). After the leaf the inner loop
        // takes the same cell again (leaf_done) without counting a step, and advances past it.
        int leaf_done = 0;
        for (;;) {
            int at_leaf = 0;
            uint leaf = 0u;
            float leaf_exit = 0.0f;
            while (scale < ESVO_SMAX) {
                if (leaf_done == 0) {  // (the leaf just tested was counted when the walk reached it)
                    tr = trace_tick(tr);
                    if (TRACE_SUSPENDED(tr)) { tr = esvo_suspend(tr, parent, idx, scale, pos, t_min, t_max); break; }
                }
                if (desc == 0u) desc = LD_U(esvo_nodes, parent);
                float tx_corner = pos.x * tx_coef - tx_bias;
                float ty_corner = pos.y * ty_coef - ty_bias;
                float tz_corner = pos.z * tz_coef - tz_bias;
                float tc_max = min(min(tx_corner, ty_corner), tz_corner);  // the cell's exit
                uint slot = idx ^ mirror;
                if (((desc >> slot) & 1u) != 0u && t_min <= t_max) {
                    float tv_max = min(t_max, tc_max);
                    float half_edge = scale_exp2 * 0.5f;
                    float tx_center = half_edge * tx_coef + tx_corner;
                    float ty_center = half_edge * ty_coef + ty_corner;
                    float tz_center = half_edge * tz_coef + tz_corner;
                    if (t_min <= tv_max) {
                        uint child = (desc >> 8) + rank_in_word(desc & 0xffu, slot);
                        if (scale == leaf_scale) {
                            if (leaf_done == 0) {  // to the outer loop, which tests it
                                at_leaf = 1;
                                leaf = child;
                                leaf_exit = tc_max / dlen;
                                tr = trace_revisit(tr, 2u);  // the outer loop and the inner loop's return
                                if (TRACE_SUSPENDED(tr)) tr = esvo_suspend(tr, parent, idx, scale, pos, t_min, t_max);
                                break;
                            }
                        } else {
                            // PUSH: remember the parent. (LK10 skips the write when the ray leaves
                            // the parent together with this child, so no POP can land there; in
                            // float32 a ray along an edge can still pop into that scale and read an
                            // older subtree's entry. Written always, the stack holds exactly the
                            // ancestors of the current cell, which a resumed slice recomputes.)
                            OCT_STACK_SET(stack_node, scale - leaf_scale - 1, parent)
                            OCT_STACK_SET(stack_tmax, scale - leaf_scale - 1, t_max)
                            parent = child;
                            idx = 0u;
                            scale -= 1;
                            scale_exp2 = half_edge;
                            if (tx_center > t_min) { idx ^= 1u; pos.x += scale_exp2; }
                            if (ty_center > t_min) { idx ^= 2u; pos.y += scale_exp2; }
                            if (tz_center > t_min) { idx ^= 4u; pos.z += scale_exp2; }
                            t_max = tv_max;
                            desc = 0u;
                            continue;
                        }
                    }
                }
                // ADVANCE: step across the exit face(s).
                leaf_done = 0;
                uint step_mask = 0u;
                if (tx_corner <= tc_max) { step_mask ^= 1u; pos.x -= scale_exp2; }
                if (ty_corner <= tc_max) { step_mask ^= 2u; pos.y -= scale_exp2; }
                if (tz_corner <= tc_max) { step_mask ^= 4u; pos.z -= scale_exp2; }
                t_min = tc_max;
                if (t_min > t_end) break;
                idx ^= step_mask;
                if ((idx & step_mask) != 0u) {
                    // POP: the step left the parent. The highest bit in which the stepped
                    // coordinates changed is the scale of the ancestor that still holds the ray.
                    uint differing = 0u;
                    if ((step_mask & 1u) != 0u) differing |= as_uint(pos.x) ^ as_uint(pos.x + scale_exp2);
                    if ((step_mask & 2u) != 0u) differing |= as_uint(pos.y) ^ as_uint(pos.y + scale_exp2);
                    if ((step_mask & 4u) != 0u) differing |= as_uint(pos.z) ^ as_uint(pos.z + scale_exp2);
                    scale = I32(as_uint(F32(differing)) >> 23) - 127;  // floor(log2): exact below 2^24
                    if (scale >= ESVO_SMAX) break;  // left the root
                    scale_exp2 = as_float(U32(scale - ESVO_SMAX + 127) << 23);
                    OCT_STACK_GET(parent, stack_node, scale - leaf_scale - 1)
                    OCT_STACK_GET(t_max, stack_tmax, scale - leaf_scale - 1)
                    // Round the position down to the cell of that scale; its bits give the slot.
                    uint shx = as_uint(pos.x) >> U32(scale);
                    uint shy = as_uint(pos.y) >> U32(scale);
                    uint shz = as_uint(pos.z) >> U32(scale);
                    pos.x = as_float(shx << U32(scale));
                    pos.y = as_float(shy << U32(scale));
                    pos.z = as_float(shz << U32(scale));
                    idx = (shx & 1u) | ((shy & 1u) << 1) | ((shz & 1u) << 2);
                    desc = 0u;
                }
            }
            if (TRACE_SUSPENDED(tr) || at_leaf == 0) break;
            // Leaf: test its candidates; done once the closest hit lies in it.
            tr = oct_test_leaf(CTX_ARG tr, gr, leaf, esvo_leaf_cell(pos, scale_exp2, mirror, res),
                               make_float2(t_min / dlen, leaf_exit));
            if (TRACE_SUSPENDED(tr)) { tr = esvo_suspend(tr, parent, idx, scale, pos, t_min, t_max); break; }
            if (trace_done(tr, gr.t_base + leaf_exit) != 0) break;
            leaf_done = 1;
        }
    }
    return trace_finish(CTX_ARG tr, id);
}

INLINE void trace_esvo_kernel(CTX_PARAM uint gid) {
    uint ray = trace_ray(CTX_ARG gid);
    store_hit(CTX_ARG ray, trace_esvo(CTX_ARG load_ray(CTX_ARG ray), ray));
}
#endif  // esvo traversal
