"""Step detection over a whole sequence of commits: a piecewise-constant model fitted to the
per-commit figures, each jump between two pieces a step that names its commit range.

The model (the idea of asv's step_detect, written anew here): the log of rays/s at commit i is
a level plus noise, the level constant between steps. The fit minimises

    sum over pieces of sum_i |y_i - median(piece)| / sigma  +  penalty * (number of pieces)

by exact dynamic programming over all partitions (optimal partitioning, Jackson et al. 2005),
O(n^2) segment costs for n commits. The L1 cost (a median per piece) keeps one wild commit from
becoming two steps unless it is off by more than twice the penalty (then it is two: a slowdown
fixed at the next commit), and the log makes a step a ratio (a 30 % slowdown is the same jump at any
speed). sigma is the noise of one commit's figure, estimated robustly from the sequence itself
(the median absolute difference of neighbours, which a few steps do not move) and never below
what the repeats within a commit say; the penalty is in units of that noise and grows with
log(n) like BIC, so a longer history does not yield more spurious steps.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

# Penalty per piece in units of sigma, times log(n). Measured on normal noise, 40 seeds each for
# n = 8..120: at 3, 6 of 80 sequences of 8-12 commits showed a spurious step (sigma from 7
# neighbour differences is itself noisy); at 4, 1 of 240 did, and a 20 % step in 3 % noise was
# still found at its commit in 239 of 240; at 5, 3 such steps were missed at n = 8.
PENALTY_PER_LOG_N = 4.0
MAD_TO_SIGMA = 1.4826  # median absolute deviation of a normal sample -> its standard deviation


@dataclass
class Step:
    """A jump of the fitted level between index `before` (last commit at the old level) and
    `after` (first commit at the new one): it happened in the commit range (before, after]."""
    before: int
    after: int
    level_before: float  # fitted value (not log) of the piece that ends at `before`
    level_after: float

    @property
    def ratio(self) -> float:
        """New level / old level (< 1: rays/s fell)."""
        return self.level_after / self.level_before


@dataclass
class Fit:
    levels: np.ndarray   # fitted value per commit (not log)
    steps: list[Step]
    sigma: float         # noise of one commit's log figure that the penalty was scaled by


def noise_sigma(y: np.ndarray, within: float = 0.0) -> float:
    """Noise of one point of y: neighbour differences (robust to a few steps), at least `within`."""
    d = np.abs(np.diff(y))
    seq = MAD_TO_SIGMA * float(np.median(d)) / math.sqrt(2.0) if len(d) else 0.0
    floor = 1e-6  # a sequence of identical figures: any real jump is then a step
    return max(seq, within, floor)


def _segment_costs(y: np.ndarray) -> np.ndarray:
    """cost[i, j] = sum |y[i:j+1] - median| for every segment i..j (inclusive), upper triangle.

    Grown one point at a time from each start with two heaps (the lower half as a max-heap, the
    upper as a min-heap) and their sums: the L1 deviation from any median is
    (m * n_low - sum_low) + (sum_up - m * n_up) with m = the lower half's largest, so all
    n^2 / 2 segments cost O(n^2 log n), not a sort each (a nightly history of hundreds of
    commits times every case)."""
    import heapq

    n = len(y)
    cost = np.zeros((n, n))
    values = [float(v) for v in y]
    for i in range(n):
        low: list[float] = []   # negated: a max-heap of the lower half (holds the extra point)
        up: list[float] = []
        sum_low = sum_up = 0.0
        for j in range(i, n):
            v = values[j]
            if low and v > -low[0]:
                heapq.heappush(up, v)
                sum_up += v
            else:
                heapq.heappush(low, -v)
                sum_low += v
            if len(low) > len(up) + 1:
                moved = -heapq.heappop(low)
                sum_low -= moved
                heapq.heappush(up, moved)
                sum_up += moved
            elif len(up) > len(low):
                moved = heapq.heappop(up)
                sum_up -= moved
                heapq.heappush(low, -moved)
                sum_low += moved
            m = -low[0]
            cost[i, j] = (m * len(low) - sum_low) + (sum_up - m * len(up))
    return cost


def fit_steps(values, within_sigma: float = 0.0, penalty: float | None = None) -> Fit:
    """Fit the piecewise-constant model to per-commit figures `values` (positive, e.g. the median
    rays/s of each commit, oldest first). within_sigma: the log-spread of one commit's figure that
    its repeats show (a floor for the noise). penalty: per piece in sigma units (default
    PENALTY_PER_LOG_N * log n)."""
    v = np.asarray(values, dtype=float)
    if len(v) == 0 or np.any(~np.isfinite(v)) or np.any(v <= 0):
        raise ValueError("fit_steps needs positive finite figures")
    y = np.log(v)
    n = len(y)
    sigma = noise_sigma(y, within_sigma)
    if n < 2:
        return Fit(levels=v.copy(), steps=[], sigma=sigma)
    gamma = penalty if penalty is not None else PENALTY_PER_LOG_N * max(math.log(n), 1.0)
    cost = _segment_costs(y) / sigma
    # best[j] = least cost of y[0:j] split into pieces; last_start[j] = where its last piece starts
    best = np.full(n + 1, np.inf)
    best[0] = 0.0
    last_start = np.zeros(n + 1, dtype=int)
    for j in range(1, n + 1):
        cands = best[:j] + cost[np.arange(j), j - 1] + gamma
        k = int(np.argmin(cands))
        best[j], last_start[j] = cands[k], k
    bounds = []
    j = n
    while j > 0:
        bounds.append((last_start[j], j))
        j = last_start[j]
    bounds.reverse()
    levels = np.empty(n)
    for a, b in bounds:
        levels[a:b] = math.exp(float(np.median(y[a:b])))
    steps = [Step(before=int(a) - 1, after=int(a), level_before=float(levels[a - 1]),
                  level_after=float(levels[a]))
             for a, _ in bounds[1:]]
    return Fit(levels=levels, steps=steps, sigma=sigma)
