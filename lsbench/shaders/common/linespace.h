// Candidate-list Line Space (Delgado Kraemer 2019, 3.3.3, Listing 1; Keul, Mueller, Lemke 2016), written once for
// every structure whose cells get a Line Space (grid-ls voxels, svo-ls / esvo-ls octree leaves).
// Needs geometry.h; the count and fill kernels also scene.h (cells are boxes in grid space).
//
// A cell's box is mapped to the unit cube ("cell-local" coordinates). Each of its 6 faces carries
// an N x N patch grid. Face f = 2 * axis + side (side 0: coordinate 0, side 1: coordinate 1);
// the patch coordinates (u, v) on a face of axis a are the local coordinates of axes (a+1)%3 and
// (a+2)%3. A shaft joins a patch on one face with a patch on another face; a shaft and its
// reverse are one, and a face is never joined with itself (coplanar patches span no volume),
// which leaves 15 face pairs ("blocks") x N^4 patch pairs = 15 N^4 shafts per cell.
//
// Shaft id within a cell (Listing 1): N^4 * block(fs, fe) + N^2 * patch_s + patch_e, where fs is
// the smaller face of the two. The thesis looks block up in faceToBlockMap; the closed form
// below enumerates the same 15 pairs (0,1),(0,2),..,(4,5) in order.
//
// Storage: one list per distinct candidate set of a cell (issue 16: 92-95 % of a cell's non-empty
// shafts repeat another shaft's set, docs/linespace-build.md). ls_shaft_offsets holds, for C Line
// Spaces of S = 15 N^4 shafts, one block of B = 1 + (S + 1) / 2 words per Line Space, then the
// set offsets:
//   [c B]                   where Line Space c's first set offset is: C B + its first set
//   [c B + 1 + s / P]       bits W (s % P) .. +W-1: shaft s's set, counted from its cell's first
//   [C B + g], g = 0..sets  set g's candidates are entries [C B + g] .. [C B + g + 1] - 1 of
//                           ls_shaft_tris (cell-local ids, LS_LOCAL_ID below)
// so a lookup (trace.h: shaft_list) reads two words of one block and a set's two offsets. A cell's
// sets number at most its S shafts, so the index width W is the narrowest of 8 and 16 bits that
// holds S: 8 bits (P = 4 per word) for N <= 2 (S <= 240), 16 bits (P = 2) for N = 3..8; then
// B = 1 + ceil(S / P). (At N = 2 the 8-bit indices take the block from 121 to 61 words, the
// difference between 50.6 % and 44 % of the one-list-per-shaft bytes on Sponza.) The sets of a
// cell are numbered in the order of their first shaft; each lists its triangles in the cell's list
// order, as the one-list-per-shaft layout before it did.
// Both arrays may be split over up to 4 buffers each (linespace.py: SplitArray, when they pass the
// driver's per-buffer limit). Kernels reach them only through these macros; the defaults below
// are the one-buffer case, split kernels get generated ones (a chain of chunk compares over
// ls_shaft_offsets, ls_shaft_offsets1, ..). A macro names its buffers only where it is used, so a
// kernel that binds an array write-only (layout: offsets; fill: candidates) never reads it.
//   LS_OFFSET(i), LS_OFFSET_STORE(i, v)       entry i of the shaft offsets
//   LS_CANDIDATE(i), LS_CANDIDATE_STORE(i, v) word i of the candidates (LS_CANDIDATE_OR: atomic OR)
// The build's per-shaft set words (LS_SHAFT_SET: index in the cell | LS_SET_HEAD on a set's first
// shaft) and set lengths, scanned into the set offsets (LS_SET_LEN), are split the same way.
// Trace kernels (LEAF_LINE_SPACE) bind both arrays as "t" (linespace.py: LS_TRACE_BUFFERS) and read
// them as texels (LD_U); the build's kernels bind them as storage buffers.
#ifndef LS_OFFSET
#ifdef LEAF_LINE_SPACE
#define LS_OFFSET(i) LD_U(ls_shaft_offsets, i)
#else
#define LS_OFFSET(i) V(ls_shaft_offsets)[i]
#endif
#define LS_OFFSET_STORE(i, v) V(ls_shaft_offsets)[i] = (v)
#endif
#ifndef LS_CANDIDATE
#ifdef LEAF_LINE_SPACE
#define LS_CANDIDATE(i) LD_U(ls_shaft_tris, i)
#else
#define LS_CANDIDATE(i) V(ls_shaft_tris)[i]
#endif
#define LS_CANDIDATE_STORE(i, v) V(ls_shaft_tris)[i] = (v)
#define LS_CANDIDATE_OR(i, v) ATOMIC_OR(V(ls_shaft_tris)[i], v)
#endif
// Candidate ids are cell-local (issue 16: half the bytes of the lists): entry k of a set is the
// position of its triangle in the cell's plain list (voxel_tris from the cell's range begin, which
// every traversal holds when it looks a shaft up: trace.h test_candidates). With LS_IDS16 (every
// cell of the structure holds at most 65,536 candidates: linespace.py candidate_id_bits) they are
// 16 bits, two per word of ls_shaft_tris, entry k in bits 16 (k & 1) of word k / 2; otherwise one
// per word. Set offsets count entries, not words.
//   LS_LOCAL_ID(k)  entry k
#ifdef LS_IDS16
#define LS_LOCAL_ID(k) ((LS_CANDIDATE((k) >> 1u) >> (((k) & 1u) << 4u)) & 0xffffu)
#else
#define LS_LOCAL_ID(k) LS_CANDIDATE(k)
#endif
// The build's count and fill address one entry per work item, (shaft, chunk of candidates), in
// ls_item_offsets (the count there, then its exclusive scan). Where every cell fits one chunk the
// items are the shafts and linespace.py binds the shaft offsets themselves under this name.
#ifndef LS_ITEM
#define LS_ITEM(i) V(ls_item_offsets)[i]
#define LS_ITEM_STORE(i, v) V(ls_item_offsets)[i] = (v)
#endif
#ifndef LS_SHAFT_SET
#define LS_SHAFT_SET(i) V(ls_shaft_sets)[i]
#define LS_SHAFT_SET_STORE(i, v) V(ls_shaft_sets)[i] = (v)
#endif
#ifndef LS_SET_LEN
#define LS_SET_LEN(i) V(ls_set_lens)[i]
#define LS_SET_LEN_STORE(i, v) V(ls_set_lens)[i] = (v)
#endif
// The count's pair bits (LS_PAIR_BITS below), word i: split the same way where they pass the
// driver's per-buffer limit (llvmpipe: 128 MiB; linespace.py keeps all cells' bits up to 256 MiB).
#ifndef LS_BITS
#define LS_BITS(i) V(ls_pair_bits)[i]
#define LS_BITS_OR(i, v) ATOMIC_OR(V(ls_pair_bits)[i], v)
#endif
// The item of a shaft that is not its set's first: the fill skips it (ls_set_len_kernel).
#define LS_SKIP 0xffffffffu
#define LS_STAT_BUCKETS 32u  // the count's stats: words 16 (k + 1) + {0, 2, 3} of ls_stats for bucket k (linespace.py)
#define LS_SET_HEAD 0x80000000u
//
// Uniforms: ls_n (N), ls_shafts (15 N^4), ls_eps (conservative margin, cell-local units).

#define LS_MAX_PLANES 8  // a hull of two face patches has at most 8 facets (brute force, N <= 5)
// Per shaft in ls_planes: its 8 facet planes, then its axis' two ends (the centres of its patches)
// with the index of the patch's mask in .w (ls_planes_kernel), so the count's work items read
// what they would otherwise decode and compute per shaft.
#define LS_PLANE_SLOTS 10
#define LS_MAX_POLY 16    // 3 triangle corners + one vertex per clipping plane, with room

// log2 P: how many set indices share a word of a block (layout above), from S = ls_shafts.
INLINE uint ls_index_log2(uint shafts) {
    return shafts <= 256u ? 2u : 1u;
}

// B: the words of one Line Space's block (its first set, then its S set indices, P per word).
INLINE uint ls_block_words(uint shafts) {
    uint per = 1u << ls_index_log2(shafts);
    return 1u + (shafts + per - 1u) / per;
}

// Shaft s's set index (counted from its cell's first set) out of its block word.
INLINE uint ls_set_index(uint word, uint shaft, uint log2_per) {
    uint bits = 32u >> log2_per;
    return (word >> (bits * (shaft & ((1u << log2_per) - 1u)))) & ((1u << bits) - 1u);
}

// Block of the unordered face pair (a, b), a < b: row a of faceToBlockMap.
INLINE uint ls_block(int a, int b) {
    return U32(a * (11 - a) / 2 + (b - a - 1));
}

// Patch index on a face from its (u, v) in [0, 1]: clamped, so points a rounding error outside
// the face land on the nearest patch (Listing 1).
INLINE uint ls_patch(uint n, float2 uv) {
    int N = I32(n);
    int ui = max(0, min(I32(floor(uv.x * F32(N))), N - 1));
    int vi = max(0, min(I32(floor(uv.y * F32(N))), N - 1));
    return U32(N * vi + ui);
}

// (u, v) of a cell-local point on a face of the given axis.
INLINE float2 ls_face_uv(float3 q, int axis) {
    return make_float2(comp3(q, (axis + 1) % 3), comp3(q, (axis + 2) % 3));
}

// Listing 1: shaft id within a cell from start/end face and the patch coordinates there.
INLINE uint ls_shaft_id(uint n, int face_s, float2 uv_s, int face_e, float2 uv_e) {
    uint ps = ls_patch(n, uv_s);
    uint pe = ls_patch(n, uv_e);
    uint n2 = n * n;
    if (face_s > face_e) return n2 * n2 * ls_block(face_e, face_s) + n2 * pe + ps;
    return n2 * n2 * ls_block(face_s, face_e) + n2 * ps + pe;
}

// The ray's chord through the unit cell with min corner `cell` (grid space) and its shaft, for a
// traversal that meets the cell on its own (svo-ls / esvo-ls leaves, Algorithm 3: entry and exit
// face and patch computed per leaf; grid-ls takes them from the grid walk's step instead).
// The chord is the ray's line through the cell, also when the origin lies inside: the shaft of
// the whole chord holds the part the ray covers. og, dg: ray in grid space; inv = 1 / dg with
// safe_rcp (an axis the ray does not move along is never an entry or exit axis).
// t_in / t_out: where the line enters and leaves the cell (t_in > t_out: it misses the cell).
STRUCT(LsChord) { uint shaft; float t_in; float t_out; };

INLINE LsChord ls_chord(uint n, float3 og, float3 dg, float3 inv, int3 cell) {
    float3 lo = make_float3(F32(cell.x), F32(cell.y), F32(cell.z));
    float ex = dg.x == 0.0f ? -INF_F : (lo.x + (dg.x > 0.0f ? 0.0f : 1.0f) - og.x) * inv.x;
    float ey = dg.y == 0.0f ? -INF_F : (lo.y + (dg.y > 0.0f ? 0.0f : 1.0f) - og.y) * inv.y;
    float ez = dg.z == 0.0f ? -INF_F : (lo.z + (dg.z > 0.0f ? 0.0f : 1.0f) - og.z) * inv.z;
    float xx = dg.x == 0.0f ? INF_F : (lo.x + (dg.x > 0.0f ? 1.0f : 0.0f) - og.x) * inv.x;
    float xy = dg.y == 0.0f ? INF_F : (lo.y + (dg.y > 0.0f ? 1.0f : 0.0f) - og.y) * inv.y;
    float xz = dg.z == 0.0f ? INF_F : (lo.z + (dg.z > 0.0f ? 1.0f : 0.0f) - og.z) * inv.z;
    int axis_in = (ex >= ey && ex >= ez) ? 0 : (ey >= ez ? 1 : 2);
    int axis_out = (xx <= xy && xx <= xz) ? 0 : (xy <= xz ? 1 : 2);
    LsChord ch;
    ch.t_in = max(ex, max(ey, ez));
    ch.t_out = min(xx, min(xy, xz));
    // Face 2a + side: the ray enters an axis it runs up through side 0 and leaves it through side 1.
    int face_in = 2 * axis_in + (comp3(dg, axis_in) > 0.0f ? 0 : 1);
    int face_out = 2 * axis_out + (comp3(dg, axis_out) > 0.0f ? 1 : 0);
    float2 uv_in = ls_face_uv(og + dg * ch.t_in - lo, axis_in);
    float2 uv_out = ls_face_uv(og + dg * ch.t_out - lo, axis_out);
    ch.shaft = ls_shaft_id(n, face_in, uv_in, face_out, uv_out);
    return ch;
}

// Corner k (0..3) of patch p on face f, cell-local.
INLINE float3 ls_patch_corner(uint n, int face, uint p, int k) {
    int axis = face / 2;
    float side = F32(face % 2);
    float u = F32(I32(p % n) + (k & 1)) / F32(n);
    float v = F32(I32(p / n) + (k >> 1)) / F32(n);
    if (axis == 0) return make_float3(side, u, v);
    if (axis == 1) return make_float3(v, side, u);
    return make_float3(u, v, side);
}

// Faces and patches of a shaft id (the inverse of ls_shaft_id for fa < fb).
STRUCT(LsShaft) { int fa; int fb; uint pa; uint pb; };

INLINE LsShaft ls_decode(uint n, uint shaft) {
    uint n2 = n * n;
    uint block = shaft / (n2 * n2);
    uint rest = shaft % (n2 * n2);
    LsShaft sh;
    sh.fa = 0;
    sh.fb = 1;
    for (int a = 0; a < 6; ++a)
        for (int b = a + 1; b < 6; ++b)
            if (ls_block(a, b) == block) { sh.fa = a; sh.fb = b; }
    sh.pa = rest / n2;
    sh.pb = rest % n2;
    return sh;
}

// Corner k (0..7) of the shaft's hull: patch a's corners 0..3, then patch b's.
INLINE float3 ls_hull_corner(uint n, LsShaft sh, int k) {
    return k < 4 ? ls_patch_corner(n, sh.fa, sh.pa, k) : ls_patch_corner(n, sh.fb, sh.pb, k - 4);
}

// The shaft's faces and patches from its two mask indices (face * N^2 + patch, ls_planes' axis
// slots): two divisions where ls_decode loops over the face pairs.
INLINE LsShaft ls_shaft_of_masks(uint n, uint mask_a, uint mask_b) {
    LsShaft sh;
    sh.fa = I32(mask_a / (n * n));
    sh.fb = I32(mask_b / (n * n));
    sh.pa = mask_a % (n * n);
    sh.pb = mask_b % (n * n);
    return sh;
}

// Plane (n.xyz, w) of a shaft facet: a point p is outside by dot(n, p) + w (unit n).
INLINE float ls_plane_dist(float4 pl, float3 p) {
    return dot(pl.xyz, p) + pl.w;
}

#ifdef KERNEL_ls_planes
// ---- Shaft volumes --------------------------------------------------------------------------
// The shaft volume is the convex hull of its two patches (every segment from a point of one patch
// to a point of the other lies in it, and a ray through both patches runs exactly along such a
// segment inside the cell). Its facets are found by brute force over the 56 corner triples: a
// triple spans a facet plane when all 8 corners lie on one side. The planes depend only on N and
// the shaft, not on the cell, so one small kernel computes them for all cells. Unused slots hold
// (0, 0, 0, -1): every point is inside them.
INLINE void ls_planes_kernel(CTX_PARAM uint shaft) {
    uint n = V(ls_n);
    LsShaft sh = ls_decode(n, shaft);
    float3 P[8];
    for (int k = 0; k < 8; ++k) P[k] = ls_hull_corner(n, sh, k);
    float4 planes[LS_MAX_PLANES];
    int count = 0;
    for (int i = 0; i < 8; ++i)
        for (int j = i + 1; j < 8; ++j)
            for (int k = j + 1; k < 8; ++k) {
                float3 nrm = cross(P[j] - P[i], P[k] - P[i]);
                float len = length(nrm);
                if (len < 1e-6f) continue;  // collinear corners span no plane
                nrm = nrm / len;
                float w = -dot(nrm, P[i]);
                float dmin = INF_F;
                float dmax = -INF_F;
                for (int q = 0; q < 8; ++q) {
                    float d = dot(nrm, P[q]) + w;
                    dmin = min(dmin, d);
                    dmax = max(dmax, d);
                }
                if (dmax > 1e-5f && dmin < -1e-5f) continue;  // corners on both sides: no facet
                if (dmax > 1e-5f) { nrm = -nrm; w = -w; }      // orient the normal outwards
                int dup = 0;
                for (int q = 0; q < count; ++q) {
                    float4 o = planes[q];
                    if (fabs(o.x - nrm.x) + fabs(o.y - nrm.y) + fabs(o.z - nrm.z) + fabs(o.w - w) < 1e-4f) dup = 1;
                }
                // More facets than slots cannot happen for these hulls; dropping one would only
                // enlarge the volume (still conservative).
                if (dup == 0 && count < LS_MAX_PLANES) {
                    planes[count] = make_float4(nrm.x, nrm.y, nrm.z, w);
                    count += 1;
                }
            }
    uint pb = shaft * U32(LS_PLANE_SLOTS);
    for (int q = 0; q < LS_MAX_PLANES; ++q)
        V(ls_planes)[pb + U32(q)] = q < count ? planes[q] : make_float4(0.0f, 0.0f, 0.0f, -1.0f);
    float3 ca = (P[0] + P[3]) * 0.5f;
    float3 cb = (P[4] + P[7]) * 0.5f;
    V(ls_planes)[pb + U32(LS_MAX_PLANES)] = make_float4(ca.x, ca.y, ca.z, F32(U32(sh.fa) * n * n + sh.pa));
    V(ls_planes)[pb + U32(LS_MAX_PLANES) + 1u] = make_float4(cb.x, cb.y, cb.z, F32(U32(sh.fb) * n * n + sh.pb));
}
#endif  // shaft volumes

#define LS_MAX_EDGES 28  // one per pair of the 8 facet planes (a polytope of 8 facets has at most 18
                         // edges; float noise at a vertex of 4 facets may add tiny ones: none is dropped)
// Per shaft: (count, R, 0, 0), then each edge's two ends, then the 8 corners of the shaft's hull
// (its patches' corners). R bounds how far the pushed volume reaches beyond the hull: the largest
// distance from an edge end (the volume's vertices) to its nearest corner.
#define LS_EDGE_CORNERS (1 + 2 * LS_MAX_EDGES)  // where the corners start
#define LS_EDGE_SLOTS (LS_EDGE_CORNERS + 8)

#ifdef KERNEL_ls_edges
// ---- The edges of the shaft volume pushed out by ls_eps (the "edges" exact test) -------------
// The volume {x : dist(pl, x) <= eps for every facet plane} (what the clipper of ls_clip_meets
// clips against). Each pair of non-parallel facets whose planes meet along a stretch inside the
// other facets' half-spaces gives an edge: the line of the two pushed planes, clipped to the
// others (Liang-Barsky). Once per N and shaft, like the planes. R also goes to ls_reach (one float
// per shaft), whose largest sizes the masks' cull margin (ls_masks_kernel) whichever exact test
// runs; with LS_REACH_ONLY (another exact test) the table is not written.
INLINE void ls_edges_kernel(CTX_PARAM uint shaft) {
    float eps = V(ls_eps);
    uint pb = shaft * U32(LS_PLANE_SLOTS);
    uint base = shaft * U32(LS_EDGE_SLOTS);
    uint n = V(ls_n);
    LsShaft sh = ls_decode(n, shaft);
    float3 P[8];  // the hull's corners: its patches'
    for (int k = 0; k < 8; ++k) P[k] = ls_hull_corner(n, sh, k);
    float reach = 0.0f;  // R: the largest distance from an edge end to its nearest corner
    uint count = 0u;
    for (int i = 0; i < LS_MAX_PLANES; ++i) {
        float4 pi = V(ls_planes)[pb + U32(i)];
        for (int j = i + 1; j < LS_MAX_PLANES; ++j) {
            float4 pj = V(ls_planes)[pb + U32(j)];
            float3 d = cross(pi.xyz, pj.xyz);
            float det = dot(d, d);  // 1 - (n_i . n_j)^2 for unit normals; 0 for unused slots
            if (det < 1e-8f) continue;
            // The point of the line in span(n_i, n_j): n_i . x = eps - w_i, n_j . x = eps - w_j.
            float g = dot(pi.xyz, pj.xyz);
            float ci = eps - pi.w, cj = eps - pj.w;
            float3 x0 = pi.xyz * ((ci - g * cj) / det) + pj.xyz * ((cj - g * ci) / det);
            float2 r = make_float2(-INF_F, INF_F);
            for (int k = 0; k < LS_MAX_PLANES; ++k) {
                if (k == i || k == j) continue;
                float4 pk = V(ls_planes)[pb + U32(k)];
                float sa = dot(pk.xyz, d);
                float sb = ls_plane_dist(pk, x0) - eps;  // inside: sb + t sa <= 0
                if (sa > 0.0f) r.y = min(r.y, -sb / sa);
                else if (sa < 0.0f) r.x = max(r.x, -sb / sa);
                else if (sb > 0.0f) r = make_float2(1.0f, 0.0f);
            }
            if (r.x < r.y && count < U32(LS_MAX_EDGES)) {
                float3 e0 = x0 + d * r.x;
                float3 e1 = x0 + d * r.y;
#ifndef LS_REACH_ONLY
                V(ls_edges)[base + 1u + 2u * count] = make_float4(e0.x, e0.y, e0.z, 0.0f);
                V(ls_edges)[base + 2u + 2u * count] = make_float4(e1.x, e1.y, e1.z, 0.0f);
#endif
                float n0 = INF_F, n1 = INF_F;
                for (int k = 0; k < 8; ++k) {
                    n0 = min(n0, length(e0 - P[k]));
                    n1 = min(n1, length(e1 - P[k]));
                }
                reach = max(reach, max(n0, n1));
                count += 1u;
            }
        }
    }
    // 1 % and 1e-6 over what float32 measured: a bound, not an estimate.
    reach = reach * 1.01f + 1e-6f;
    V(ls_reach)[shaft] = reach;
#ifndef LS_REACH_ONLY
    uint corners = base + U32(LS_EDGE_CORNERS);
    for (int k = 0; k < 8; ++k) V(ls_edges)[corners + U32(k)] = make_float4(P[k].x, P[k].y, P[k].z, 0.0f);
    V(ls_edges)[base] = make_float4(F32(count), reach, 0.0f, 0.0f);
#endif
}
#endif

#if defined(KERNEL_ls_count) || defined(KERNEL_ls_fill) || defined(KERNEL_ls_masks)
#define LS_CULL_BITS 0x3ffffffu     // bits 0..25: 13 axes x (below, above)
#define LS_MEETS_PATCH 0x4000000u   // the triangle crosses the patch
#define LS_ABOVE_PLANE 0x8000000u   // the triangle covers the cell and the patch lies above its plane
#define LS_BELOW_PLANE 0x10000000u  // ... below it

// fn(lo, hi, key): the largest cell c in [lo, hi) with buf[c] <= key, buf being an exclusive scan
// over the cells (ls_ref_bases: a mask row's cell; ls_item_bases: a work item's cell).
#define LS_CELL_SEARCH(fn, buf) INLINE uint fn(CTX_PARAM uint lo, uint hi, uint key) { \
    while (hi - lo > 1u) { uint mid = lo + (hi - lo) / 2u; if (V(buf)[mid] <= key) lo = mid; else hi = mid; } \
    return lo; }
LS_CELL_SEARCH(ls_ref_cell, ls_ref_bases)
#endif

#if defined(KERNEL_ls_count) || defined(KERNEL_ls_fill)
LS_CELL_SEARCH(ls_item_cell, ls_item_bases)
#endif

// A fill with the count's pair bits (LS_PAIR_BITS) tests nothing and binds no scene or masks.
#if defined(KERNEL_ls_count) || (defined(KERNEL_ls_fill) && !defined(LS_PAIR_BITS))
// ---- Triangle / shaft test ------------------------------------------------------------------
// Conservative: the shaft's facet planes are pushed out by ls_eps (cell-local units), so float
// rounding in the build or in the traversal's patch lookup never drops a triangle the shaft meets.
// Cheap outcomes first (ls_facet_verdict, below): all corners outside one plane -> no; all inside every
// plane -> yes; otherwise the exact test the build compiles in (linespace.py: exact_test): by
// default "edges" (LS_EXACT_EDGES: a triangle edge in the pushed volume or a volume edge through
// the triangle, ls_volume_edge_meets); or clip the triangle against the planes (Sutherland-Hodgman,
// thesis 3.3.3) and see whether anything is left (LS_CLIP_SH); or the separating-axis test
// ls_sat_meets. The quick test uses the 8 planes as named values: no variable-indexed
// arrays, which llvmpipe handles slowly.
INLINE int ls_clip_meets(CTX_PARAM uint shaft, float3 a, float3 b, float3 c, float eps) {
    float3 poly[LS_MAX_POLY];
    float3 next[LS_MAX_POLY];
    poly[0] = a;
    poly[1] = b;
    poly[2] = c;
    int n = 3;
    for (int q = 0; q < LS_MAX_PLANES; ++q) {
        float4 pl = LD_F4(ls_planes, shaft * U32(LS_PLANE_SLOTS) + U32(q));
        int m = 0;
        for (int i = 0; i < n; ++i) {
            float3 cur = poly[i];
            float3 nxt = poly[(i + 1) % n];
            float dc = ls_plane_dist(pl, cur) - eps;
            float dn = ls_plane_dist(pl, nxt) - eps;
            if (dc <= 0.0f && m < LS_MAX_POLY) { next[m] = cur; m += 1; }
            if ((dc <= 0.0f) != (dn <= 0.0f) && m < LS_MAX_POLY) {
                next[m] = cur + (nxt - cur) * (dc / (dc - dn));
                m += 1;
            }
        }
        if (m == 0) return 0;
        for (int i = 0; i < m; ++i) poly[i] = next[i];
        n = m;
    }
    return 1;
}

// Separating-axis test of the triangle against the shaft volume (convex hull of the corners
// P0..P3 of one patch and Q0..Q3 of the other) for the triangles the facet planes leave undecided.
// Exact like clipping the triangle against the shaft (Sutherland-Hodgman), but without the
// variable-indexed polygon arrays that make llvmpipe 10x slower. Axes: the triangle normal and
// the cross products of the triangle edges with every hull edge direction (the hull's edges are
// patch sides, i.e. coordinate axes, or join a P corner to a Q corner: a superset never separates
// wrongly); the facet normals were tested before. Margin eps * |axis|: conservative, scale-free.
INLINE int ls_sep(float3 ax, float3 a, float3 b, float3 c, float3 P0, float3 P1, float3 P2, float3 P3,
                  float3 Q0, float3 Q1, float3 Q2, float3 Q3, float eps) {
    float ta = dot(ax, a), tb = dot(ax, b), tc = dot(ax, c);
    float tmin = min(ta, min(tb, tc)), tmax = max(ta, max(tb, tc));
    float h0 = dot(ax, P0), h1 = dot(ax, P1), h2 = dot(ax, P2), h3 = dot(ax, P3);
    float h4 = dot(ax, Q0), h5 = dot(ax, Q1), h6 = dot(ax, Q2), h7 = dot(ax, Q3);
    float hmin = min(min(min(h0, h1), min(h2, h3)), min(min(h4, h5), min(h6, h7)));
    float hmax = max(max(max(h0, h1), max(h2, h3)), max(max(h4, h5), max(h6, h7)));
    float m = eps * length(ax);
    return (tmin > hmax + m || tmax < hmin - m) ? 1 : 0;
}

INLINE int ls_sep_edges(float3 e, float3 a, float3 b, float3 c, float3 P0, float3 P1, float3 P2, float3 P3,
                        float3 Q0, float3 Q1, float3 Q2, float3 Q3, float eps) {
    if (ls_sep(cross(e, make_float3(1.0f, 0.0f, 0.0f)), a, b, c, P0, P1, P2, P3, Q0, Q1, Q2, Q3, eps) != 0) return 1;
    if (ls_sep(cross(e, make_float3(0.0f, 1.0f, 0.0f)), a, b, c, P0, P1, P2, P3, Q0, Q1, Q2, Q3, eps) != 0) return 1;
    if (ls_sep(cross(e, make_float3(0.0f, 0.0f, 1.0f)), a, b, c, P0, P1, P2, P3, Q0, Q1, Q2, Q3, eps) != 0) return 1;
    for (int i = 0; i < 4; ++i) {
        float3 p = i == 0 ? P0 : (i == 1 ? P1 : (i == 2 ? P2 : P3));
        if (ls_sep(cross(e, Q0 - p), a, b, c, P0, P1, P2, P3, Q0, Q1, Q2, Q3, eps) != 0) return 1;
        if (ls_sep(cross(e, Q1 - p), a, b, c, P0, P1, P2, P3, Q0, Q1, Q2, Q3, eps) != 0) return 1;
        if (ls_sep(cross(e, Q2 - p), a, b, c, P0, P1, P2, P3, Q0, Q1, Q2, Q3, eps) != 0) return 1;
        if (ls_sep(cross(e, Q3 - p), a, b, c, P0, P1, P2, P3, Q0, Q1, Q2, Q3, eps) != 0) return 1;
    }
    return 0;
}

INLINE int ls_sat_meets(uint n, LsShaft sh, float3 a, float3 b, float3 c, float eps) {
    float3 P0 = ls_patch_corner(n, sh.fa, sh.pa, 0), P1 = ls_patch_corner(n, sh.fa, sh.pa, 1);
    float3 P2 = ls_patch_corner(n, sh.fa, sh.pa, 2), P3 = ls_patch_corner(n, sh.fa, sh.pa, 3);
    float3 Q0 = ls_patch_corner(n, sh.fb, sh.pb, 0), Q1 = ls_patch_corner(n, sh.fb, sh.pb, 1);
    float3 Q2 = ls_patch_corner(n, sh.fb, sh.pb, 2), Q3 = ls_patch_corner(n, sh.fb, sh.pb, 3);
    if (ls_sep(cross(b - a, c - a), a, b, c, P0, P1, P2, P3, Q0, Q1, Q2, Q3, eps) != 0) return 0;
    if (ls_sep_edges(b - a, a, b, c, P0, P1, P2, P3, Q0, Q1, Q2, Q3, eps) != 0) return 0;
    if (ls_sep_edges(c - b, a, b, c, P0, P1, P2, P3, Q0, Q1, Q2, Q3, eps) != 0) return 0;
    if (ls_sep_edges(a - c, a, b, c, P0, P1, P2, P3, Q0, Q1, Q2, Q3, eps) != 0) return 0;
    return 1;
}

#ifdef LS_EXACT_EDGES
#define LS_IN_TRIANGLE_TOL 1e-5f  // cell-local units: 1 % of ls_eps, far above float32 noise at 1
// 1 when x (in the triangle's plane) lies in triangle a b c of normal nrm, or within
// LS_IN_TRIANGLE_TOL of it in the plane (edge function e = |edge| |nrm| x the signed distance).
INLINE int ls_edge_side_ok(float3 nrm, float3 v, float3 w, float3 x) {
    float3 e = w - v;
    float f = dot(cross(e, x - v), nrm);
    return (f >= 0.0f || f * f <= LS_IN_TRIANGLE_TOL * LS_IN_TRIANGLE_TOL * dot(e, e) * dot(nrm, nrm)) ? 1 : 0;
}
INLINE int ls_in_triangle(float3 nrm, float3 a, float3 b, float3 c, float3 x) {
    return (ls_edge_side_ok(nrm, a, b, x) != 0 && ls_edge_side_ok(nrm, b, c, x) != 0 &&
            ls_edge_side_ok(nrm, c, a, x) != 0) ? 1 : 0;
}

// The second half of the "edges" exact test, after no triangle edge met the pushed volume P
// (ls_segment_in_shaft with eps): a triangle meets a convex polytope iff one of its edges meets
// the polytope or one of the polytope's edges meets the triangle. The same predicate as clipping
// against the pushed planes (ls_clip_meets), without its variable-indexed polygon arrays.
// With the first half known to be 0, ONE point decides: the cut C of P with the triangle's plane
// is convex and no triangle edge meets it, so C lies wholly inside the triangle or wholly outside
// (a segment from a point of C inside to one outside would cross an edge). Any point of C will
// do, found cheapest first: (1) where the shaft's axis (centre of patch a to centre of patch b,
// ca -> cb, inside the shaft) crosses the plane: no loads; (2) else on the segment from ca to a
// hull corner on the plane's other side (the hull of the two patches lies in the shaft); (3) else,
// the hull lying wholly on one side, the plane misses P when it is further from the hull than P
// reaches beyond it (R, ls_edges_kernel); (4) else the first polytope edge that crosses the
// plane gives a point of P's boundary in it, and where none does the plane misses P. On Sponza
// 64³ N=3, 30.3 M pairs reach this test: (1) decides 16.4 M of them, 5.0 M miss the plane.
// Float noise can make the first half miss an edge that only grazes C; then C lies inside the
// triangle up to that noise, hence the tolerance of ls_in_triangle (conservative: it may keep a
// triangle within 1e-5 of P, inside the reference tests' band around eps).
INLINE int ls_volume_edge_meets(CTX_PARAM uint shaft, float3 a, float3 b, float3 c, float3 ca, float3 cb) {
    float3 nrm = cross(b - a, c - a);
    float nn = dot(nrm, nrm);
    if (nn == 0.0f) return 0;  // a degenerate triangle is its edges: tested before
    float da = dot(nrm, ca - a);
    float db = dot(nrm, cb - a);
    if ((da <= 0.0f && db >= 0.0f) || (da >= 0.0f && db <= 0.0f))
        return ls_in_triangle(nrm, a, b, c, da == db ? ca : ca + (cb - ca) * (da / (da - db)));
    // The axis lies on one side (da != 0). A hull corner on the other side gives a point of the
    // hull in the plane, on the segment from ca to that corner.
    uint base = shaft * U32(LS_EDGE_SLOTS);
    uint corners = base + U32(LS_EDGE_CORNERS);
    float side = da > 0.0f ? 1.0f : -1.0f;
    float nearest = INF_F;  // the hull's least distance to the plane (x |nrm|), on ca's side
    for (uint k = 0u; k < 8u; ++k) {
        float3 q = LD_F4(ls_edges, corners + k).xyz;
        float dq = dot(nrm, q - a);
        if (side * dq <= 0.0f) return ls_in_triangle(nrm, a, b, c, ca + (q - ca) * (da / (da - dq)));
        nearest = min(nearest, side * dq);
    }
    // The hull lies beyond the plane; the pushed volume reaches no further than R past the hull.
    float reach = LD_F4(ls_edges, base).y;
    if (nearest * nearest > reach * reach * nn) return 0;
    uint count = U32(LD_F4(ls_edges, base).x);
    for (uint e = 0u; e < count; ++e) {
        float3 p = LD_F4(ls_edges, base + 1u + 2u * e).xyz;
        float3 q = LD_F4(ls_edges, base + 2u + 2u * e).xyz;
        float dp = dot(nrm, p - a);
        float dq = dot(nrm, q - a);
        if ((dp > 0.0f && dq > 0.0f) || (dp < 0.0f && dq < 0.0f)) continue;
        // dp == dq (both 0): the edge lies in the plane, and p is a point of C.
        float3 x = dp == dq ? p : p + (q - p) * (dp / (dp - dq));
        return ls_in_triangle(nrm, a, b, c, x);
    }
    return 0;  // the plane misses P
}
#endif

// ---- Build: count pass (ls_count) and fill pass (ls_fill), per (shaft, chunk) of each cell ------
// Cells: ls_cell_boxes (float4 lo, hi per cell, grid space), ls_cell_ranges (uint begin, end per
// cell into ls_cell_tris). Cell c has k_c chunks of at most ls_chunk candidates (the driver's loop
// budget, linespace.py: candidate_chunk) and 15 N^4 k_c work items from ls_item_bases[c], shaft-
// major: item ls_item_bases[c] + shaft * k_c + chunk. A work item walks its chunk in list order,
// and the fill puts each chunk's candidates right after the previous chunk's (ls_item_first), so it writes
// every shaft's list in cell-list order: no atomics, deterministic, and the same lists as one item
// per shaft. A dispatch covers the cells [ls_cell_first, ls_cell_end) of one
// batch (item ls_item_base + gid); their patch masks (ls_masks_kernel) start at dense reference
// ls_ref_base.
//
// Per (shaft, triangle) pair, cheapest decision first (docs/linespace-build.md has the figures):
// 1. cull: the AND of the triangle's masks (ls_masks_kernel) of the shaft's two patches; a common
//    bit is an axis on which both patches, hence their hull, lie beyond the triangle by
//    ls_cull_margin (ls_masks_kernel), beyond the reach of anything the tests of 3 accept;
// 2. certain: the triangle crosses one of the two patches (LS_MEETS_PATCH), or it covers the
//    cell's cut with its plane and the patches lie on opposite sides (LS_ABOVE/BELOW_PLANE), or
//    after the facet planes of 3 left it undecided, one of its edges runs inside the shaft
//    (ls_segment_in_shaft): the triangle meets the shaft volume itself, which every test of 3
//    accepts with the margin ls_eps to spare;
// 3. otherwise the facet planes (ls_facet_verdict) and the exact test, as before.
// 1 and 2 only skip work whose outcome they know: the lists are those of 3 alone (the tests
// compare them with the numpy reference of lsbench/oracle/reference.py: shaft_candidates, and
// docs/linespace-build.md with the lists of the build before 1 and 2 on Sponza).

// Does the triangle meet the shaft? Steps 1-3 above, for a run of up to 32 candidates of a cell
// (ls_run_meets), whose masks of the shaft's patches are ls_masks[ra] and ls_masks[rb]
// (ls_masks_kernel: a cell's masks patch-major) and whose cell-local triangles are references
// tri_ref.. (LS_TRI_ARGS), as bits of the candidates that meet it. Each step is a loop of its own
// over what the step before left, in one of two forms: vector blocks where work items run one
// after the other (LS_CULL_RUNS: PoCL), loops over the bits left where the lanes are shafts
// (llvmpipe, GPUs) (docs/linespace-build.md).
#if defined(LS_CULL_RUNS) && !defined(LS_RUN_LANES)
#define LS_RUN_LANES 8u  // pairs per block of ls_run_meets' vector loops (linespace.py sets it): 8-wide vectors
#endif
#if defined(LS_PAIR_QUEUE) && (!defined(KERNEL_ls_count) || !defined(LS_PAIR_BITS) || defined(LS_CULL_RUNS) || LS_PAIR_QUEUE > 128u)
#error "LS_PAIR_QUEUE: the count with pair bits where the lanes are shafts, at most 128 pairs (ls_count_queued)"
#endif

// Step 2's certain bits: the triangle crosses one of the two patches, or covers the cell's cut
// with its plane and the patches lie on opposite sides.
INLINE int ls_masks_certain(uint ma, uint mb) {
    return (((ma | mb) & LS_MEETS_PATCH) != 0u || ((ma & LS_ABOVE_PLANE) != 0u && (mb & LS_BELOW_PLANE) != 0u) ||
            ((ma & LS_BELOW_PLANE) != 0u && (mb & LS_ABOVE_PLANE) != 0u)) ? 1 : 0;
}

// Reference r's cell-local triangle (ls_masks_kernel writes it): ls_local_tris[3 r .. 3 r + 2],
// (a, 0), (b, 0), (c, 0). Where the pair steps are vector loops (LS_CULL_RUNS, ls_run_meets)
// linespace.py binds the buffer as plain floats, coordinate-major: coordinate c (a.x, a.y, .., c.z)
// of reference r at c * ls_tri_stride + r, so a block of consecutive candidates loads each
// coordinate as one contiguous vector (ls_run_meets), where 12 floats per reference made it 9
// gathers (Sponza grid-ls 64³ N=3: ls_count 3.39 -> 3.17 s, docs/linespace-build.md). Scalar forms
// keep those loops free of vector-typed values, which LLVM's loop vectorizer does not take.
// Elsewhere the vec4 loads stay (llvmpipe's count took 10 % longer with 9 float loads). The
// indices are ints: a signed 32-bit index lets x86 gather with 32-bit offsets (vgatherdps,
// ls_run_meets' exact test and other gathers), where an unsigned one, widened to 64 bits, took two
// vgatherqps (Sponza grid-ls 64³ N=3: ls_count 4.16-4.31 -> 3.68-3.72 s). The buffer holds a
// batch's references, 9 x 4 bytes each (plus a block of padding) in a buffer the driver allows
// (linespace.py: plan_build, 48 bytes per reference), so 9 ls_tri_stride < 2^31.
#ifdef LS_CULL_RUNS
#define LS_TRI_AT(c, r) LD_F(ls_local_tris, I32((c) * V(ls_tri_stride) + (r)))
#define LS_TRI_ARGS(r) LS_TRI_AT(0u, r), LS_TRI_AT(1u, r), LS_TRI_AT(2u, r), LS_TRI_AT(3u, r), LS_TRI_AT(4u, r), \
    LS_TRI_AT(5u, r), LS_TRI_AT(6u, r), LS_TRI_AT(7u, r), LS_TRI_AT(8u, r)
#else
#define LS_TRI_ARGS(r) LD_F4(ls_local_tris, 3u * (r)).x, LD_F4(ls_local_tris, 3u * (r)).y, LD_F4(ls_local_tris, 3u * (r)).z, \
    LD_F4(ls_local_tris, 3u * (r) + 1u).x, LD_F4(ls_local_tris, 3u * (r) + 1u).y, LD_F4(ls_local_tris, 3u * (r) + 1u).z, \
    LD_F4(ls_local_tris, 3u * (r) + 2u).x, LD_F4(ls_local_tris, 3u * (r) + 2u).y, LD_F4(ls_local_tris, 3u * (r) + 2u).z
#endif
#define LS_TRI_PARAMS float ax, float ay, float az, float bx, float by, float bz, float cx, float cy, float cz
#define LS_PLANE_PARAMS float4 p0, float4 p1, float4 p2, float4 p3, float4 p4, float4 p5, float4 p6, float4 p7

INLINE float ls_dist3(float4 pl, float x, float y, float z) {
    return pl.x * x + pl.y * y + pl.z * z + pl.w;
}

// One facet plane of step 3 for the triangle's corners (distances past the plane pushed out by
// eps): sep > 0 once a plane has all three corners outside it; wa/wb/wc each corner's largest
// distance, so a corner lies inside every plane where its w <= 0. (The same comparisons as
// counting each plane's outside corners, in fewer operations: ls_count 3.39 -> 3.34 s.)
#define LS_FACET_STEP(pl) { \
    float da = ls_dist3(pl, ax, ay, az) - eps, db = ls_dist3(pl, bx, by, bz) - eps, dc = ls_dist3(pl, cx, cy, cz) - eps; \
    sep = max(sep, min(da, min(db, dc))); \
    wa = max(wa, da); wb = max(wb, db); wc = max(wc, dc); }

// Step 3's facet planes: 0 separated by one of them, 1 inside all, 2 undecided. With the edges
// test (LS_EXACT_EDGES) also 1 where a corner lies inside all of them: the triangle then meets the
// pushed volume, and the edges test would accept it by the segments from that corner (at t = 0),
// so the decision is the same and the pair skips the edge clipping (Sponza 64³ N=3: 37.7 M of the
// 73.5 M pairs that the triangle edges accepted).
// A shaft's hull has 5, 6 or 8 facets (N = 3: 252, 675 and 288 of the 1,215 shafts); the slots
// past them hold planes every point is inside (ls_planes_kernel), which decide nothing. Where a
// work item is one shaft (LS_CULL_RUNS) the pair loops run the variant for its facets only
// (ls_facet_verdict5 / 6, ls_edges_in_shaft5 / 6: the same decisions, fewer planes; Sponza grid-ls
// 64³ N=3 PoCL ls_count 3.50-3.73 -> 3.37-3.41 s, docs/linespace-build.md).
#ifdef LS_EXACT_EDGES
#define LS_FACET_INSIDE(wa, wb, wc) min(wa, min(wb, wc))  // a corner inside every plane
#else
#define LS_FACET_INSIDE(wa, wb, wc) max(wa, max(wb, wc))  // every corner inside every plane
#endif
// step(p0) .. step(p4), .. step(p5), .. step(p7): a step per facet slot of a 5-, 6- or 8-facet hull
#define LS_PLANES5(step) step(p0) step(p1) step(p2) step(p3) step(p4)
#define LS_PLANES6(step) LS_PLANES5(step) step(p5)
#define LS_PLANES8(step) LS_PLANES6(step) step(p6) step(p7)
#define LS_FACET_VERDICT(name, steps) INLINE int name(LS_TRI_PARAMS, float eps, LS_PLANE_PARAMS) { \
    float sep = -INF_F; \
    float wa = -INF_F, wb = -INF_F, wc = -INF_F; \
    steps \
    return sep > 0.0f ? 0 : (LS_FACET_INSIDE(wa, wb, wc) <= 0.0f ? 1 : 2); }
LS_FACET_VERDICT(ls_facet_verdict, LS_PLANES8(LS_FACET_STEP))
#ifdef LS_CULL_RUNS
LS_FACET_VERDICT(ls_facet_verdict6, LS_PLANES6(LS_FACET_STEP))
LS_FACET_VERDICT(ls_facet_verdict5, LS_PLANES5(LS_FACET_STEP))
#endif

// 1 when some point of the segment (x0, y0, z0) -> (x1, y1, z1) lies in the shaft volume with its
// facet planes pushed out by m (m = 0: the shaft itself, which the triangle then meets; m = eps:
// the volume the exact tests accept). Liang-Barsky; the division only where the segment crosses
// the plane (SIMD lanes that all stay on one side skip it).
#define LS_CLIP_STEP(pl) { \
    float da = ls_dist3(pl, x0, y0, z0) - m, db = ls_dist3(pl, x1, y1, z1) - m; \
    gone = gone || (da > 0.0f && db > 0.0f); \
    if ((da > 0.0f) != (db > 0.0f)) { \
        float t = da / (da - db); \
        if (da > 0.0f) r0 = max(r0, t); else r1 = min(r1, t); } }
#define LS_SEGMENT_IN_SHAFT(name, steps) \
    INLINE int name(LS_PLANE_PARAMS, float x0, float y0, float z0, float x1, float y1, float z1, float m) { \
    float r0 = 0.0f, r1 = 1.0f; \
    bool gone = false; \
    steps \
    return !gone && r0 <= r1 ? 1 : 0; }
LS_SEGMENT_IN_SHAFT(ls_segment_in_shaft, LS_PLANES8(LS_CLIP_STEP))
#ifdef LS_CULL_RUNS
LS_SEGMENT_IN_SHAFT(ls_segment_in_shaft6, LS_PLANES6(LS_CLIP_STEP))
LS_SEGMENT_IN_SHAFT(ls_segment_in_shaft5, LS_PLANES5(LS_CLIP_STEP))
#endif

// After the facet planes left it undecided: with LS_EXACT_EDGES the exact test's first half (a
// triangle edge in the volume pushed out by eps), else step 2's last certain case (an edge in the
// shaft itself). 1 decides "meets"; 0 leaves the pair to the exact test.
#ifdef LS_EXACT_EDGES
#define LS_EDGE_MARGIN eps
#else
#define LS_EDGE_MARGIN 0.0f
#endif
#define LS_EDGES_IN_SHAFT(name, segment) INLINE int name(LS_TRI_PARAMS, float eps, LS_PLANE_PARAMS) { \
    float m = LS_EDGE_MARGIN; \
    return (segment(p0, p1, p2, p3, p4, p5, p6, p7, ax, ay, az, bx, by, bz, m) != 0 || \
            segment(p0, p1, p2, p3, p4, p5, p6, p7, bx, by, bz, cx, cy, cz, m) != 0 || \
            segment(p0, p1, p2, p3, p4, p5, p6, p7, cx, cy, cz, ax, ay, az, m) != 0) ? 1 : 0; }
LS_EDGES_IN_SHAFT(ls_edges_in_shaft, ls_segment_in_shaft)
#ifdef LS_CULL_RUNS
LS_EDGES_IN_SHAFT(ls_edges_in_shaft6, ls_segment_in_shaft6)
LS_EDGES_IN_SHAFT(ls_edges_in_shaft5, ls_segment_in_shaft5)
#endif

// The exact test the build compiles in, for a pair the steps before left.
INLINE int ls_exact_meets(CTX_PARAM uint n, LsShaft sh, uint shaft, LS_TRI_PARAMS, float eps, float3 ca, float3 cb) {
    float3 a = make_float3(ax, ay, az), b = make_float3(bx, by, bz), c = make_float3(cx, cy, cz);
#ifdef LS_EXACT_EDGES
    return ls_volume_edge_meets(CTX_ARG shaft, a, b, c, ca, cb);  // second half: a volume edge through it
#elif defined(LS_CLIP_SH)
    return ls_clip_meets(CTX_ARG shaft, a, b, c, eps);  // Sutherland-Hodgman
#else
    return ls_sat_meets(n, sh, a, b, c, eps);  // separating axes
#endif
}

#ifndef LS_CULL_RUNS
// Steps 1-3 for a run of candidates [k0, k0 + span) (span <= 32) of a shaft, as bits k - k0 of
// the candidates that meet it, where the lanes are shafts (llvmpipe, GPUs): each step a loop over
// the bits the step before left. llvmpipe runs both sides of every branch for all its lanes
// (gallivm's if only masks them; a loop ends when no lane goes on), so one loop over the pairs
// with the steps as branches paid every step for every pair, culled or not: here a step costs as
// many iterations as the group's busiest lane has pairs for it (grid-ls glsl 128³ N=2, ls_count:
// Sponza 5.68 -> 5.24 s, BMW 5.60 -> 2.83 s; docs/linespace-build.md). On GPUs the same: a warp
// runs each step only while one of its lanes has a pair there. But gallivm also runs each loop's
// body once where no lane has an iteration, so each run pays one pass of every step: groups of
// one-chunk cells queue their pairs instead (ls_count_queued); the fill, which lists a shaft's
// candidates in order, and the cells of several chunks (full runs) use this.
// Steps 1 (cull) and 2 (certain) from the masks for a run of span <= 32 candidates whose masks of
// the shaft's patches start at ls_masks[ra] and ls_masks[rb]: (the bits of the candidates the
// masks say meet the shaft, the bits of those they leave to step 3).
INLINE uint2 ls_masks_run(CTX_PARAM uint ra, uint rb, uint span) {
    uint met = 0u;
    uint live = 0u;
    for (uint k = 0u; k < span; ++k) {
        uint ma = LD_U(ls_masks, ra + k);
        uint mb = LD_U(ls_masks, rb + k);
        if ((ma & mb & LS_CULL_BITS) == 0u) {
            if (ls_masks_certain(ma, mb) != 0) met |= 1u << k;
            else live |= 1u << k;
        }
    }
    return make_uint2(met, live);
}

INLINE uint ls_run_meets(CTX_PARAM uint ra, uint rb, uint tri_ref, uint k0, uint span, float eps, uint facets,
                         uint n, LsShaft sh, uint shaft, float3 ca, float3 cb, float4 p0, float4 p1, float4 p2,
                         float4 p3, float4 p4, float4 p5, float4 p6, float4 p7) {
    uint2 masks = ls_masks_run(CTX_ARG ra + k0, rb + k0, span);
    uint met = masks.x;
    uint live = masks.y;
    uint undecided = 0u;  // 3. facet planes
    for (; live != 0u; live &= live - 1u) {
        uint k = LOWEST_BIT(live);
        int v = ls_facet_verdict(LS_TRI_ARGS(tri_ref + k0 + k), eps, p0, p1, p2, p3, p4, p5, p6, p7);
        if (v == 1) met |= 1u << k;
        if (v == 2) undecided |= 1u << k;
    }
    uint exact = 0u;  // the triangle's edges
    for (; undecided != 0u; undecided &= undecided - 1u) {
        uint k = LOWEST_BIT(undecided);
        if (ls_edges_in_shaft(LS_TRI_ARGS(tri_ref + k0 + k), eps, p0, p1, p2, p3, p4, p5, p6, p7) != 0) met |= 1u << k;
        else exact |= 1u << k;
    }
    for (; exact != 0u; exact &= exact - 1u) {  // the exact test
        uint k = LOWEST_BIT(exact);
        if (ls_exact_meets(CTX_ARG n, sh, shaft, LS_TRI_ARGS(tri_ref + k0 + k), eps, ca, cb) != 0) met |= 1u << k;
    }
    return met;
}
#else
// Steps 1-3 for a run of candidates [k0, k0 + span) (span <= 32) of a shaft, as bits k - k0 of
// the candidates that meet it. Where work items run one after the other (PoCL) each step is a
// loop of its own over blocks of LS_RUN_LANES consecutive candidates, the pairs it decides kept
// as bits: without a branch per pair the compiler makes the cull, the facet planes and the
// triangle edges vector code, 8 pairs per instruction (contiguous loads of the coordinate-major
// triangles, LS_TRI_ARGS), where one loop over the pairs paid a data-dependent branch per pair
// and step (Sponza grid-ls 64³ N=3: ls_count 4.9-5.1 s with the cull alone in a vector loop,
// 4.0-4.4 s so). A block the step before decided whole is skipped; the lanes it decided in
// part are computed and dropped, which costs less than packing the pairs left and gathering
// their triangles (48.2 M such blocks against 35.4 M packed ones on that scene; ls_count
// 3.39 -> 3.17 s, docs/linespace-build.md).
INLINE uint ls_run_meets(CTX_PARAM uint ra, uint rb, uint tri_ref, uint k0, uint span, float eps, uint facets,
                         uint n, LsShaft sh, uint shaft, float3 ca, float3 cb, float4 p0, float4 p1, float4 p2,
                         float4 p3, float4 p4, float4 p5, float4 p6, float4 p7) {
    // 1. cull and 2. certain from the masks, as bits of the run: blocks of LS_RUN_LANES (a constant
    // trip count: vector code even for the runs of sparse cells, shorter than a vector); a block
    // may read past the run's masks (linespace.py pads ls_masks by LS_RUN_LANES words), whose bits
    // are dropped.
    uint live = 0u;
    uint met = 0u;
    for (uint k8 = 0u; k8 < span; k8 += LS_RUN_LANES) {
        for (uint l = 0u; l < LS_RUN_LANES; ++l) {
            uint k = k8 + l;
            uint ma = LD_U(ls_masks, ra + k0 + k);
            uint mb = LD_U(ls_masks, rb + k0 + k);
            uint uncut = (ma & mb & LS_CULL_BITS) == 0u ? 1u : 0u;
            live |= uncut << k;
            met |= (uncut & U32(ls_masks_certain(ma, mb))) << k;
        }
    }
    uint in_run = span < 32u ? (1u << span) - 1u : 0xffffffffu;
    met &= in_run;
    live &= in_run & ~met;
    if (live == 0u) return met;  // the masks decided the run (3 in 4 runs on Sponza 64³ N=3): ls_count 3.2 -> 3.07 s
    // 3. facet planes, then the triangle's edges, a loop for the shaft's number of facets: every
    // block with a pair left. A test's verdict 1 accepts; `next` (facets 2, edges 0) leaves the
    // pair to the step after.
#define LS_BLOCKS(pairs, test, next, left) for (uint k8 = 0u; k8 < span; k8 += LS_RUN_LANES) { \
        uint sel = (pairs >> k8) & ((1u << LS_RUN_LANES) - 1u); \
        if (sel == 0u) continue; \
        int v8[LS_RUN_LANES]; \
        for (uint l = 0u; l < LS_RUN_LANES; ++l) { \
            uint r = tri_ref + k0 + k8 + l; \
            v8[l] = test(LS_TRI_ARGS(r), eps, p0, p1, p2, p3, p4, p5, p6, p7); } \
        uint yes = 0u, on = 0u; \
        for (uint l = 0u; l < LS_RUN_LANES; ++l) { \
            yes |= (v8[l] == 1 ? 1u : 0u) << l; on |= (v8[l] == next ? 1u : 0u) << l; } \
        met |= (yes & sel) << k8; left |= (on & sel) << k8; }
    uint undecided = 0u;
    if (facets > 6u) LS_BLOCKS(live, ls_facet_verdict, 2, undecided)
    else if (facets == 6u) LS_BLOCKS(live, ls_facet_verdict6, 2, undecided)
    else LS_BLOCKS(live, ls_facet_verdict5, 2, undecided)
    uint exact = 0u;
    if (facets > 6u) LS_BLOCKS(undecided, ls_edges_in_shaft, 0, exact)
    else if (facets == 6u) LS_BLOCKS(undecided, ls_edges_in_shaft6, 0, exact)
    else LS_BLOCKS(undecided, ls_edges_in_shaft5, 0, exact)
    for (; exact != 0u; exact &= exact - 1u) {  // the exact test, one pair at a time
        uint k = LOWEST_BIT(exact);
        if (ls_exact_meets(CTX_ARG n, sh, shaft, LS_TRI_ARGS(tri_ref + k0 + k), eps, ca, cb) != 0) met |= 1u << k;
    }
    return met;
}
#endif

#endif  // triangle / shaft test

#if defined(LS_PAIR_BITS) || defined(KERNEL_ls_insert) || defined(KERNEL_ls_cell_find_sets) || defined(KERNEL_ls_head_len) \
    || defined(KERNEL_ls_head_fill) || (defined(KERNEL_ls_shaft_set) && defined(LS_HEAD_LIST))
// Where shaft `shaft` of cell `cell` starts in ls_pair_bits, and its length (the cell's references).
INLINE uint ls_row_start(CTX_PARAM uint cell, uint shaft, uint len) {
    return (V(ls_ref_bases)[cell] - V(ls_bits_base)) * V(ls_shafts) + shaft * len;
}
#endif

#if defined(KERNEL_ls_head_len) || defined(KERNEL_ls_head_fill)
// Head shaft s's row (s counted over all cells): its first bit and its length.
STRUCT(LsRow) { uint start; uint len; };

INLINE LsRow ls_shaft_row(CTX_PARAM uint s) {
    uint cell = s / V(ls_shafts);
    LsRow row;
    row.len = V(ls_cell_ranges)[2u * cell + 1u] - V(ls_cell_ranges)[2u * cell];
    row.start = ls_row_start(CTX_ARG cell, s - cell * V(ls_shafts), row.len);
    return row;
}
#endif

#if defined(KERNEL_ls_insert) || defined(KERNEL_ls_cell_find_sets) || (defined(KERNEL_ls_fill) && defined(LS_PAIR_BITS)) \
    || defined(KERNEL_ls_head_len) || defined(KERNEL_ls_head_fill) || (defined(KERNEL_ls_shaft_set) && defined(LS_HEAD_LIST)) \
    || defined(LS_PAIR_QUEUE)
// A row of pair bits (a shaft's decisions for its cell's candidates, from any bit): the fill
// from the bits and the sets' kernels (ls_insert_kernel) read it a word at a time.
// Word k (bits 32 k .. 32 k + 31) of a row of `len` bits from bit `start`: reads no bit past the row.
INLINE uint ls_row_word(CTX_PARAM uint start, uint len, uint k) {
    uint pos = start + 32u * k;
    uint bits = min(len - 32u * k, 32u);
    uint off = pos & 31u;
    uint w = LS_BITS(pos >> 5u) >> off;
    if (off != 0u && off + bits > 32u) w |= LS_BITS((pos >> 5u) + 1u) << (32u - off);
    return bits < 32u ? (w & ((1u << bits) - 1u)) : w;
}
#endif

#if defined(KERNEL_ls_fill) || defined(KERNEL_ls_head_fill)
// The fill's entry `count` of an item whose part of its set starts at entry `first`: the
// `position` of the candidate in its cell's list (cell-local ids, layout above). With LS_IDS16 two
// entries share a word: `pend` gathers the word's low half until its high half comes; a word the
// item shares with a neighbouring item (its first and last where its part starts or ends
// mid-word) is ORed into the zeroed array atomically, every other word stored whole.
INLINE uint ls_put_candidate(CTX_PARAM uint first, uint count, uint position, uint pend) {
#ifdef LS_IDS16
    uint k = first + count;
    pend |= position << ((k & 1u) << 4u);
    if ((k & 1u) == 0u) return pend;
    if (count == 0u) {
        LS_CANDIDATE_OR(k >> 1u, pend);
    } else {
        LS_CANDIDATE_STORE(k >> 1u, pend);
    }
    return 0u;
#else
    LS_CANDIDATE_STORE(first + count, position);
    return pend;
#endif
}

// After an item's last entry: its last word, where the item ends mid-word.
INLINE void ls_put_last(CTX_PARAM uint first, uint count, uint pend) {
#ifdef LS_IDS16
    if (count > 0u && ((first + count) & 1u) != 0u) {
        LS_CANDIDATE_OR((first + count) >> 1u, pend);
    }
#endif
}
#endif

#if (defined(KERNEL_ls_fill) && defined(LS_PAIR_BITS)) || defined(KERNEL_ls_head_fill)
// The fill from the count's pair bits: the row of `len` bits from bit `bit`, 32 at a time, its
// set bits in order as entries from `first` (positions position0 + k in the cell's list).
INLINE void ls_fill_row(CTX_PARAM uint bit, uint len, uint first, uint position0) {
    uint count = 0u;
    uint pend = 0u;
    for (uint k0 = 0u; k0 < len; k0 += 32u) {
        for (uint w = ls_row_word(CTX_ARG bit, len, k0 >> 5u); w != 0u; w &= w - 1u) {
            pend = ls_put_candidate(CTX_ARG first, count, position0 + k0 + LOWEST_BIT(w), pend);
            count += 1u;
        }
    }
    ls_put_last(CTX_ARG first, count, pend);
}
#endif

#if defined(KERNEL_ls_count) || defined(KERNEL_ls_fill)
// With LS_PAIR_BITS the count keeps every decision in ls_pair_bits (one bit per (shaft, candidate):
// cell c's bits start at (ls_ref_bases[c] - ls_bits_base) * 15 N^4, shaft-major: the bits of all
// cells, or of one batch where they do not all fit), the sets are found from them (ls_insert_kernel
// below) and the fill only reads them. Either fill writes only each set's first shaft: the other
// shafts' items hold LS_SKIP.
//
// Where every cell of the batch is one chunk (ls_grouped = 1), a work item takes one shaft of a
// group of consecutive cells (gid / shafts: the group, [ls_cell_groups[g], ls_cell_groups[g + 1]);
// gid % shafts: the shaft) and walks them in turn, so that the shaft's set-up (its 10 plane slots,
// the division) is paid once per group; neighbouring lanes take neighbouring shafts of the same
// cells, so their cell loops run in step. The host makes the groups (linespace.py:
// BuildPlan.cell_groups): at most CELLS_PER_ITEM cells (16; 256 on GL) whose candidates fit one
// chunk. Otherwise (ls_grouped = 0) a work item is one chunk of one cell, found by a search over
// the cells.
#ifdef KERNEL_ls_fill
// Where the item's part of its set's list starts, from `left` = LS_ITEM(item): ls_set_len_kernel
// left the set's index in its shaft's first item and in each later chunk's item the counts of the
// chunks before it; the scan since made the set's length its offset.
INLINE uint ls_item_first(CTX_PARAM uint item, uint chunk, uint left) {
    return chunk == 0u ? LS_SET_LEN(left) : LS_SET_LEN(LS_ITEM(item - chunk)) + left;
}
#endif

#if defined(KERNEL_ls_count) && defined(LS_PAIR_BITS)
// The bits `met` of a run of candidates into ls_pair_bits from bit `at`: one or two words, which
// neighbouring items share.
INLINE void ls_bits_or_run(CTX_PARAM uint at, uint met) {
    if (met != 0u) LS_BITS_OR(at >> 5u, met << (at & 31u));
    if ((at & 31u) != 0u && (met >> (32u - (at & 31u))) != 0u) LS_BITS_OR((at >> 5u) + 1u, met >> (32u - (at & 31u)));
}
#endif

#ifdef LS_PAIR_QUEUE
// The count of a group of one-chunk cells where the lanes are shafts (llvmpipe, GPUs;
// linespace.py _grouped_count): steps 1 and 2 (the masks) for runs of up to 32 candidates, cell
// after cell, each pair they leave queued (its cell-local triangle and its bit); once the next run
// might overflow the queue, the facet planes, the triangle's edges and the exact test each make
// one loop over the queued pairs the step before left, and the bits of the pairs that meet the
// shaft go out, one atomic per word. Why: llvmpipe runs a loop's body at least once, masked, even
// where no lane has an iteration (docs/linespace-build.md), so ls_run_meets' step loops, run per
// run, cost a facet, an edge and an exact test for every run of every cell: with those loops
// present but never iterating, Sponza grid-ls glsl 128³ N=2's count took 4.0 of its 5.2 s,
// without them 1.0 s. Queued, they run once per LS_PAIR_QUEUE candidates (3.2-3.4 s). The queue
// fills by candidates, the same in every lane of a group, so the lanes test their queues together.
// Cells of several chunks (one item per chunk of one cell: dense cells) keep ls_run_meets, whose
// runs there are full (BMW grid-ls glsl 128³ N=2: queued 3.32 s against 3.07 s).
// The count per item and the stats are read back from the finished rows (ls_shaft_kernel).
// A set of queue entries: the bits of a uint4 (LS_PAIR_QUEUE <= 128). Add entry q where `on`;
// take the lowest entry q of a non-empty set, removing it.
#define LS_QSET(m, q, on) { uint b_ = ((on) ? 1u : 0u) << ((q) & 31u); uint w_ = (q) >> 5u; \
        m.x |= w_ == 0u ? b_ : 0u; m.y |= w_ == 1u ? b_ : 0u; m.z |= w_ == 2u ? b_ : 0u; m.w |= w_ == 3u ? b_ : 0u; }
#define LS_QANY(m) ((m.x | m.y | m.z | m.w) != 0u)
#define LS_QTAKE(m, q) { uint o_ = m.x != 0u ? 0u : (m.y != 0u ? 32u : (m.z != 0u ? 64u : 96u)); \
        uint w_ = o_ == 0u ? m.x : (o_ == 32u ? m.y : (o_ == 64u ? m.z : m.w)); \
        q = o_ + LOWEST_BIT(w_); w_ &= w_ - 1u; \
        m.x = o_ == 0u ? w_ : m.x; m.y = o_ == 32u ? w_ : m.y; m.z = o_ == 64u ? w_ : m.z; m.w = o_ == 96u ? w_ : m.w; }
INLINE void ls_count_queued(CTX_PARAM uint cell_first, uint cell_end, uint shaft, uint patches, uint mask_a, uint mask_b,
                            float eps, uint n, LsShaft sh, float3 ca, float3 cb, float4 p0, float4 p1, float4 p2,
                            float4 p3, float4 p4, float4 p5, float4 p6, float4 p7) {
    uint q_tri[LS_PAIR_QUEUE];  // a queued pair's cell-local triangle (reference)
    uint q_bit[LS_PAIR_QUEUE];  // and its bit in ls_pair_bits
    uint cell = cell_first;
    uint k0 = 0u;  // the next run's first candidate in the cell's list
    while (cell < cell_end) {
        uint queued = 0u;
        uint consumed = 0u;  // candidates of this pass: the same in the lanes of a group's cells
        while (cell < cell_end) {
            uint len = V(ls_cell_ranges)[2u * cell + 1u] - V(ls_cell_ranges)[2u * cell];
            uint span = min(len - k0, 32u);
            if (consumed + span > LS_PAIR_QUEUE) break;
            consumed += span;
            uint cell_ref = V(ls_ref_bases)[cell] - V(ls_ref_base);  // the cell's first reference in the batch
            uint ra = cell_ref * patches + mask_a * len + k0;  // the run's masks (ls_masks_kernel)
            uint rb = cell_ref * patches + mask_b * len + k0;
            uint tri = cell_ref + k0;
            uint bit = ls_row_start(CTX_ARG cell, shaft, len) + k0;
            uint2 masks = ls_masks_run(CTX_ARG ra, rb, span);  // 1. cull and 2. certain
            uint met = masks.x;
            uint live = masks.y;
            ls_bits_or_run(CTX_ARG bit, met);
            for (; live != 0u; live &= live - 1u) {
                uint k = LOWEST_BIT(live);
                q_tri[queued] = tri + k;
                q_bit[queued] = bit + k;
                queued += 1u;
            }
            k0 += 32u;
            if (k0 >= len) {
                k0 = 0u;
                cell += 1u;
            }
        }
        uint4 meet = make_uint4(0u, 0u, 0u, 0u);  // the queued pairs that meet the shaft
        uint4 left = make_uint4(0u, 0u, 0u, 0u);  // those the step leaves to the next
        for (uint q = 0u; q < queued; ++q) {  // 3. facet planes
            int v = ls_facet_verdict(LS_TRI_ARGS(q_tri[q]), eps, p0, p1, p2, p3, p4, p5, p6, p7);
            LS_QSET(meet, q, v == 1)
            LS_QSET(left, q, v == 2)
        }
        uint4 exact = make_uint4(0u, 0u, 0u, 0u);
        while (LS_QANY(left)) {  // the triangle's edges
            uint q;
            LS_QTAKE(left, q)
            int e = ls_edges_in_shaft(LS_TRI_ARGS(q_tri[q]), eps, p0, p1, p2, p3, p4, p5, p6, p7);
            LS_QSET(meet, q, e != 0)
            LS_QSET(exact, q, e == 0)
        }
        while (LS_QANY(exact)) {  // the exact test
            uint q;
            LS_QTAKE(exact, q)
            LS_QSET(meet, q, ls_exact_meets(CTX_ARG n, sh, shaft, LS_TRI_ARGS(q_tri[q]), eps, ca, cb) != 0)
        }
        // The bits of the pairs that meet it, in increasing order: one atomic per word
        uint word = 0xffffffffu;
        uint bits = 0u;
        while (LS_QANY(meet)) {
            uint q;
            LS_QTAKE(meet, q)
            uint at = q_bit[q];
            if ((at >> 5u) != word) {
                if (bits != 0u) LS_BITS_OR(word, bits);
                word = at >> 5u;
                bits = 0u;
            }
            bits |= 1u << (at & 31u);
        }
        if (bits != 0u) LS_BITS_OR(word, bits);
    }
}
#endif

// The count's tally of an item's cell: its count (until ls_set_len_kernel puts what the fill needs
// there) and the stats (a cell of one chunk with candidates; the candidates, in 64 bits).
#ifndef LS_NO_ITEM_COUNTS
#define LS_ITEM_COUNT(item, count) LS_ITEM_STORE(item, count);
#else
#define LS_ITEM_COUNT(item, count)
#endif
#define LS_TALLY(item, count) { LS_ITEM_COUNT(item, count) \
        non_empty += chunks == 1u && (count) > 0u ? 1u : 0u; \
        sum_hi += sum_lo + (count) < sum_lo ? 1u : 0u; \
        sum_lo += (count); }

INLINE void ls_shaft_kernel(CTX_PARAM uint gid) {
    uint shafts = V(ls_shafts);
    uint grouped = V(ls_grouped);
    uint cell_first, cell_end, shaft, chunk;
    uint chunks = 1u;
    if (grouped != 0u) {
        uint group = gid / shafts;
        cell_first = V(ls_cell_groups)[group];
        cell_end = V(ls_cell_groups)[group + 1u];
        shaft = gid % shafts;
        chunk = 0u;
    } else {
        uint item = gid + V(ls_item_base);
        cell_first = ls_item_cell(CTX_ARG V(ls_cell_first), V(ls_cell_end), item);
        cell_end = cell_first + 1u;
        uint item0 = V(ls_item_bases)[cell_first];
        chunks = (V(ls_item_bases)[cell_first + 1u] - item0) / shafts;
        shaft = (item - item0) / chunks;
        chunk = (item - item0) % chunks;
    }
#if !(defined(KERNEL_ls_fill) && defined(LS_PAIR_BITS))
    float eps = V(ls_eps);
    uint n = V(ls_n);
    uint patches = 6u * n * n;
    uint pb = shaft * U32(LS_PLANE_SLOTS);
    float4 axis_a = LD_F4(ls_planes, pb + U32(LS_MAX_PLANES));  // the patches' centres and mask indices
    float4 axis_b = LD_F4(ls_planes, pb + U32(LS_MAX_PLANES) + 1u);
    float3 ca = axis_a.xyz;
    float3 cb = axis_b.xyz;
    uint mask_a = U32(axis_a.w);
    uint mask_b = U32(axis_b.w);
    LsShaft sh = ls_shaft_of_masks(n, mask_a, mask_b);  // the SAT's patch corners (unused otherwise)
    float4 p0 = LD_F4(ls_planes, pb);
    float4 p1 = LD_F4(ls_planes, pb + 1u);
    float4 p2 = LD_F4(ls_planes, pb + 2u);
    float4 p3 = LD_F4(ls_planes, pb + 3u);
    float4 p4 = LD_F4(ls_planes, pb + 4u);
    float4 p5 = LD_F4(ls_planes, pb + 5u);
    float4 p6 = LD_F4(ls_planes, pb + 6u);
    float4 p7 = LD_F4(ls_planes, pb + 7u);
#ifdef LS_CULL_RUNS
    // The hull's facets: the slots past them hold (0, 0, 0, -1) (ls_planes_kernel), 5 at least
    uint facets = (p5.x == 0.0f && p5.y == 0.0f && p5.z == 0.0f) ? 5u
                : ((p6.x == 0.0f && p6.y == 0.0f && p6.z == 0.0f) ? 6u : 8u);
#else
    uint facets = 8u;  // every slot (lanes are shafts: a branch on the count runs every variant)
#endif
#endif
#ifndef KERNEL_ls_fill
    uint non_empty = 0u;  // shafts of one-chunk cells with candidates (stats; ls_set_len counts the others)
    uint sum_lo = 0u;  // the item's candidates, 64 bits as two words (stats: all shafts' lists)
    uint sum_hi = 0u;
#endif
#ifdef LS_PAIR_QUEUE
    ls_count_queued(CTX_ARG cell_first, cell_end, shaft, patches, mask_a, mask_b, eps, n, sh, ca, cb,
                    p0, p1, p2, p3, p4, p5, p6, p7);
#if !defined(LS_NO_ITEM_COUNTS) || !defined(LS_NO_COUNT_STATS)
    // the count per item and the stats from the rows the queued count finished
    for (uint cell = cell_first; cell < cell_end; ++cell) {
#ifndef LS_NO_ITEM_COUNTS
        uint item = grouped != 0u ? V(ls_item_base) + (cell - V(ls_cell_first)) * shafts + shaft : gid + V(ls_item_base);
#endif
        uint begin = V(ls_cell_ranges)[2u * cell];
        uint end = V(ls_cell_ranges)[2u * cell + 1u];
        uint first_i = begin + chunk * V(ls_chunk);
        uint len = end - first_i > V(ls_chunk) ? V(ls_chunk) : end - first_i;
        uint bit = ls_row_start(CTX_ARG cell, shaft, end - begin) + (first_i - begin);
        uint count = 0u;
        for (uint w = 0u; 32u * w < len; ++w) count += POPCOUNT(ls_row_word(CTX_ARG bit, len, w));
        LS_TALLY(item, count)
    }
#endif
#else
    for (uint cell = cell_first; cell < cell_end; ++cell) {
        uint item = grouped != 0u ? V(ls_item_base) + (cell - V(ls_cell_first)) * shafts + shaft : gid + V(ls_item_base);
#ifdef KERNEL_ls_fill
        uint left = LS_ITEM(item);
        if (left == LS_SKIP) continue;  // not its set's head (ls_set_len_kernel): most shafts, before any other load
#endif
        uint begin = V(ls_cell_ranges)[2u * cell];
        uint end = V(ls_cell_ranges)[2u * cell + 1u];
        uint first_i = begin + chunk * V(ls_chunk);
        uint end_i = end - first_i > V(ls_chunk) ? first_i + V(ls_chunk) : end;
#ifdef LS_PAIR_BITS
        uint bit = ls_row_start(CTX_ARG cell, shaft, end - begin) + (first_i - begin);
#endif
#if defined(KERNEL_ls_fill) && defined(LS_PAIR_BITS)
        ls_fill_row(CTX_ARG bit, end_i - first_i, ls_item_first(CTX_ARG item, chunk, left), first_i - begin);
#else
        uint cell_ref = V(ls_ref_bases)[cell] - V(ls_ref_base);  // the cell's first reference in the batch
        // first_i's masks of the shaft's two patches (the cell's block, patch-major: ls_masks_kernel)
        // and its cell-local vertices
        uint ra = cell_ref * patches + mask_a * (end - begin) + (first_i - begin);
        uint rb = cell_ref * patches + mask_b * (end - begin) + (first_i - begin);
        uint tri_ref = cell_ref + (first_i - begin);
#ifdef KERNEL_ls_fill
        uint first = ls_item_first(CTX_ARG item, chunk, left);
#endif
        uint count = 0u;
#ifdef KERNEL_ls_fill
        uint pend = 0u;
#endif
        // Runs of 32 candidates (ls_run_meets), their bits in list order (the fill's lists and the
        // pair bits as one pass over all).
        for (uint k0 = 0u; k0 < end_i - first_i; k0 += 32u) {
            uint met = ls_run_meets(CTX_ARG ra, rb, tri_ref, k0, min(end_i - first_i - k0, 32u), eps, facets, n, sh, shaft,
                                    ca, cb, p0, p1, p2, p3, p4, p5, p6, p7);
#ifdef KERNEL_ls_fill
            for (uint put = met; put != 0u; put &= put - 1u) {  // in list order
                pend = ls_put_candidate(CTX_ARG first, count, first_i + k0 + LOWEST_BIT(put) - begin, pend);
                count += 1u;
            }
#else
            count += POPCOUNT(met);
#endif
#ifdef LS_PAIR_BITS
            ls_bits_or_run(CTX_ARG bit + k0, met);  // the run's bits start at bit + k0
#endif
        }
#ifdef KERNEL_ls_fill
        ls_put_last(CTX_ARG first, count, pend);
#else
        LS_TALLY(item, count)
#endif
#endif
    }
#endif  // LS_PAIR_QUEUE
#ifndef KERNEL_ls_fill
    // The item's stats go to one of LS_STAT_BUCKETS cache lines, by its index (linespace.py sums
    // them), so that the cores' atomics seldom take a line from each other (PoCL, Sponza grid-ls
    // 64³ N=3: the count took 0.1-0.2 s less without these atomics, 0.05 s less with the buckets
    // than with one line for all).
#ifndef LS_NO_COUNT_STATS  // ls_cell_find_sets_kernel counts them (LS_CELL_STATS)
    uint stat = 16u * (1u + ((gid >> 3u) & (LS_STAT_BUCKETS - 1u)));
    if (non_empty > 0u) ATOMIC_ADD(V(ls_stats)[stat], non_empty);
    if (sum_lo > 0u) {
        uint before = ATOMIC_ADD(V(ls_stats)[stat + 2u], sum_lo);
        sum_hi += before + sum_lo < before ? 1u : 0u;
    }
    if (sum_hi > 0u) ATOMIC_ADD(V(ls_stats)[stat + 3u], sum_hi);
#endif
#endif
#ifndef KERNEL_ls_fill
    if (loops_intact(V(loop_probe)) == 0) ATOMIC_ADD(V(ls_stats)[1], 1u);  // the driver cut loops: geometry.h
#endif
}
#endif  // build: count and fill

#ifdef KERNEL_ls_masks
// ---- Build: the masks of a batch of cells' triangles ---------------------------------------
// One work item per reference: dense reference ls_ref_base + gid (numbered by ls_ref_bases) of its
// cell, writing the 6 N^2 masks of patches face * N^2 + p (see `row` below). The triangle's set-up
// (its cell, vertices, axes and intervals) is paid once for the 6 faces: with an item per (reference,
// face) it took half of this kernel at N = 2.
// Cull bits: bit 2k is set when on axis k the patch lies below the triangle by the cull margin
// (scaled by the axis length), bit 2k + 1 when above. A shaft's hull projects onto an axis as the
// hull of its two patches' projections, so the hull lies beyond the triangle on axis k iff both
// patches have the same bit: one AND per pair. Axes: the 13 of a triangle/box test (Akenine-
// Moeller 2001), the cell axes, the triangle normal and the edges crossed with the cell axes; none
// depends on the shaft, so a triangle's 6 N^2 masks serve all 15 N^4 shafts of its cell.
// Certain bits: LS_MEETS_PATCH, LS_ABOVE_PLANE / LS_BELOW_PLANE (linespace.h, build section).
// The cull margin (cell-local units): how far beyond a shaft's hull a triangle that a test of
// step 3 accepts can lie, so that the cull removes only pairs those tests reject. Each accepted
// triangle meets the volume P of the facet planes pushed out by ls_eps (the clipper exactly; the
// edges test up to LS_IN_TRIANGLE_TOL; the SAT lies within ls_eps of the hull along the axis of
// the closest features), and P is the hull of its vertices, each within R of a hull corner
// (ls_edges_kernel), so P lies in the hull grown by a ball of radius R and reaches at most R past
// the hull's interval on any unit axis. The uniform ls_cull_margin is the largest R (ls_reach) over the
// shafts (0.0076 at N = 3; never below ls_eps) plus linespace.py's LS_CULL_SLACK; each triangle
// adds 1e-6 of its largest cell-local coordinate for the float32 rounding of its projections.
// (Until the twenty-ninth session a fixed 0.05 = 50 ls_eps; 0.005 was found to cull accepted pairs.)
// Projection interval of a patch (face axis `axis` at coordinate `side`, in-face ranges u, v) on
// axis ax: the corners differ only in u and v.
INLINE float2 ls_patch_interval(float3 ax, int axis, float side, float2 u, float2 v) {
    float au = comp3(ax, (axis + 1) % 3);
    float av = comp3(ax, (axis + 2) % 3);
    float base = comp3(ax, axis) * side;
    return make_float2(base + min(au * u.x, au * u.y) + min(av * v.x, av * v.y),
                       base + max(au * u.x, au * u.y) + max(av * v.x, av * v.y));
}

// The cull thresholds of axis ax: the triangle's interval t on it widened by the margin (x |ax|).
INLINE float2 ls_cull_range(float3 ax, float2 t, float margin) {
    float m = margin * length(ax);
    return make_float2(t.x - m, t.y + m);
}

// Axis ax on a face (axis `axis`, coordinate `side`): its u and v components and the face's offset
// along it, as ls_patch_interval uses them; once per face and axis, not per patch.
INLINE float3 ls_face_terms(float3 ax, int axis, float side) {
    return make_float3(comp3(ax, (axis + 1) % 3), comp3(ax, (axis + 2) % 3), comp3(ax, axis) * side);
}

// An axis' v terms (face terms f) for a row of patches v: its least and greatest f.y v.
INLINE float2 ls_axis_v(float3 f, float2 v) {
    return make_float2(min(f.y * v.x, f.y * v.y), max(f.y * v.x, f.y * v.y));
}

// Cull bits of an axis (face terms f, the row's v terms fv, thresholds r) for the patch u x v:
// ls_patch_interval's arithmetic on the hoisted terms (the same floats, so the same bits).
INLINE uint ls_axis_bits(float3 f, float2 fv, float2 r, float2 u, uint bit) {
    float lo = f.z + min(f.x * u.x, f.x * u.y) + fv.x;
    float hi = f.z + max(f.x * u.x, f.x * u.y) + fv.y;
    return ((hi < r.x ? 1u : 0u) | (lo > r.y ? 2u : 0u)) << bit;
}

INLINE float2 ls_tri_interval(float3 ax, float3 a, float3 b, float3 c) {
    float ta = dot(ax, a), tb = dot(ax, b), tc = dot(ax, c);
    return make_float2(min(ta, min(tb, tc)), max(ta, max(tb, tc)));
}

// Keep t in r where lo <= x0 + t (x1 - x0) <= hi (Liang-Barsky, one coordinate).
INLINE float2 ls_clip_1d(float x0, float x1, float lo, float hi, float2 r) {
    float d = x1 - x0;
    if (d == 0.0f) return (x0 < lo || x0 > hi) ? make_float2(1.0f, 0.0f) : r;
    float t0 = (lo - x0) / d;
    float t1 = (hi - x0) / d;
    return make_float2(max(r.x, min(t0, t1)), min(r.y, max(t0, t1)));
}

INLINE float3 ls_plane_cut(float3 p, float3 q, float dp, float dq) {
    return p + (q - p) * (dp / (dp - dq));
}

// 1 when the triangle holds its plane's whole cut with the cell: every cell corner on the inner
// side of each edge (within the triangle's plane). Every segment that crosses the plane inside
// the cell then crosses the triangle.
INLINE int ls_edge_covers(float3 nrm, float3 v, float3 e) {
    float3 inward = cross(nrm, e);
    // The smallest dot(in, x - v) over the unit cube's corners.
    return min(inward.x, 0.0f) + min(inward.y, 0.0f) + min(inward.z, 0.0f) - dot(inward, v) >= 0.0f ? 1 : 0;
}

INLINE int ls_covers_cell(float3 a, float3 b, float3 c, float3 nrm) {
    if (dot(nrm, nrm) == 0.0f) return 0;
    return ls_edge_covers(nrm, a, b - a) * ls_edge_covers(nrm, b, c - b) * ls_edge_covers(nrm, c, a - c);
}

INLINE void ls_masks_kernel(CTX_PARAM uint gid) {
    uint n = V(ls_n);
    uint n2 = n * n;
    uint ref = V(ls_ref_base) + gid;
    uint cell = ls_ref_cell(CTX_ARG V(ls_cell_first), V(ls_cell_end), ref);
    float3 lo = V(ls_cell_boxes)[2u * cell].xyz;
    float3 hi = V(ls_cell_boxes)[2u * cell + 1u].xyz;
    float3 inv = make_float3(1.0f / (hi.x - lo.x), 1.0f / (hi.y - lo.y), 1.0f / (hi.z - lo.z));
    uint nth = ref - V(ls_ref_bases)[cell];  // the reference's place in its cell
    uint tri = V(ls_cell_tris)[V(ls_cell_ranges)[2u * cell] + nth];
    Triangle t = load_grid_triangle(CTX_ARG tri);
    float3 a = (t.a - lo) * inv;
    float3 b = (t.b - lo) * inv;
    float3 c = (t.c - lo) * inv;
#ifdef LS_CULL_RUNS
    uint row = ref - V(ls_ref_base);  // coordinate-major (LS_TRI_ARGS)
    uint st = V(ls_tri_stride);
    V(ls_local_tris)[row] = a.x;
    V(ls_local_tris)[st + row] = a.y;
    V(ls_local_tris)[2u * st + row] = a.z;
    V(ls_local_tris)[3u * st + row] = b.x;
    V(ls_local_tris)[4u * st + row] = b.y;
    V(ls_local_tris)[5u * st + row] = b.z;
    V(ls_local_tris)[6u * st + row] = c.x;
    V(ls_local_tris)[7u * st + row] = c.y;
    V(ls_local_tris)[8u * st + row] = c.z;
#else
    uint tri_row = 3u * (ref - V(ls_ref_base));  // the pair tests read these, not the scene's indexed vertices
    V(ls_local_tris)[tri_row] = make_float4(a.x, a.y, a.z, 0.0f);
    V(ls_local_tris)[tri_row + 1u] = make_float4(b.x, b.y, b.z, 0.0f);
    V(ls_local_tris)[tri_row + 2u] = make_float4(c.x, c.y, c.z, 0.0f);
#endif
    float3 nrm = cross(b - a, c - a);
    float3 ex = make_float3(1.0f, 0.0f, 0.0f), ey = make_float3(0.0f, 1.0f, 0.0f), ez = make_float3(0.0f, 0.0f, 1.0f);
    float3 e0 = b - a, e1 = c - b, e2 = a - c;
    float3 x0 = cross(e0, ex), x1 = cross(e0, ey), x2 = cross(e0, ez);
    float3 x3 = cross(e1, ex), x4 = cross(e1, ey), x5 = cross(e1, ez);
    float3 x6 = cross(e2, ex), x7 = cross(e2, ey), x8 = cross(e2, ez);
    float3 far = max(fabs(a), max(fabs(b), fabs(c)));
    float margin = V(ls_cull_margin) + 1e-6f * max(1.0f, max(far.x, max(far.y, far.z)));
    float2 rx = ls_cull_range(ex, ls_tri_interval(ex, a, b, c), margin), ry = ls_cull_range(ey, ls_tri_interval(ey, a, b, c), margin);
    float2 rz = ls_cull_range(ez, ls_tri_interval(ez, a, b, c), margin), rn = ls_cull_range(nrm, ls_tri_interval(nrm, a, b, c), margin);
    float2 r0 = ls_cull_range(x0, ls_tri_interval(x0, a, b, c), margin), r1 = ls_cull_range(x1, ls_tri_interval(x1, a, b, c), margin);
    float2 r2 = ls_cull_range(x2, ls_tri_interval(x2, a, b, c), margin), r3 = ls_cull_range(x3, ls_tri_interval(x3, a, b, c), margin);
    float2 r4 = ls_cull_range(x4, ls_tri_interval(x4, a, b, c), margin), r5 = ls_cull_range(x5, ls_tri_interval(x5, a, b, c), margin);
    float2 r6 = ls_cull_range(x6, ls_tri_interval(x6, a, b, c), margin), r7 = ls_cull_range(x7, ls_tri_interval(x7, a, b, c), margin);
    float2 r8 = ls_cull_range(x8, ls_tri_interval(x8, a, b, c), margin);
    int covers = ls_covers_cell(a, b, c, nrm);
    float nd = dot(nrm, a);
    float fn = F32(n);
    // Patch-major within the cell (the cell's K references x 6 N^2 patches, mask of reference k and
    // patch q at q * K + k): a shaft's pair loop then reads its two patches' masks as two runs.
    uint refs = V(ls_cell_ranges)[2u * cell + 1u] - V(ls_cell_ranges)[2u * cell];
    for (int face = 0; face < 6; ++face) {
        // The triangle's cut with the face plane (x0 -> x1 in face coordinates), if it crosses it; a
        // triangle in the plane gets no LS_MEETS_PATCH.
        int axis = face / 2;
        float side = F32(face % 2);
        float da = comp3(a, axis) - side, db = comp3(b, axis) - side, dc = comp3(c, axis) - side;
        int ia = da <= 0.0f ? 1 : 0, ib = db <= 0.0f ? 1 : 0, ic = dc <= 0.0f ? 1 : 0;
        int cuts = (ia == ib && ib == ic) ? 0 : 1;
        float2 cut0 = ls_face_uv(ia != ib ? ls_plane_cut(a, b, da, db) : ls_plane_cut(b, c, db, dc), axis);
        float2 cut1 = ls_face_uv((ia != ib && ib != ic) ? ls_plane_cut(b, c, db, dc) : ls_plane_cut(c, a, dc, da), axis);
        uint row = (V(ls_ref_bases)[cell] - V(ls_ref_base)) * 6u * n2 + U32(face) * n2 * refs + nth;
        float3 fx = ls_face_terms(ex, axis, side), fy = ls_face_terms(ey, axis, side), fz = ls_face_terms(ez, axis, side);
        float3 fnrm = ls_face_terms(nrm, axis, side), f0 = ls_face_terms(x0, axis, side), f1 = ls_face_terms(x1, axis, side);
        float3 f2 = ls_face_terms(x2, axis, side), f3 = ls_face_terms(x3, axis, side), f4 = ls_face_terms(x4, axis, side);
        float3 f5 = ls_face_terms(x5, axis, side), f6 = ls_face_terms(x6, axis, side), f7 = ls_face_terms(x7, axis, side);
        float3 f8 = ls_face_terms(x8, axis, side);
        // A row of patches (v) at a time: its axes' v terms once for the row's N patches.
        for (uint pj = 0u; pj < n; ++pj) {
            float pv = F32(I32(pj));
            float2 v = make_float2(pv / fn, (pv + 1.0f) / fn);
            float2 vx = ls_axis_v(fx, v), vy = ls_axis_v(fy, v), vz = ls_axis_v(fz, v), vn = ls_axis_v(fnrm, v);
            float2 v0 = ls_axis_v(f0, v), v1 = ls_axis_v(f1, v), v2 = ls_axis_v(f2, v), v3 = ls_axis_v(f3, v);
            float2 v4 = ls_axis_v(f4, v), v5 = ls_axis_v(f5, v), v6 = ls_axis_v(f6, v), v7 = ls_axis_v(f7, v);
            float2 v8 = ls_axis_v(f8, v);
            for (uint pi = 0u; pi < n; ++pi) {
                float pu = F32(I32(pi));
                float2 u = make_float2(pu / fn, (pu + 1.0f) / fn);
                uint bits = ls_axis_bits(fx, vx, rx, u, 0u) | ls_axis_bits(fy, vy, ry, u, 2u) | ls_axis_bits(fz, vz, rz, u, 4u)
                          | ls_axis_bits(fnrm, vn, rn, u, 6u) | ls_axis_bits(f0, v0, r0, u, 8u) | ls_axis_bits(f1, v1, r1, u, 10u)
                          | ls_axis_bits(f2, v2, r2, u, 12u) | ls_axis_bits(f3, v3, r3, u, 14u) | ls_axis_bits(f4, v4, r4, u, 16u)
                          | ls_axis_bits(f5, v5, r5, u, 18u) | ls_axis_bits(f6, v6, r6, u, 20u) | ls_axis_bits(f7, v7, r7, u, 22u)
                          | ls_axis_bits(f8, v8, r8, u, 24u);
                if (cuts != 0) {
                    float2 r = ls_clip_1d(cut0.x, cut1.x, u.x, u.y, make_float2(0.0f, 1.0f));
                    r = ls_clip_1d(cut0.y, cut1.y, v.x, v.y, r);
                    if (r.x <= r.y) bits |= LS_MEETS_PATCH;
                }
                if (covers != 0) {
                    float2 h = ls_patch_interval(nrm, axis, side, u, v);
                    if (h.x > nd) bits |= LS_ABOVE_PLANE;
                    if (h.y < nd) bits |= LS_BELOW_PLANE;
                }
                V(ls_masks)[row + (pj * n + pi) * refs] = bits;
            }
        }
    }
}
#endif

#if defined(KERNEL_ls_insert) || defined(KERNEL_ls_cell_find_sets)
// ---- Build: one list per distinct candidate set of a cell (issue 16) -----------------------
// A group of cells [ls_cell_first, ls_cell_end) at a time, its shafts numbered b = 0.. from the
// group's first: shaft b's decisions are its row of ls_pair_bits (one bit per reference of its
// cell, in list order), so two shafts have the same set iff their rows are equal. (1) ls_insert:
// each shaft hashes its row and looks it up in its cell's open-addressing table of 2 x 15 N^4
// slots from the hash's slot, claiming an empty slot (compare-and-swap) or joining the slot whose
// member has, compared word by word, the same row: the hash only picks the first slot, it never
// decides equality (a kernel of its own wrote the hashes for a compare before the rows' until the
// twenty-eighth session: PoCL 0.18 s, Sponza grid-ls 64³ N=3, where the table's slots are mostly
// free and a row is one or two words). A joining shaft lowers the slot to itself where it is
// smaller (atomic min), so each slot ends holding its smallest member whichever claimed it first;
// every member's row is the same, so a compare against whichever member the slot holds at the
// time decides the same (until the twenty-ninth session a kernel of its own, ls_min, took the
// minimum afterwards). (2) ls_heads: that member is the set's first shaft (its "head"); (3)
// ls_shaft_set: a shaft's set index within its cell = the heads before its head, so sets are
// numbered in the order of their first shaft.
#define LS_HASH_SEED 2166136261u  // FNV-1a over the row's words
INLINE uint ls_hash_word(uint h, uint w) { return (h ^ w) * 16777619u; }
INLINE uint ls_hash_mask(uint h) {
#ifdef LS_HASH_MASK
    h &= LS_HASH_MASK;  // tests: a hash that collides, so only the word-by-word compare tells sets apart
#endif
    return h;
}
INLINE uint ls_row_hash(CTX_PARAM uint start, uint len) {
    uint h = LS_HASH_SEED;
    for (uint k = 0u; 32u * k < len; ++k) h = ls_hash_word(h, ls_row_word(CTX_ARG start, len, k));
    return ls_hash_mask(h);
}

INLINE int ls_rows_equal(CTX_PARAM uint start_a, uint start_b, uint len) {
    for (uint k = 0u; 32u * k < len; ++k)
        if (ls_row_word(CTX_ARG start_a, len, k) != ls_row_word(CTX_ARG start_b, len, k)) return 0;
    return 1;
}

#endif

#ifdef KERNEL_ls_insert
// Table slots hold member + 1 (0: empty); ls_set_slot[b] gets the slot shaft b joined.
// One integer division per shaft (its cell): the hash picks its slot by a multiply (MUL_HI, the
// high word of hash x size), and a claimer's row lies (claimer - b) rows from b's (same cell).
// The divisions of each compare and of the slot took a fifth of the kernel on PoCL (perf annotate).
INLINE void ls_insert_kernel(CTX_PARAM uint b) {
    uint shafts = V(ls_shafts);
    uint b0 = V(ls_cell_first) * shafts;
    uint cell = (b0 + b) / shafts;
    uint len = V(ls_cell_ranges)[2u * cell + 1u] - V(ls_cell_ranges)[2u * cell];
    uint start = ls_row_start(CTX_ARG cell, b0 + b - cell * shafts, len);
    uint size = 2u * shafts;
    uint region = (cell - V(ls_cell_first)) * size;
    uint slot = MUL_HI(ls_row_hash(CTX_ARG start, len), size);
    // At most `shafts` of the `size` slots are ever taken, so an empty one comes within size probes.
    for (uint probe = 0u; probe < size; ++probe) {
        uint at = region + slot;
        uint v = V(ls_set_table)[at];
        if (v == 0u) {
            v = ATOMIC_CAS(V(ls_set_table)[at], 0u, b + 1u);
            if (v == 0u) { V(ls_set_slot)[b] = at; return; }
        }
        uint other = v - 1u;  // uint arithmetic: start + (other - b) len wraps back into range when other < b
        if (ls_rows_equal(CTX_ARG start + (other - b) * len, start, len) != 0) {
            if (b < other) ATOMIC_MIN(V(ls_set_table)[at], b + 1u);  // mostly not: smaller shafts tend to come first
            V(ls_set_slot)[b] = at;
            return;
        }
        slot = slot + 1u == size ? 0u : slot + 1u;
    }
}
#endif

#ifdef KERNEL_ls_cell_find_sets
// The head lists' builds: a work item per cell of the group walks its shafts in order and inserts
// each row into the cell's table (the same table, hash and row compare as ls_insert_kernel), so a
// row not seen before starts the next set: sets numbered in the order of their first shaft, as
// ls_insert .. ls_shaft_set number them, with no atomics, no pass to resolve the heads and no
// ranks to look up per shaft (Sponza grid-ls 64³ N=3, PoCL: those passes took 0.95 s, this one
// 0.5 s; grid-ls glsl 128³ N=2: 1.95 against 1.1 s; docs/linespace-build.md). It packs the set
// indices into the cell's block words (the offsets' layout, top), keeps each shaft's index in
// ls_set_slot (the cell's shafts from c x 15 N^4) for the shafts that join it and for
// ls_cell_head_list_kernel, and its set count in ls_group_sets[c] (scanned next). A cell of
// several chunks has its non-empty shafts counted here from their rows (stats, ls_stats[3]), as
// ls_shaft_set_kernel does; where no loop budget can cut a cell (LS_CELL_STATS: PoCL) every
// shaft's are, and the candidates of all its shafts' lists (ls_stats[4], [5]), which the count
// then leaves out (LS_NO_COUNT_STATS: its atomics were 0.1 s of PoCL's 3.6 s, Sponza grid-ls
// 64³ N=3). All of a cell's probes run in one invocation: where a driver's loop budget cut them
// (geometry.h), ls_stats[2] counts the cell and the host finds that group's sets again by the
// passes per shaft (linespace.py; a group takes this pass only where its densest cell fits half
// the budget: cells_fit_loop_budget).
INLINE void ls_cell_find_sets_kernel(CTX_PARAM uint c) {
    uint shafts = V(ls_shafts);
    uint at = V(ls_cell_first) + c;
    uint len = V(ls_cell_ranges)[2u * at + 1u] - V(ls_cell_ranges)[2u * at];
    uint start0 = ls_row_start(CTX_ARG at, 0u, len);
    uint size = 2u * shafts;
    uint region = c * 2u * size;  // per slot: member + 1 (0: empty), then its row's hash
    uint b0 = c * shafts;
    uint log2_per = ls_index_log2(shafts);
    uint per_mask = (1u << log2_per) - 1u;
    uint bits = 32u >> log2_per;
    uint word_base = at * ls_block_words(shafts) + 1u;  // the block's words after its first
    if (c == 0u) V(ls_group_sets)[V(ls_cell_end) - V(ls_cell_first)] = 0u;  // the scan's total
    // The cell's table cleared here, where the probes will find it in the cache (a fill of the
    // group's whole table before this pass left every cell's first probes to miss).
    for (uint k = 0u; k < 2u * size; ++k) V(ls_set_table)[region + k] = 0u;
    uint sets = 0u;
    uint non_empty = 0u;
    uint sum_lo = 0u;  // LS_CELL_STATS: the cell's candidates in all its shafts' lists, as two words
    uint sum_hi = 0u;
    uint word = 0u;
    for (uint s = 0u; s < shafts; ++s) {
        uint start = start0 + s * len;
        uint h = LS_HASH_SEED;
        uint met = 0u;  // the shaft's candidates
        for (uint k = 0u; 32u * k < len; ++k) {
            uint w = ls_row_word(CTX_ARG start, len, k);
            h = ls_hash_word(h, w);
            met += POPCOUNT(w);
        }
#ifdef LS_CELL_STATS
        non_empty += met != 0u ? 1u : 0u;
        sum_hi += sum_lo + met < sum_lo ? 1u : 0u;
        sum_lo += met;
#else
        non_empty += len > V(ls_chunk) && met != 0u ? 1u : 0u;  // several count chunks (a loop budget)
#endif
        uint slot = MUL_HI(ls_hash_mask(h), size);
        uint index = sets;
        // Fewer sets than shafts, in 2 x 15 N^4 slots: an empty slot comes within `size` probes.
        for (uint probe = 0u; probe < size; ++probe) {
            uint member = V(ls_set_table)[region + 2u * slot];
            if (member == 0u) {
                V(ls_set_table)[region + 2u * slot] = s + 1u;
                V(ls_set_table)[region + 2u * slot + 1u] = h;
                sets += 1u;
                break;
            }
            // A row of one word (len <= 32) is its hash's only preimage (ls_hash_word is a
            // bijection of the word): equal hashes, equal rows, without reading the member's row.
            if (V(ls_set_table)[region + 2u * slot + 1u] == h &&
                (len <= 32u || ls_rows_equal(CTX_ARG start0 + (member - 1u) * len, start, len) != 0)) {
                index = V(ls_set_slot)[b0 + member - 1u];
                break;
            }
            slot = slot + 1u == size ? 0u : slot + 1u;
        }
        V(ls_set_slot)[b0 + s] = index;
        word |= index << (bits * (s & per_mask));
        if ((s & per_mask) == per_mask || s + 1u == shafts) {
            LS_SHAFT_SET_STORE(word_base + (s >> log2_per), word);
            word = 0u;
        }
    }
    V(ls_group_sets)[c] = sets;
    if (loops_intact(V(loop_probe)) == 0) ATOMIC_ADD(V(ls_stats)[2], 1u);
    if (non_empty > 0u) ATOMIC_ADD(V(ls_stats)[3], non_empty);  // the host keeps it where no cell was cut
#ifdef LS_CELL_STATS
    if (sum_lo > 0u) {
        uint before = ATOMIC_ADD(V(ls_stats)[4], sum_lo);
        sum_hi += before + sum_lo < before ? 1u : 0u;
    }
    if (sum_hi > 0u) ATOMIC_ADD(V(ls_stats)[5], sum_hi);
#endif
}
#endif

#ifdef KERNEL_ls_cell_head_list
// After ls_cell_find_sets_kernel and the scan of ls_group_sets (the sets of the group's cells
// before c): cell c's set count, and its heads in shaft order, a shaft being the head of set `next`
// where its index is `next` (sets are numbered by their first shaft), as global shaft numbers.
INLINE void ls_cell_head_list_kernel(CTX_PARAM uint c) {
    uint shafts = V(ls_shafts);
    uint b0 = c * shafts;
    uint rank = V(ls_group_sets)[c];
    uint sets = V(ls_group_sets)[c + 1u] - rank;
    V(ls_cell_sets)[V(ls_cell_first) + c] = sets;
    uint next = 0u;
    for (uint s = 0u; next < sets; ++s) {
        if (V(ls_set_slot)[b0 + s] == next) {
            V(ls_head_list)[rank + next] = V(ls_cell_first) * shafts + b0 + s;
            next += 1u;
        }
    }
}
#endif

#ifdef KERNEL_ls_heads
// ls_set_slot[b] becomes b's head; heads are flagged in ls_set_heads (one bit per group shaft)
// and counted per cell in ls_cell_sets.
INLINE void ls_heads_kernel(CTX_PARAM uint b) {
    uint head = V(ls_set_table)[V(ls_set_slot)[b]] - 1u;
    V(ls_set_slot)[b] = head;
    if (head == b) {
        ATOMIC_OR(V(ls_set_heads)[b >> 5u], 1u << (b & 31u));
        ATOMIC_ADD(V(ls_cell_sets)[(V(ls_cell_first) * V(ls_shafts) + b) / V(ls_shafts)], 1u);
    }
}
#endif

#ifdef KERNEL_ls_head_counts
// The heads in each word of ls_set_heads; the host scans them (exclusive) into ls_head_counts.
INLINE void ls_head_counts_kernel(CTX_PARAM uint w) {
    V(ls_head_counts)[w] = POPCOUNT(V(ls_set_heads)[w]);
}
#endif

#ifdef KERNEL_ls_shaft_set
// The heads among group shafts [0, x): those of the words before x's (ls_head_counts, the scanned
// per-word counts) and those of x's word below it. Two reads and a popcount per shaft, where
// counting the words from the cell's first shaft took up to 15 N^4 / 32 (38 at N = 3).
INLINE uint ls_heads_before(CTX_PARAM uint x) {
    uint w = x >> 5u;
    return V(ls_head_counts)[w] + rank_in_word(V(ls_set_heads)[w], x & 31u);
}

#ifdef LS_HEAD_LIST
// The head lists' builds (linespace.py): a work item per word of the group's cells' blocks (the
// offsets array's layout, top), its P shafts' set indices packed as ls_layout copies them (no set
// word per shaft, which ls_set_len reads in the other builds: Sponza grid-ls 64³ N=3 took 323 MiB of
// them where the packed words are 170 MiB); and the group's heads in shaft order, so that the set
// lengths and the fill visit only them (a head's rank among all heads is its set's global index:
// cells in order, a cell's sets in the order of their heads). A cell of several chunks (more
// candidates than ls_chunk) had a count item per chunk, none of which saw the whole row, so its
// non-empty shafts are counted here from their rows (stats, ls_stats[0]).
INLINE void ls_shaft_set_kernel(CTX_PARAM uint w) {
    uint shafts = V(ls_shafts);
    uint block = ls_block_words(shafts);
    uint cell = w / block;  // of the group
    uint j = w - cell * block;
    if (j == 0u) return;  // the cell's first set: ls_first_sets_kernel writes it
    uint log2_per = ls_index_log2(shafts);
    uint bits = 32u >> log2_per;
    uint first = (j - 1u) << log2_per;
    uint b0 = cell * shafts;
    uint before = ls_heads_before(CTX_ARG b0);
    uint at = V(ls_cell_first) + cell;
    uint len = V(ls_cell_ranges)[2u * at + 1u] - V(ls_cell_ranges)[2u * at];
    uint v = 0u;
    uint non_empty = 0u;
    for (uint k = 0u; k < (1u << log2_per) && first + k < shafts; ++k) {
        uint b = b0 + first + k;
        uint head = V(ls_set_slot)[b];
        uint rank = ls_heads_before(CTX_ARG head);
        v |= (rank - before) << (bits * k);
        if (head == b) V(ls_head_list)[rank] = V(ls_cell_first) * shafts + b;
        if (len > V(ls_chunk)) {
            uint start = ls_row_start(CTX_ARG at, first + k, len);
            uint any = 0u;
            for (uint q = 0u; 32u * q < len && any == 0u; ++q) any = ls_row_word(CTX_ARG start, len, q);
            non_empty += any != 0u ? 1u : 0u;
        }
    }
    LS_SHAFT_SET_STORE(V(ls_cell_first) * block + w, v);
    if (non_empty > 0u) ATOMIC_ADD(V(ls_stats)[0], non_empty);
}
#else
INLINE void ls_shaft_set_kernel(CTX_PARAM uint b) {
    uint shafts = V(ls_shafts);
    uint head = V(ls_set_slot)[b];
    uint index = ls_heads_before(CTX_ARG head) - ls_heads_before(CTX_ARG b - b % shafts);  // group shafts of one cell are aligned
    LS_SHAFT_SET_STORE(V(ls_cell_first) * shafts + b, index | (head == b ? LS_SET_HEAD : 0u));
}
#endif
#endif

#ifdef KERNEL_ls_head_len
// Where all cells' pair bits are kept and the densest row fits one invocation (linespace.py): set
// V(ls_head_base) + i is the set of head shaft ls_head_list[i], and its length the set bits of the
// head's row. Only the heads are visited (Sponza grid-ls 128³ N=2: 2.9 M of 74.8 M shafts), where
// ls_set_len_kernel reads every shaft's set word and marks its items; and the count keeps no
// count per shaft for these builds (LS_NO_ITEM_COUNTS: a buffer of 4 bytes per shaft, 323 MiB at
// Sponza grid-ls 64³ N=3, neither zeroed nor written), since the row holds it.
INLINE void ls_head_len_kernel(CTX_PARAM uint i) {
    LsRow row = ls_shaft_row(CTX_ARG V(ls_head_list)[i]);
    uint count = 0u;
    for (uint k = 0u; 32u * k < row.len; ++k) count += POPCOUNT(ls_row_word(CTX_ARG row.start, row.len, k));
    LS_SET_LEN_STORE(V(ls_head_base) + i, count);
}
#endif

#ifdef KERNEL_ls_head_fill
// The fill of those builds: head shaft ls_head_list[i] writes its row's candidates (the count's pair
// bits, list order) from its set's offset (the scanned lengths), as ls_shaft_kernel's fill from the
// bits does for an item, without visiting the other shafts' items.
INLINE void ls_head_fill_kernel(CTX_PARAM uint i) {
    LsRow row = ls_shaft_row(CTX_ARG V(ls_head_list)[i]);
    ls_fill_row(CTX_ARG row.start, row.len, LS_SET_LEN(V(ls_head_base) + i), 0u);
}
#endif

#ifdef KERNEL_ls_set_len
// The first count/fill item of shaft s (of all cells), its cell's items per shaft, and its cell.
STRUCT(LsItems) { uint first; uint chunks; uint cell; };

INLINE LsItems ls_shaft_items(CTX_PARAM uint s) {
    uint shafts = V(ls_shafts);
    LsItems it;
    it.cell = s / shafts;
    uint item0 = V(ls_item_bases)[it.cell];
    it.chunks = (V(ls_item_bases)[it.cell + 1u] - item0) / shafts;
    it.first = item0 + (s - it.cell * shafts) * it.chunks;
    return it;
}

// After the sets: each head writes its set's length, the sum of its items' counts (then scanned
// into the set offsets), and leaves in its items what the fill needs to find where each item's
// part of the list goes (ls_item_first): the set's index in its first item, the counts of the
// chunks before in each later one. Every other shaft's items get LS_SKIP. (Until the thirtieth
// session a pass of its own after the scan, ls_dest, wrote each item's place: Sponza grid-ls
// glsl 128³ N=2 0.88 s, opencl 64³ N=3 0.15 s.) The count kernel counted the non-empty shafts of
// one-chunk cells (stats); a shaft of several chunks, whose count items each saw one chunk, is
// counted here.
INLINE uint ls_set_len_of(CTX_PARAM uint s) {  // 1 where s is a non-empty shaft of several chunks
    uint set = LS_SHAFT_SET(s);
    bool head = (set & LS_SET_HEAD) != 0u;
#ifdef LS_ONE_CHUNK
    // Every cell one chunk (the variant linespace.py compiles for such builds): shaft s's item is s,
    // no lookup of its cell's items.
    if (!head) {
        LS_ITEM_STORE(s, LS_SKIP);
        return 0u;
    }
    uint index = V(ls_cell_sets)[s / V(ls_shafts)] + (set & ~LS_SET_HEAD);
    LS_SET_LEN_STORE(index, LS_ITEM(s));
    LS_ITEM_STORE(s, index);
    return 0u;
#else
    LsItems it = ls_shaft_items(CTX_ARG s);
    if (!head && it.chunks == 1u) {
        LS_ITEM_STORE(it.first, LS_SKIP);
        return 0u;
    }
    uint index = V(ls_cell_sets)[it.cell] + (set & ~LS_SET_HEAD);
    uint len = 0u;
    for (uint k = 0u; k < it.chunks; ++k) {
        uint count = LS_ITEM(it.first + k);
        LS_ITEM_STORE(it.first + k, head ? (k == 0u ? index : len) : LS_SKIP);
        len += count;
    }
    if (head) LS_SET_LEN_STORE(index, len);
    return it.chunks > 1u && len > 0u ? 1u : 0u;
#endif
}

#ifdef LS_NONEMPTY_STRIDE
// Where the lanes run in step (llvmpipe, GPUs): item g takes shafts g, g + M, g + 2M, ... (M items,
// ls_shaft_total shafts), so every lane loops as often as its neighbours and one atomic counts up
// to LS_NONEMPTY_STRIDE shafts (dense cells of several chunks can be many: one atomic per shaft was
// 0.83 of this kernel's 1.43 s on llvmpipe when it counted every shaft).
INLINE void ls_set_len_kernel(CTX_PARAM uint g) {
    uint non_empty = 0u;
    for (uint s = g; s < V(ls_shaft_total); s += V(n_items)) non_empty += ls_set_len_of(CTX_ARG s);
    if (non_empty > 0u) ATOMIC_ADD(V(ls_stats)[0], non_empty);
}
#else
INLINE void ls_set_len_kernel(CTX_PARAM uint s) {
    if (ls_set_len_of(CTX_ARG s) != 0u) ATOMIC_ADD(V(ls_stats)[0], 1u);
}
#endif
#endif

#ifdef KERNEL_ls_layout
// ---- Build: the Line Spaces' ls_shaft_offsets (layout at the top), one entry per work item ----
#ifdef LS_HEAD_LIST
// The head lists' builds: ls_shaft_set packed the blocks' set indices already, so the entries are
// a copy of those words and then the sets' offsets, with no division per entry to find a block's
// first word (that division was 0.25 of PoCL's 0.35 s here, Sponza grid-ls 64³ N=3):
// ls_first_sets_kernel writes the first words after this pass.
INLINE void ls_layout_kernel(CTX_PARAM uint e) {
    uint set_start = V(ls_cell_end) * ls_block_words(V(ls_shafts));
    LS_OFFSET_STORE(e, e >= set_start ? LS_SET_LEN(e - set_start) : LS_SHAFT_SET(e));
}
#else
INLINE void ls_layout_kernel(CTX_PARAM uint e) {
    uint shafts = V(ls_shafts);
    uint block = ls_block_words(shafts);
    uint set_start = V(ls_cell_end) * block;
    uint v;
    if (e >= set_start) v = LS_SET_LEN(e - set_start);
    else if (e % block == 0u) v = set_start + V(ls_cell_sets)[e / block];
    else {
        uint log2_per = ls_index_log2(shafts);
        uint bits = 32u >> log2_per;
        uint first = (e % block - 1u) << log2_per;
        uint s = (e / block) * shafts + first;
        v = 0u;
        for (uint k = 0u; k < (1u << log2_per) && first + k < shafts; k++)
            v |= (LS_SHAFT_SET(s + k) & ((1u << bits) - 1u)) << (bits * k);
    }
    LS_OFFSET_STORE(e, v);
}
#endif
#endif

#ifdef KERNEL_ls_first_sets
// Cell c's block starts with its first set's entry among the sets' offsets (layout at the top).
INLINE void ls_first_sets_kernel(CTX_PARAM uint c) {
    uint block = ls_block_words(V(ls_shafts));
    LS_OFFSET_STORE(c * block, V(ls_cell_end) * block + V(ls_cell_sets)[c]);
}
#endif

#ifdef KERNEL_ls_carry
// ---- Scan of a split offset array: add the total of the chunks before this one --------------
INLINE void ls_carry_kernel(CTX_PARAM uint gid) {
    V(ls_carry_chunk)[gid] += V(ls_carry);
}
#endif
