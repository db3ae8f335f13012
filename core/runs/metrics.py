"""The paper's localization metrics A–E (Simulation section), from a per-scan log.

All metrics are counts of scans from the start of the sequence ("number of scans until …"), so
an event at 0-based scan index k counts k + 1 scans. A metric that is never met is ``None`` and
counts as a failure in aggregates (never as missing data).

- B: scans until the localization rule is first met.
- A: scans spent until localized over the whole sequence: every scan not localized, plus the
  scan at which each (re-)localization happened (so A = B when localization is never lost, and
  re-localization after false positives and losses adds to it).
- C: first scan k where the rule holds (the localized flag is set at k) and the mean position is
  within 5 m (3D Euclidean) of the truth for every scan in [k, k+10].
- D: the same for [k, k+50]; E: as D with 2.5 m.
- rmse_pos_after_D_m / rmse_yaw_after_D_deg: RMSE of position and yaw from D's scan to the end.

A window that runs past the end of the sequence does not count as met (the condition must be
observed for the whole window).

Beyond the paper, whether the filter's confidence can be trusted (:func:`confidence_metrics`):

- consistency_2sigma: the share of localized scans whose true x-y error lies inside the filter's
  own 2σ ellipse (Mahalanobis distance ≤ 2 under the particles' x-y covariance). A filter whose
  covariance is honest scores near 0.86 (the probability mass of a 2-D Gaussian within 2σ); one
  collapsed onto a single particle scores near 0 however small its error.
- false_fire: whether the localization rule was met (a "localized" onset) at a scan whose true
  error was above 5 m (the metrics' own "within 5 m" bound).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..rules.truth import FALSE_FIRE_M


@dataclass
class ScanLog:
    """The columns metrics need; arrays of equal length, one entry per processed scan."""

    localized: np.ndarray  # bool
    error_m: np.ndarray  # float, |p_est − p_true| in 3D (NaN where no truth)
    yaw_error_rad: np.ndarray | None = None


def _first_window(localized: np.ndarray, ok: np.ndarray, length: int) -> int | None:
    n = len(ok)
    # run[i] = number of consecutive ok scans starting at i
    run = np.zeros(n + 1, dtype=np.int64)
    for i in range(n - 1, -1, -1):
        run[i] = run[i + 1] + 1 if ok[i] else 0
    need = length + 1  # [k, k+length] inclusive
    hits = np.flatnonzero(localized & (run[:n] >= need))
    return int(hits[0]) if hits.size else None


def compute_metrics(log: ScanLog) -> dict:
    localized = np.asarray(log.localized, dtype=bool)
    err = np.asarray(log.error_m, dtype=float)
    first = np.flatnonzero(localized)
    B = int(first[0]) + 1 if first.size else None
    onsets = int(np.count_nonzero(localized[1:] & ~localized[:-1]) + (1 if len(localized) and localized[0] else 0))
    A = int((~localized).sum()) + onsets if first.size else None
    ok5 = np.nan_to_num(err, nan=np.inf) <= 5.0
    ok25 = np.nan_to_num(err, nan=np.inf) <= 2.5
    kC = _first_window(localized, ok5, 10)
    kD = _first_window(localized, ok5, 50)
    kE = _first_window(localized, ok25, 50)
    out = {
        "A": A,
        "B": B,
        "C": None if kC is None else kC + 1,
        "D": None if kD is None else kD + 1,
        "E": None if kE is None else kE + 1,
        "rmse_pos_after_D_m": None,
        "rmse_yaw_after_D_deg": None,
        "scans": int(len(localized)),
    }
    if kD is not None:
        tail = err[kD:]
        out["rmse_pos_after_D_m"] = float(np.sqrt(np.nanmean(tail**2)))
        if log.yaw_error_rad is not None:
            yaw = np.asarray(log.yaw_error_rad, float)[kD:]
            out["rmse_yaw_after_D_deg"] = float(np.degrees(np.sqrt(np.nanmean(yaw**2))))
    return out


METRIC_KEYS = ("A", "B", "C", "D", "E")


def aggregate(per_run: list[dict]) -> dict:
    """Median, 75th percentile, max and success ratio of each metric; failures count as +∞
    inside the percentiles (so a max of ``None`` in the JSON means some run never met it)."""
    out = {"runs": len(per_run)}
    for key in METRIC_KEYS + ("rmse_pos_after_D_m", "rmse_yaw_after_D_deg"):
        values = np.array([np.inf if r.get(key) is None else float(r[key]) for r in per_run], dtype=float)
        success = float(np.isfinite(values).mean()) if len(values) else 0.0

        def stat(q):
            if not len(values):
                return None
            v = float(np.percentile(values, q, method="inverted_cdf"))  # an observed value, never interpolated with ∞
            return v if np.isfinite(v) else None

        out[key] = {"median": stat(50), "p75": stat(75), "max": stat(100), "success": success}
    return out


# ------------------------------------------------------------------------------ confidence
def confidence_metrics(localized, error_m, inside) -> dict:
    """``consistency_2sigma`` and ``false_fire`` of one run (see the module docstring), from
    per-scan arrays: the localized flag, the 3D error (NaN where no truth) and inside_2sigma (None
    or NaN where no truth). Both are None without truth; consistency also without a localized
    scan."""
    localized = np.asarray(localized, dtype=bool)
    err = np.asarray(error_m, dtype=float)
    inside = np.array([np.nan if v is None else float(v) for v in inside], dtype=float)
    if not np.isfinite(err).any():
        return {"consistency_2sigma": None, "false_fire": None}
    judged = localized & np.isfinite(inside)
    consistency = float(inside[judged].mean()) if judged.any() else None
    onset = localized & ~np.r_[False, localized[:-1]]
    onset_err = err[onset]
    false_fire = bool(np.any(onset_err[np.isfinite(onset_err)] > FALSE_FIRE_M))
    return {"consistency_2sigma": consistency, "false_fire": false_fire}


def aggregate_confidence(summaries: list[dict]) -> dict:
    """Over runs (their summary.json dicts): ``consistency_2sigma``, the median of the runs' own
    values, and ``false_fire_rate``, the share of runs whose rule fired more than 5 m from the
    truth. Runs without a value (no truth, or never localized) are left out; None if none has one."""
    cons = [float(s["consistency_2sigma"]) for s in summaries if s.get("consistency_2sigma") is not None]
    fires = [bool(s["false_fire"]) for s in summaries if s.get("false_fire") is not None]
    return {
        "consistency_2sigma": float(np.median(cons)) if cons else None,
        "false_fire_rate": float(np.mean(fires)) if fires else None,
    }
