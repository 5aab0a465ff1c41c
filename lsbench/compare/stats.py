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


# Ties among few samples (two processes with equal medians, timer granularity): the normal
# approximation can then give p below what any ordering allows (2 v 2: 0.097 < 1/6), so the
# null distribution of the midranks is enumerated instead, up to this many splits.
EXACT_TIES_MAX = 20000


def _exact_tied_p(ranks: np.ndarray, m: int, u_x: float) -> float:
    """P(U <= u_x) over every split of the pooled midranks into m and the rest, equally likely
    under the null (the permutation distribution, ties included)."""
    from itertools import combinations

    total = len(ranks)
    sums = np.fromiter((ranks[list(c)].sum() for c in combinations(range(total), m)), dtype=float)
    u = sums - m * (m + 1) / 2.0
    return float(np.mean(u <= u_x + 1e-9))


def mann_whitney_less(x, y) -> tuple[float, float]:
    """One-sided Mann-Whitney U test, alternative: x tends to be smaller than y.

    Returns (U_x, p) with U_x = #pairs x > y (+1/2 per tie). Exact null distribution when the
    samples are small (the usual 3..30 repeats; with ties, enumerated over the midranks up to
    EXACT_TIES_MAX splits); otherwise the normal approximation with tie and continuity correction.
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
    if has_ties and math.comb(m + n, m) <= EXACT_TIES_MAX:
        return u_x, _exact_tied_p(ranks, m, u_x)
    mu = m * n / 2.0
    N = m + n
    _, t = np.unique(both, return_counts=True)
    tie_term = float((t ** 3 - t).sum()) / (N * (N - 1)) if N > 1 else 0.0
    var = m * n / 12.0 * ((N + 1) - tie_term)
    if var <= 0:
        return u_x, 1.0
    z = (u_x - mu + 0.5) / math.sqrt(var)
    return u_x, 0.5 * math.erfc(-z / math.sqrt(2.0))


def min_p_value(m: int, n: int) -> float:
    """The smallest one-sided p the exact U test can give for samples of m and n (all of one
    below all of the other): 1 / C(m+n, m). A test at a level below it can never reject."""
    return 1.0 / math.comb(m + n, m) if m and n else 1.0


def samples_needed(level: float, max_n: int = 200) -> int | None:
    """The smallest n such that n against n samples can reach p <= level (None past max_n)."""
    for n in range(1, max_n + 1):
        if min_p_value(n, n) <= level:
            return n
    return None


def _lower_tail(m: int, n: int, u: int) -> float:
    """P(U <= u) under the null (exact counts for small samples, else normal approximation)."""
    if u < 0:
        return 0.0
    if m <= 50 and n <= 50:
        counts = _u_counts(m, n)
        return sum(counts[: u + 1]) / math.comb(m + n, m)
    mu, sd = m * n / 2.0, math.sqrt(m * n * (m + n + 1) / 12.0)
    return 0.5 * math.erfc(-((u + 0.5 - mu) / sd) / math.sqrt(2.0))


def ratio_interval(x, y, coverage: float = 0.9) -> tuple[float, float, float, float] | None:
    """Distribution-free interval for the ratio x / y of two positive samples (Hodges-Lehmann
    estimate with the Moses interval, on the logs): (estimate, low, high, coverage achieved).

    The k-th smallest and k-th largest of the m*n pairwise ratios x_i / y_j bound the ratio with
    probability 1 - 2 P(U <= k-1); k is the largest with at least `coverage`, or 1 when even the
    full range of the pairwise ratios does not reach it (then the achieved coverage is less, and
    said). None for an empty sample."""
    lx = np.log(np.asarray(x, dtype=float))
    ly = np.log(np.asarray(y, dtype=float))
    m, n = len(lx), len(ly)
    if m == 0 or n == 0:
        return None
    d = np.sort((lx[:, None] - ly[None, :]).ravel())
    k = 1
    while k < (m * n + 1) // 2 and 1.0 - 2.0 * _lower_tail(m, n, k) >= coverage:
        k += 1
    achieved = max(0.0, 1.0 - 2.0 * _lower_tail(m, n, k - 1))
    return (float(np.exp(np.median(d))), float(np.exp(d[k - 1])), float(np.exp(d[m * n - k])), achieved)


def detectable_ratio(x, y, level: float) -> float | None:
    """The largest ratio r <= 1 such that x rescaled to y's median and then times r is slower
    than y at p <= level (one-sided U test): the smallest slowdown these samples, with their own
    spread, could show. None when no ratio can (too few samples for the level)."""
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    if len(x) == 0 or len(y) == 0 or min_p_value(len(x), len(y)) > level:
        return None
    xs = x * (np.median(y) / np.median(x))
    lo, hi = math.log(1e-6), 0.0   # p(lo) <= level (all of x below all of y), p(hi) may not be
    if mann_whitney_less(xs, y)[1] <= level:
        return 1.0
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        if mann_whitney_less(xs * math.exp(mid), y)[1] <= level:
            lo = mid
        else:
            hi = mid
    return math.exp(lo)
