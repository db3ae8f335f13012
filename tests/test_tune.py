"""``lidarloc tune``'s search on Ray Tune with Optuna: it starts from the given settings, finds
better ones, stops a trial whose seed fails, and writes trials.csv, best.yaml and the importance."""

from __future__ import annotations

import csv

import pytest
import yaml
from lidarloc.app.sweep.sweep import Settings
from lidarloc.app.sweep.tune import PENALTY, parse_params, run_tune
from lidarloc.core.errors import LidarlocError
from lidarloc.core.sequences.factory import SourceSpec
from ray_local import ray_local  # noqa: F401  (a fixture)
from sweep_fakes import fake_localize, no_prepare


@pytest.mark.slow
def test_tune_beats_the_starting_settings_and_stops_failing_trials(tmp_path, ray_local):
    settings = Settings(SourceSpec(), None, ("pf.sigma=2",), None, None, tmp_path / "cache")
    params = parse_params(["pf.sigma=0.2:3", "pf.d_max=1:5"])
    summary = run_tune(
        settings,
        params,
        trials=6,
        runs=2,
        workers=2,
        out_dir=tmp_path / "tune",
        run_fn=fake_localize,
        prepare=no_prepare,
    )
    rows = list(csv.DictReader(open(tmp_path / "tune" / "trials.csv")))
    assert len(rows) == summary["trials"] == 6
    # the first trial is the starting settings (σ = 2: RMSE ≈ 1.1 m), and the best beats it
    start = summary["defaults"]["trial"]
    assert start["pf.sigma"] == 2.0 and start["met"]
    assert summary["best"]["rmse_median"] < start["rmse_median"]
    assert summary["improvement_m"] == pytest.approx(start["rmse_median"] - summary["best"]["rmse_median"])
    best = yaml.safe_load((tmp_path / "tune" / "best.yaml").read_text())
    assert best["pf"]["sigma"] == pytest.approx(summary["best"]["pf.sigma"], abs=1e-5)
    # a setting that fires falsely ends at its first seed with the penalty
    for r in rows:
        if float(r["pf.sigma"]) > 2.5:
            assert r["seeds_done"] == "1" and float(r["objective"]) >= PENALTY and r["met"] == "False"
    assert summary["importance"] is not None and set(summary["importance"]) == {"pf.sigma", "pf.d_max"}
    assert (tmp_path / "tune" / "importance.png").stat().st_size > 0


def test_params_are_parsed():
    a, b = parse_params(["pf.sigma=0.2:3", "pf.n_particles=200:2000"])
    assert (a.key, a.low, a.high, a.integer) == ("pf.sigma", 0.2, 3.0, False)
    assert (b.integer, b.fmt(512.4)) == (True, "512")
    for bad in ([], ["pf.sigma=3:1"], ["pf.sigma=1"], ["pf.sigma=1:2", "pf.sigma=2:3"]):
        with pytest.raises(LidarlocError):
            parse_params(bad)
