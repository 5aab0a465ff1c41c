"""Profiling: exact work counters, the device clock, EXR/PNG heatmaps, `lsbench stability`."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from lsbench import backends
from lsbench.backends import BuildParams
from lsbench.profile import heatmaps as profile
from lsbench.profile import simd
from lsbench.profile import stability
from lsbench.inputs.rays import RaySet
from lsbench.inputs.scene import Scene

REPO = Path(__file__).resolve().parents[1]


def wall_scene(x_wall: float = 8.0) -> Scene:
    """Triangle A in the plane x = x_wall (y + z <= 2 over [-1, 3]^2); a small triangle B at
    x = 0 in the far (y, z) corner only pins the bounds, so rays near y = z = 0 never meet it."""
    v = np.array([[x_wall, -1, -1], [x_wall, 3, -1], [x_wall, -1, 3],
                  [0, 2.5, 2.5], [0, 3, 2.5], [0, 2.5, 3]], np.float32)
    f = np.array([[0, 1, 2], [3, 4, 5]], np.uint32)
    return Scene("wall", v, f, "test")


def test_counters_exact_on_hand_built_grid(device):
    """Rays along +x in the (y, z) = (0, 0) row of an n x 2 x 2 grid: a ray entering voxel j
    walks n - j voxels (the last holds A) and tests A once; a ray pointing away walks none."""
    n = 8
    scene = wall_scene(float(n))
    built = backends.build(device, "grid", scene, BuildParams(resolution=(n, 2, 2)))
    starts = [-1.0, 0.5, 3.5, 6.5, 7.5]  # outside, then inside voxels 0, 3, 6, 7
    origins = [[x, 0.0, 0.0] for x in starts] + [[-1.0, 0.0, 0.0]]
    dirs = [[1, 0, 0]] * len(starts) + [[-1, 0, 0]]  # the last ray leaves the scene
    rays = RaySet("line", np.array(origins, np.float32), np.array(dirs, np.float32))
    hits = backends.trace(built, rays, work=True)
    built.release()
    work = hits.work
    # Voxel j spans x in [j, j + 1] (bounds padded by a hair): a start at x enters voxel floor(x).
    expect_iter = [n] + [n - int(x) for x in starts[1:]]
    assert list(hits.prim_ids) == [0] * len(starts) + [-1]
    np.testing.assert_allclose(hits.distances[:len(starts)], [n - x for x in starts], rtol=1e-5)
    assert list(work[:, 0]) == expect_iter + [0], "iterations = voxels walked"
    assert list(work[:, 1]) == [1] * len(starts) + [0], "candidate tests = A once per ray"
    assert list(work[:, 2]) == [0] * (len(starts) + 1), "the grid makes no Line Space lookups"
    # one group (6 rays < 32): steps 8 8 5 2 1 0 = 24 useful of 6 x 8 issued lane-steps
    assert simd.simd_efficiency(work[:, 0], None, simd.WARP) == pytest.approx(24 / 48)
    assert simd.simd_efficiency(work[:, 1], None, simd.WARP) == pytest.approx(5 / 6)
    clock = profile.clock_info(device)
    if clock["available"]:
        assert (work[:len(starts), 3] > 0).all()
    else:
        assert (work[:, 3] == 0).all()
        assert clock["note"].startswith("no device clock on ")


def test_simd_efficiency_by_hand():
    """Groups in dispatch order: order[i] = the ray launched as item i; efficiency weighted by
    each group's max (lane-slots issued), groups that count nothing weigh 0."""
    steps = np.array([4, 4, 4, 4, 1, 0, 0, 3, 0, 0], np.uint32)  # ray order
    order = np.array([0, 1, 2, 3, 4, 7, 5, 6, 8, 9])  # launch items: rays 0..4, 7, 5, 6, 8, 9
    eff, maxes = simd.group_efficiency(steps, order, 4)
    # groups [4 4 4 4], [1 3 0 0], [0 0]: 16/16, 4/12, no work
    np.testing.assert_allclose(eff[:2], [1.0, 4 / 12])
    assert np.isnan(eff[2]) and list(maxes) == [4, 3, 0]
    assert simd.simd_efficiency(steps, order, 4) == pytest.approx(20 / (16 + 12))
    assert simd.simd_efficiency(steps, None, 4) == pytest.approx(20 / (16 + 4 * 3))  # [4 4 4 4] [1 0 0 3] [0 0]
    assert simd.simd_efficiency(steps, order, 1) == 1.0
    assert simd.simd_efficiency(np.zeros(5, np.uint32), None, 4) is None
    per_ray = simd.per_ray_group_efficiency(steps, order, 4)
    np.testing.assert_allclose(per_ray[[0, 3, 4, 5, 6, 7]], [1, 1, 4 / 12, 4 / 12, 4 / 12, 4 / 12])
    assert np.isnan(per_ray[[8, 9]]).all()


def test_device_simd_width(device):
    info = device.info()
    width, source = simd.device_simd_width(info)
    if "llvmpipe" in info["device"]:
        bits = int(info["device"].split(" bits")[0].rsplit(" ", 1)[1])
        assert width == bits // 32 and "llvmpipe" in source
    elif "Portable Computing Language" in info["driver"] and "CPU" in info["device_type"]:
        assert width == 1 and "one work-item at a time" in source
    assert simd.device_simd_width({"device": "x", "vendor": "y"}) == (None, "group width of x not known")
    assert simd.device_simd_width({"device": "NVIDIA H200", "vendor": "NVIDIA Corporation"})[0] == 32


def test_clock_info_names_the_device(device):
    info = profile.clock_info(device)
    name = device.info()["device"]
    assert name in info["note"]
    if device.info().get("backend") == "opencl" and "nvidia" not in device.info()["vendor"].lower():
        assert not info["available"] and info["unit"] is None


def test_exr_round_trip(tmp_path):
    rng = np.random.default_rng(1)
    chans = {name: rng.integers(0, 5000, (24, 32)).astype(np.float32) for name in profile.CHANNELS}
    chans["clock"][0, 0] = np.float32(3.0e9)  # big tick counts survive as float32 values
    path = tmp_path / "w.exr"
    profile.write_exr(path, chans, {"lsbench_case": "x|y"})
    back = profile.read_exr(path)
    assert set(back) == set(profile.CHANNELS)
    for name, arr in chans.items():
        assert back[name].dtype == np.float32 and back[name].shape == (24, 32)
        np.testing.assert_array_equal(back[name], arr)


def test_png_writer_reads_back(tmp_path):
    from matplotlib import image

    rgb = np.zeros((5, 7, 3), np.uint8)
    rgb[1, 2] = (255, 10, 0)
    rgb[4, 6] = (0, 0, 200)
    profile.write_png(tmp_path / "a.png", rgb)
    assert profile.png_size(tmp_path / "a.png") == (7, 5)
    back = (image.imread(tmp_path / "a.png")[..., :3] * 255 + 0.5).astype(np.uint8)
    np.testing.assert_array_equal(back, rgb)


def test_image_shape_layouts():
    r = RaySet("x", np.zeros((10, 3), np.float32), np.ones((10, 3), np.float32))
    assert profile.image_shape(r) == (3, 4)  # near-square, padded
    assert profile.image_shape(r, "s|f.npz@5x2|grid") == (2, 5)  # the case's size holds exactly the rays
    img = profile.to_image(np.arange(10, dtype=np.float32), (3, 4))
    assert img[0, 3] == 3 and img[2, 1] == 9 and np.isnan(img[2, 2])


def test_heatmaps_written_and_match_counters(device, tmp_path):
    from lsbench.inputs.rays import primary_rays
    from lsbench.inputs.scenes import load_scene

    scene = load_scene("cornell")
    rays = primary_rays(scene, 32, 24)
    built = backends.build(device, "grid", scene, BuildParams(resolution=(16, 16, 16)))
    key = f"cornell|primary@32x24|grid|{device.backend}|r16|n0|k0"
    files = profile.write_heatmaps(built, rays, tmp_path / "heatmaps", key)
    ref = backends.trace(built, rays, work=True).work
    built.release()
    for name, rel in files.items():
        assert rel.startswith("heatmaps/"), "paths are relative to the run folder (out_dir's parent)"
        assert (tmp_path / rel).is_file(), name
    for name in ("exr", "iterations", "candidate_tests", "candidate_tests_max32", "combined", "summary"):
        assert name in files
    for name, rel in files.items():
        if rel.endswith(".png") and name != "colorbars":  # every heatmap has the image's size
            assert profile.png_size(tmp_path / rel) == (32, 24), name
    exr = profile.read_exr(tmp_path / files["exr"])
    for i, name in enumerate(profile.CHANNELS[:3]):  # deterministic counters equal a second trace
        np.testing.assert_array_equal(exr[name], ref[:, i].reshape(24, 32).astype(np.float32))
    # the standard luminance channel ordinary viewers show: tests / 32
    np.testing.assert_allclose(exr["Y"], ref[:, 1].reshape(24, 32) / 32.0, rtol=1e-6)
    # SIMD efficiency per 32-ray group of the launch (8x8 tiles: a group is 8x4 pixels)
    order = backends.launch_order(rays)
    for counter, short in simd.COUNTERS.items():
        name = f"simd_{short}_w32"
        assert name in files and profile.png_size(tmp_path / files[name]) == (32, 24)
        expect = simd.per_ray_group_efficiency(ref[:, profile.CHANNELS.index(counter)], order, 32)
        np.testing.assert_allclose(exr[name], expect.reshape(24, 32).astype(np.float32), rtol=1e-6)
        block = exr[name][0:4, 0:8]  # launch items 0..31: rows 0-3 of the first tile
        assert np.all(block == block[0, 0]) or np.isnan(block).all()
    assert profile.png_size(tmp_path / files["colorbars"])[0] == 420  # the legend of every PNG's scale
    summary = json.loads((tmp_path / files["summary"]).read_text())
    assert summary["width"] == 32 and summary["height"] == 24
    assert summary["simd"]["simd_efficiency_steps_w32"] == pytest.approx(simd.simd_efficiency(ref[:, 0], order, 32))
    assert summary["counters"]["iterations"]["mean"] == pytest.approx(float(ref[:, 0].mean()))
    assert summary["counters"]["candidate_tests"]["max"] == int(ref[:, 1].max())
    assert summary["normalization"]["candidate_tests_max32"]["max"] == 32
    if summary["clock"]["available"]:
        assert "clock" in files and "clock_over_scene" in files and summary["clock"]["unit"]
        assert (exr["clock"] > 0).all()
    else:
        assert "clock" not in files and summary["not_drawn"]["clock"].startswith("no device clock on ")
        assert (exr["clock"] == 0).all()


def test_heatmap_row_one_scale(tmp_path):
    """Thesis Fig. 4 side by side: two cases' candidate tests in one PNG at the larger p99."""
    a = np.arange(48, dtype=np.float32).reshape(6, 8)
    b = 3 * a
    paths = []
    for name, img in (("a", a), ("b", b)):
        path = tmp_path / f"{name}.exr"
        profile.write_exr(path, {c: img for c in profile.CHANNELS})
        paths.append((name, path))
    drawn = profile.write_heatmap_row(paths, "candidate_tests", tmp_path / "row.png")
    assert drawn["max"] == pytest.approx(np.percentile(b, 99)) and drawn["labels"] == ["a", "b"]
    w, h = profile.png_size(tmp_path / "row.png")
    assert w > 2 * h  # a row, not a column
    assert profile.write_heatmap_row(paths, "iterations", tmp_path / "row2.png", vmax=10)["max"] == 10


def busy_scene(count: int = 3000, seed: int = 3) -> Scene:
    """Tiny triangles scattered through the unit cube: a ray crossing it tests many and hits few."""
    rng = np.random.default_rng(seed)
    centres = rng.random((count, 1, 3)).astype(np.float32)
    tris = centres + rng.normal(0, 2e-3, (count, 3, 3)).astype(np.float32)
    corners = np.array([[[0, 0, 0]] * 3, [[1, 1, 1]] * 3], np.float32)  # pin the bounds
    tris = np.concatenate([tris, corners])
    return Scene("busy", tris.reshape(-1, 3), np.arange(3 * len(tris), dtype=np.uint32).reshape(-1, 3), "test")


def test_clock_grows_with_work(tmp_path, monkeypatch):
    """GLSL clock: 512 rays crossing a cube full of candidates take clearly more ticks than 512
    rays that leave the grid at once (groups aligned to work groups, so no SIMD group mixes them)."""
    # In the given order: the two groups share their origins, so where timing picks the
    # origin-cells order (backends/ray_order.py) their rays share SIMD groups, and llvmpipe's
    # clock (one value per 8 lanes) gave the light rays the heavy ones' ticks (CI, 3 Dec 2026).
    monkeypatch.setenv("LSBENCH_RAY_ORDER", "given")
    device = backends.get_device("glsl")
    if not profile.clock_info(device)["available"]:
        pytest.skip("GL driver has no GL_ARB_shader_clock")
    scene = busy_scene()
    built = backends.build(device, "grid", scene, BuildParams(resolution=(4, 4, 4)))
    rng = np.random.default_rng(4)
    m = 512
    heavy_o = np.column_stack([np.full(m, -0.5), rng.uniform(0.1, 0.9, m), rng.uniform(0.1, 0.9, m)])
    heavy_d = np.column_stack([np.ones(m), rng.uniform(-0.2, 0.2, m), rng.uniform(-0.2, 0.2, m)])
    light_o = heavy_o.copy()
    light_d = -heavy_d  # away from the cube: no voxel, no test
    origins = np.concatenate([heavy_o, light_o]).astype(np.float32)
    dirs = np.concatenate([heavy_d, light_d])
    dirs = (dirs / np.linalg.norm(dirs, axis=1, keepdims=True)).astype(np.float32)
    hits, work = profile.profile_trace(built, RaySet("two", origins, dirs), clock_runs=3)
    built.release()
    heavy, light = work[:m], work[m:]
    assert heavy[:, 1].mean() > 50 and (light[:, :2] == 0).all(), "the two groups must differ in work"
    # Measured: medians ~33 000 ns against ~120 ns. (Within the heavy group the correlation of
    # ticks with tests is ~0.7 on a quiet machine but drops to ~0.3 on busy cores: not asserted.)
    assert np.median(heavy[:, 3]) > 3 * max(np.median(light[:, 3]), 1)
    assert heavy[:, 3].mean() > light[:, 3].mean()


def _cli(*args, timeout=300):
    env = dict(os.environ, PYTHONPATH=str(REPO))
    return subprocess.run([sys.executable, "-m", "lsbench", *args], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=timeout)


def test_cli_trace_writes_heatmaps(tmp_path):
    out = tmp_path / "run" / "heatmaps"
    res = _cli("trace", "--scene", "cornell", "--structure", "grid", "--backend", "glsl", "--size", "32x24",
               "--resolution", "16", "--repeats", "2", "--heatmaps", str(out), "--json")
    assert res.returncode == 0, res.stderr
    rec = json.loads(res.stdout)
    assert rec["status"] == "ok"
    hm = rec["heatmaps"]
    assert {"exr", "iterations", "candidate_tests", "combined", "summary", "simd_steps_w32", "colorbars"} <= set(hm)
    assert 0 < rec["simd_efficiency_steps_w32"] <= 1 and 0 < rec["simd_efficiency_tests_w32"] <= 1
    if "llvmpipe" in rec["device"]:  # 8 lanes: less idling than in a 32-wide group
        assert rec["simd_width_device"] == 8 and "simd_steps_w8" in hm
        assert rec["simd_efficiency_steps_device"] >= rec["simd_efficiency_steps_w32"]
    for rel in hm.values():
        assert (tmp_path / "run" / rel).is_file()
    assert len(list(out.glob("*.png"))) >= 4 and len(list(out.glob("*.exr"))) == 1


def test_cli_stability(tmp_path):
    out = tmp_path / "stab.json"
    res = _cli("stability", "--scene", "cornell", "--structure", "grid", "--backend", "glsl", "--resolution", "8",
               "--size", "16x16", "--processes", "2", "--repeats", "2", "--out", str(out))
    assert res.returncode == 0, res.stderr + res.stdout
    data = json.loads(out.read_text())
    for group in ("in_process", "cross_process"):
        s = data[group]
        assert s["ok"] == 2 and len(s["values"]) == 2 and s["min"] <= s["median"] <= s["max"]
        assert s["spread"] >= 0
    assert data["cross_over_in_process_median"] > 0
    assert "same process" in res.stdout and "separate processes" in res.stdout


def test_spread_counts_failures():
    recs = [{"status": "ok", "trace_seconds": 1.0, "trace_cv": 0.1},
            {"status": "ok", "trace_seconds": 3.0, "trace_cv": 0.3},
            {"status": "failed", "reason": "boom"}]
    s = stability.spread(recs)
    assert s["ok"] == 2 and s["failed"] == ["boom"]
    assert s["median"] == 2.0 and s["spread"] == pytest.approx(1.0)
    assert s["within_run_cv_mean"] == pytest.approx(0.2)


def test_hotloop_cpu_seconds():
    """The A/B tool of docs/profiles.md: CPU seconds per launch for us and Embree, one JSON line."""
    res = subprocess.run([sys.executable, "-m", "lsbench.profile.hotloop", "cornell", "grid", "opencl", "8",
                          "--size", "16x16", "--cpu-repeats", "2"], cwd=REPO, capture_output=True, text=True,
                         timeout=300, env=dict(os.environ, PYTHONPATH=str(REPO)))
    assert res.returncode == 0, res.stderr
    out = json.loads(res.stdout.strip().splitlines()[-1])
    assert out["case"] == "grid opencl r8 primary"
    assert out["cpu_seconds"] > 0 and out["embree_cpu_seconds"] > 0
    assert out["mrays_per_cpu_second"] == pytest.approx(256 / out["cpu_seconds"] / 1e6)


@pytest.mark.parametrize("variant", [["--leaf-size", "8", "--leaf-size-b", "2"], ["--defines", "UNUSED_DEFINE=3"],
                                     ["--packet-b", "8"]])
def test_ab_alternates_two_variants_in_one_process(variant):
    """lsbench.profile.ab (docs/profiles.md, sections 7 and 8): both variants traced, the same hits
    (a BVH's leaf size, an unused define and packets of primary rays change no closest hit), one
    line with the ratio."""
    res = subprocess.run([sys.executable, "-m", "lsbench.profile.ab", "cornell", "bvh", "opencl", "1",
                          "--size", "16x16", "--pairs", "3", *variant], cwd=REPO, capture_output=True, text=True,
                         timeout=300, env=dict(os.environ, PYTHONPATH=str(REPO)))
    assert res.returncode == 0, res.stderr
    line = res.stdout.strip().splitlines()[-1]
    assert line.startswith("bvh opencl primary, B = ") and "3 pairs" in line
    assert line.endswith("hits identical: True")
