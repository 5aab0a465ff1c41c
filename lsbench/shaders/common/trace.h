// What every traversal shares (Delgado Kraemer 2019, 3.3: all structures answer the same closest-hit query):
// rays and hits, the closest-hit rule, the work counters of profiling builds, the ray in grid
// space, and the one loop that tests a cell's candidate list, whatever the cell (grid voxel,
// grid-ls voxel, octree leaf) and wherever its list lives (voxel_tris or a Line Space shaft).
// Needs geometry.h, scene.h and, for LEAF_LINE_SPACE kernels, linespace.h.
//
// Buffers: rays (float4 pairs: origin.xyz + tmin, direction.xyz + tmax), hit_prim (int, -1 =
// miss), hit_t (float), voxel_tris (uint: the cells' plain candidate lists), tri_verts (float4: each
// triangle's vertices, load_candidate); work (uint4 per ray)
// in COUNT_WORK builds. Feature defines (set by the KernelSpec): LEAF_LINE_SPACE (cells may hold
// a Line Space: svo-ls, esvo-ls, grid-ls), COUNT_WORK (profiling counters), QUERY_ANY (the any-hit
// query of shadow and ambient-occlusion rays: is anything in [tmin, tmax)? The first hit found
// ends the candidate loop and the walk, so hit_prim/hit_t name *a* hit in that range, not the
// closest one; backends/structures/base.py: for_query).
//
// ---- Traversal in bounded slices (SLICED builds; issue 14) ------------------------------------
// llvmpipe ends a shader invocation's loops after 65535 iterations in all (geometry.h), and a real
// GPU has a watchdog: a ray that meets millions of candidates cannot run to its end in one
// launch. A SLICED kernel runs at most slice_budget loop iterations per ray (walk steps and
// candidate tests together), stores where the ray stopped, and the host re-dispatches only the
// unfinished rays (backends/__init__.py: trace) until none is left. The budget is a device
// property (Device.loop_budget; None = one launch runs whole rays and nothing of this compiles in).
//
// The API every walk uses (grid.h, svo.h, esvo.h; a new structure does the same):
//   kernel entry   uint ray = trace_ray(CTX_ARG gid);  (the slice's compacted ray list, or gid)
//                  store_hit(CTX_ARG ray, trace_<walk>(CTX_ARG load_ray(CTX_ARG ray), ray));
//   walk start     Trace tr = trace_start(CTX_ARG ray, id);  tr.resumed != 0: the ray ran in an
//                  earlier slice; tr.wa / tr.wb hold the 8 words the walk saved, and the walk
//                  restores its loop state from them instead of starting at the ray's entry.
//   loop top       tr = trace_tick(tr);  if (TRACE_SUSPENDED(tr)) { save; break; }
//   a cell's loop  tr = trace_revisit(tr, n);  where a step takes n more loop iterations than its
//                  tick (a cell whose candidates an outer loop tests: grid.h's non-empty voxels
//                  in its inner loop, n = 1; the octree walks' leaves, n = 2: svo.h, esvo.h)
//   after a cell   tr = test_candidates(CTX_ARG tr, c);  if (TRACE_SUSPENDED(tr)) { save; break; }
//                  (before trace_done: a cell whose list the budget cut must finish first)
//   save           tr.wa = ...; tr.wb = ...;  the walk's loop state at the top of the iteration
//                  that did not finish, exactly (no restart from a distance: the resumed walk is
//                  the same walk, so hits are bit-identical to one launch and no cell is skipped);
//                  the cell's candidate index is trace.h's (a list longer than the budget resumes
//                  inside it), as are the best hit and the work counters.
//   walk end       return trace_finish(CTX_ARG tr, id);
// Per ray the state is SLICE_WORDS uints in slice_state (the compacted ray list of the slice
// follows them, at slice_list_base). A suspended ray reports SLICE_PENDING as its hit; a ray
// whose loops the driver still cut (the budget is per lane, llvmpipe's limit per SIMD group, and
// lanes diverge) reports LOOP_CUT_PRIM and keeps its state of before the slice, so the host
// reruns it with a smaller budget; only at the smallest (MIN_SLICE_BUDGET, backends/__init__.py)
// is the cut a failure (the last guard).


STRUCT(Ray) { float3 o; float tmin; float3 d; float tmax; };

INLINE Ray load_ray(CTX_PARAM uint ray) {
    float4 o = V(rays)[2u * ray];
    float4 d = V(rays)[2u * ray + 1u];
    Ray r;
    r.o = o.xyz;
    r.tmin = o.w;
    r.d = d.xyz;
    r.tmax = d.w;
    return r;
}

STRUCT(Hit) { float t; int prim; };

INLINE Hit no_hit(float tmax) { Hit h; h.t = tmax; h.prim = -1; return h; }

INLINE void store_hit(CTX_PARAM uint ray, Hit h) {
    V(hit_prim)[ray] = h.prim;
    V(hit_t)[ray] = h.prim >= 0 ? h.t : INF_F;
}

// Closest-hit update with a deterministic tie-break (smaller id wins at equal t), so a run
// gives the same ids whatever order the candidates arrive in (fill order is not deterministic).
// Only a hit before tmax counts, so a miss (t = INF_F) never becomes one while best.t = tmax = inf.
INLINE Hit closer(Hit best, float t, int prim, float tmin) {
    if (t >= tmin && (t < best.t || (t == best.t && best.prim >= 0 && prim < best.prim))) {
        best.t = t;
        best.prim = prim;
    }
    return best;
}

// Hit id of a ray whose loops the driver cut short (the probe of geometry.h); backends.trace fails
// the case naming the limit.
#define LOOP_CUT_PRIM -2
INLINE Hit cut_hit(CTX_PARAM Hit best) {
    if (loops_intact(V(loop_probe)) == 0) best.prim = LOOP_CUT_PRIM;
    return best;
}

// Hit id of a ray a SLICED kernel suspended: it runs on in the next slice.
#define SLICE_PENDING -3
// Words of slice_state per ray: 0 phase (0 fresh, 1 suspended), 1 candidate index to resume at,
// 2 best t (bits), 3 best prim, 4-7 work counters (iterations, tests, lookups, clock so far),
// 8-15 the walk's words (wa, wb).
#define SLICE_WORDS 16u

#define ORDER_PREFETCH_AHEAD 4u
// The ray this work item traces: the slice's list entry (SLICED), the sorted order's
// (ORDERED_RAYS: order_ids, backends/ray_order.py) or the item itself.
INLINE uint trace_ray(CTX_PARAM uint gid) {
#ifdef SLICED
    return V(slice_state)[V(slice_list_base) + gid];
#elif defined(ORDERED_RAYS)
    // The rays of a sorted order lie scattered: where work items run one after the other (PoCL),
    // the ray 4 items ahead and its hit slots are prefetched, else each ray's first load waits for
    // memory (Sponza 256² incoherent, bvh on PoCL: 27.4 ms without, 21.6 with, 24.6 in the given
    // order; BMW 10.4, 5.0 and 4.8 ms). PREFETCH is nothing on GPUs and in GLSL (preludes).
    if (gid + ORDER_PREFETCH_AHEAD < V(n_items)) {
        uint ahead = V(order_ids)[gid + ORDER_PREFETCH_AHEAD];
        PREFETCH(&V(rays)[2u * ahead]);
        PREFETCH(&V(hit_prim)[ahead]);
        PREFETCH(&V(hit_t)[ahead]);
    }
    return V(order_ids)[gid];
#else
    return gid;
#endif
}

// Tick source of CLOCK_START()/CLOCK_ELAPSED() (preludes). USE_CLOCK and CLOCK_PTX come from
// Device.clock_defines (backends/glsl.py, backends/opencl.py) only in COUNT_WORK builds and only
// where the device has a clock; every other build reads 0, so the counters' clock field is 0.
#if defined(USE_CLOCK) && defined(LANG_GLSL)
#define CLOCK_NOW() clock2x32ARB().x
#elif defined(USE_CLOCK) && defined(CLOCK_PTX)
INLINE uint clock_now_ptx(void) {
    uint c;
    __asm__ __volatile__("mov.u32 %0, %%clock;" : "=r"(c));
    return c;
}
#define CLOCK_NOW() clock_now_ptx()
#else
#define CLOCK_NOW() 0u
#endif

// ---- One traversal's state ---------------------------------------------------------------------
// The ray prepared for the watertight triangle test, the closest hit so far, and the work
// counters (iterations of the walk, candidate tests, Line Space lookups, clock at the start),
// which only COUNT_WORK builds store: the compiler drops them from the timed kernels.
// SLICED builds add the slice's budget left, whether the budget ran out (suspended), the
// candidate index to resume at in the first cell, whether this ray resumes (resumed), the
// clock of earlier slices and the walk's saved words (wa, wb); the other builds never read them.
STRUCT(Trace) {
    WRay wr; float tmin; Hit best; uint iterations; uint tests; uint lookups; uint clock0;
    uint budget; int suspended; uint resume; int resumed; uint clock_before; uint4 wa; uint4 wb;
};

#ifdef SLICED
#define TRACE_SUSPENDED(tr) ((tr).suspended != 0)
#else
#define TRACE_SUSPENDED(tr) (0 != 0)
#endif

INLINE Trace trace_start(CTX_PARAM Ray r, uint ray) {
    Trace tr;
    tr.clock0 = CLOCK_START();
    tr.best = no_hit(r.tmax);
    tr.wr = make_wray(r.o, r.d);
    tr.tmin = r.tmin;
    tr.iterations = 0u;
    tr.tests = 0u;
    tr.lookups = 0u;
    tr.budget = 0u;
    tr.suspended = 0;
    tr.resume = 0u;
    tr.resumed = 0;
    tr.clock_before = 0u;
    tr.wa = make_uint4(0u, 0u, 0u, 0u);
    tr.wb = make_uint4(0u, 0u, 0u, 0u);
#ifdef SLICED
    tr.budget = V(slice_budget);
    uint base = SLICE_WORDS * ray;
    if (V(slice_state)[base] != 0u) {
        tr.resumed = 1;
        tr.resume = V(slice_state)[base + 1u];
        tr.best.t = as_float(V(slice_state)[base + 2u]);
        tr.best.prim = I32(V(slice_state)[base + 3u]);
        tr.iterations = V(slice_state)[base + 4u];
        tr.tests = V(slice_state)[base + 5u];
        tr.lookups = V(slice_state)[base + 6u];
        tr.clock_before = V(slice_state)[base + 7u];
        tr.wa = make_uint4(V(slice_state)[base + 8u], V(slice_state)[base + 9u], V(slice_state)[base + 10u],
                           V(slice_state)[base + 11u]);
        tr.wb = make_uint4(V(slice_state)[base + 12u], V(slice_state)[base + 13u], V(slice_state)[base + 14u],
                           V(slice_state)[base + 15u]);
    }
#endif
    return tr;
}

// One step of the walk (a cell or node visited), at the top of the walk's loop: counted, and in a
// SLICED build paid from the budget; with none left the ray suspends before the step.
INLINE Trace trace_tick(Trace tr) {
#ifdef SLICED
    if (tr.budget == 0u) {
        tr.suspended = 1;
        return tr;
    }
    tr.budget -= 1u;
#endif
    tr.iterations += 1u;
    return tr;
}

// Loop iterations besides trace_tick's for one step (a walk that crosses the cells without
// candidates in an inner loop and tests a cell's candidates in the outer one: grid.h, svo.h, esvo.h):
// paid from the budget too, since the driver counts every loop's iterations; with fewer than `n`
// left the ray suspends before the step, which the resumed walk then takes (and counts) again.
INLINE Trace trace_revisit(Trace tr, uint n) {
#ifdef SLICED
    if (tr.budget < n) {
        tr.suspended = 1;
        tr.iterations -= 1u;
        return tr;
    }
    tr.budget -= n;
#endif
    return tr;
}

// The walk may stop: the closest hit lies before t (the current cell's exit), so no later cell
// can hold a nearer one. An any-hit query stops at the first hit: closer() took it only inside
// [tmin, tmax), and any such hit answers "occluded".
#ifdef QUERY_ANY
INLINE int trace_done(Trace tr, float t) { return tr.best.prim >= 0 ? 1 : 0; }
#else
INLINE int trace_done(Trace tr, float t) { return (tr.best.prim >= 0 && tr.best.t <= t) ? 1 : 0; }
#endif

// The hit to store: the counters written first (COUNT_WORK), then the loop probe (geometry.h).
// SLICED: the probe first, and only an intact invocation stores anything: a suspended ray its
// state (reporting SLICE_PENDING), a finished one its counters and hit.
INLINE Hit trace_finish(CTX_PARAM Trace tr, uint ray) {
#ifdef SLICED
    Hit h = tr.best;
    if (loops_intact(V(loop_probe)) == 0) {
        h.prim = LOOP_CUT_PRIM;  // the state of before this slice stands: the host reruns the ray
        return h;
    }
    uint clock = tr.clock_before + CLOCK_ELAPSED(tr.clock0);
    if (tr.suspended != 0) {
        uint base = SLICE_WORDS * ray;
        V(slice_state)[base] = 1u;
        V(slice_state)[base + 1u] = tr.resume;
        V(slice_state)[base + 2u] = as_uint(tr.best.t);
        V(slice_state)[base + 3u] = U32(tr.best.prim);
        V(slice_state)[base + 4u] = tr.iterations;
        V(slice_state)[base + 5u] = tr.tests;
        V(slice_state)[base + 6u] = tr.lookups;
        V(slice_state)[base + 7u] = clock;
        V(slice_state)[base + 8u] = tr.wa.x;
        V(slice_state)[base + 9u] = tr.wa.y;
        V(slice_state)[base + 10u] = tr.wa.z;
        V(slice_state)[base + 11u] = tr.wa.w;
        V(slice_state)[base + 12u] = tr.wb.x;
        V(slice_state)[base + 13u] = tr.wb.y;
        V(slice_state)[base + 14u] = tr.wb.z;
        V(slice_state)[base + 15u] = tr.wb.w;
        h.prim = SLICE_PENDING;
        return h;
    }
#ifdef COUNT_WORK
    V(work)[ray] = make_uint4(tr.iterations, tr.tests, tr.lookups, clock);
#endif
    return h;
#else
#ifdef COUNT_WORK
    V(work)[ray] = make_uint4(tr.iterations, tr.tests, tr.lookups, CLOCK_ELAPSED(tr.clock0));
#endif
    return cut_hit(CTX_ARG tr.best);
#endif
}

// The ray in grid space (scene.h), for walks over cells and for Line Space lookups: o is the point
// of the ray's line at t = t_base, and a walk measures t from there: its t is t_base + t in world
// terms (trace_done takes the world t). Near the box t_base is 0 and o the ray's origin; from far
// away (GRID_NEAR_VOXELS) o is the line's point nearest the box's centre. span: where [tmin, tmax]
// lies in the box, from t_base (span.x > span.y: the ray misses the box). voxel_t: one voxel edge
// along the ray's main axis, in t (the most t a chord through one voxel can span along that axis).
// Unused fields cost nothing: the compiler drops them.
// Why the move, and why in double: an origin 1e4 scene diagonals away lies millions of voxels
// from the box (2.2e6 at 128³), where float32 grid coordinates are 0.25 voxels apart and t values
// (1.7e5 for a 17-unit scene) 0.016 apart. The grid walk took its entry cell from such a point and
// stepped t there by adding one voxel's t (0.13) per step, rounded each time: it drifted off the
// ray's line, past the build's overlap margin (BOX_EPS 1e-3 voxels), and lost hits
// (tests/test_far_origins.py: 242 of 1024 rays at 128³). The far frame's point is placed in double
// (preludes: F64; a dozen multiply-adds, no division), exactly on the ray's line for its t_base,
// which itself need not be exact: so the walk starts on the line to float32 precision of the box's
// own coordinates and its t values stay as small as the box. Within GRID_NEAR_VOXELS of the box's
// centre, float32 grid coordinates are at most 2^-13 voxels apart, an eighth of BOX_EPS, and the
// origin serves as it is (the double path cost PoCL 2 % of Sponza's primary rays for nothing there).
#define GRID_NEAR_VOXELS 1024.0f
STRUCT(GridRay) { float3 o; float3 d; float3 inv; float voxel_t; float t_base; float2 span; };

INLINE GridRay make_grid_ray(CTX_PARAM Ray r) {
    GridRay g;
    float3 scale = V(grid_inv_voxel).xyz;
    float3 box = make_float3(F32(V(grid_res).x), F32(V(grid_res).y), F32(V(grid_res).z));
    g.d = r.d * scale;
    g.inv = make_float3(safe_rcp(g.d.x), safe_rcp(g.d.y), safe_rcp(g.d.z));
    g.voxel_t = 1.0f / max(fabs(g.d.x), max(fabs(g.d.y), fabs(g.d.z)));
    g.o = to_grid(CTX_ARG r.o);
    g.t_base = 0.0f;
    float3 off = g.o - 0.5f * box;
    if (max(fabs(off.x), max(fabs(off.y), fabs(off.z))) > GRID_NEAR_VOXELS) {
        // Far: the frame's point is the line's nearest to the box's centre. Its t from the float32
        // origin is rough (any t near the box serves); the point itself is exact: the origin
        // and direction in grid space are exact in double (products and differences of floats),
        // so is o + d t_base up to one rounding.
        g.t_base = -dot(off, g.d) / dot(g.d, g.d);
        double3 scale64 = F64_3(scale);
        double3 o = (F64_3(r.o) - F64_3(V(grid_origin).xyz)) * scale64;
        g.o = F32_3(o + F64_3(r.d) * scale64 * F64(g.t_base));
    }
    float2 span = ray_box(g.o, g.inv, g.d, make_float3(0.0f, 0.0f, 0.0f), box);
    g.span = make_float2(max(span.x, r.tmin - g.t_base), min(span.y, r.tmax - g.t_base));
    return g;
}

// ---- A cell's candidates and the loop that tests them ----------------------------------------
// begin..end in voxel_tris (a plain list), or with from_shaft in a Line Space shaft's list
// (LS_LOCAL_ID, linespace.h), whose entries are positions in the cell's plain list, which starts
// at voxel_tris[base].
STRUCT(Candidates) { uint begin; uint end; int from_shaft; uint base; };

INLINE Candidates plain_list(uint begin, uint end) {
    Candidates c;
    c.begin = begin;
    c.end = end;
    c.from_shaft = 0;
    c.base = begin;
    return c;
}

#ifdef LEAF_LINE_SPACE
// The cell with index `cell` (a voxel, an octree leaf) has Line Space ls_ids[cell] iff
// ls_ids[cell + 1] > ls_ids[cell] (ls_ids: exclusive scan of the "has a Line Space" flags);
// LS_NONE otherwise.
#define LS_NONE 0xffffffffu
INLINE uint cell_line_space(CTX_PARAM uint cell) {
    uint ls = LD_U(ls_ids, cell);
    return LD_U(ls_ids, cell + 1u) > ls ? ls : LS_NONE;
}

// The candidates of shaft `shaft` (ls_shaft_id, linespace.h) of Line Space `ls`: its block's
// first set and the shaft's 8- or 16-bit set index, then that set's range (layout: top of
// linespace.h); `cell` is the cell's plain list, which the set's cell-local ids index.
INLINE Candidates shaft_list(CTX_PARAM uint ls, uint shaft, Candidates cell) {
    uint shafts = V(ls_shafts);
    uint log2_per = ls_index_log2(shafts);
    uint block = ls * ls_block_words(shafts);
    uint word = LS_OFFSET(block + 1u + (shaft >> log2_per));
    uint set = LS_OFFSET(block) + ls_set_index(word, shaft, log2_per);
    Candidates c;
    c.begin = LS_OFFSET(set);
    c.end = LS_OFFSET(set + 1u);
    c.from_shaft = 1;
    c.base = cell.begin;
    return c;
}
#endif

// A candidate's vertices from tri_verts (float4 triples in triangle order, bound by every trace
// kernel: backends/kernels.py TRACE_SCENE_BUFFERS): one contiguous record, no face-index indirection.
// LIST_ORDER_RECORDS: the structure binds its own tri_verts with the records in the order of its
// plain lists (voxel_tris), and the candidate loop loads the record at the list position (`bvh`,
// whose leaves are ranges of one list: a leaf's records are then adjacent, and their load does not
// wait for the id's); the id still comes from voxel_tris.
// The records' w components hold the triangle's unit normal (geometry.h: triangle_plane_t).
STRUCT(TriRecord) { float3 a; float3 b; float3 c; float3 n; };

INLINE TriRecord load_candidate(CTX_PARAM uint tri) {
    float4 a = LD_F4(tri_verts, 3u * tri);
    float4 b = LD_F4(tri_verts, 3u * tri + 1u);
    float4 c = LD_F4(tri_verts, 3u * tri + 2u);
    TriRecord t;
    t.a = a.xyz;
    t.b = b.xyz;
    t.c = c.xyz;
    t.n = make_float3(a.w, b.w, c.w);
    return t;
}

// Candidates are tested against the original ray (the watertight test of geometry.h, so t is the
// world distance). Every hit is kept, wherever along the ray it lies: the walk ends only once the
// closest hit lies before the current cell's exit (trace_done), so a farther hit of a triangle that
// spans several cells is beaten by any nearer one in the cells still to come. (A hit past the exit
// used to be thrown away, so a triangle listed in no later cell was lost when float rounding put
// its t a hair beyond the exit: strips in the grid's boundary planes, issue 13 item 1.)
// QUERY_ANY: the loop ends at the first hit in [tmin, tmax) (trace_done then ends the walk).
// SLICED: each test is paid from the budget; the first cell after a resume starts at the saved
// index, and a list the budget cuts saves the index of its first untested candidate (the walk's
// step and lookup of this cell are then uncounted: the resumed walk visits it again).
INLINE Trace test_candidates(CTX_PARAM Trace tr, Candidates c) {
    uint start = c.begin + tr.resume;
    uint i = start;
    tr.resume = 0u;
    for (; i < c.end; ++i) {
#ifdef SLICED
        if (tr.budget == 0u) {
            tr.suspended = 1;
            tr.resume = i - c.begin;
            tr.iterations -= 1u;
            tr.lookups -= U32(c.from_shaft);
            break;
        }
        tr.budget -= 1u;
#endif
#ifdef LEAF_LINE_SPACE
        uint tri = LD_U(voxel_tris, c.from_shaft != 0 ? c.base + LS_LOCAL_ID(i) : i);
#else
        uint tri = LD_U(voxel_tris, i);
#endif
#ifdef LIST_ORDER_RECORDS
        TriRecord T = load_candidate(CTX_ARG i);
#else
        TriRecord T = load_candidate(CTX_ARG tri);
#endif
        float t = ray_triangle_wt(tr.wr, T.a, T.b, T.c, T.n);
        tr.best = closer(tr.best, t, I32(tri), tr.tmin);
#ifdef QUERY_ANY
        if (tr.best.prim >= 0) { ++i; break; }
#endif
    }
    tr.tests += i - start;
    tr.lookups += U32(c.from_shaft);
    return tr;
}
