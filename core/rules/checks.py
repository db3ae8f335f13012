"""What the localizer checks about its inputs and its own estimate, apart from the scan loop.

- **Start** (``--init``): the particles go around the sequence's ``initial_guess`` (in the map
  file's frame) at every (re)start; the guess's height is the ground under it (the lowest tenth of
  the map points within ``INIT_GROUND_RADIUS``) plus ``pf.sensor_height``. A guess with no map
  point that near is refused.
- **Frames**: a map and scans in different frames (another place, units or axes) do not fail
  silently. Over the first ``FRAME_CHECK_SCANS`` scans the best inlier share at the
  highest-weight particle is kept (after the global S2M matches that land there); if it never
  reaches ``FRAME_MIN_INLIER_SHARE`` a ``frame_mismatch`` event says so, and so does one at the
  start when the truth's first pose lies farther than d_max outside the map's bounds.
- **Confidence**: a ``confidence_low`` event marks the scan at which, while localized, the inlier
  share falls below ``localize.min_inlier_share``: once, until it recovers or localization ends
  (a new localization may fire it again).
"""

from __future__ import annotations

import numpy as np

from ..errors import LidarlocError

#: ``--init``: the ground under the guess is looked for within this radius (m)
INIT_GROUND_RADIUS = 5.0
#: ``--init``: spreads of the states the guess does not give (z in m; pitch, roll in rad)
INIT_SIGMA_Z = 0.3
INIT_SIGMA_TILT = np.radians(1.0)
#: the frame check's window (scans) and the inlier share below which map and scans are taken
#: to be in different frames (a scan in the map's frame, even before localization, finds map
#: points within d_max at its best particle for several times this share)
FRAME_CHECK_SCANS = 10
FRAME_MIN_INLIER_SHARE = 0.05


def initial_pose_on_map(guess, prior_map, sensor_height: float):
    """``--init``'s (4×4 pose in the map's local frame, 6 stds), or None for a global start."""
    if guess is None:
        return None
    from ..sequences.factory import initial_pose

    pts = prior_map.points
    origin = prior_map.origin
    d = np.hypot(pts[:, 0] - (guess.x - origin[0]), pts[:, 1] - (guess.y - origin[1]))
    near = pts[d <= INIT_GROUND_RADIUS, 2]
    if near.size == 0:
        raise LidarlocError(
            f"--init {guess.x:g},{guess.y:g}: no map point within {INIT_GROUND_RADIUS:g} m "
            f"(the nearest is {float(d.min()):.0f} m away); give a pose on the map, in its frame"
        )
    z = float(np.percentile(near, 10)) + sensor_height
    std = (guess.sigma_xy, guess.sigma_xy, INIT_SIGMA_Z, guess.sigma_yaw, INIT_SIGMA_TILT, INIT_SIGMA_TILT)
    return initial_pose(guess, origin, z), std


def truth_outside_map(seq, bounds: tuple, origin, d_max: float) -> str | None:
    """Why the truth's first pose looks to be in another frame than the map (it lies more than
    ``d_max`` outside the map's bounds), or None."""
    if not seq.has_poses or len(seq) == 0:
        return None
    p = seq.pose(0)[:2, 3]
    lo, hi = bounds[0][:2], bounds[1][:2]
    outside = float(np.linalg.norm(np.maximum(lo - p, 0) + np.maximum(p - hi, 0)))
    if outside <= d_max:
        return None
    return (
        f"the ground truth's first pose ({p[0] + origin[0]:.1f}, {p[1] + origin[1]:.1f}) lies {outside:.0f} m "
        "outside the map: are the map and the ground truth in the same frame?"
    )


class ScanFrameCheck:
    """The scan-side frame check over a run's first ``FRAME_CHECK_SCANS`` scans."""

    def __init__(self):
        self.best_share = 0.0  # best inlier share at the highest-weight particle so far

    def wanted(self, step: int) -> bool:
        """Whether the scan of ``step`` (scans processed before it) is still inside the window."""
        return step < FRAME_CHECK_SCANS

    def update(self, step: int, n_scans: int, share: float, d_max: float) -> str | None:
        """Take one scan's inlier share; at the window's last scan, why the frames look different
        (or None)."""
        self.best_share = max(self.best_share, float(share))
        last = min(FRAME_CHECK_SCANS, n_scans) - 1
        if step != last or self.best_share >= FRAME_MIN_INLIER_SHARE:
            return None
        return (
            f"over the first {last + 1} scans at most {100 * self.best_share:.1f} % of a scan's points came "
            f"within {d_max:g} m of the map: the scans and the map look to be in different frames "
            "(another place, units or axes)"
        )


class ConfidenceWatch:
    """When to record ``confidence_low``: once per drop while localized."""

    def __init__(self):
        self.armed = True

    def update(self, localized: bool, share: float, residual: float | None, min_share: float) -> str | None:
        """The event's detail when it fires at this scan, else None."""
        if localized and share < min_share:
            if self.armed:
                self.armed = False
                return f"inlier share {share:.2f} < {min_share:g}" + (
                    "" if residual is None else f", mean residual {residual:.2f} m"
                )
            return None
        self.armed = True
        return None
