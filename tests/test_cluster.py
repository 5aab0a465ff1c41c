"""Sweeps on a Ray cluster (issue 19, lsbench/running/cluster.py): a local two-node cluster
(ray.cluster_utils.Cluster: a head and one more node in this machine) runs a small scenario and
its records equal a local run's case for case; a node killed mid-case loses nothing (the case
runs again on the other node) or, without retries, fails naming the lost node; a second
submission into a folder in use is refused. Real drivers, Embree and Ray; the cornell box."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from lsbench.running.cluster import Node, place

REPO = Path(__file__).resolve().parents[1]
CASES = 4  # cornell: grid on both backends, svo on OpenCL, esvo-ls on GLSL


def lsbench(*args, timeout=300):
    return subprocess.run([sys.executable, "-m", "lsbench", *map(str, args)], cwd=REPO, capture_output=True,
                          text=True, timeout=timeout)


def start(*args) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "lsbench", *map(str, args)], cwd=REPO, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)


def records(out: Path) -> dict[str, dict]:
    lines = [json.loads(line) for line in (out / "results.jsonl").read_text().splitlines() if line.strip()]
    by_key = {r["key"]: r for r in lines}
    assert len(by_key) == len(lines), "a case stored twice"
    return by_key


def scenario(tmp_path: Path) -> Path:
    p = tmp_path / "cluster.toml"
    p.write_text('name = "cluster"\n[run]\nwidth = 32\nheight = 32\nrepeats = 1\nembree_timing = false\n'
                 'timeout_seconds = 120\n'
                 '[[cases]]\nscenes = ["cornell"]\nstructures = ["grid"]\nbackends = ["glsl", "opencl"]\n'
                 'resolutions = [16]\n'
                 '[[cases]]\nscenes = ["cornell"]\nstructures = ["svo"]\nbackends = ["opencl"]\n'
                 'resolutions = [16]\n'
                 '[[cases]]\nscenes = ["cornell"]\nstructures = ["esvo-ls"]\nbackends = ["glsl"]\n'
                 'resolutions = [8]\nls_n = [1]\n')
    return p


@pytest.fixture(scope="module")
def cluster():
    """A Ray head with one CPU (so it runs one case at a time) in this machine; the tests add and
    kill the second node."""
    try:
        from ray.cluster_utils import Cluster
    except ImportError:
        message = "ray is not installed (pip install 'lsbench[cluster]')"
        if os.environ.get("CI"):
            pytest.fail(message + "; CI is set, and .ci/run installs the cluster extra")
        pytest.skip(message)
    c = Cluster(initialize_head=True, head_node_args={"num_cpus": 1})
    try:
        yield c
    finally:
        c.shutdown()


def result_lines(stdout: str, key: str) -> list[str]:
    return [line for line in stdout.splitlines() if f"{key}: ok (" in line or f"{key}: FAILED (" in line]


def wait_for_results(proc: subprocess.Popen, count: int) -> list[str]:
    """Read the run's output until `count` cases have finished; the lines read."""
    seen = []
    for line in proc.stdout:
        seen.append(line)
        if sum(": ok (" in s or ": FAILED (" in s for s in seen) == count:
            return seen
    raise AssertionError(f"run ended before {count} cases finished: {''.join(seen)}{proc.stderr.read()}")


def hung_workers() -> list[int]:
    """Case workers (runner's spawned processes) hanging in LSBENCH_FAULT=hang: the flaky node's."""
    found = []
    for proc in Path("/proc").glob("[0-9]*"):
        try:
            if b"spawn_main" in (proc / "cmdline").read_bytes() \
                    and b"LSBENCH_FAULT=hang" in (proc / "environ").read_bytes().split(b"\0"):
                found.append(int(proc.name))
        except OSError:
            pass
    return found


def gone(pids: list[int], timeout: float = 30) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if not any(Path(f"/proc/{pid}").exists() and "Z" not in Path(f"/proc/{pid}/stat").read_text().split()[2]
                   for pid in pids if Path(f"/proc/{pid}").exists()):
            return True
        time.sleep(0.2)
    return False


def test_two_nodes_record_what_a_local_run_records(cluster, tmp_path):
    node = cluster.add_node(num_cpus=1)
    try:
        scen = scenario(tmp_path)
        local = lsbench("run", scen, "--out", tmp_path / "local")
        assert local.returncode == 0, local.stdout + local.stderr
        t0 = time.monotonic()
        run = lsbench("run", scen, "--out", tmp_path / "cluster", "--cluster", cluster.address, "--heatmaps")
        assert run.returncode == 0, run.stdout + run.stderr
        assert time.monotonic() - t0 < 120
    finally:
        cluster.remove_node(node)
    mine, theirs = records(tmp_path / "local"), records(tmp_path / "cluster")
    assert len(mine) == CASES and list(theirs) != [] and set(theirs) == set(mine)
    for key, rec in mine.items():
        other = theirs[key]
        for f in ("status", "agreement", "unexplained", "scene_hash", "rays_hash", "device", "driver",
                  "commit", "ray_count"):
            assert other[f] == rec[f], (key, f, other[f], rec[f])
        assert rec["status"] == "ok" and rec["node"] is None
        assert other["node"]["id"] in {cluster.head_node.node_id, node.node_id}
        for path in other["heatmaps"].values():  # written on the node, stored in the run folder
            assert (tmp_path / "cluster" / path).is_file(), path
    assert {r["node"]["id"] for r in theirs.values()} == {cluster.head_node.node_id, node.node_id}
    info = json.loads((tmp_path / "cluster" / "run.json").read_text())
    assert {n["id"] for n in info["cluster"]["nodes"]} == {cluster.head_node.node_id, node.node_id}
    # the cluster's records stand for the cases here too: a local rerun reuses every one
    again = lsbench("run", scen, "--out", tmp_path / "cluster")
    assert again.returncode == 0 and f"reusing {CASES} of {CASES} earlier records" in again.stdout, again.stdout


def test_a_node_killed_mid_case_loses_nothing(cluster, tmp_path):
    # the second node hangs in every case it gets (LSBENCH_FAULT, as in test_limits): the run
    # cannot end until that node dies and its case runs again on the head
    flaky = cluster.add_node(num_cpus=1, env_vars={"LSBENCH_FAULT": "hang"})
    out = tmp_path / "run"
    run = start("run", scenario(tmp_path), "--out", out, "--cluster", cluster.address)
    try:
        seen = wait_for_results(run, CASES - 1)
        hung = hung_workers()
        assert len(hung) == 1, "the flaky node runs no case"  # it is mid-case
        cluster.remove_node(flaky, allow_graceful=False)
        stdout, stderr = run.communicate(timeout=120)
    finally:
        if run.poll() is None:
            run.kill()
    stdout = "".join(seen) + stdout
    assert run.returncode == 0, stdout + stderr
    assert gone(hung), "the lost node's case worker outlived it"
    recs = records(out)
    assert len(recs) == CASES and all(r["status"] == "ok" for r in recs.values())
    assert {r["node"]["id"] for r in recs.values()} == {cluster.head_node.node_id}
    for key in recs:
        assert len(result_lines(stdout, key)) == 1, (key, stdout)


def test_without_retries_the_case_fails_naming_the_lost_node_and_the_folder_stays_locked(cluster, tmp_path):
    flaky = cluster.add_node(num_cpus=1, env_vars={"LSBENCH_FAULT": "hang"})
    out, scen = tmp_path / "run", scenario(tmp_path)
    run = start("run", scen, "--out", out, "--cluster", cluster.address, "--cluster-retries", "0")
    try:
        seen = wait_for_results(run, CASES - 1)
        assert len(hung_workers()) == 1, "the flaky node runs no case"
        second = lsbench("run", scen, "--out", out, "--cluster", cluster.address)
        assert second.returncode == 2 and "in use by another run" in second.stderr, second.stdout + second.stderr
        assert "submitted" not in second.stdout
        cluster.remove_node(flaky, allow_graceful=False)
        stdout, stderr = run.communicate(timeout=120)
    finally:
        if run.poll() is None:
            run.kill()
    assert run.returncode == 1, "".join(seen) + stdout + stderr  # a failed case
    recs = records(out)
    failed = [r for r in recs.values() if r["status"] != "ok"]
    assert len(recs) == CASES and len(failed) == 1
    lost = failed[0]
    assert lost["node"]["id"] == flaky.node_id
    assert f"lost with node {lost['node']['host']} " in lost["reason"] and flaky.node_id[:12] in lost["reason"]
    assert lost["scene_hash"] and lost["device"]  # the record still says what it was to run on


def test_cases_go_to_the_nodes_that_open_their_backend_and_to_gpus_first():
    cpu = {"device": "llvmpipe", "driver": "mesa", "backend_version": "1"}
    gpu = {"device": "NVIDIA H100", "driver": "550", "backend_version": "1"}
    cpu_node = Node("a" * 56, "cpu-box", "10.0.0.1", {"CPU": 2}, {"glsl": cpu, "opencl": {"device": None,
                                                                                          "error": "no platform"}},
                    {"glsl": False})
    gpu_node = Node("b" * 56, "gpu-box", "10.0.0.2", {"CPU": 8, "GPU": 1, "h100": 1}, {"glsl": gpu, "opencl": gpu},
                    {"glsl": True, "opencl": True})
    other_code = Node("c" * 56, "stale", "10.0.0.3", {"CPU": 8}, {"glsl": cpu}, {"glsl": False},
                      unusable="runs other lsbench code")
    nodes = [cpu_node, gpu_node, other_code]
    glsl = place("glsl", nodes, {})
    assert glsl.nodes == (gpu_node,) and glsl.num_gpus == 1  # a GPU where one opens the backend
    assert glsl.options({}, 2)["label_selector"] == {"ray.io/node-id": f"in({'b' * 56})"}
    assert place("glsl", [cpu_node, other_code], {}).nodes == (cpu_node,)
    assert place("glsl", [cpu_node], {}).num_gpus == 0
    assert place("opencl", nodes, {}).nodes == (gpu_node,)
    none = place("opencl", [cpu_node, other_code], {})
    assert none.nodes == () and "no node of the cluster opens backend opencl" in none.none_because
    assert "cpu-box" in none.none_because and "no platform" in none.none_because
    assert "runs other lsbench code" in none.none_because
    pinned = place("glsl", nodes, {"h100": 1})
    assert pinned.nodes == (gpu_node,) and pinned.options({"h100": 1}, 0)["resources"] == {"h100": 1}
    assert place("glsl", nodes, {"a100": 1}).nodes == ()


@pytest.mark.parametrize("flag", [["--cluster", "nowhere"], ["--cluster", "host:99999"],
                                  ["--cluster", "auto", "--cluster-resource", "GPU=1"],
                                  ["--cluster", "auto", "--cluster-resource", "h100=0"],
                                  ["--cluster", "auto", "--cluster-retries", "-1"],
                                  ["--cluster", "127.0.0.1:1"]])  # nothing listens: at once, not after minutes
def test_bad_cluster_flags_are_one_line(flag, tmp_path):
    res = lsbench("run", scenario(tmp_path), "--out", tmp_path / "run", *flag, timeout=60)
    lines = res.stderr.strip().splitlines()
    assert res.returncode == 2 and len(lines) == 1 and flag[-1] in lines[0], res.stderr
    assert not (tmp_path / "run" / "results.jsonl").exists()
