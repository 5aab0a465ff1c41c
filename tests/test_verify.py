"""Accuracy categories against hand-made reference arrays."""
import math

import numpy as np
import pytest

from lsbench.oracle.verify import (
    AGREE, DISTANCE, EXTRA, MISSED, TIE, WRONG, Accuracy, classify, compare, disagreement_indices,
    resolve_abs_tol,
)

INF = np.inf
# One ray per case:            ref prim, ref t, our prim, our t,   category
CASES = [
    ("same prim",               3, 2.0,    3, 2.0,       AGREE),
    ("same prim, t off",        3, 2.0,    3, 2.5,       DISTANCE),  # right triangle, wrong t
    ("same prim, t in tol",     3, 2.0,    3, 2.0001,    AGREE),     # 1e-4 <= 1e-6 + 1e-4*2.0001
    ("both miss",              -1, INF,   -1, INF,       AGREE),
    ("both miss, odd t",       -1, INF,   -1, np.nan,    AGREE),  # a miss's t is not read
    ("tie on shared edge",      4, 10.0,   5, 10.0005,   TIE),    # 5e-4 <= 1e-6 + 1e-4*10.0005
    ("different prim, far",     4, 10.0,   5, 10.01,     WRONG),
    ("missed",                  2, 1.0,   -1, INF,       MISSED),
    ("extra",                  -1, INF,    2, 1.0,       EXTRA),
    ("NaN hit, same prim",      6, 1.0,    6, np.nan,    WRONG),
    ("NaN hit, other prim",     6, 1.0,    7, np.nan,    WRONG),
    ("NaN hit, ref misses",    -1, INF,    7, np.nan,    EXTRA),
    ("inf hit, other prim",     6, 1.0,    7, INF,       WRONG),
]


def arrays(cases=CASES):
    ref_p = np.array([c[1] for c in cases], np.int32)
    ref_t = np.array([c[2] for c in cases], np.float32)
    p = np.array([c[3] for c in cases], np.int32)
    t = np.array([c[4] for c in cases], np.float32)
    return p, t, ref_p, ref_t


def test_each_case_lands_in_its_category():
    got = classify(*arrays())
    want = [c[5] for c in CASES]
    for case, g, w in zip(CASES, got.tolist(), want):
        assert g == w, case[0]


def test_counts_and_agreement():
    acc = compare(*arrays())
    assert isinstance(acc, Accuracy)
    assert (acc.agree, acc.ties, acc.missed, acc.extra, acc.wrong, acc.distance) == (4, 1, 1, 2, 4, 1)
    assert acc.ray_count == len(CASES) and acc.disagreements == 8
    assert acc.agreement == pytest.approx(5 / len(CASES))
    assert acc.rel_tol == 1e-4 and acc.abs_tol == 1e-6


def test_distance_statistics_over_rays_where_both_hit():
    p = np.array([0, 1, 2, -1, 3])
    t = np.array([1.0, 2.5, 3.0, INF, np.nan])
    ref_p = np.array([0, 1, 9, 4, 3])
    ref_t = np.array([1.0, 2.0, 3.25, 1.0, 1.0])
    acc = compare(p, t, ref_p, ref_t)
    # |dt| over the both-hit rays with a real distance: 0, 0.5, 0.25 (the NaN one is left out).
    assert acc.max_abs_dt == pytest.approx(0.5)
    assert acc.median_abs_dt == pytest.approx(0.25)
    assert not math.isnan(acc.max_abs_dt)


def test_no_common_hits_gives_zero_statistics():
    acc = compare([-1, -1], [INF, INF], [-1, -1], [INF, INF])
    assert (acc.max_abs_dt, acc.median_abs_dt, acc.agreement) == (0.0, 0.0, 1.0)


def test_empty():
    acc = compare([], [], [], [])
    assert acc.ray_count == 0 and acc.agreement == 1.0


def test_distance_counts_for_the_same_primitive():
    """Issue 13 item 4: the right triangle at the wrong distance (say, measured from a cell's
    entry) is a disagreement, with the same tolerance a tie gets."""
    args = ([7, 7], [1.5, 1.0000001], [7, 7], [1.0, 1.0])
    assert classify(*args).tolist() == [DISTANCE, AGREE]
    acc = compare(*args)
    assert (acc.agree, acc.distance, acc.disagreements) == (1, 1, 1) and acc.agreement == 0.5
    assert acc.max_abs_dt == pytest.approx(0.5)


def test_tolerance_rules():
    assert resolve_abs_tol(None, None) == 1e-6
    assert resolve_abs_tol(None, 200.0) == pytest.approx(2e-3)
    assert resolve_abs_tol(0.5, 200.0) == 0.5
    # |dt| = 1e-3 at t = 1: a tie only once abs_tol covers it.
    args = ([1], [1.001], [0], [1.0])
    assert classify(*args)[0] == WRONG
    assert classify(*args, scene_extent=200.0)[0] == TIE  # 1e-3 <= 2e-3 + 1e-4
    assert classify(*args, abs_tol=0.0, rel_tol=1e-3)[0] == TIE  # 1e-3 <= 1e-3 * 1.001
    assert classify(*args, abs_tol=0.0, rel_tol=1e-4)[0] == WRONG


def test_unsigned_miss_encoding():
    """A GPU buffer read back as uint32 says 0xFFFFFFFF for a miss."""
    p = np.array([0xFFFFFFFF, 3], np.uint32)
    acc = compare(p, [INF, 1.0], [-1, 3], [INF, 1.0])
    assert acc.agree == 2


def test_disagreement_indices():
    idx = disagreement_indices(*arrays())
    want = [i for i, c in enumerate(CASES) if c[5] in (MISSED, EXTRA, WRONG, DISTANCE)]
    assert idx.tolist() == want and idx.dtype == np.int64


def test_shape_mismatch_raises():
    with pytest.raises(ValueError):
        compare([0, 1], [1.0], [0, 1], [1.0, 1.0])


def test_to_dict_is_plain():
    d = compare(*arrays()).to_dict()
    assert d["ray_count"] == len(CASES) and d["wrong"] == 4
    assert all(isinstance(v, (int, float)) for v in d.values())


def test_large_random_vectorized():
    rng = np.random.default_rng(3)
    n = 200_000
    ref_p = rng.integers(-1, 50, n)
    ref_t = np.where(ref_p >= 0, rng.uniform(1, 100, n), INF)
    acc = compare(ref_p.copy(), ref_t.copy(), ref_p, ref_t)
    assert acc.agree == n and acc.agreement == 1.0 and acc.max_abs_dt == 0.0
