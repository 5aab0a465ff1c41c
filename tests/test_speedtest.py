"""`lsbench speedtest`: one row per structure x backend against Embree in the same worker, a failed
case as a failed row with its reason, the table of best settings (scenarios/speedtest.toml)."""
from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from lsbench import backends
from lsbench.backends.structures import bvh
from lsbench.profile import simd
from lsbench.cli import build_parser
from lsbench.commands.speedtest import speedtest_cases
from lsbench.inputs.scenario import load_scenario
from test_cli import lsbench

TINY = ("cornell", "--size", "32x32", "--structures", "grid", "svo", "--resolution", "16")
PAIRS = {(s, b) for s in ("grid", "svo") for b in backends.BACKENDS}


def table_rows(stdout: str) -> dict[tuple[str, str], list[str]]:
    """(structure, backend) -> the cells of its line in the printed table."""
    lines = stdout.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("scene ")) + 2
    rows = {}
    for line in lines[start:]:
        if not line.strip():
            break
        cells = line.split()
        assert (cells[1], cells[2]) not in rows, f"two rows for {cells[1]} {cells[2]}"
        rows[(cells[1], cells[2])] = cells
    return rows


def test_speedtest_table_json(tmp_path):
    out = tmp_path / "speed.json"
    proc = lsbench("speedtest", *TINY, "--work", "--out", out, check=0)
    header = next(line for line in proc.stdout.splitlines() if line.startswith("scene "))
    columns = header.split()
    assert columns[:11] == ["scene", "structure", "backend", "res", "N", "Mrays/s", "Embree", "Mrays/s",
                            "×", "Embree", "MiB"]
    printed = table_rows(proc.stdout)
    assert set(printed) == PAIRS
    data = json.loads(out.read_text())
    rows = {(r["structure"], r["backend"]): r for r in data["rows"]}
    records = {(r["structure"], r["backend"]): r for r in data["records"]}
    assert set(rows) == set(records) == PAIRS
    for pair, row in rows.items():
        rec = records[pair]
        assert row["status"] == "ok" and row["resolution"] == "16" and row["width"] == 32
        assert row["agreement"] == 1.0 and row["unexplained"] == 0
        # x Embree is the worker's own two figures, lsbench's rays/s over Embree's on the same rays
        assert rec["embree_rays_per_second"] > 0 and rec["rays_per_second"] > 0
        assert row["x_embree"] == pytest.approx(rec["rays_per_second"] / rec["embree_rays_per_second"])
        assert row["x_embree"] > 0
        cells = printed[pair]
        assert cells[7] == f"{row['x_embree']:.3f}" and cells[10] == "1.000000" and cells[11] == "0"
        assert cells[-1] == "ok"
        # --work: steps and candidate tests per ray from the profiling kernel's counters
        assert row["iterations_per_ray"] > 0 and row["candidate_tests_per_ray"] > 0
        assert cells[12] == f"{row['iterations_per_ray']:.1f}"
        # and their SIMD efficiency per 32-ray group and per group of the device's own lanes
        assert 0 < row["simd_efficiency_steps_w32"] <= 1 and cells[14] == f"{row['simd_efficiency_steps_w32']:.2f}"
        width = simd.device_simd_width(backends.get_device(pair[1]).info())[0]  # llvmpipe 8 here, PoCL 1
        assert cells[16] == str(row["simd_width_device"]) == str(width)
        if pair[1] == "opencl":  # device time per build kernel from OpenCL event profiling
            kernels = row["build_kernel_seconds"]
            assert {"voxelize_count", "voxelize_fill"} <= set(kernels)
            assert all(s >= 0 for s in kernels.values()) and sum(kernels.values()) <= row["build_seconds"]
        else:  # llvmpipe times no single compute dispatch
            assert row["build_kernel_seconds"] is None
    assert "voxelize_count" in proc.stdout.split("build kernel", 1)[1]


def test_speedtest_failed_row_csv(tmp_path):
    out = tmp_path / "speed.csv"
    proc = lsbench("speedtest", *TINY, "--resolution", "svo=12", "--out", out, check=1)
    printed = table_rows(proc.stdout)
    assert set(printed) == PAIRS
    for backend in backends.BACKENDS:
        assert printed[("grid", backend)][-1] == "ok"
        line = " ".join(printed[("svo", backend)])
        assert "FAILED: ValueError: octree resolution must be a power of two" in line and "got 12" in line
    assert "2 of 4 cases failed" in proc.stdout
    with open(out, newline="") as f:
        rows = {(r["structure"], r["backend"]): r for r in csv.DictReader(f)}
    assert set(rows) == PAIRS
    assert {rows[("svo", b)]["status"] for b in backends.BACKENDS} == {"failed"}
    assert all("power of two" in rows[("svo", b)]["reason"] for b in backends.BACKENDS)
    assert all(float(rows[("grid", b)]["x_embree"]) > 0 for b in backends.BACKENDS)


@pytest.mark.parametrize("args,needle", [
    (("--resolution", "kdtree=3"), "'kdtree' is not a structure"),
    (("--ls-n", "grid-ls=-1"), "-1 is not"),
    (("--out", "speed.txt"), "does not end in .json or .csv"),
    (("--structures", "grid", "--backends", "vulkan"), "invalid choice: 'vulkan'"),
])
def test_speedtest_bad_flags(args, needle):
    proc = lsbench("speedtest", *args, check=2)
    assert needle in proc.stderr and proc.stdout == ""


def test_settings_cover_every_structure_and_backend():
    """The shipped table of best settings has one for every structure on every backend, on one
    scene and camera, and the speedtest without arguments runs exactly its cases."""
    scenario = load_scenario("speedtest")
    pairs = [(c.structure, c.backend) for c in scenario.cases]
    assert sorted(pairs) == sorted({(s, b) for s in backends.structure_names() for b in backends.BACKENDS})
    assert scenario.settings.embree_timing and len({(c.scene, c.camera) for c in scenario.cases}) == 1
    args = build_parser().parse_args(["speedtest"])
    s = scenario.settings
    cases = speedtest_cases(args, scenario, s.width, s.height)
    assert {c.key for c in cases} == {c.key for c in scenario.cases}
    # a flag for one structure changes that one only; N only where there is a Line Space
    args = build_parser().parse_args(["speedtest", "q.ply", "--resolution", "32", "--resolution", "svo=8",
                                      "--ls-n", "4", "--structures", "grid", "svo", "grid-ls"])
    got = {(c.structure, c.backend): (c.scene, c.resolution, c.ls_n, c.camera)
           for c in speedtest_cases(args, scenario, 64, 64)}
    assert got == {("grid", b): ("q.ply", "32", 0, None) for b in backends.BACKENDS} \
        | {("svo", b): ("q.ply", "8", 0, None) for b in backends.BACKENDS} \
        | {("grid-ls", b): ("q.ply", "32", 4, None) for b in backends.BACKENDS}


def test_embree_is_timed_between_the_timed_launches(device):
    """execute.py times Embree once after each timed launch (Device.time_dispatch's `between`),
    so the two speeds of a case's ratio are taken under the same load."""
    from lsbench.backends import BuildParams
    from lsbench.inputs.rays import primary_rays
    from lsbench.inputs.scenes import load_scene

    scene = load_scene("cornell")
    rays = primary_rays(scene, 16, 16)
    built = backends.build(device, "grid", scene, BuildParams(resolution=(8, 8, 8)))
    try:
        calls = []
        timing = backends.time_trace(built, rays, 1, 3, between=lambda: calls.append(len(calls)))
    finally:
        built.release()
    assert calls == [0, 1, 2] and len(timing.seconds) == 3


def test_launch_order_is_pixel_tiles():
    """An image's rays go to the device in 8x8 pixel tiles (one work group of 64), other sets as given."""
    from lsbench.backends import RAY_TILE, launch_order
    from lsbench.inputs.rays import RaySet

    def image(w, h):
        return RaySet("primary", np.zeros((w * h, 3), np.float32), np.ones((w * h, 3), np.float32), w, h)

    order = launch_order(image(32, 24))
    assert sorted(order.tolist()) == list(range(32 * 24))
    y, x = np.divmod(order, 32)
    for group in range(len(order) // 64):  # each work group's 64 rays are one 8x8 tile
        g = slice(64 * group, 64 * group + 64)
        assert np.ptp(y[g]) == np.ptp(x[g]) == RAY_TILE - 1 and len(set(zip(y[g], x[g]))) == 64
    assert (order[:8] == np.arange(8)).all() and order[8] == 32  # row by row within a tile
    edge = launch_order(image(20, 13))  # edge tiles are cut to the image
    assert sorted(edge.tolist()) == list(range(20 * 13)) and edge[64] == 8
    assert launch_order(RaySet("given", np.zeros((64, 3), np.float32), np.ones((64, 3), np.float32))) is None
    # computed once per image size and shared by every trace: no caller may change it
    assert launch_order(image(32, 24)) is order and launch_order(image(24, 32)) is not order
    with pytest.raises(ValueError):
        order[0] = 1


@pytest.mark.parametrize("structure,resolution,ls_n", [("grid", (12, 16, 9), 0), ("esvo-ls", (16,) * 3, 2)])
def test_tiled_trace_equals_given_order(device, structure, resolution, ls_n):
    """Hits and work counters of an image traced in tiles are those of the same rays traced as
    given, bit for bit, in the ray set's order."""
    from lsbench.backends import BuildParams
    from lsbench.inputs.rays import RaySet, primary_rays
    from lsbench.inputs.scenes import load_scene

    scene = load_scene("cornell")
    image = primary_rays(scene, 20, 13)
    # a per-ray tmax travels with its ray: about half the hits lie past it
    image.tmax = np.random.default_rng(5).uniform(0.5, 6.0, image.count).astype(np.float32)
    given = RaySet("given", image.origins, image.directions, tmax=image.tmax)
    built = backends.build(device, structure, scene, BuildParams(resolution=resolution, ls_n=ls_n))
    try:
        tiled, plain = backends.trace(built, image, work=True), backends.trace(built, given, work=True)
        unbounded = backends.trace(built, primary_rays(scene, 20, 13))
    finally:
        built.release()
    assert 0.2 < (tiled.prim_ids >= 0).mean() < (unbounded.prim_ids >= 0).mean() - 0.1
    np.testing.assert_array_equal(tiled.prim_ids, plain.prim_ids)
    np.testing.assert_array_equal(tiled.distances, plain.distances)
    np.testing.assert_array_equal(tiled.work[:, :3], plain.work[:, :3])  # [:, 3] is the clock


def test_a_bvh_row_names_its_leaf_size(tmp_path):
    """A BVH has no grid resolution: its row gives the leaf size it was built with."""
    out = tmp_path / "speed.json"
    proc = lsbench("speedtest", "cornell", "--size", "16x16", "--structures", "bvh", "--backends", "opencl",
                   "--out", out, check=0)
    row = json.loads(out.read_text())["rows"][0]
    assert row["status"] == "ok" and row["leaf_size"] == bvh.DEFAULT_LEAF_SIZE
    assert table_rows(proc.stdout)[("bvh", "opencl")][3] == f"leaf={bvh.DEFAULT_LEAF_SIZE}"
