"""What the report reads from a case record: did it run, is it a Line Space case, how a person
names it (scene, resolution, case label) and in which order resolutions go. Structures are
ordered by the catalogue (lsbench.backends.structures.display_order)."""
from __future__ import annotations

import math
import os
import re

from lsbench.backends.structures import STRUCTURES


def succeeded(rec) -> bool:
    return rec.get("status") == "ok"


def has_line_space(rec) -> bool:
    info = STRUCTURES.get(str(rec.get("structure", "")))
    return bool(rec.get("ls_n")) or (info is not None and info.line_space)


def resolution_order(res) -> tuple:
    """Sort key: voxel count, then the text (64 < 64x64x128 < 128)."""
    dims = [int(x) for x in re.findall(r"\d+", str(res))] or [0]
    return (math.prod(dims), str(res))


def resolution_label(res) -> str:
    s = str(res)
    return f"{s}³" if s.isdigit() else s


def _stem(path: str) -> str:
    base = os.path.basename(path.rstrip("/")) or path
    return os.path.splitext(base)[0] if "." in base else base


def scene_name(rec) -> str:
    """The scene's file stem or built-in name; the label label_scenes gave it when two scene
    files share a stem."""
    return rec.get("scene_label") or _stem(str(rec.get("scene", "?")))


def label_scenes(records) -> None:
    """Two scene files with one name in different folders are two scenes (two cases each): give
    each record whose stem is shared by another source a label with its folder, so the report's
    tables and charts keep them apart."""
    sources: dict[str, set] = {}
    for r in records:
        src = str(r.get("scene_source") or r.get("scene", "?"))
        sources.setdefault(_stem(src), set()).add(src)
    for r in records:
        src = str(r.get("scene_source") or r.get("scene", "?"))
        if len(sources[_stem(src)]) > 1:
            r["scene_label"] = f"{_stem(src)} ({os.path.dirname(src) or '.'})"


def case_label(rec, with_scene=False) -> str:
    """"grid 64³ glsl", "svo-ls 32³ N=2 opencl", "bvh leaf 8 opencl" (a BVH has no grid
    resolution: its leaf size instead); with_scene puts the scene first."""
    leaf = rec.get("leaf_size")
    parts = [rec.get("structure", "?"),
             f"leaf {leaf}" if leaf else resolution_label(rec.get("resolution", "?"))]
    if rec.get("ls_n"):
        parts.append(f"N={rec['ls_n']}")
    parts.append(rec.get("backend", "?"))
    if with_scene:
        parts.insert(0, scene_name(rec))
    return " ".join(str(p) for p in parts)
