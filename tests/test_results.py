"""What a run leaves behind (core/runs/results.py, written by app/headless.py's run loop): parseable
trajectory, ground-truth, per-scan and event files, and the summary with its CPU and real-time
figures."""

import csv
import json

import numpy as np
import pytest
from lidarloc.core.runs.results import lag_summary


def test_run_writes_parseable_files(recorded_town_run):
    """The session's recorded 14-scan run of the short town (conftest.recorded_town_run: made as
    ``lidarloc run`` makes it, 300 particles), read back."""
    out, summary = recorded_town_run
    n = 14
    assert summary["scans"] == n
    kitti = np.loadtxt(out / "trajectory_kitti.txt")
    assert kitti.shape == (n, 12)
    tum = np.loadtxt(out / "trajectory_tum.txt")
    assert tum.shape == (n, 8) and np.allclose(np.linalg.norm(tum[:, 4:], axis=1), 1, atol=1e-6)
    assert np.loadtxt(out / "groundtruth_kitti.txt").shape == (n, 12)
    rows = list(csv.DictReader(open(out / "scans.csv")))
    assert len(rows) == n and {"scan", "std_x", "n_eff", "localized", "error_m", "pf_ms"} <= set(rows[0])
    assert {
        "n_particles",
        "n_eff_share",
        "converged",
        "inlier_share",
        "mean_residual_m",
        "cov_xx",
        "cov_xy",
        "cov_yy",
        "inside_2sigma",
    } <= set(rows[0])
    events = json.loads((out / "events.json").read_text())
    assert any(e["kind"] == "s2m_started" for e in events)
    s = json.loads((out / "summary.json").read_text())
    for key in (
        "localized_at_scan",
        "within_5m_for_50_at_scan",
        "rmse_after_localized_m",
        "pf_ms_median",
        "scans_per_second",
        "preset",
        "consistency_2sigma",
        "false_fire",
    ):
        assert key in s
    assert s["n_particles_median"] == 300
    # the first fix in the drive's own seconds: the town's scans are 0.1 s apart
    if s["localized_at_scan"] is None:
        assert s["localized_at_s"] is None
    else:
        assert s["localized_at_s"] == pytest.approx(0.1 * s["localized_at_scan"])
    assert s["world"]["sensor"] == "hdl64e"  # the generated town says what world it drove in
    # what each block's process cost: the PF here, KISS-ICP and S2M in their children
    cpu = s["cpu_ms_per_scan"]
    assert set(cpu) == {"main", "rpe", "s2m"}
    assert cpu["main"] > 0 and cpu["rpe"] > 0 and cpu["s2m"] > 0
    cpu_seconds, wall_seconds = sum(cpu.values()) * n / 1000, n / s["scans_per_second"]
    assert s["cpu_percent"] == pytest.approx(100 * cpu_seconds / wall_seconds)


def test_realtime_lag_summary():
    """How the real-time clock kept up, from each step's start lag after its scan's arrival."""
    assert lag_summary(None)["kept_up_from_scan"] is None  # replay: no real-time figures
    s = lag_summary([0.0, 250.0, 400.0, 120.0, 80.0, 10.0, 0.0])
    assert s == {"late_scans": 3, "max_lag_ms": 400.0, "lag_at_end_ms": 0.0, "kept_up_from_scan": 4}
    assert lag_summary([0.0, 5.0])["kept_up_from_scan"] == 0
    assert lag_summary([0.0, 150.0, 300.0])["kept_up_from_scan"] is None  # still late at the end
