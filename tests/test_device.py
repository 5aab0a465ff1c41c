"""Device buffers: what the builds rely on from every backend's alloc and fill_zero."""
from __future__ import annotations

import numpy as np
import pytest


@pytest.mark.parametrize("nbytes", [4, 1020, 4 * 1000003])
def test_fill_zero_clears_the_given_bytes_only(device, nbytes):
    """fill_zero(buf, n) zeroes the first n bytes and leaves the rest (PoCL clears by a kernel on
    all cores, with a partial last work group; llvmpipe by the driver's clear)."""
    words = nbytes // 4 + 37
    pattern = np.arange(1, words + 1, dtype=np.uint32) * np.uint32(2654435761)
    buf = device.upload("pattern", pattern)
    try:
        device.fill_zero(buf, nbytes)
        got = device.read(buf, np.uint32)
        assert not got[: nbytes // 4].any()
        np.testing.assert_array_equal(got[nbytes // 4:], pattern[nbytes // 4:])
        device.fill_zero(buf)
        assert not device.read(buf, np.uint32).any()
    finally:
        device.release(buf)


def test_alloc_zeroed(device):
    buf = device.alloc("zeroed", 4 * 300007, zero=True)
    try:
        assert not device.read(buf, np.uint32).any()
    finally:
        device.release(buf)


def test_glsl_reads_structures_as_texels_within_the_driver_limit(monkeypatch):
    """GLSL trace kernels read their structure as buffer textures ("t" buffers, kernels.Buf): the
    device's per-buffer limit covers a uint buffer texture, the hits and work are OpenCL's, a
    released buffer's textures go with it (GL may give its name to the next buffer), and a buffer
    past the texel limit fails the launch naming it."""
    from lsbench import backends
    from lsbench.backends import BuildParams
    from lsbench.backends.device import DeviceLimitError
    from lsbench.inputs.rays import make_rays
    from lsbench.inputs.scenes import load_scene

    glsl = backends.get_device("glsl")
    info = glsl.info()
    assert glsl.max_buffer_bytes == min(int(glsl.ctx.info["GL_MAX_SHADER_STORAGE_BLOCK_SIZE"]),
                                        4 * info["max_texture_buffer_texels"])
    scene = load_scene("cornell")
    rays = make_rays("primary", scene, 8, 8, None, ())
    opencl = backends.get_device("opencl")
    textures = len(glsl._textures.textures)
    for res in (16, 4, 16):  # the octrees differ: a stale texture would read the last one's nodes
        reference = backends.build(opencl, "esvo", scene, BuildParams(resolution=(res,) * 3))
        built = backends.build(glsl, "esvo", scene, BuildParams(resolution=(res,) * 3))
        try:
            want, got = backends.trace(reference, rays, work=True), backends.trace(built, rays, work=True)
            np.testing.assert_array_equal(got.prim_ids, want.prim_ids)
            np.testing.assert_array_equal(got.work[:, :2], want.work[:, :2])  # steps, tests
            assert (got.prim_ids >= 0).any()
        finally:
            built.release()
            reference.release()
        assert len(glsl._textures.textures) == textures  # released with their buffers
    built = backends.build(glsl, "esvo", scene, BuildParams(resolution=(16,) * 3))
    try:
        monkeypatch.setattr(glsl._textures, "max_texels", 2)
        with pytest.raises(DeviceLimitError, match=r"texels, over the driver's 2 per buffer texture \(GL_MAX_TEXTURE_BUFFER_SIZE\)"):
            backends.trace(built, rays)
    finally:
        built.release()


@pytest.mark.parametrize("structure", ["bvh", "esvo"])
def test_trace_items_run_as_one_work_items_loop_where_work_items_run_one_after_the_other(structure):
    """On PoCL's CPU device a trace kernel's work group of local_size items is one work item's
    loop (KernelSpec.item_loop; opencl.py kernel_source): the entry point loops, the launch has one
    work item per group, and the hits and work counters are those of one item per work item, for
    a ray count that leaves the last group part full."""
    import dataclasses

    from lsbench import backends
    from lsbench.backends import BuildParams
    from lsbench.backends.opencl import kernel_source
    from lsbench.inputs.rays import make_rays
    from lsbench.inputs.scenes import load_scene

    device = backends.get_device("opencl")
    if not device.serial_work_items:
        pytest.skip("the item loop is for devices that run work items one after the other")
    scene = load_scene("cornell")
    rays = make_rays("incoherent", scene, 37, 29, None, ())  # 1073 rays: 16 groups of 64 and one of 49
    built = backends.build(device, structure, scene, BuildParams(resolution=(16,) * 3))
    try:
        spec = built.trace_spec
        assert spec.item_loop and spec.local_size == 64
        looped = kernel_source(spec, item_loop=True)
        assert "for (uint gid = first; gid < end; ++gid)" in looped and "if (gid >= n_items)" not in looped
        assert "for (uint gid" not in kernel_source(spec)
        got = backends.trace(built, rays, work=True)
        one_per_item = dataclasses.replace(built, trace_spec=dataclasses.replace(spec, item_loop=False))
        want = backends.trace(one_per_item, rays, work=True)
        assert (want.prim_ids >= 0).sum() > 500
        np.testing.assert_array_equal(got.prim_ids, want.prim_ids)
        np.testing.assert_array_equal(got.distances, want.distances)
        np.testing.assert_array_equal(got.work, want.work)
    finally:
        built.release()
