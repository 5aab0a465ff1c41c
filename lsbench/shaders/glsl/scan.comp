#version 450
// Prefix sum over uint32 for the GLSL backend (OpenCL uses pyopencl's scan instead).
// SCAN_BLOCKS: exclusive scan of each block of BLOCK items in shared memory (Hillis & Steele,
// log2(BLOCK) steps) and the block's total into block_sums. ADD_BLOCKS: add the scanned block
// totals back. backends/glsl.py recurses over the block sums.
layout(local_size_x = BLOCK) in;
layout(std430, binding = 0) buffer Data { uint data[]; };
layout(std430, binding = 1) buffer Sums { uint block_sums[]; };
uniform uint n_items;
shared uint tmp[BLOCK];

void main() {
    uint block = gl_WorkGroupID.y * gl_NumWorkGroups.x + gl_WorkGroupID.x;
    uint local_id = gl_LocalInvocationID.x;
    uint i = block * uint(BLOCK) + local_id;
    if (block * uint(BLOCK) >= n_items) return;  // whole group leaves together
#ifdef SCAN_BLOCKS
    uint x = i < n_items ? data[i] : 0u;
    tmp[local_id] = x;
    barrier();
    for (uint offset = 1u; offset < uint(BLOCK); offset <<= 1) {
        uint add = local_id >= offset ? tmp[local_id - offset] : 0u;
        barrier();
        tmp[local_id] += add;
        barrier();
    }
    if (i < n_items) data[i] = tmp[local_id] - x;
    if (local_id == uint(BLOCK) - 1u) block_sums[block] = tmp[local_id];
#endif
#ifdef ADD_BLOCKS
    if (i < n_items) data[i] += block_sums[block];
#endif
}
