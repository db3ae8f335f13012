"""``lidarloc bench localize`` (app/bench/localize.py) end to end: a 2-run smoke bench with 2 workers
(A–E, within 5 m to the end, 2σ consistency and false fires), resumable, refusing runs of other
code; and Ray ≡ process pool."""

import json

import numpy as np
import pytest
from lidarloc.core.config import Config
from lidarloc.core.sequences.factory import SourceSpec
from ray_local import ray_local  # noqa: F401  (a fixture: the Ray tests share one local instance)

SCANS = 12
RUNS = 2  # the aggregate over runs is what is checked: two runs of two workers show it


def small_cfg():
    cfg = Config()
    cfg.pf.n_particles = 300
    cfg.localize.recorded_odometry = True  # as `lidarloc bench localize` sets it
    cfg.town.n_scans = 150  # a short mapping drive: its map builds in seconds
    return cfg


@pytest.fixture(scope="module")
def pool_bench(tmp_path_factory, town_map_entry):
    """The smoke bench on the process pool, run once: (its folder, its cache, its aggregate). The
    smoke test checks it, the Ray test compares Ray's with it."""
    from helpers import cache_with
    from lidarloc.app.bench.localize import run_bench

    root = tmp_path_factory.mktemp("pool")
    out = root / "bench"
    cache = cache_with(town_map_entry, root / "cache")  # the town's map, and nothing of a run
    agg = run_bench(SourceSpec(scans=SCANS), small_cfg(), runs=RUNS, workers=2, out_dir=out, cache_root=cache)
    return out, cache, agg


@pytest.mark.slow
def test_smoke_bench_two_runs_two_workers(pool_bench):
    from lidarloc.app.bench.localize import run_bench

    out, cache, agg = pool_bench
    for name in ("summary.json", "runs.csv", "metrics_boxplot.png", "latency_hist.png", "report.md"):
        assert (out / name).is_file() and (out / name).stat().st_size > 0, name
    summary = json.loads((out / "summary.json").read_text())
    assert summary["runs"] == RUNS and summary["scans_per_run"] == SCANS
    import csv

    rows = list(csv.DictReader(open(out / "runs.csv")))
    assert len(rows) == RUNS and [int(r["seed"]) for r in rows] == list(range(RUNS))
    for key in "ABCDE":  # the aggregate agrees with the per-run table, failures included
        met = [float(r[key]) for r in rows if r[key] != ""]
        assert summary[key]["success"] == len(met) / RUNS
        assert summary[key]["max"] == (max(met) if len(met) == RUNS else None)
    assert summary["pf_ms_median"] > 0
    assert "| B |" in (out / "report.md").read_text()
    # the "within 5 m to the end" figures, per run and in aggregate
    within = [r["within_5m_to_end"] for r in rows]
    assert all(w in ("0", "1") for w in within)
    assert all(r["localized_at_scan"] != "" for r in rows if r["within_5m_to_end"] == "1")
    assert summary["within_5m_to_end_ratio"] == sum(w == "1" for w in within) / RUNS
    # the filter's own uncertainty over runs: the median run's 2σ consistency, the share of false fires
    runs = [json.loads((out / "runs" / f"seed_{s:03d}" / "summary.json").read_text()) for s in range(RUNS)]
    cons = [r["consistency_2sigma"] for r in runs if r["consistency_2sigma"] is not None]
    assert summary["consistency_2sigma"] == (float(np.median(cons)) if cons else None)
    assert summary["false_fire_rate"] == sum(r["false_fire"] for r in runs) / RUNS
    # the first fix's wait: a run that never localized counts as the longest
    waits = sorted(np.inf if r["localized_at_s"] is None else r["localized_at_s"] for r in runs)
    mid = float(np.median(waits))
    assert summary["localized_at_s_median"] == (mid if np.isfinite(mid) else None)
    assert [r["false_fire"] for r in rows] == [str(int(r["false_fire"])) for r in runs]
    assert "2σ ellipse" in (out / "report.md").read_text()
    # the world of the town's drive is in the summary and the report
    assert summary["world"] == runs[0]["world"] and summary["world"]["changes"] == 0.0
    assert "World of the drive: changes 0" in (out / "report.md").read_text()
    # the odometry was computed once into the cache, and the town's scans stored once
    assert list(cache.glob("map-*/odometry-kiss-*/poses.npy"))
    assert len(list(cache.glob("map-*-scans/*.npy"))) == SCANS
    # resumable: a second call keeps the finished runs (same numbers, nothing recomputed)
    stamp = (out / "runs" / "seed_000" / "summary.json").stat().st_mtime_ns
    agg2 = run_bench(SourceSpec(scans=SCANS), small_cfg(), runs=RUNS, workers=2, out_dir=out, cache_root=cache)
    assert (out / "runs" / "seed_000" / "summary.json").stat().st_mtime_ns == stamp
    assert agg2["B"] == agg["B"]
    # … but not into runs of other code: they would mix two versions' numbers in one report
    from lidarloc.app.bench import localize as bench_localize
    from lidarloc.core.errors import LidarlocError

    marker = out / "bench_config.json"
    assert json.loads(marker.read_text())["code"] == bench_localize.code_fingerprint()
    marker.write_text(marker.read_text().replace(bench_localize.code_fingerprint(), "0" * 64))
    with pytest.raises(LidarlocError, match="version of lidarloc's code"):
        run_bench(SourceSpec(scans=SCANS), small_cfg(), runs=RUNS, workers=2, out_dir=out, cache_root=cache)


@pytest.mark.slow
def test_ray_matches_process_pool(tmp_path, ray_local, pool_bench, town_cache):
    from lidarloc.app.bench.localize import run_bench

    pool, _, a = pool_bench  # the same bench on the process pool
    spec = SourceSpec(scans=SCANS)
    b = run_bench(
        spec, small_cfg(), runs=RUNS, workers=2, out_dir=tmp_path / "ray", executor="ray", cache_root=town_cache
    )
    for key in "ABCDE":
        assert a[key] == b[key]
    ta = np.loadtxt(pool / "runs" / "seed_001" / "trajectory_kitti.txt")
    tb = np.loadtxt(tmp_path / "ray" / "runs" / "seed_001" / "trajectory_kitti.txt")
    assert np.array_equal(ta, tb)
