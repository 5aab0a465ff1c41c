// Raster voxelizer, stage 3: this fragment is one voxel column; test its depth neighbours.
flat in uint v_tri;
flat in int v_axis;

void main() {
    voxelize_column(v_tri, v_axis, int(floor(gl_FragCoord.x)), int(floor(gl_FragCoord.y)));
}
