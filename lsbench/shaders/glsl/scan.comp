#version 450
// Prefix sum over uint32 for the GLSL backend (OpenCL uses pyopencl's scan instead).
// A work group of BLOCK invocations scans BLOCK * CHUNK consecutive items: each invocation scans
// its CHUNK items serially, the BLOCK chunk totals are scanned in shared memory (Hillis & Steele,
// log2(BLOCK) steps), and each invocation adds its chunk's offset. llvmpipe runs a barrier as a
// switch of every invocation of the group, so the serial chunks cut the barriers per item by CHUNK
// (docs/linespace-build.md: the scans of a Line Space build took 4.4 s of 32 with one item per
// invocation). SCAN_BLOCKS: the exclusive scan of each block, its total into block_sums;
// ADD_BLOCKS: add the scanned block totals back. backends/glsl.py recurses over the block sums.
layout(local_size_x = BLOCK) in;
layout(std430, binding = 0) buffer Data { uint data[]; };
layout(std430, binding = 1) buffer Sums { uint block_sums[]; };
uniform uint n_items;
shared uint tmp[BLOCK];

void main() {
    uint block = gl_WorkGroupID.y * gl_NumWorkGroups.x + gl_WorkGroupID.x;
    uint local_id = gl_LocalInvocationID.x;
    uint first = block * uint(BLOCK * CHUNK);
    if (first >= n_items) return;  // whole group leaves together
    uint begin = first + local_id * uint(CHUNK);
    uint end = min(begin + uint(CHUNK), n_items);
#ifdef SCAN_BLOCKS
    uint total = 0u;
    for (uint i = begin; i < end; ++i) total += data[i];
    tmp[local_id] = total;
    barrier();
    for (uint offset = 1u; offset < uint(BLOCK); offset <<= 1) {
        uint add = local_id >= offset ? tmp[local_id - offset] : 0u;
        barrier();
        tmp[local_id] += add;
        barrier();
    }
    uint running = tmp[local_id] - total;  // exclusive: the chunks before this one
    for (uint i = begin; i < end; ++i) {
        uint x = data[i];
        data[i] = running;
        running += x;
    }
    if (local_id == uint(BLOCK) - 1u) block_sums[block] = tmp[local_id];
#endif
#ifdef ADD_BLOCKS
    uint add = block_sums[block];
    for (uint i = begin; i < end; ++i) data[i] += add;
#endif
}
