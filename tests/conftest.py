"""Shared fixtures: real drivers (llvmpipe via EGL, PoCL), real Embree, real scenes."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SCENES = Path(os.environ.get("LSBENCH_SCENES", REPO.parent / "shared" / "scenes"))


def scene_path(name: str) -> str:
    """Path of a real scene. Absent: the test is skipped on a developer's machine, but fails when
    CI is set (a CI run without the shared scenes must not pass by checking nothing)."""
    path = SCENES / name
    if not path.is_file():
        message = f"real scene {path} absent (set LSBENCH_SCENES to the shared scenes folder)"
        if os.environ.get("CI"):
            pytest.fail(message + "; CI is set, so a missing scene is a failure")
        pytest.skip(message)
    return str(path)


@pytest.fixture(autouse=True, scope="session")
def _embree_cache(tmp_path_factory):
    # Keep Embree results of the test run apart from a user's cache.
    os.environ.setdefault("LSBENCH_CACHE", str(tmp_path_factory.mktemp("embree-cache")))


@pytest.fixture(params=["glsl", "opencl"])
def device(request):
    from lsbench import backends

    return backends.get_device(request.param)
