// Raster voxelizer, stage 1: one point per triangle; the geometry shader fetches the corners.
void main() { gl_Position = vec4(0.0); }
