"""What a result was measured on: the code (commit, dirty), the machine and Python, the package
versions that change figures, and whether the backends run on a GPU."""
from __future__ import annotations

import datetime as _dt
import importlib.metadata
import os
import platform
import socket
import subprocess
import sys

from lsbench.paths import source_checkout

# Packages whose versions change measured numbers or accuracy (kernel compilers, Embree,
# mesh loading); recorded with every run so two runs can be told apart.
TRACKED_PACKAGES = ("numpy", "trimesh", "embreex", "moderngl", "pyopencl", "matplotlib")

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
        "versions": {name: package_version(name) for name in TRACKED_PACKAGES},
    }


def code_state() -> tuple[str, bool]:
    """(commit, dirty) of the lsbench source; ("unknown", False) for an installed copy."""
    top = source_checkout()
    commit, dirty = git_state(top) if top is not None else (None, None)
    return (commit or "unknown"), bool(dirty)


def record_env() -> dict:
    """The code fields every record carries."""
    commit, dirty = code_state()
    return {"commit": commit, "dirty": dirty}


def uses_gpu(backend_names) -> bool:
    """True when any of the backends runs on a GPU (scenarios then use their gpu_width/height)."""
    from lsbench import backends

    for name in backend_names:
        info = backends.get_device(name).info()
        if name == "opencl" and "GPU" in str(info.get("device_type", "")):
            return True
        if name == "glsl" and not any(s in info["device"].lower() for s in ("llvmpipe", "softpipe", "lavapipe")):
            return True
    return False
