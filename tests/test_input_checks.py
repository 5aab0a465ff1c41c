"""Every bad input value is one line on stderr naming the key or flag, the value and what is
allowed, exit 2, before any device work (issue 13, items 12 and 13); valid inputs still run.
All through the real CLI (`python -m lsbench ...` in a subprocess)."""
from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def lsbench(*args, timeout=300):
    return subprocess.run([sys.executable, "-m", "lsbench", *map(str, args)], cwd=REPO,
                          capture_output=True, text=True, timeout=timeout, env=dict(os.environ))


def assert_one_line_error(proc, needles):
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert proc.stdout == ""  # nothing that looks like a result
    assert "Traceback" not in proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("lsbench: error:"), proc.stderr
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])


def scenario_text(run: str = "", case: str = "", top: str = "") -> str:
    """A valid one-case scenario (quad, grid, OpenCL) with lines added to the top level, [run]
    and the [[cases]] block."""
    return (f'name = "checks"\n{top}\n[run]\nwidth = 8\nheight = 8\nrepeats = 1\n{run}\n'
            f'[[cases]]\nscenes = ["quad"]\nstructures = ["grid"]\nresolutions = [4]\n{case}\n')


CASES_ONLY = '[[cases]]\nscenes = ["quad"]\nstructures = ["grid"]\nresolutions = [4]\n'
ALLOWED_INT1 = "is not an integer >= 1"

# Item 12: (scenario text, what the one line must contain: key, value, what is allowed)
BAD_SCENARIOS = {
    "backend-typo": (scenario_text(case='backend = ["glsl"]'),
                     ['[[cases]] #1', 'unknown key "backend"', 'did you mean "backends"', "allowed: scenes"]),
    "misspelt-Run": ('name = "x"\n[Run]\nwidth = 8\n' + CASES_ONLY,
                     ['unknown key "Run"', 'did you mean "run"', "allowed: name, run, cases"]),
    "top-level-typo": (scenario_text(top='nmae = "y"'), ['unknown key "nmae"', 'did you mean "name"']),
    "run-key-typo": (scenario_text(run="repeat = 3"),
                     ['[run] unknown key "repeat"', 'did you mean "repeats"', "allowed: width, height"]),
    "width-wide": (scenario_text(run="").replace("width = 8", 'width = "wide"'),
                   ['[run] width = "wide" (a string)', ALLOWED_INT1]),
    "repeats-string": (scenario_text().replace("repeats = 1", 'repeats = "3"'),
                       ['[run] repeats = "3" (a string)', ALLOWED_INT1]),
    "width-fraction": (scenario_text().replace("width = 8", "width = 32.5"), ["[run] width = 32.5", ALLOWED_INT1]),
    "width-bool": (scenario_text().replace("width = 8", "width = true"),
                   ["[run] width = true (a boolean)", ALLOWED_INT1]),
    "repeats-zero": (scenario_text().replace("repeats = 1", "repeats = 0"), ["[run] repeats = 0", ALLOWED_INT1]),
    "warmup-negative": (scenario_text(run="warmup = -1"), ["[run] warmup = -1", "is not an integer >= 0"]),
    "min-agreement-high": (scenario_text(run='min_agreement = "high"'),
                           ['[run] min_agreement = "high"', "is not a number in [0, 1]"]),
    "min-agreement-range": (scenario_text(run="min_agreement = 1.5"),
                            ["[run] min_agreement = 1.5", "is not a number in [0, 1]"]),
    "rel-tol-nan": (scenario_text(run="rel_tol = nan"), ["[run] rel_tol = nan", "is not a finite number >= 0"]),
    "rel-tol-negative": (scenario_text(run="rel_tol = -1"), ["[run] rel_tol = -1", "is not a finite number >= 0"]),
    "timeout-zero": (scenario_text(run="timeout_seconds = 0"),
                     ["[run] timeout_seconds = 0", "is not a finite number > 0"]),
    "heatmaps-int": (scenario_text(run="heatmaps = 1"), ["[run] heatmaps = 1", "is not true or false"]),
    "rays-typo": (scenario_text(run='rays = "primery"'),
                  ['[run] rays = "primery" is an unknown ray set', 'did you mean "primary"',
                   "allowed: a ray set (adversarial, ao, diffuse, incoherent, primary, shadow) or a path to a .npz file"]),
    "image-too-large": (scenario_text().replace("width = 8\nheight = 8", "width = 100000\nheight = 100000"),
                        ["[run] width x height = 100000x100000", "over the limit of 67108864"]),
    "gpu-width-alone": (scenario_text(run="gpu_width = 1920"), ["gpu_width and gpu_height", "both or neither"]),
    "cases-string": ('name = "x"\ncases = "nope"\n', ['cases = "nope"', "is not a non-empty array of tables"]),
    "cases-table": ('name = "x"\n[cases]\nscenes = ["quad"]\n', ["cases = {", "array of tables"]),
    "run-number": ('name = "x"\nrun = 5\n' + CASES_ONLY, ["run = 5", "is not a table"]),
    "backends-empty": (scenario_text(case="backends = []"),
                       ["[[cases]] #1: backends = []", 'one of "glsl", "opencl", or a non-empty list']),
    "backend-unknown": (scenario_text(case='backends = ["openCL"]'),
                        ['backends[0] = "openCL" is an unknown backend', 'did you mean "opencl"',
                         'allowed: one of "glsl", "opencl"']),
    "structure-unknown": (scenario_text().replace('["grid"]', '["gird"]'),
                          ['structures[0] = "gird" is an unknown structure', 'did you mean "grid"',
                           'allowed: one of "grid", "svo"']),
    "scenes-empty": (scenario_text().replace('["quad"]', "[]"), ["scenes = []", "a non-empty string"]),
    "resolution-zero": (scenario_text().replace("resolutions = [4]", 'resolutions = [4, 0]'),
                        ["resolutions[1] = 0", 'a positive integer or "RxRyRz"']),
    "resolution-text": (scenario_text().replace("resolutions = [4]", 'resolutions = ["4by4"]'),
                        ['resolutions[0] = "4by4"', 'a positive integer or "RxRyRz"']),
    "ls-n-negative": (scenario_text(case="ls_n = [1, -1]"), ["ls_n[1] = -1", "is not an integer >= 0"]),
    "ls-min-candidates-text": (scenario_text(case='ls_min_candidates = "many"'),
                               ['ls_min_candidates = "many"', 'an integer >= 0, or "auto"', "or a non-empty list"]),
    "missing-resolutions": (scenario_text().replace("resolutions = [4]\n", ""),
                            ["missing resolutions", "needed: scenes, structures, resolutions"]),
    "camera-fov-0": (scenario_text(case="camera = { eye = [0, 0, 3], target = [0, 0, 0], fov = 0 }"),
                     ["camera.fov = 0", "is not a number in (0, 180)"]),
    "camera-fov-180": (scenario_text(case="camera = { eye = [0, 0, 3], target = [0, 0, 0], fov = 180 }"),
                       ["camera.fov = 180", "is not a number in (0, 180)"]),
    "camera-eye-2": (scenario_text(case="camera = { eye = [0, 3], target = [0, 0, 0] }"),
                     ["camera.eye = [0, 3]", "is not 3 finite numbers"]),
    "camera-target-nan": (scenario_text(case="camera = { eye = [0, 0, 3], target = [0, nan, 0] }"),
                          ["camera.target = [0, nan, 0]", "is not 3 finite numbers"]),
    "camera-up-text": (scenario_text(case='camera = { eye = [0, 0, 3], target = [0, 0, 0], up = "y" }'),
                       ['camera.up = "y"', "is not 3 finite numbers"]),
    "camera-eye-is-target": (scenario_text(case="camera = { eye = [0, 0, 3], target = [0, 0, 3] }"),
                             ["camera.eye = [0, 0, 3]", "equals target"]),
    "camera-key-typo": (scenario_text(case="camera = { eye = [0, 0, 3], target = [0, 0, 0], fovy = 40 }"),
                        ['camera: unknown key "fovy"', 'did you mean "fov"', "allowed: eye, target, up, fov"]),
}


@pytest.mark.parametrize("name", sorted(BAD_SCENARIOS))
def test_bad_scenario_value_is_one_line(tmp_path, name):
    text, needles = BAD_SCENARIOS[name]
    path = tmp_path / "s.toml"
    path.write_text(text)
    for command in ("run", "gate"):
        out = tmp_path / f"out-{command}"
        assert_one_line_error(lsbench(command, path, "--out", out), [str(path), *needles])
        assert not out.exists()  # refused before the run folder is made


# Item 13: (command line, what the one line must contain)
TRACE = ["trace", "--scene", "quad", "--structure", "grid", "--backend", "opencl"]
SCENARIO = REPO / "scenarios" / "ci.toml"
BAD_FLAGS = {
    "repeats-0": (TRACE + ["--repeats", "0"], ["argument --repeats: 0", ALLOWED_INT1]),
    "warmup-negative": (TRACE + ["--warmup=-1"], ["argument --warmup: -1", "is not an integer >= 0"]),
    "rel-tol-nan": (TRACE + ["--rel-tol", "nan"], ["argument --rel-tol: nan", "is not a finite number >= 0"]),
    "rel-tol-negative": (TRACE + ["--rel-tol=-1"], ["argument --rel-tol: -1", "is not a finite number >= 0"]),
    "size-huge": (TRACE + ["--size", "100000x100000"],
                  ["argument --size: 100000x100000", "10000000000 rays", "over the limit of 67108864"]),
    "size-zero": (TRACE + ["--size", "0x8"], ["argument --size: 0x8", "is not WxH with W, H >= 1"]),
    "camera-fov-0": (TRACE + ["--camera", "0,0,3:0,0,0:0"], ["argument --camera", "fov = 0.0", "(0, 180)"]),
    "camera-fov-180": (TRACE + ["--camera", "0,0,3:0,0,0:180"], ["argument --camera", "fov = 180.0", "(0, 180)"]),
    "camera-nan": (TRACE + ["--camera", "0,0,nan:0,0,0"], ["argument --camera", "eye = [0.0, 0.0, nan]",
                                                          "3 finite numbers"]),
    "resolution-0": (TRACE + ["--resolution", "0"], ["argument --resolution: 0", "a positive integer or"]),
    "ls-n-negative": (TRACE + ["--ls-n=-1"], ["argument --ls-n: -1", "is not an integer >= 0"]),
    "factor-0": (["compare", "a", "b", "--factor", "0"], ["argument --factor: 0", "is not a finite number >= 1"]),
    "factor-negative": (["compare", "a", "b", "--factor=-1"], ["argument --factor: -1", "finite number >= 1"]),
    "alpha-2": (["compare", "a", "b", "--alpha", "2"], ["argument --alpha: 2", "is not a number in (0, 1)"]),
    "alpha-nan": (["compare-commits", "a", "b", "s.toml", "--alpha", "nan"],
                  ["argument --alpha: nan", "is not a number in (0, 1)"]),
    "budget-0": (["run", SCENARIO, "--memory-budget", "0"], ["argument --memory-budget: 0", "finite number > 0"]),
    "budget-negative": (["gate", SCENARIO, "--memory-budget=-5"], ["argument --memory-budget: -5", "> 0"]),
    "budget-nan": (["run", SCENARIO, "--memory-budget", "nan"], ["argument --memory-budget: nan", "> 0"]),
    "processes-0": (["stability", *TRACE[1:], "--processes", "0"], ["argument --processes: 0", ALLOWED_INT1]),
    "timeout-0": (["stability", *TRACE[1:], "--timeout", "0"], ["argument --timeout: 0", "finite number > 0"]),
}


@pytest.mark.parametrize("name", sorted(BAD_FLAGS))
def test_bad_flag_value_is_one_line(name):
    argv, needles = BAD_FLAGS[name]
    assert_one_line_error(lsbench(*argv), needles)


def _out_cases(tmp_path):
    a_file = tmp_path / "a-file"
    a_file.write_text("kept\n")
    # /proc takes no new files, not even from root (chmod would not stop root)
    return {"a-file": (a_file, "is a file"), "under-a-file": (a_file / "run", "cannot be created"),
            "read-only": (Path("/proc/lsbench-out"), "is not writable")}


@pytest.mark.parametrize("command", ["run", "gate", "compare-commits", "report"])
@pytest.mark.parametrize("kind", ["a-file", "under-a-file", "read-only"])
def test_unusable_out_folder_is_one_line(tmp_path, command, kind):
    out, words = _out_cases(tmp_path)[kind]
    scenario = tmp_path / "s.toml"
    scenario.write_text(scenario_text())
    argv = {"run": ["run", scenario], "gate": ["gate", scenario], "report": ["report", tmp_path],
            "compare-commits": ["compare-commits", "HEAD", "HEAD", scenario]}[command]
    allowed = "allowed: a folder that exists or can be created, and is writable"
    assert_one_line_error(lsbench(*argv, "--out", out), [f"argument --out: {out}", words, allowed])
    assert (tmp_path / "a-file").read_text() == "kept\n"


# --- a device that cannot start under the memory budget says so, not "install drivers" --------

START_UNDER_LIMIT = """
import resource, sys
from lsbench import backends
import moderngl, pyopencl  # their Python modules are in; the drivers' libraries are not yet
size = int([l for l in open("/proc/self/status") if l.startswith("VmSize")][0].split()[1]) * 1024
limit = size + 32 * 2**20  # what is in use, and 32 MiB: too little for llvmpipe or PoCL to start
resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
try:
    backends.get_device(sys.argv[1])
    print("started")
except backends.DeviceError as exc:
    print(exc)
"""


@pytest.mark.parametrize("backend", ["glsl", "opencl"])
def test_device_start_under_an_address_space_limit_names_the_limit(backend):
    """Where the message comes from: the backends' start (glsl.py, opencl.py) told the user to
    install drivers when RLIMIT_AS, which --memory-budget sets in each case worker, was the
    cause."""
    proc = subprocess.run([sys.executable, "-c", START_UNDER_LIMIT, backend], cwd=REPO,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    message = proc.stdout.strip()
    assert message != "started"
    assert "address-space limit of" in message and "--memory-budget" in message, message
    assert "the likely cause" in message and "install" not in message, message


def test_run_under_a_small_memory_budget_names_the_budget(tmp_path):
    """`lsbench run --memory-budget 300` (the issue's command): every case fails, and each reason
    puts it down to the budget (a worker that crashed, or a device that did not start), never
    to missing drivers."""
    scenario = tmp_path / "s.toml"
    scenario.write_text(scenario_text(case='backends = ["glsl", "opencl"]'))
    out = tmp_path / "out"
    proc = lsbench("run", scenario, "--out", out, "--memory-budget", 300)
    assert "Traceback" not in proc.stderr, proc.stderr
    records = [json.loads(line) for line in (out / "results.jsonl").read_text().splitlines()]
    assert [r["backend"] for r in records] == ["glsl", "opencl"]
    for r in records:
        assert r["status"] == "failed", r
        assert "memory-budget" in r["reason"] and "install" not in r["reason"], r["reason"]


# --- valid inputs still run -------------------------------------------------------------------

VALID = """
name = "valid"
[run]
width = 16
height = 12
repeats = 1
warmup = 0
rel_tol = 0
min_agreement = 1
timeout_seconds = 120.5
heatmaps = false
embree_timing = false
[[cases]]
scenes = ["quad"]
structures = "grid"
backends = "opencl"
resolutions = [4, "4x2x3"]
camera = { eye = [0.2, 0.1, 3], target = [0, 0, 0], up = [0, 1, 0], fov = 50 }
[[cases]]
scenes = ["quad"]
structures = ["grid-ls"]
backends = ["glsl"]
resolutions = [4]
ls_n = 1
ls_min_candidates = [0]
"""


def test_valid_scenario_runs(tmp_path):
    scenario = tmp_path / "valid.toml"
    scenario.write_text(VALID)
    out = tmp_path / "made" / "here"  # an --out that does not exist yet is created
    proc = lsbench("gate", scenario, "--out", out, "--memory-budget", 8000.5)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    records = [json.loads(line) for line in (out / "results.jsonl").read_text().splitlines()]
    assert [(r["structure"], r["backend"], r["resolution"]) for r in records] == [
        ("grid", "opencl", "4"), ("grid", "opencl", "4x2x3"), ("grid-ls", "glsl", "4")]
    assert all(r["status"] == "ok" and r["agreement"] == 1.0 for r in records), records
    assert all((r["width"], r["height"]) == (16, 12) for r in records)


def test_valid_flags_run(tmp_path):
    proc = lsbench(*TRACE, "--size", "16x12", "--camera", "0.2,0.1,3:0,0,0:179.5", "--rel-tol", "0",
                   "--repeats", "1", "--warmup", "0", "--resolution", "4x2x3", "--json",
                   "--heatmaps", tmp_path / "new" / "heatmaps")
    assert proc.returncode == 0, proc.stderr[-2000:]
    rec = json.loads(proc.stdout)
    assert rec["status"] == "ok" and rec["ray_count"] == 16 * 12 and rec["agreement"] == 1.0


def test_every_run_setting_has_a_rule_its_default_meets():
    """A new [run] setting must say what it allows (RUN_RULES) or it would go unchecked."""
    from lsbench.inputs.scenario import RUN_RULES, RunSettings

    fields = dataclasses.fields(RunSettings)
    assert sorted(RUN_RULES) == sorted(f.name for f in fields)
    for f in fields:
        if f.default is not None:
            RUN_RULES[f.name].check(f.name, f.default)


def test_bvh_blocks_need_no_resolution_and_get_one_case(tmp_path):
    """A BVH builds no grid: a block of BVHs only may leave out resolutions, and in a block with
    grids a BVH is one case, not one identical case per resolution; a grid block still needs them."""
    from lsbench.inputs.scenario import ScenarioError, load_scenario

    path = tmp_path / "s.toml"
    path.write_text('[[cases]]\nscenes = ["cornell"]\nstructures = ["bvh", "bvh-ls"]\nbackends = ["opencl"]\n'
                    '[[cases]]\nscenes = ["cornell"]\nstructures = ["grid", "bvh"]\nbackends = ["opencl"]\n'
                    'resolutions = [8, 16]\n')
    cases = load_scenario(str(path)).cases
    assert sorted((c.structure, c.resolution) for c in cases) == [
        ("bvh", "1"), ("bvh", "8"), ("bvh-ls", "1"), ("grid", "16"), ("grid", "8")]
    path.write_text('[[cases]]\nscenes = ["cornell"]\nstructures = ["grid", "bvh"]\n')
    with pytest.raises(ScenarioError, match="missing resolutions"):
        load_scenario(str(path))
