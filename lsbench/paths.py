"""Where lsbench finds its own files and the user's: kernel sources and shipped scenarios (package
data, found with importlib.resources, so a wheel works from any directory), the source checkout
when there is one (commit of the results, default report folder), and the real-scene folder."""
from __future__ import annotations

import os
from importlib import resources
from pathlib import Path

PACKAGE_ROOT = Path(str(resources.files("lsbench")))
SHADER_ROOT = PACKAGE_ROOT / "shaders"
SCENARIO_ROOT = PACKAGE_ROOT / "scenarios"


def source_checkout() -> Path | None:
    """The git checkout lsbench runs from (an editable install or PYTHONPATH), else None."""
    top = PACKAGE_ROOT.parent
    return top if (top / ".git").exists() and (top / "pyproject.toml").is_file() else None


def reports_dir() -> Path:
    """Default parent of run folders: <checkout>/reports, else ./reports."""
    top = source_checkout()
    return (top if top is not None else Path.cwd()) / "reports"


def scenes_dir() -> Path:
    """Value of `$SCENES` in scenario files: env LSBENCH_SCENES, else the shared scenes beside the
    checkout (../shared/scenes), else ./shared/scenes."""
    if os.environ.get("LSBENCH_SCENES"):
        return Path(os.environ["LSBENCH_SCENES"])
    top = source_checkout()
    base = top.parent if top is not None else Path.cwd()
    return base / "shared" / "scenes"


def shipped_scenario(name: str) -> Path | None:
    """A scenario shipped with lsbench by name ("ci", "default", ...), or None."""
    path = SCENARIO_ROOT / f"{name}.toml"
    return path if path.is_file() else None
