"""KLD-sampling (Fox 2003, "Adapting the sample size in particle filters through KLD-sampling"):
how many particles the posterior needs, from how many bins of the state space it occupies.

With k occupied bins, n particles drawn from the posterior are, with probability 1 − δ, within
Kullback–Leibler divergence ε of the binned posterior when

    n ≥ (k − 1)/(2ε) · {1 − 2/(9(k − 1)) + √(2/(9(k − 1)))·z_{1−δ}}³

(Wilson–Hilferty's approximation of the χ² quantile). A converged cloud occupies a few bins and
needs a few hundred particles; a cloud spread over the map occupies about as many bins as it has
particles, and the bound exceeds any particle budget.

Choices where the method leaves room, kept explicit:

- Bins are (x, y, yaw): x and y in squares of ``bin_xy``, yaw in sectors of ``bin_yaw`` (the
  filter's z, pitch and roll are nearly fixed by the ground and would only multiply the count).
- Fox draws one particle at a time and stops once the count reaches the bound for the bins seen
  so far. :func:`kld_count` does the same on a given sequence of draws (vectorised: the first
  occurrence of each bin, the running bin count, the first prefix long enough). The filter
  feeds it a systematic resample of its full budget in a random order, so every prefix is a
  fair sample of the posterior and the chosen prefix is the new particle set.
- The bound is clamped to [n_min, n_max]; k ≤ 1 asks for n_min.

The count is only as honest as the weights. With the paper's likelihood they collapse onto one
particle at every scan, from a global start too: the resampled cloud is one bin and the count
drops to n_min after the first scan (measured on the real drive: 100 of 1000 from scan 1 on).
With a per-point tempered likelihood it follows the cloud (real drive, default bins, 1000 at
most: 100 → 307 → 600 → 909 → 1000 over the first five scans from a global start, whose first
scan still collapses; about 660 while tracking, about 260 with 2 m / 20° bins).
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import LidarlocError
from ..geometry import wrap_angle

_FIELD = 1 << 20  # bin indices are packed as three 21-bit fields (±1M bins per axis)


def kld_bound(k, epsilon: float, z: float) -> np.ndarray:
    """The KLD bound (float, unclamped) for k occupied bins; 0 for k ≤ 1. Vectorised over k."""
    k = np.asarray(k, dtype=np.float64)
    km1 = np.maximum(k - 1.0, 1.0)
    a = 2.0 / (9.0 * km1)
    n = km1 / (2.0 * epsilon) * (1.0 - a + np.sqrt(a) * z) ** 3
    return np.where(k > 1.0, n, 0.0)


def bin_keys(states: np.ndarray, bin_xy: float, bin_yaw: float) -> np.ndarray:
    """One int64 key per (x, y, yaw) bin of each (N, ≥4) state. Non-finite or far-off
    positions fall into the edge bins of the packed range (they are no particles worth binning)."""
    s = np.asarray(states, dtype=np.float64)
    ix = np.nan_to_num(np.floor(s[:, 0] / bin_xy), nan=0.0)
    iy = np.nan_to_num(np.floor(s[:, 1] / bin_xy), nan=0.0)
    iyaw = np.nan_to_num(np.floor((wrap_angle(s[:, 3]) + math.pi) / bin_yaw), nan=0.0)
    lim = _FIELD - 1
    ix = np.clip(ix, -lim, lim).astype(np.int64) + _FIELD
    iy = np.clip(iy, -lim, lim).astype(np.int64) + _FIELD
    iyaw = np.clip(iyaw, -lim, lim).astype(np.int64) + _FIELD
    return (ix << 42) | (iy << 21) | iyaw


def kld_count(keys: np.ndarray, epsilon: float, z: float, n_min: int, n_max: int) -> tuple[int, int]:
    """Fox's stopping rule on a sequence of draws: (n, k), the shortest prefix length n with
    n ≥ max(n_min, bound(k_n)) where k_n is the number of distinct bins among the first n draws,
    clamped to [min(n_min, n_max), n_max] (n_max if no prefix of ``keys`` is long enough, or if
    ``keys`` is shorter than n_max); k: the bins among those n draws."""
    n_min, n_max = int(n_min), int(n_max)
    if n_max < 1 or n_min < 1:
        raise LidarlocError(f"KLD particle counts must be ≥ 1, got min {n_min}, max {n_max}")
    if not (0 < epsilon < 1 and z > 0):
        raise LidarlocError(f"KLD needs 0 < epsilon < 1 and z > 0, got {epsilon}, {z}")
    keys = np.asarray(keys, dtype=np.int64)
    m = min(len(keys), n_max)
    if m == 0:
        return min(n_min, n_max), 0
    keys = keys[:m]
    first = np.zeros(m, np.int64)
    first[np.unique(keys, return_index=True)[1]] = 1
    k_seen = np.cumsum(first)  # bins among the first i + 1 draws
    need = np.maximum(np.ceil(kld_bound(k_seen, epsilon, z)), n_min)
    ok = np.flatnonzero(np.arange(1, m + 1) >= need)
    n = int(ok[0]) + 1 if ok.size else n_max
    n = min(max(n, min(n_min, n_max)), n_max)
    return n, int(k_seen[min(n, m) - 1])
