"""Embree ground truth: hand-checked hits, misses, tmin, degenerate triangles, cache, threads."""
import numpy as np
import pytest

from lsbench.oracle import embree as groundtruth
from lsbench.oracle.embree import embree_closest, embree_version
from lsbench.inputs.rays import RaySet
from lsbench.inputs.scene import Scene


def quad_scene(z=5.0):
    """Unit square [0,1]^2 at height z, split along the diagonal (0,0)-(1,1):
    prim 0 covers x > y, prim 1 covers y > x."""
    vertices = np.array([[0, 0, z], [1, 0, z], [1, 1, z], [0, 1, z]], np.float32)
    faces = np.array([[0, 1, 2], [0, 2, 3]], np.uint32)
    return Scene(name="quad", vertices=vertices, faces=faces, source="test")


def rays(origins, directions, tmin=0.0):
    o = np.asarray(origins, np.float32).reshape(-1, 3)
    d = np.asarray(directions, np.float64).reshape(-1, 3)
    d = (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)
    if len(d) == 1:
        d = np.repeat(d, len(o), axis=0)
    return RaySet(name="r", origins=o, directions=d, tmin=tmin)


def test_quad_straight_on_hits_and_misses(tmp_path):
    origins = [[0.7, 0.2, 0], [0.2, 0.7, 0], [0.5, 0.5, 10], [2, 2, 0], [0.5, 0.2, 6]]
    directions = [[0, 0, 1], [0, 0, 1], [0, 0, -1], [0, 0, 1], [0, 0, 1]]
    prim, t = embree_closest(quad_scene(), rays(origins, directions), tmp_path)
    assert prim.dtype == np.int32 and t.dtype == np.float32
    # x>y -> 0; y>x -> 1; from above at the diagonal either triangle; outside -> miss;
    # above the quad looking up -> miss.
    assert prim[0] == 0 and prim[1] == 1 and prim[2] in (0, 1)
    assert prim[3] == -1 and prim[4] == -1
    np.testing.assert_allclose(t[:3], [5, 5, 5], rtol=1e-6)
    assert np.isinf(t[3]) and np.isinf(t[4])


def test_oblique_ray_distance(tmp_path):
    d = np.array([0.1, 0.05, 1.0])
    prim, t = embree_closest(quad_scene(), rays([[0.05, 0.02, 0]], d), tmp_path)  # (0.55, 0.27)
    # Hits z=5 after 5 / cos(angle to z) = 5 * |d| / d_z.
    assert prim[0] == 0
    np.testing.assert_allclose(t[0], 5 * np.linalg.norm(d) / d[2], rtol=1e-6)


def test_tmin_skips_near_hits(tmp_path):
    """Two quads at z=1 (prims 0,1) and z=3 (prims 2,3); embreex has no tnear, tmin is emulated."""
    a, b = quad_scene(1.0), quad_scene(3.0)
    scene = Scene(
        name="two",
        vertices=np.concatenate([a.vertices, b.vertices]),
        faces=np.concatenate([a.faces, b.faces + 4]),
        source="test",
    )
    origin = [[0.7, 0.2, 0]]
    prim, t = embree_closest(scene, rays(origin, [0, 0, 1], tmin=0.0), tmp_path)
    assert (prim[0], t[0]) == (0, pytest.approx(1.0))
    prim, t = embree_closest(scene, rays(origin, [0, 0, 1], tmin=1.5), tmp_path)
    assert (prim[0], t[0]) == (2, pytest.approx(3.0, rel=1e-6))
    prim, t = embree_closest(scene, rays(origin, [0, 0, 1], tmin=4.0), tmp_path)
    assert prim[0] == -1 and np.isinf(t[0])


def test_degenerate_triangles_are_never_hit(tmp_path):
    """Zero-area triangles (repeated index, collinear corners, a point) in front of the quad:
    the build accepts them and rays pass through to the quad."""
    quad = quad_scene(5.0)
    extra = np.array([[0, 0, 2], [1, 1, 2], [2, 2, 2], [0.5, 0.5, 3]], np.float32)
    vertices = np.concatenate([quad.vertices, extra])
    faces = np.concatenate([quad.faces, [[4, 5, 6], [4, 4, 5], [7, 7, 7]]]).astype(np.uint32)
    scene = Scene(name="degenerate", vertices=vertices, faces=faces, source="test")
    origins = [[0.5, 0.5, 0], [0.3, 0.3, 0], [0.7, 0.2, 0]]  # on the segments and the point
    prim, t = embree_closest(scene, rays(origins, [0, 0, 1]), tmp_path)
    assert set(prim.tolist()) <= {0, 1}
    np.testing.assert_allclose(t, 5.0, rtol=1e-6)


def test_rejects_non_unit_directions(tmp_path):
    bad = RaySet(name="bad", origins=np.zeros((1, 3), np.float32),
                 directions=np.array([[0, 0, 2]], np.float32))
    with pytest.raises(ValueError, match="unit length"):
        embree_closest(quad_scene(), bad, tmp_path)


def test_cache_returns_identical_arrays_without_tracing(tmp_path, monkeypatch):
    scene = quad_scene()
    rs = rays([[0.7, 0.2, 0], [3, 3, 0]], [0, 0, 1])
    first = embree_closest(scene, rs, tmp_path)
    files = list(tmp_path.iterdir())
    assert [f.suffix for f in files] == [".npz"]  # no temp file left behind

    def fail(*args, **kwargs):
        raise AssertionError("traced again despite a cached result")

    monkeypatch.setattr(groundtruth, "_trace", fail)
    second = embree_closest(scene, rs, tmp_path)
    for a, b in zip(first, second):
        assert a.dtype == b.dtype
        np.testing.assert_array_equal(a, b)
    # tmin is not part of RaySet.content_hash, so it must be part of the cache key.
    assert groundtruth.cache_path(scene, rs, tmp_path) != groundtruth.cache_path(
        scene, rays([[0.7, 0.2, 0], [3, 3, 0]], [0, 0, 1], tmin=0.5), tmp_path
    )


def test_corrupt_or_stale_cache_is_recomputed(tmp_path):
    scene = quad_scene()
    rs = rays([[0.7, 0.2, 0]], [0, 0, 1])
    path = groundtruth.cache_path(scene, rs, tmp_path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"not a zip file")
    prim, t = embree_closest(scene, rs, tmp_path)
    assert prim[0] == 0
    np.savez(path, prim_ids=np.array([7], np.int32), t=np.array([1.0], np.float32),
             format=groundtruth.CACHE_FORMAT, embree="embree 0.0.0")
    assert embree_closest(scene, rs, tmp_path)[0][0] == 0


def test_cache_dir_from_environment(tmp_path, monkeypatch):
    monkeypatch.setenv("LSBENCH_CACHE", str(tmp_path / "env"))
    embree_closest(quad_scene(), rays([[0.7, 0.2, 0]], [0, 0, 1]))
    assert len(list((tmp_path / "env").glob("*.npz"))) == 1


def random_scene(rng, count=3000):
    centres = rng.uniform(-1, 1, size=(count, 1, 3))
    corners = centres + rng.normal(scale=0.05, size=(count, 3, 3))
    return Scene(
        name="random",
        vertices=corners.reshape(-1, 3).astype(np.float32),
        faces=np.arange(3 * count, dtype=np.uint32).reshape(-1, 3),
        source="test",
    )


def test_threaded_equals_serial():
    rng = np.random.default_rng(7)
    scene = random_scene(rng)
    n = 100_000
    d = rng.normal(size=(n, 3))
    d = (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)
    rs = RaySet(name="rnd", origins=rng.uniform(-1.2, 1.2, (n, 3)).astype(np.float32), directions=d)
    serial = embree_closest(scene, rs, use_cache=False, threads=1)
    threaded = embree_closest(scene, rs, use_cache=False, threads=4)
    assert 0.2 < np.mean(serial[0] >= 0) < 1.0  # a mix of hits and misses
    np.testing.assert_array_equal(serial[0], threaded[0])
    np.testing.assert_array_equal(serial[1], threaded[1])


def test_empty_inputs(tmp_path):
    empty_rays = RaySet(name="none", origins=np.zeros((0, 3), np.float32),
                        directions=np.zeros((0, 3), np.float32))
    prim, t = embree_closest(quad_scene(), empty_rays, tmp_path)
    assert prim.shape == (0,) and t.shape == (0,)


def test_version_string():
    assert embree_version().startswith(("embree ", "embreex "))
