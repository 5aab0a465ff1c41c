"""The wheel a user builds (`pip wheel .`) is the whole tool: kernels and scenarios ship as package
data, the package is `lsbench`, and `lsbench trace` works from another directory."""
from __future__ import annotations

import json
import subprocess
import sys
import sysconfig
import venv
import zipfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test_wheel_installs_and_traces_from_another_directory(tmp_path):
    wheels = tmp_path / "wheels"
    build = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(wheels), str(REPO)],
                           capture_output=True, text=True, timeout=600)
    assert build.returncode == 0, build.stderr
    (wheel,) = wheels.glob("lsbench-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    for shipped in ("lsbench/shaders/common/grid.h", "lsbench/shaders/glsl/prelude.glsl",
                    "lsbench/shaders/opencl/prelude.cl", "lsbench/scenarios/ci.toml", "lsbench/cli.py"):
        assert shipped in names, shipped
    assert not any(n.startswith(("harness/", "backends/", "tests/")) for n in names)

    # A fresh environment with only the wheel installed; its dependencies are this interpreter's
    # (a path entry, not a site dir: the checkout's editable-install hook is not run there).
    env_dir = tmp_path / "venv"
    venv.create(env_dir, with_pip=True)
    py = env_dir / "bin" / "python"
    site = subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                          capture_output=True, text=True, check=True).stdout.strip()
    Path(site, "deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    install = subprocess.run([str(py), "-m", "pip", "install", "--no-deps", "-q", str(wheel)],
                             capture_output=True, text=True, timeout=300)
    assert install.returncode == 0, install.stderr

    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    where = subprocess.run([str(py), "-c", "import lsbench; print(lsbench.__file__)"], cwd=elsewhere,
                           capture_output=True, text=True, check=True).stdout.strip()
    assert where.startswith(str(env_dir)), where
    trace = subprocess.run([str(env_dir / "bin" / "lsbench"), "trace", "--scene", "cornell", "--structure", "grid",
                            "--backend", "opencl", "--resolution", "4", "--size", "16x16", "--repeats", "1", "--json"],
                           cwd=elsewhere, capture_output=True, text=True, timeout=300)
    assert trace.returncode == 0, trace.stderr
    rec = json.loads(trace.stdout)
    assert rec["status"] == "ok" and rec["agreement"] == 1.0 and rec["ray_count"] == 256
    # a shipped scenario by name, found inside the installed package
    by_name = subprocess.run([str(py), "-c", "from lsbench.inputs.scenario import load_scenario; "
                              "s = load_scenario('ci'); print(s.path, len(s.cases))"], cwd=elsewhere,
                             capture_output=True, text=True, timeout=120)
    assert by_name.returncode == 0, by_name.stderr
    path, count = by_name.stdout.split()
    assert path.startswith(str(env_dir)) and int(count) > 0
    listed = subprocess.run([str(env_dir / "bin" / "lsbench"), "run", "no-such-scenario"], cwd=elsewhere,
                            capture_output=True, text=True, timeout=120)
    assert listed.returncode == 2 and "no-such-scenario" in listed.stderr
