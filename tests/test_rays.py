"""Ray sets: primary camera rays, .npz ray files, the name registry."""
from __future__ import annotations

import numpy as np
import pytest

from lsbench.inputs.rays import RAY_SETS, RayError, RaySet, load_rays_file, make_rays, primary_rays
from lsbench.inputs.scene import Camera
from lsbench.inputs.scenes import load_scene


@pytest.fixture(scope="module")
def quad():
    return load_scene("quad")


def test_primary_rays_shape_types_and_unit_length(quad):
    rays = primary_rays(quad, 16, 9)
    assert isinstance(rays, RaySet) and rays.name == "primary"
    assert (rays.width, rays.height, rays.count) == (16, 9, 144)
    assert rays.origins.dtype == np.float32 and rays.directions.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(rays.directions, axis=1), 1.0, atol=1e-6)
    np.testing.assert_array_equal(rays.origins, np.tile(np.float32(quad.camera.eye), (144, 1)))


@pytest.mark.parametrize("width, height", [(1, 1), (5, 3), (7, 11)])
def test_centre_pixel_points_at_the_target(width, height):
    cam = Camera(eye=(1.0, 2.0, 3.0), target=(-2.0, 0.5, -4.0), fov_deg=45.0)
    rays = primary_rays(load_scene("single-triangle"), width, height, cam)
    centre = (height // 2) * width + width // 2
    expected = np.subtract(cam.target, cam.eye)
    expected /= np.linalg.norm(expected)
    np.testing.assert_allclose(rays.directions[centre], expected, atol=1e-6)


def test_row_zero_is_the_top_and_x_grows_to_the_right(quad):
    rays = primary_rays(quad, 4, 6)  # camera on +z looking down -z, up +y
    d = rays.directions.reshape(6, 4, 3)
    assert np.all(d[0, :, 1] > 0) and np.all(d[-1, :, 1] < 0)  # top row looks up
    assert np.all(np.diff(d[:, :, 1], axis=0) < 0)  # y falls row by row
    assert np.all(np.diff(d[:, :, 0], axis=1) > 0)  # x grows along a row


def test_field_of_view_is_vertical():
    cam = Camera(eye=(0.0, 0.0, 0.0), target=(0.0, 0.0, -1.0), fov_deg=90.0)
    rays = primary_rays(load_scene("quad"), 200, 100, cam)
    d = rays.directions.reshape(100, 200, 3)
    # the top edge of the image is 45° up; the first row's centre is half a pixel below it
    top = np.degrees(np.arctan2(d[0, 100, 1], -d[0, 100, 2]))
    assert 44.0 < top < 45.0
    right = np.degrees(np.arctan2(d[50, -1, 0], -d[50, -1, 2]))
    assert right == pytest.approx(np.degrees(np.arctan(2.0)), abs=0.5)  # aspect 2


def test_primary_rays_default_camera_for_scene_without_one(quad):
    quad.camera, saved = None, quad.camera
    try:
        rays = primary_rays(quad, 3, 3)
    finally:
        quad.camera = saved
    assert np.isfinite(rays.directions).all()


def test_camera_looking_straight_down_still_works(quad):
    cam = Camera(eye=(0.0, 5.0, 0.0), target=(0.0, 0.0, 0.0))
    rays = primary_rays(quad, 3, 3, cam)
    np.testing.assert_allclose(rays.directions[4], [0, -1, 0], atol=1e-6)
    assert np.isfinite(rays.directions).all()


def test_make_rays_primary_and_unknown(quad):
    assert make_rays("primary", quad, 4, 4).content_hash == primary_rays(quad, 4, 4).content_hash
    assert "primary" in RAY_SETS
    with pytest.raises(RayError, match="primary"):
        make_rays("adversarial-typo", quad, 4, 4)


# --- .npz files -----------------------------------------------------------------------------


def test_npz_round_trip_normalizes_directions(tmp_path, quad):
    rays = primary_rays(quad, 5, 4)
    path = tmp_path / "myrays.npz"
    np.savez(path, origins=rays.origins, directions=rays.directions * 3.0)
    loaded = make_rays(str(path), quad, 0, 0)
    assert loaded.name == "myrays" and (loaded.width, loaded.height) == (0, 0)
    assert loaded.origins.dtype == np.float32 and loaded.directions.dtype == np.float32
    np.testing.assert_array_equal(loaded.origins, rays.origins)
    np.testing.assert_allclose(loaded.directions, rays.directions, atol=1e-6)


def _npz(tmp_path, **arrays):
    path = tmp_path / "rays.npz"
    np.savez(path, **arrays)
    return str(path)


ONE = np.zeros((1, 3), np.float32)
UP = np.array([[0, 1, 0]], np.float32)


@pytest.mark.parametrize("arrays, words", [
    ({"origins": ONE}, "missing array(s) directions"),
    ({"origins": ONE, "directions": np.ones((2, 3), np.float32)}, "differ"),
    ({"origins": np.zeros((0, 3), np.float32), "directions": np.zeros((0, 3), np.float32)},
     "no rays"),
    ({"origins": np.zeros((4,), np.float32), "directions": np.ones((4,), np.float32)}, "(N, 3)"),
    ({"origins": np.array([[np.nan, 0, 0]], np.float32), "directions": UP}, "NaN/Inf"),
    ({"origins": ONE, "directions": np.array([[np.inf, 0, 0]], np.float32)}, "NaN/Inf"),
    ({"origins": ONE, "directions": np.array([[1e300, 0, 0]])}, "NaN/Inf"),  # float32 overflow
    ({"origins": np.zeros((2, 3), np.float32), "directions": np.array([[0, 1, 0], [0, 0, 0]],
                                                                       np.float32)},
     "zero length (first: ray 1)"),
])
def test_bad_npz_raises_one_line_ray_error(tmp_path, arrays, words):
    with pytest.raises(RayError) as info:
        load_rays_file(_npz(tmp_path, **arrays))
    assert words in str(info.value) and "\n" not in str(info.value)


def test_missing_and_corrupt_npz(tmp_path):
    with pytest.raises(RayError, match="not found"):
        load_rays_file(str(tmp_path / "nope.npz"))
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip at all")
    with pytest.raises(RayError, match="cannot read"):
        load_rays_file(str(bad))
    assert issubclass(RayError, ValueError)
