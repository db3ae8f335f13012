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


# with the optional peers installed, MapClosures first runs KISS-ICP over the 150-scan town once
@pytest.mark.timeout(600)
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
    # each optional peer either ran (its figures) or was skipped (its reason), never both
    for peer in ("kiss_matcher", "mapclosures"):
        assert (f"{peer}_success" in r) != (peer in r["skipped"]), peer
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


# ------------------------------------------------------------------ the optional peers ([peers])
OPTIONAL_FIELDS = ("success", "success_count", "ms_median", "err_m_median", "accepted", "repeatable", "settings")


def _absent(monkeypatch, *modules):
    """Imports of ``modules`` fail here as where the package is not installed."""
    import sys

    for module in modules:
        monkeypatch.setitem(sys.modules, module, None)  # `import module` raises ImportError


def test_an_absent_peer_is_skipped_with_its_reason(monkeypatch):
    from lidarloc.app.bench import peers_optional

    _absent(monkeypatch, "kiss_matcher", "map_closures")
    part = {"rows": [{"scan": 0}]}
    # nothing to run: neither the source nor the map is opened (a spec that cannot open says so)
    skipped = peers_optional.add_optional_peers(part, SourceSpec(kitti_raw="/nonexistent"), Config())
    assert set(skipped) == {"kiss_matcher", "mapclosures"}
    assert "kiss-matcher is not installed" in skipped["kiss_matcher"]
    assert "map-closures is not installed" in skipped["mapclosures"]
    assert part == {"rows": [{"scan": 0}]}  # no figure for a peer that did not run
    lines = peers_optional.notes({"skipped": skipped})
    assert len(lines) == 2 and all("\n" not in line and "lidarloc[peers]" in line for line in lines)
    assert lines[0].startswith("bench peers: kiss_matcher skipped: kiss-matcher is not installed")


def test_the_headline_leaves_out_a_peer_that_did_not_run():
    rows = [{}, {}]
    for row, ok, ms in zip(rows, (True, False), (100.0, 300.0)):
        for n in ("m3rsm", "fpfh_ransac", "fgr"):
            row.update({f"{n}_success": ok, f"{n}_ms": ms})
    tracking = {
        "lidarloc": {"rmse_m": 0.2, "cpu_ms_per_scan": 50.0, "pf_ms_median": 10.0},
        "gicp": {"rmse_m": 0.2, "cpu_ms_per_scan": 40.0, "ms_median": 30.0},
    }
    for who in tracking.values():
        who.update(recovered_after_kidnap=False, recovery_scans=None)
    out = peers.headline({"global_town": {"rows": rows}, "tracking": tracking})
    assert out["m3rsm_success_count"] == 1 and out["fpfh_ransac_success"] == 0.5
    assert not any(k.startswith(("kiss_matcher", "mapclosures")) for k in out)
    assert out["best_global_peer"] in ("fpfh_ransac", "fgr")
    # MapClosures' cost is its query with its stitching, row by row
    for row, (ok, ms, stitch) in zip(rows, ((True, 40.0, 10.0), (True, 60.0, 30.0))):
        row.update(mapclosures_success=ok, mapclosures_ms=ms, mapclosures_stitch_ms=stitch)
        row.update(mapclosures_single_success=False, mapclosures_single_ms=ms)
        row.update(kiss_matcher_success=False, kiss_matcher_ms=1000.0)
    out = peers.headline({"global_town": {"rows": rows}, "tracking": tracking})
    assert out["mapclosures_success_count"] == 2 and out["kiss_matcher_success_count"] == 0
    assert out["best_global_peer"] == "mapclosures" and out["best_global_peer_ms_median"] == 70.0
    assert out["global_target_met"] is False  # M3RSM finds 1 of 2 where MapClosures finds both


@pytest.mark.timeout(600)
def test_the_optional_peers_on_a_few_town_scans(cache_root):
    from lidarloc.app.bench import peers_optional
    from lidarloc.app.bench.peers_global import global_localization

    for peer in peers_optional.PACKAGES:
        if (reason := peers_optional.missing(peer)) is not None:
            pytest.skip(f"{peer}: {reason}")
    cfg = Config()
    cfg.town.n_scans = MAPPING_SCANS
    spec = SourceSpec(scans=12)  # the town's first 12 scans, in the map of its 150
    part = global_localization(spec, cfg, 2, cache_root, peers=False)
    assert peers_optional.add_optional_peers(part, spec, cfg, cache_root) == {}
    for peer in ("kiss_matcher", "mapclosures"):
        for field in OPTIONAL_FIELDS:
            assert f"{peer}_{field}" in part, (peer, field)
        assert 0.0 <= part[f"{peer}_success"] <= 1.0
        assert part[f"{peer}_success_count"] == sum(r[f"{peer}_success"] for r in part["rows"])
        assert part[f"{peer}_ms_median"] > 0
        for row in part["rows"]:  # each scan judged by the same rule as FPFH + RANSAC
            assert row[f"{peer}_success"] == (row[f"{peer}_err_m"] <= 2.0 and row[f"{peer}_err_deg"] <= 5.0)
    assert part["mapclosures_tiles"] >= 1 and part["mapclosures_stitch_ms_median"] > 0
    assert "mapclosures_single_success_count" in part and part["mapclosures_single_ms_median"] > 0
    # the local map is the scan and the ones before it, as many as the drive has
    assert [r["mapclosures_local_scans"] for r in part["rows"]] == [min(r["scan"] + 1, 10) for r in part["rows"]]
