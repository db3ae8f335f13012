"""``lidarloc bench city`` (app/bench/city.py) on a small town: every figure the command promises is
there, the tiled search agrees with the whole-map search, and a second run starts from the cache."""

import math

import pytest
from lidarloc.app.bench.city import judge, localize_figures, run
from lidarloc.core.config import load_config
from lidarloc.core.sequences.factory import SourceSpec

KEYS = (
    "build_s", "start_s", "cache_mb", "rss_tracking_mb", "global_match_ms_median", "global_success",
    "whole_map_ms_median", "whole_map_success", "fpfh_ransac_ms_median", "fpfh_ransac_success", "localize_success",
)  # fmt: skip


def test_judge_is_two_metres_and_five_degrees():
    import numpy as np

    truth = np.eye(4)
    assert judge(1.9, 0.0, math.radians(4.9), truth)[0]
    assert not judge(2.1, 0.0, 0.0, truth)[0] and not judge(0.0, 0.0, math.radians(5.1), truth)[0]
    assert judge(math.nan, 0.0, 0.0, truth) == (False, math.inf)


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_bench_city_reports_every_figure(cache_root, monkeypatch):
    import numpy as np
    from lidarloc.app.bench import city
    from lidarloc.core.maps import mapping

    cfg = load_config(overrides=["town.extent_m=150", "town.n_scans=40"])
    spec = SourceSpec()
    out = run(spec, cfg, cache_root=cache_root, global_scans=3, peer_scans=1, tile_m=50.0, bev_tile_m=32.0)
    for key in KEYS:
        assert key in out
    assert out["tiled_score_equals_whole_map"] == 1.0
    assert out["global_success"] == out["whole_map_success"]
    assert out["start_s"] is not None and out["start_s"] < 30 and out["rss_tracking_mb"] > 0
    assert out["build_s"] > 0 and out["cache_mb"] > 0
    # again from the cache, the map mapped as a city's is (every map counts as large here): the
    # same tables, the same matches
    monkeypatch.setattr(mapping, "LARGE_MAP_POINTS", 0)
    mapped = []

    def loading(*args, **kwargs):
        got = mapping.load_or_build_map(*args, **kwargs)
        mapped.append(isinstance(got.value.points, np.memmap))
        return got

    monkeypatch.setattr(city, "load_or_build_map", loading)
    again = run(spec, cfg, cache_root=cache_root, global_scans=3, peer_scans=1, tile_m=50.0, bev_tile_m=32.0)
    assert mapped == [True]
    assert again["build_parts_s"] == out["build_parts_s"]  # the tiles came from the cache
    assert [r["tiled_err_m"] for r in again["rows"]] == [r["tiled_err_m"] for r in out["rows"]]
    assert again["fpfh_ransac_success"] == out["fpfh_ransac_success"]


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_localize_runs_give_localize_success(cache_root, tmp_path):
    """``--localize-runs``: seeded runs of full localization on the city's drive, summed up as
    bench localize sums them (the share of runs localized and within 5 m to the end)."""
    import json

    cfg = load_config(overrides=["town.extent_m=150", "town.n_scans=40"])
    out = tmp_path / "localize"
    got = localize_figures(SourceSpec(scans=30), cfg, runs=1, workers=1, out_dir=out, cache_root=cache_root)
    summary = json.loads((out / "summary.json").read_text())
    assert got["localize_runs"] == 1 and got["localize_success"] in (0.0, 1.0)
    assert got["localize_success"] == summary["within_5m_to_end_ratio"]
    assert got["localize_false_fire_rate"] == summary["false_fire_rate"]
