"""``lidarloc bench peers`` on a few scans of the short town: every figure ``--json`` promises is
there and means what it says (a tracker started at the truth tracks; none recovers from a jump
it is not told of within a window too short for a global search), and the helpers' rules."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import MAPPING_SCANS
from lidarloc.app.bench import peers
from lidarloc.core.config import Config
from lidarloc.core.sequences.factory import SourceSpec

PROMISED = (
    "m3rsm_success",
    "m3rsm_ms_median",
    "fpfh_ransac_success",
    "fpfh_ransac_ms_median",
    "fgr_success",
    "fgr_ms_median",
    "lidarloc_tracking_rmse_m",
    "gicp_tracking_rmse_m",
    "lidarloc_cpu_ms_per_scan",
    "gicp_cpu_ms_per_scan",
    "lidarloc_recovered_after_kidnap",
    "gicp_recovered_after_kidnap",
)


def test_recovery_counts_scans_until_the_error_stays_small():
    assert peers.recovery([0.1, 0.2]) == 0
    assert peers.recovery([30.0, 12.0, 1.5, 0.3, 0.2]) == 2
    assert peers.recovery([30.0, 0.5, 9.0, 0.3]) == 3
    assert peers.recovery([30.0, 0.5, 9.0]) is None  # still off at the end of the window
    assert peers.recovery([float("inf"), 0.1]) == 1  # a scan without an error counts as off


def test_the_kidnap_lands_fifty_metres_along_the_drive():
    class Straight:  # 2 m per scan along x
        poses = np.tile(np.eye(4), (100, 1, 1))

    Straight.poses[:, 0, 3] = 2.0 * np.arange(100)
    assert peers.kidnap_target(Straight, 10) == 35  # 25 scans × 2 m = 50 m
    assert peers.kidnap_target(Straight, 90) == 99  # the drive ends first


@pytest.mark.timeout(300)
def test_bench_peers_on_a_few_scans(cache_root):
    cfg = Config()
    cfg.town.n_scans = MAPPING_SCANS
    cfg.pf.n_particles = 300
    r = peers.run(
        SourceSpec(),
        cfg,
        global_scans=2,
        track_scans=20,
        after_kidnap=6,
        real=False,
        paper=False,
        cache_root=cache_root,
    )
    for key in PROMISED:
        assert key in r, key
    for key in ("m3rsm_success", "fpfh_ransac_success", "fgr_success"):
        assert 0.0 <= r[key] <= 1.0
    for key in ("m3rsm_ms_median", "fpfh_ransac_ms_median", "fgr_ms_median", "gicp_cpu_ms_per_scan"):
        assert r[key] > 0
    assert len(r["global_town"]["rows"]) == 2 and "global_real" not in r and "paper" not in r
    # GICP tracking from the true start on the map's own drive stays on it
    assert r["gicp_tracking_rmse_m"] < 0.5
    t = r["tracking"]
    assert t["kidnap_to_scan"] > t["kidnap_from_scan"] + 1 and t["kidnap_m"] > 10
    # tens of metres off and told nothing: local scan matching cannot come back
    assert r["gicp_recovered_after_kidnap"] is False
    assert isinstance(r["lidarloc_recovered_after_kidnap"], bool)
    assert r["tracking_target_met"] == (
        r["lidarloc_tracking_rmse_m"] is not None
        and r["lidarloc_tracking_rmse_m"] <= 1.1 * r["gicp_tracking_rmse_m"]
        and r["lidarloc_cpu_ms_per_scan"] <= r["gicp_cpu_ms_per_scan"]
    )
