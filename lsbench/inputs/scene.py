"""Scene: an indexed triangle mesh plus a default camera (plain data).

Triangle ids are the face order of the source file (loaded with trimesh `process=False`),
so the id a backend reports is the id Embree reports.
"""
from __future__ import annotations

import hashlib
from dataclasses import dataclass, field

import numpy as np


def arrays_hash(*arrays: np.ndarray) -> str:
    """Short sha256 of the arrays' bytes in order: the identity of a scene or ray set in caches
    and records (callers fix the dtypes, so the same data always hashes the same)."""
    h = hashlib.sha256()
    for a in arrays:
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()[:16]


class SceneError(ValueError):
    """Bad scene input (missing/corrupt file, empty mesh, NaN/Inf vertices): one-line message."""


@dataclass(frozen=True)
class Camera:
    eye: tuple[float, float, float]
    target: tuple[float, float, float]
    up: tuple[float, float, float] = (0.0, 1.0, 0.0)
    fov_deg: float = 60.0  # vertical field of view


@dataclass
class Scene:
    name: str
    vertices: np.ndarray  # (V, 3) float32
    faces: np.ndarray  # (F, 3) uint32, indices into vertices
    source: str  # file path, or "builtin:<name>"
    camera: Camera | None = None  # default view; None -> derived from bounds
    _hash: str | None = field(default=None, repr=False)

    @property
    def triangle_count(self) -> int:
        return int(self.faces.shape[0])

    @property
    def triangles(self) -> np.ndarray:
        """(F, 3, 3) float32 corner positions."""
        return self.vertices[self.faces]

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Bounds of the referenced vertices (unreferenced vertices do not count)."""
        referenced = np.zeros(len(self.vertices), bool)
        referenced[np.asarray(self.faces).ravel()] = True  # a mask, not np.unique: no sort of 3F ids
        used = self.vertices[referenced]
        return used.min(axis=0), used.max(axis=0)

    @property
    def content_hash(self) -> str:
        if self._hash is None:
            self._hash = arrays_hash(np.asarray(self.vertices, np.float32), np.asarray(self.faces, np.uint32))
        return self._hash
