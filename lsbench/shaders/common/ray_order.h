// Ray reordering for ray sets without locality (backends/ray_order.py): the rays are traced in the
// order of the cell of their origin, so that rays traced one after another (a work group, or on a
// CPU device one work item after the other) start in the same part of the structure and find its
// nodes, cells and triangles in the cache. A counting sort over ORDER_CELLS cells of the structure's
// bounds (ORDER_BITS per axis, cells numbered along the Morton curve), on the device and timed with
// the trace: zero the counts, count (one atomic per ray), an exclusive scan of the counts (one work
// item: ORDER_CELLS additions), place (one atomic per ray gives its slot, which gets the ray's id).
// The rays stay where they are: the trace's work item g traces ray order_ids[g] (trace.h,
// ORDERED_RAYS; in slices, the first slice's ray list is order_ids) and stores its hit at the ray's
// own index, so no hit moves either (copying the rays into slot order and the hits back took 2.0 of
// the 3.3 ms the sort took for 65,536 rays on PoCL). Rays in one cell keep no particular order (the
// atomics decide), which changes no hit: every ray is traced alone.
// Buffers: rays (the set's float4 pairs), order_counts (uint per cell), order_ids (uint per slot:
// the ray traced there). Uniforms: order_origin (the bounds' low corner), order_scale (cells per
// unit along each axis).

#define ORDER_BITS 4
#define ORDER_CELLS 4096u  // 2^(3 * ORDER_BITS)

#if defined(KERNEL_ray_order_count) || defined(KERNEL_ray_order_place)
INLINE uint order_spread4(uint x) {  // 4 bits -> every third bit
    x &= 0xfu;
    x = (x | (x << 4)) & 0x0c3u;
    x = (x | (x << 2)) & 0x249u;
    return x;
}

INLINE uint order_cell(CTX_PARAM uint ray) {
    float4 o = V(rays)[2u * ray];
    float3 c = (o.xyz - V(order_origin).xyz) * V(order_scale).xyz;
    uint top = U32((1 << ORDER_BITS) - 1);  // origins outside the bounds take the nearest cell; the
    uint x = min(U32(clamp(c.x, 0.0f, F32(top))), top);  // min keeps a NaN's conversion in range
    uint y = min(U32(clamp(c.y, 0.0f, F32(top))), top);
    uint z = min(U32(clamp(c.z, 0.0f, F32(top))), top);
    return order_spread4(x) | (order_spread4(y) << 1) | (order_spread4(z) << 2);
}
#endif

#ifdef KERNEL_ray_order_zero
INLINE void ray_order_zero_kernel(CTX_PARAM uint cell) { V(order_counts)[cell] = 0u; }
#endif

#ifdef KERNEL_ray_order_count
INLINE void ray_order_count_kernel(CTX_PARAM uint ray) {
    ATOMIC_ADD(V(order_counts)[order_cell(CTX_ARG ray)], 1u);
}
#endif

#ifdef KERNEL_ray_order_scan
INLINE void ray_order_scan_kernel(CTX_PARAM uint gid) {
    uint sum = 0u;
    for (uint cell = 0u; cell < ORDER_CELLS; ++cell) {
        uint count = V(order_counts)[cell];
        V(order_counts)[cell] = sum;
        sum += count;
    }
}
#endif

#ifdef KERNEL_ray_order_place
INLINE void ray_order_place_kernel(CTX_PARAM uint ray) {
    uint slot = ATOMIC_ADD(V(order_counts)[order_cell(CTX_ARG ray)], 1u);
    V(order_ids)[slot] = ray;
}
#endif
