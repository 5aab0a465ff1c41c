"""RaySet: origins + normalized directions (plain data); generators live below."""
from __future__ import annotations

import hashlib
from dataclasses import dataclass, field

import numpy as np


@dataclass
class RaySet:
    name: str
    origins: np.ndarray  # (N, 3) float32
    directions: np.ndarray  # (N, 3) float32, unit length (distances compare with Embree's)
    width: int = 0  # image size for camera ray sets (0 = not an image)
    height: int = 0
    tmin: float = 0.0
    _hash: str | None = field(default=None, repr=False)

    @property
    def count(self) -> int:
        return int(self.origins.shape[0])

    @property
    def content_hash(self) -> str:
        if self._hash is None:
            h = hashlib.sha256()
            h.update(np.ascontiguousarray(self.origins, dtype=np.float32).tobytes())
            h.update(np.ascontiguousarray(self.directions, dtype=np.float32).tobytes())
            self._hash = h.hexdigest()[:16]
        return self._hash
