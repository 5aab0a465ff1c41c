// Raster voxelizer, stage 2 (Delgado Kraemer 2019, 3.4): project the triangle along its dominant normal axis
// and dilate its footprint so that every voxel column it touches gets a fragment. llvmpipe has
// no conservative rasterization, so the footprint is the triangle's projected bounds grown by
// half a pixel plus the overlap epsilon (and a snapping margin): a pixel centre lies inside exactly when its column
// square (grown by eps) meets the bounds. Over-covered columns are rejected per fragment by the
// exact triangle/box test.
layout(points) in;
layout(triangle_strip, max_vertices = 4) out;
flat out uint v_tri;
flat out int v_axis;
uniform float viewport_size;

void main() {
#ifdef VOXELIZE_MAX_CELLS
    uint tri = raster_tris[1u + uint(gl_PrimitiveIDIn)];  // the triangles the compute pass left (grid.h)
#else
    uint tri = uint(gl_PrimitiveIDIn);
#endif
    Triangle t = load_triangle(tri);
    vec3 a = to_grid(t.a), b = to_grid(t.b), c = to_grid(t.c);
    vec3 n = abs(cross(b - a, c - a));
    int w = (n.x >= n.y && n.x >= n.z) ? 0 : (n.y >= n.z ? 1 : 2);
    int u = (w + 1) % 3, v = (w + 2) % 3;
    // + 1/32 px: rasterizers snap vertices to 1/256 px (llvmpipe, NVIDIA), which would eat a
    // smaller margin and put a column centre exactly on the footprint edge.
    float r = 0.5 + box_eps + 1.0 / 32.0;
    vec2 lo = vec2(min(a[u], min(b[u], c[u])), min(a[v], min(b[v], c[v]))) - vec2(r);
    vec2 hi = vec2(max(a[u], max(b[u], c[u])), max(a[v], max(b[v], c[v]))) + vec2(r);
    // Footprint entirely off the grid: nothing to draw.
    if (hi.x < 0.0 || hi.y < 0.0 || lo.x > float(grid_res[u]) || lo.y > float(grid_res[v])) return;
    lo = max(lo, vec2(-1.0));
    hi = min(hi, vec2(viewport_size + 1.0));
    vec2 s = 2.0 / vec2(viewport_size);
    vec2 corner[4] = vec2[4](vec2(lo.x, lo.y), vec2(hi.x, lo.y), vec2(lo.x, hi.y), vec2(hi.x, hi.y));
    for (int i = 0; i < 4; ++i) {
        v_tri = tri;
        v_axis = w;
        gl_Position = vec4(corner[i] * s - 1.0, 0.0, 1.0);
        EmitVertex();
    }
    EndPrimitive();
}
