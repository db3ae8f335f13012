"""De-skewing in the localizer (``localize.deskew``, core/localizer.py with core/odometry/deskew.py and
core/odometry/feed.py): each scan is moved into its mid-sweep frame with the newest odometry step's
constant velocity before the PF, the RPE and S2M use it."""

import numpy as np
import pytest
from helpers import StreetSequence
from lidarloc.core.config import Config
from lidarloc.core.geometry import pose_matrix
from lidarloc.core.localizer import Localizer
from lidarloc.core.odometry.deskew import deskew, sweep_offsets, twist_from_relative_pose

SPEED = 20.0  # m/s: 1 m of travel per sweep, so the skew is plain to see


class SkewedStreet(StreetSequence):
    """The test street driven straight at SPEED, each scan swept over 0.1 s while moving (the
    sweep convention of core/odometry/deskew.py: a point seen at τ from mid-sweep was measured from where
    the sensor was then)."""

    name = "test-street-skewed"

    def __init__(self, n: int = 12):
        super().__init__(n=n)
        x = SPEED * self._t
        self._poses = pose_matrix(x, np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(n))

    def identity(self) -> str:
        return f"{self.name}|{SPEED}"

    def _read_scan(self, i):
        scan = super()._read_scan(i)
        if getattr(self, "unskewed", False):
            return scan
        tau = sweep_offsets(scan, 0.1)
        out = scan.copy()
        out[:, 0] -= (tau * SPEED).astype(np.float32)  # the inverse of de-skewing (no rotation)
        return out


def localizer(seq, cache_root, deskewed: bool) -> Localizer:
    cfg = Config()
    cfg.pf.n_particles = 100
    cfg.s2m.enabled = False
    cfg.localize.deskew = deskewed
    return Localizer(seq, cfg, cache_root)


def capture(loc):
    """Record the scan handed to the RPE and the prepared scan handed to the PF, per scan."""
    to_rpe, to_pf = {}, {}
    real_submit, real_update = loc.odometry.submit, loc.pf.update

    def submit(k, scan, t):
        to_rpe[k] = np.array(scan)
        real_submit(k, scan, t)

    def update(prepared):
        to_pf[loc.k] = np.array(prepared)
        real_update(prepared)

    loc.odometry.submit, loc.pf.update = submit, update
    return to_rpe, to_pf


@pytest.mark.parametrize("deskewed", [False, True])
def test_scans_are_deskewed_with_the_last_odometry_step(cache_root, deskewed):
    seq = SkewedStreet()
    with localizer(seq, cache_root, deskewed) as loc:
        to_rpe, _ = capture(loc)
        loc.run(5)
        for k in range(5):
            raw = seq.scan(k)
            if not deskewed or k < 2:  # no odometry step known before scan 2
                np.testing.assert_array_equal(to_rpe[k], raw)
                continue
            step = loc.odometry.rpe.relative(k - 2, k - 1)
            want = deskew(raw, sweep_offsets(raw, 0.1), *twist_from_relative_pose(step, 0.1))
            np.testing.assert_allclose(to_rpe[k], want, atol=1e-4)


def test_deskewing_gives_back_the_unskewed_scan(cache_root):
    """The scans the localizer uses are, point for point, close to what an unskewed sensor would
    have seen: the odometry's speed estimate undoes a skew of ~0.4 m per point."""
    seq = SkewedStreet()
    truth = SkewedStreet()
    truth.unskewed = True
    with localizer(seq, cache_root, True) as loc:
        to_rpe, _ = capture(loc)
        loc.run(8)
    skew, left = [], []
    for k in range(2, 8):
        clean = truth.scan(k)[:, :3]
        skew.append(np.mean(np.linalg.norm(seq.scan(k)[:, :3] - clean, axis=1)))
        left.append(np.mean(np.linalg.norm(to_rpe[k][:, :3] - clean, axis=1)))
    assert np.mean(skew) > 0.3
    assert np.mean(left) < 0.2 * np.mean(skew), (skew, left)
