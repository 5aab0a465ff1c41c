// The scene's triangles, in world and in grid space, for every kernel that binds the scene
// buffers (voxelization, Line Space count/fill, the BVH build), and grid space for every
// traversal too. Needs geometry.h.
// Buffers: vertices (float, xyz packed), faces (uint, 3 per triangle); not bound by traversals
// (TRIANGLE_RECORDS: they read trace.h's tri_verts instead, backends/kernels.py).
// Uniforms: grid_origin, grid_inv_voxel (float4), grid_res (int4).

STRUCT(Triangle) { float3 a; float3 b; float3 c; };

#ifndef TRIANGLE_RECORDS  // traversals read trace.h's tri_verts records and bind no vertices/faces
INLINE float3 load_vertex(CTX_PARAM uint i) {
    return make_float3(V(vertices)[3u * i], V(vertices)[3u * i + 1u], V(vertices)[3u * i + 2u]);
}

INLINE Triangle load_triangle(CTX_PARAM uint tri) {
    Triangle t;
    t.a = load_vertex(CTX_ARG V(faces)[3u * tri]);
    t.b = load_vertex(CTX_ARG V(faces)[3u * tri + 1u]);
    t.c = load_vertex(CTX_ARG V(faces)[3u * tri + 2u]);
    return t;
}
#endif

// ---- Grid space ------------------------------------------------------------------------------
// Every structure lays its cells over the scene in grid space: p' = (p - grid_origin) *
// grid_inv_voxel, so voxel (i,j,k) is the unit cube [i,i+1]x[j,j+1]x[k,k+1] and voxel index =
// i + rx*(j + ry*k). Affine maps keep the ray parameter, so a t found in grid space is the world
// distance along the unit direction. The octrees use the bounding cube's cubic voxels (Delgado
// Kraemer 2019, 3.3.2, 5.2.1), anchored at grid_origin, with grid_res the scene's box in them (octree.h).
INLINE float3 to_grid(CTX_PARAM float3 p) {
    return (p - V(grid_origin).xyz) * V(grid_inv_voxel).xyz;
}

#ifndef TRIANGLE_RECORDS
INLINE Triangle load_grid_triangle(CTX_PARAM uint tri) {
    Triangle t = load_triangle(CTX_ARG tri);
    t.a = to_grid(CTX_ARG t.a);
    t.b = to_grid(CTX_ARG t.b);
    t.c = to_grid(CTX_ARG t.c);
    return t;
}
#endif

INLINE uint voxel_index(CTX_PARAM int3 c) {
    int3 r = V(grid_res).xyz;
    return U32(c.x) + U32(r.x) * (U32(c.y) + U32(r.y) * U32(c.z));
}
