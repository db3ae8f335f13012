"""How the truth grades an estimate, where a source has it. The truth never feeds the filter:
these only measure it (the per-scan record, the summary, the viewer's truth alarm)."""

from __future__ import annotations

import math

import numpy as np

#: An onset of "localized" farther than this from the truth is a false fire (m); the same bound
#: as metrics C and D.
FALSE_FIRE_M = 5.0
#: Variance added to the x-y covariance before inverting it (m²): a filter collapsed onto one
#: particle has a singular covariance; with this its ellipse is a 2 mm disc, not undefined.
COV_JITTER_M2 = 1e-6


def mahalanobis_xy(error_xy, cov_xy) -> float:
    """Mahalanobis distance of an x-y error (estimate − truth, m) under a 2×2 covariance (m²)."""
    e = np.asarray(error_xy, dtype=np.float64).reshape(2)
    c = np.asarray(cov_xy, dtype=np.float64).reshape(2, 2) + COV_JITTER_M2 * np.eye(2)
    d2 = float(e @ np.linalg.solve(c, e))
    return math.sqrt(max(d2, 0.0))


def inside_2sigma(error_xy, cov_xy) -> bool:
    """Whether the truth lies inside the 2σ ellipse of the estimate (Mahalanobis distance ≤ 2)."""
    return mahalanobis_xy(error_xy, cov_xy) <= 2.0


def truth_alarm(localized: bool, error_m: float | None) -> str | None:
    """The rule says localized while the truth is farther than :data:`FALSE_FIRE_M`: what the
    viewer shows in red (the test of summary.json's ``false_fire``, at every localized scan)."""
    if not localized or error_m is None or not math.isfinite(error_m) or error_m <= FALSE_FIRE_M:
        return None
    return f"the rule says localized; the truth is {error_m:.0f} m away"
