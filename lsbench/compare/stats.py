"""Mann-Whitney U test, one-sided, without scipy: does one sample of per-repeat speeds tend to be
smaller than another? Exact null distribution for small samples without ties (the usual 3..30
timing repeats), else the normal approximation with tie and continuity correction."""
from __future__ import annotations

import math
from functools import lru_cache

import numpy as np


@lru_cache(maxsize=None)
def _u_counts(m: int, n: int) -> tuple:
    """Number of orderings of m x's and n y's with U_x = u, u = 0..m*n (no ties).

    Recurrence on the largest value: it is an x (which then beats all n y's: U grows by n) or a
    y (U unchanged): f(m, n, u) = f(m-1, n, u-n) + f(m, n-1, u).
    """
    if m == 0 or n == 0:
        return (1,)
    a = _u_counts(m - 1, n)
    b = _u_counts(m, n - 1)
    out = [0] * (m * n + 1)
    for u, c in enumerate(a):
        out[u + n] += c
    for u, c in enumerate(b):
        out[u] += c
    return tuple(out)


def _rank(values: np.ndarray) -> np.ndarray:
    """Ranks 1..N, ties get the mean of their ranks."""
    order = np.argsort(values, kind="mergesort")
    ranks = np.empty(len(values), dtype=float)
    sorted_vals = values[order]
    i = 0
    while i < len(values):
        j = i
        while j + 1 < len(values) and sorted_vals[j + 1] == sorted_vals[i]:
            j += 1
        ranks[order[i:j + 1]] = (i + j) / 2.0 + 1.0
        i = j + 1
    return ranks


def mann_whitney_less(x, y) -> tuple[float, float]:
    """One-sided Mann-Whitney U test, alternative: x tends to be smaller than y.

    Returns (U_x, p) with U_x = #pairs x > y (+1/2 per tie). Exact null distribution when there
    are no ties and the samples are small (the usual 3..30 repeats); otherwise the normal
    approximation with tie and continuity correction.
    """
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    m, n = len(x), len(y)
    if m == 0 or n == 0:
        return float("nan"), 1.0
    both = np.concatenate([x, y])
    ranks = _rank(both)
    u_x = float(ranks[:m].sum() - m * (m + 1) / 2.0)
    has_ties = len(np.unique(both)) < len(both)
    if not has_ties and m <= 30 and n <= 30:
        counts = _u_counts(m, n)
        total = math.comb(m + n, m)
        p = sum(counts[: int(round(u_x)) + 1]) / total
        return u_x, min(1.0, p)
    mu = m * n / 2.0
    N = m + n
    _, t = np.unique(both, return_counts=True)
    tie_term = float((t ** 3 - t).sum()) / (N * (N - 1)) if N > 1 else 0.0
    var = m * n / 12.0 * ((N + 1) - tie_term)
    if var <= 0:
        return u_x, 1.0
    z = (u_x - mu + 0.5) / math.sqrt(var)
    return u_x, 0.5 * math.erfc(-z / math.sqrt(2.0))
