"""Device buffers: what the builds rely on from every backend's alloc and fill_zero."""
from __future__ import annotations

import numpy as np
import pytest


@pytest.mark.parametrize("nbytes", [4, 1020, 4 * 1000003])
def test_fill_zero_clears_the_given_bytes_only(device, nbytes):
    """fill_zero(buf, n) zeroes the first n bytes and leaves the rest (PoCL clears by a kernel on
    all cores, with a partial last work group; llvmpipe by the driver's clear)."""
    words = nbytes // 4 + 37
    pattern = np.arange(1, words + 1, dtype=np.uint32) * np.uint32(2654435761)
    buf = device.upload("pattern", pattern)
    try:
        device.fill_zero(buf, nbytes)
        got = device.read(buf, np.uint32)
        assert not got[: nbytes // 4].any()
        np.testing.assert_array_equal(got[nbytes // 4:], pattern[nbytes // 4:])
        device.fill_zero(buf)
        assert not device.read(buf, np.uint32).any()
    finally:
        device.release(buf)


def test_alloc_zeroed(device):
    buf = device.alloc("zeroed", 4 * 300007, zero=True)
    try:
        assert not device.read(buf, np.uint32).any()
    finally:
        device.release(buf)
