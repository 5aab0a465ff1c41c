"""Image-level accuracy (lsbench/oracle/image.py): CIEDE2000 between the shaded pictures of a
case's hits and Embree's, on the real Cornell box and real Embree hits."""
from __future__ import annotations

import numpy as np
import pytest

from lsbench.inputs.rays import make_rays
from lsbench.inputs.scenes import load_scene
from lsbench.oracle import image, verify
from lsbench.oracle.embree import embree_closest

W, H = 32, 24


@pytest.fixture(scope="module")
def cornell():
    scene = load_scene("cornell")
    rays = make_rays("primary", scene, W, H)
    prim, t = embree_closest(scene, rays)
    return scene, rays, np.asarray(prim).astype(np.int64), np.asarray(t, np.float32)


def _accuracy(prim, t, ref_prim, ref_t, scene):
    lo, hi = scene.bounds
    return verify.compare(prim, t, ref_prim, ref_t, scene_extent=float(np.linalg.norm(hi - lo)))


def test_identical_hits_have_no_colour_difference(cornell, tmp_path):
    scene, rays, prim, t = cornell
    assert image.is_image(rays) and (prim >= 0).sum() > W * H // 2
    fields = image.image_accuracy(scene, rays, prim, t, prim, t, _accuracy(prim, t, prim, t, scene),
                                  tmp_path / "heatmaps", "cornell|primary")
    assert fields["image_delta_e_mean"] == 0.0 and fields["image_delta_e_max"] == 0.0
    assert fields["image_jnd_pixels"] == 0
    assert set(fields["image_files"]) == {"delta_e", "pixel_errors"}
    import matplotlib.image
    de_png = matplotlib.image.imread(tmp_path / fields["image_files"]["delta_e"])
    assert de_png.shape[:2] == (H, W)
    assert np.allclose(de_png[..., :3], de_png[0, 0, :3])  # ΔE 0 everywhere: one colour


def test_jnd_count_is_the_planted_wrong_pixels(cornell, tmp_path):
    scene, rays, ref_prim, ref_t = cornell
    prim, t = ref_prim.copy(), ref_t.copy()
    hit = np.flatnonzero(ref_prim >= 0)
    rng = np.random.default_rng(3)
    missed = rng.choice(hit, 5, replace=False)
    prim[missed] = -1
    # wrong: another triangle whose face turns a clearly different way to this pixel's ray
    normals = np.cross(*(scene.triangles[:, k] - scene.triangles[:, 0] for k in (1, 2)))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    wrong = []
    for i in rng.permutation(np.setdiff1d(hit, missed)):
        cos = np.abs(normals @ rays.directions[i])
        far = np.flatnonzero(np.abs(cos - cos[ref_prim[i]]) > 0.3)
        if len(far):
            prim[i], t[i] = far[0], ref_t[i] * 1.5
            wrong.append(i)
        if len(wrong) == 3:
            break
    acc = _accuracy(prim, t, ref_prim, ref_t, scene)
    assert (acc.missed, acc.wrong) == (5, 3)
    fields = image.image_accuracy(scene, rays, prim, t, ref_prim, ref_t, acc, tmp_path / "heatmaps",
                                  "cornell|planted")
    assert fields["image_jnd_pixels"] == 8
    de = image.delta_e(scene, rays, prim, ref_prim)
    planted = np.concatenate([missed, wrong])
    assert np.all(de[planted] > image.JND) and np.all(np.delete(de, planted) == 0.0)
    assert fields["image_delta_e_max"] == pytest.approx(de.max())
    assert fields["image_delta_e_mean"] == pytest.approx(de.sum() / (W * H))
    # the pixel map paints each planted pixel in its category's colour, and nothing else
    from lsbench.profile.heatmaps import png_size
    import matplotlib.image
    path = tmp_path / fields["image_files"]["pixel_errors"]
    assert png_size(path) == (W, H)
    px = (matplotlib.image.imread(path)[..., :3].reshape(-1, 3) * 255 + 0.5).astype(int)
    assert all(tuple(px[i]) == image.CATEGORY_COLORS[verify.MISSED] for i in missed)
    assert all(tuple(px[i]) == image.CATEGORY_COLORS[verify.WRONG] for i in wrong)
    painted = {i for i, c in enumerate(map(tuple, px)) if c in image.CATEGORY_COLORS.values()}
    assert painted == set(planted.tolist())


def test_rays_that_make_no_picture_have_no_image_fields(cornell):
    scene, rays, prim, t = cornell
    shadow = make_rays("shadow", scene, W, H)
    fields = image.image_accuracy(scene, shadow, prim, t, prim, t, _accuracy(prim, t, prim, t, scene))
    assert not image.is_image(shadow)
    assert fields == {"image_delta_e_mean": None, "image_delta_e_max": None, "image_jnd_pixels": None,
                      "image_files": {}}


def test_a_case_records_its_image_accuracy(tmp_path):
    from lsbench.inputs.scenario import Case, RunSettings
    from lsbench.running.execute import execute

    rec = execute(Case("cornell", "grid", "opencl", "8", width=16, height=12),
                  RunSettings(width=16, height=12, repeats=1, embree_timing=False),
                  heatmap_dir=str(tmp_path / "heatmaps"))
    assert rec["status"] == "ok" and rec["agreement"] == 1.0
    assert rec["image_delta_e_max"] == 0.0 and rec["image_jnd_pixels"] == 0
    for rel in rec["image_files"].values():
        assert (tmp_path / rel).is_file()
