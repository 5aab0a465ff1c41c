"""What a result was measured on: the code (commit, dirty), the machine and Python, the package
versions that change figures, and whether the backends run on a GPU."""
from __future__ import annotations

import datetime as _dt
import hashlib
import importlib.metadata
import os
import platform
import socket
import subprocess
import sys
from pathlib import Path

from lsbench.paths import source_checkout

# Packages whose versions change measured numbers or accuracy (kernel compilers, Embree,
# mesh loading); recorded with every run so two runs can be told apart.
TRACKED_PACKAGES = ("numpy", "trimesh", "embreex", "moderngl", "pyopencl", "matplotlib",
                    "colour-science")  # colour-science: the image ΔE (oracle/image.py)

def git_state(repo_dir=".") -> tuple[str | None, bool | None]:
    """(commit sha, dirty) of the work tree at repo_dir; (None, None) outside a git repository.

    Dirty counts modified tracked files and untracked, not ignored ones: both change what runs.
    """
    def git(*args):
        return subprocess.run(["git", "-C", str(repo_dir), *args], capture_output=True,
                              text=True, timeout=30)
    try:
        head = git("rev-parse", "HEAD")
        if head.returncode != 0:
            return None, None
        status = git("status", "--porcelain")
    except (OSError, subprocess.TimeoutExpired):
        return None, None
    return head.stdout.strip(), bool(status.stdout.strip()) if status.returncode == 0 else None


def package_version(name: str) -> str | None:
    try:
        return importlib.metadata.version(name)
    except importlib.metadata.PackageNotFoundError:
        return None


def package_versions() -> dict[str, str | None]:
    return {name: package_version(name) for name in TRACKED_PACKAGES}


def environment_info() -> dict:
    """What the machine and Python environment are; the runner adds devices and scenario."""
    return {
        "date": _dt.datetime.now(_dt.timezone.utc).astimezone().isoformat(timespec="seconds"),
        "host": socket.gethostname(),
        "machine": platform.machine(),
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "python": sys.version.split()[0],
        "python_implementation": platform.python_implementation(),
        "versions": package_versions(),
    }


def code_state() -> tuple[str, bool]:
    """(commit, dirty) of the lsbench source; ("unknown", False) for an installed copy."""
    top = source_checkout()
    commit, dirty = git_state(top) if top is not None else (None, None)
    return (commit or "unknown"), bool(dirty)


def diff_hash(repo_dir) -> str | None:
    """Short sha256 of a dirty work tree's changes against HEAD (tracked diffs and the untracked,
    not ignored files), so records of two different dirty trees at one commit are told apart;
    None for a clean tree or outside git."""
    def git(*args) -> bytes | None:
        try:
            proc = subprocess.run(["git", "-C", str(repo_dir), *args], capture_output=True, timeout=60)
        except (OSError, subprocess.TimeoutExpired):
            return None
        return proc.stdout if proc.returncode == 0 else None

    diff = git("diff", "HEAD", "--binary")
    untracked = git("ls-files", "--others", "--exclude-standard", "-z")
    if diff is None or untracked is None or not (diff or untracked):
        return None
    h = hashlib.sha256(diff)
    for name in sorted(filter(None, untracked.split(b"\0"))):
        h.update(b"\0" + name + b"\0")
        try:
            h.update((Path(repo_dir) / os.fsdecode(name)).read_bytes())
        except OSError:  # gone or unreadable since git listed it
            pass
    return h.hexdigest()[:16]


def machine_env() -> dict:
    """The record fields that describe this machine's software, not the code: package versions
    and the test-only planted defect (a cluster node records its own)."""
    return {"versions": package_versions(),
            # the test-only defect backends.build plants: it changes what an ok case measures
            "planted_defect": os.environ.get("LSBENCH_PLANT_DEFECT") or None}


def record_env() -> dict:
    """The code and package fields every record carries (lsbench/results/record.py)."""
    commit, dirty = code_state()
    top = source_checkout()
    return {"commit": commit, "dirty": dirty, "diff_hash": diff_hash(top) if dirty and top else None,
            **machine_env()}


def on_gpu(backend_name: str, info: dict) -> bool:
    """Whether a backend's device (its Device.info()) is a GPU rather than a CPU driver."""
    if backend_name == "opencl":
        return "GPU" in str(info.get("device_type", ""))
    if backend_name == "glsl":
        return not any(s in str(info.get("device", "")).lower() for s in ("llvmpipe", "softpipe", "lavapipe"))
    return False


def uses_gpu(backend_names) -> bool:
    """True when any of the backends runs on a GPU (scenarios then use their gpu_width/height)."""
    from lsbench import backends

    return any(on_gpu(name, backends.get_device(name).info()) for name in backend_names)


def device_info(backend_names) -> dict[str, dict]:
    """{backend: {"device", "driver", "backend_version"}} as this run sees them (run.json, and
    what a record must match to be reused); a backend that cannot start gets {"device": None,
    "error": why} (its cases fail and say it too)."""
    from lsbench import backends

    devices = {}
    for name in sorted(set(backend_names)):
        try:
            d = backends.get_device(name).info()
            devices[name] = {"device": d["device"], "driver": d["driver"], "backend_version": d["backend_version"]}
        except Exception as exc:
            devices[name] = {"device": None, "error": str(exc).splitlines()[0] if str(exc) else type(exc).__name__}
    return devices
