"""The per-scan confidence (core/localizer.py, core/snapshot.py, core/runs/metrics.py, core/runs/results.py):
what each scan reports about its own estimate, the ``confidence_low`` event, and the run's and
the benchmark's calibration figures (consistency_2sigma, false_fire)."""

import csv
import math

import numpy as np
import pytest
from helpers import scripted_std, short_town
from lidarloc.core.config import Config
from lidarloc.core.geometry import pose_to_xyz_ypr
from lidarloc.core.localizer import Localizer
from lidarloc.core.rules.truth import inside_2sigma, mahalanobis_xy
from lidarloc.core.runs.metrics import aggregate_confidence, confidence_metrics
from lidarloc.core.runs.results import summarize_run, write_records_csv

CONFIDENCE = (
    "n_particles",
    "n_eff_share",
    "converged",
    "inlier_share",
    "mean_residual_m",
    "cov_xx",
    "cov_xy",
    "cov_yy",
    "inside_2sigma",
)


# ------------------------------------------------------------------------------ the figures
def test_mahalanobis_distance_of_the_xy_error():
    cov = np.diag([1.0, 4.0])  # σx = 1 m, σy = 2 m
    assert mahalanobis_xy([2.0, 0.0], cov) == pytest.approx(2.0, rel=1e-5)
    assert mahalanobis_xy([0.0, 2.0], cov) == pytest.approx(1.0, rel=1e-5)
    assert inside_2sigma([0.0, 3.9], cov) and not inside_2sigma([0.0, 4.1], cov)
    # an ellipse along the diagonal: long along (1, 1), short across it
    c, s = math.cos(math.pi / 4), math.sin(math.pi / 4)
    R = np.array([[c, -s], [s, c]])
    tilted = R @ np.diag([9.0, 0.25]) @ R.T
    assert inside_2sigma([4.0, 4.0], tilted)  # 5.7 m along the long axis (σ 3 m)
    assert not inside_2sigma([0.8, -0.8], tilted)  # 1.1 m across it (σ 0.5 m)
    # a filter collapsed onto one particle: any error of more than a few mm is outside
    assert not inside_2sigma([0.01, 0.0], np.zeros((2, 2)))


def test_run_confidence_metrics():
    loc = np.array([False, False, True, True, True, True, False, True, True])
    err = np.array([40, 30, 8.0, 1.0, 1.0, 1.0, 50, 2.0, 2.0])
    inside = [False, False, True, False, True, True, False, True, None]
    m = confidence_metrics(loc, err, inside)
    assert m["consistency_2sigma"] == pytest.approx(4 / 5)  # localized scans with a verdict: 5, inside: 4
    assert m["false_fire"] is True  # the first onset (scan 2) was 8 m off
    m = confidence_metrics(loc, np.where(np.arange(9) == 2, 4.0, err), inside)
    assert m["false_fire"] is False  # both onsets within 5 m
    assert confidence_metrics(loc, np.full(9, np.nan), [None] * 9) == {"consistency_2sigma": None, "false_fire": None}
    never = confidence_metrics(np.zeros(9, bool), err, inside)
    assert never == {"consistency_2sigma": None, "false_fire": False}


def test_benchmark_aggregate():
    runs = [
        {"consistency_2sigma": 0.9, "false_fire": False},
        {"consistency_2sigma": 0.1, "false_fire": True},
        {"consistency_2sigma": 0.5, "false_fire": False},
        {"consistency_2sigma": None, "false_fire": False},
    ]
    assert aggregate_confidence(runs) == {"consistency_2sigma": 0.5, "false_fire_rate": 0.25}
    assert aggregate_confidence([{"consistency_2sigma": None, "false_fire": None}]) == {
        "consistency_2sigma": None,
        "false_fire_rate": None,
    }


# ------------------------------------------------------------------------------ the localizer


@pytest.fixture(scope="module")
def town():
    return short_town(40)


def make(seq, cache_root, **localize) -> Localizer:
    """Without S2M, so the paper's rule alone (no confirmation) decides when the filter is
    localized: these tests are about what the confidence says, not about S2M's word."""
    cfg = Config()
    cfg.pf.n_particles = 300
    cfg.s2m.enabled = False
    cfg.localize.require_s2m_confirmation = False
    for key, value in localize.items():
        setattr(cfg.localize, key, value)
    return Localizer(seq, cfg, cache_root)


def test_every_scan_reports_its_confidence(town, cache_root, tmp_path):
    with make(town, cache_root) as loc:
        first = loc.snapshot()
        assert first.inlier_share is None and first.inside_2sigma is None  # no scan yet
        loc.reset(pose=town.poses[0])
        loc.run(8)
        snap = loc.snapshot()
        records = loc.records
    for r in records:
        assert r.n_particles == 300
        assert r.n_eff_share == pytest.approx(r.n_eff / 300)
        assert r.cov_xx == pytest.approx(r.std_x**2) and r.cov_yy == pytest.approx(r.std_y**2)
        assert r.converged == (max(r.std_x, r.std_y, r.std_z) < loc.cfg.localize.std_threshold)
        assert 0.0 <= r.inlier_share <= 1.0 and 0.0 <= r.mean_residual_m <= loc.cfg.pf.d_max
        cov = np.array([[r.cov_xx, r.cov_xy], [r.cov_xy, r.cov_yy]])
        assert r.inside_2sigma == inside_2sigma([r.x - r.gt_x, r.y - r.gt_y], cov)
    # started at the truth: the scan fits the map at the estimate
    assert all(r.inlier_share > 0.8 and r.mean_residual_m < 1.0 for r in records), [
        (r.inlier_share, r.mean_residual_m) for r in records
    ]
    assert snap.inlier_share == records[-1].inlier_share and snap.n_eff_share == records[-1].n_eff_share
    assert (snap.cov_xx, snap.cov_xy, snap.cov_yy) == (records[-1].cov_xx, records[-1].cov_xy, records[-1].cov_yy)
    write_records_csv(tmp_path / "scans.csv", records)
    rows = list(csv.DictReader(open(tmp_path / "scans.csv")))
    assert set(CONFIDENCE) <= set(rows[0]) and rows[0]["inside_2sigma"] in ("0", "1")


def test_a_wrong_estimate_fits_the_scan_worse(town, cache_root):
    """The fit measures the estimate: particles 20 m and 90° away from the truth (and no S2M to
    bring them back) leave fewer points within d_max of the map than particles at the truth, and
    those farther from it. (In a dense town most points of a wrong pose still fall within 5 m of
    something: the mean residual is the sharper of the two.)"""
    shares, residuals = [], []
    for offset in (0.0, 20.0):
        with make(town, cache_root) as loc:
            loc.pf.set_q_std(np.zeros(11))  # the particles stay where they are put:
            pose = town.poses[0].copy()
            pose[1, 3] += offset
            if offset:
                pose[:3, :3] = pose[:3, :3] @ np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
            loc.reset(pose=pose)
            loc.pf.states[:, :6] = pose_to_xyz_ypr(pose)  # all of them at that pose, at rest
            loc.pf.states[:, 6:] = 0.0
            loc.run(1)
            shares.append(loc.records[0].inlier_share)
            residuals.append(loc.records[0].mean_residual_m)
    assert shares[0] > shares[1] + 0.05, shares
    assert residuals[1] > 4.0 * residuals[0], residuals


def test_confidence_low_fires_once_while_localized_and_rearms(town, cache_root):
    """With min_inlier_share 1 every scan is "low": the event fires at the scan the rule is met,
    and not again until the share has recovered (here: the threshold lowered for one scan)."""
    with make(town, cache_root, min_inlier_share=1.0) as loc:
        scripted_std(loc, [3.0] * 40)
        loc.run(25)  # scans 0–24
        localized = next(e.scan for e in loc.events if e.kind == "localized")
        low = [e for e in loc.events if e.kind == "confidence_low"]
        assert [e.scan for e in low] == [localized] and low[0].detail.startswith("inlier share")
        loc.cfg.localize.min_inlier_share = 0.0  # recovered at scan 25 …
        loc.run(1)
        loc.cfg.localize.min_inlier_share = 1.0  # … and low again from scan 26 on: once
        loc.run(3)
        assert [e.scan for e in loc.events if e.kind == "confidence_low"] == [localized, 26]


def test_no_confidence_low_with_a_fitting_scan(town, cache_root):
    with make(town, cache_root) as loc:  # the default threshold, 0.5
        scripted_std(loc, [3.0] * 40)
        loc.reset(pose=town.poses[0])
        loc.run(20)
        assert loc.rules.localized
        assert not any(e.kind == "confidence_low" for e in loc.events)


def test_summary_reports_calibration(town, cache_root):
    with make(town, cache_root) as loc:
        scripted_std(loc, [3.0] * 40)
        loc.reset(pose=town.poses[0])
        loc.run(15)
        s = summarize_run(loc, 1.0, preset="paper")
        recs = loc.records
    assert s["preset"] == "paper" and s["n_particles_median"] == 300
    localized = [r for r in recs if r.localized]
    assert localized and s["consistency_2sigma"] == pytest.approx(
        sum(r.inside_2sigma for r in localized) / len(localized)
    )
    onset = localized[0]
    assert s["false_fire"] is (onset.error_m > 5.0)
    assert "world" in s
