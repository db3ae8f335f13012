"""``lidarloc bench city`` (app/bench/city.py) on a small town: every figure the command promises is
there, the tiled search agrees with the whole-map search, and a second run starts from the cache."""

import math

import pytest
from lidarloc.app.bench.city import localize_figures, run
from lidarloc.app.bench.city_rows import GlobalRows, judge, missed, scan_order
from lidarloc.core.config import load_config
from lidarloc.core.sequences.factory import SourceSpec

KEYS = (
    "build_s", "start_s", "cache_mb", "rss_tracking_mb", "global_match_ms_median", "global_success",
    "whole_map_ms_median", "whole_map_success", "fpfh_ransac_ms_median", "fpfh_ransac_success", "localize_success",
    "global_confident_wrong", "global_ambiguous", "second_opinion_ms_median", "exact_success", "places",
)  # fmt: skip


def test_judge_is_two_metres_and_five_degrees():
    import numpy as np

    truth = np.eye(4)
    assert judge(1.9, 0.0, math.radians(4.9), truth)[0]
    assert not judge(2.1, 0.0, 0.0, truth)[0] and not judge(0.0, 0.0, math.radians(5.1), truth)[0]
    assert judge(math.nan, 0.0, 0.0, truth) == (False, math.inf)


def test_a_scan_placed_elsewhere_is_named_with_both_places():
    import numpy as np

    truth = np.eye(4)
    truth[:2, 3] = (10.0, 20.0)
    row = {"scan": 7, "tiled_err_m": 812.0, "tiled_pose": [700.0, 420.0, math.pi / 2], "tiled_score": 93.0}
    got = missed(row, truth, lambda x, y: "downtown" if x < 100 else "suburb")
    assert got == {
        "scan": 7, "err_m": 812.0, "truth_xy": [10.0, 20.0], "matched_xy_yaw_deg": [700.0, 420.0, 90.0],
        "score": 93.0, "truth_district": "downtown", "matched_district": "suburb",
    }  # fmt: skip
    nothing = missed({**row, "tiled_pose": [math.nan, math.nan, math.nan]}, truth, lambda x, y: "park")
    assert nothing["matched_district"] is None and "truth_district" not in missed(row, truth)


def test_the_scans_of_a_shorter_run_are_the_first_of_a_longer_one():
    few, many = scan_order(1000, 10, 7), scan_order(1000, 200, 7)
    assert few == many[:10] and len(set(many)) == 200 and all(0 <= k < 1000 for k in many)
    assert sorted(scan_order(5, 10, 7)) == [0, 1, 2, 3, 4]
    assert scan_order(1000, 10, 8) != few


def test_global_rows_resume_only_their_own_source_configuration_and_code(tmp_path):
    """Rows kept after each scan come back as they were (numpy numbers as plain ones) for the same
    identity; another identity, or a file that is not a rows file, is refused in one line."""
    import numpy as np
    from lidarloc.core.errors import LidarlocError

    identity = {"source": "town", "config": {"seed": 0}, "code": "abc"}
    rows = GlobalRows(tmp_path, identity)
    assert rows.rows == {}
    rows.add({"scan": np.int64(12), "tiled_ms": np.float64(1.5), "tiled_success": True, "tiled_err_m": math.inf})
    rows.add({"scan": 3, "tiled_ms": 2.0, "tiled_success": False, "tiled_err_m": 40.0})
    again = GlobalRows(tmp_path, dict(identity))
    assert again.rows == {
        12: {"scan": 12, "tiled_ms": 1.5, "tiled_success": True, "tiled_err_m": math.inf},
        3: {"scan": 3, "tiled_ms": 2.0, "tiled_success": False, "tiled_err_m": 40.0},
    }
    assert [p.name for p in tmp_path.iterdir()] == ["rows.json"]  # no temporary file left
    with pytest.raises(LidarlocError, match="another source, configuration or version"):
        GlobalRows(tmp_path, {**identity, "code": "def"})
    (tmp_path / "rows.json").write_text('{"rows": [{"no scan": 1}]')
    with pytest.raises(LidarlocError, match="not a bench city rows file"):
        GlobalRows(tmp_path, identity)


_ROW_MODULES = """
import json, sys, tempfile
from pathlib import Path
import lidarloc
from lidarloc.app.bench.city_rows import match_row, prepare, warm_up
from lidarloc.app.bench.common import open_source
from lidarloc.core.config import load_config
from lidarloc.core.maps.bev import load_or_build_pyramid
from lidarloc.core.maps.mapping import load_or_build_map
from lidarloc.core.maps.tiled_bev import TiledBEV
from lidarloc.core.sequences.factory import SourceSpec
cfg = load_config(overrides=["town.extent_m=150", "town.n_scans=40"])
seq = open_source(SourceSpec(), cfg, "city", need_poses=True)
prior, map_dir, _ = load_or_build_map(seq.map_source, cfg.map, None, memory_map=True)
with tempfile.TemporaryDirectory() as tmp:
    kind = "binary" if cfg.s2m.binary_cells else None
    bev = TiledBEV.load_or_build(prior.points_bev, Path(tmp), map_dir.name, cfg.s2m.match_resolution, 32.0, kind)
    pyramid = load_or_build_pyramid(prior, map_dir, cfg.s2m).value
    scan = prepare(seq.scan(3), cfg)
    warm_up(bev, pyramid, scan, cfg.s2m.angle_step)
    row = match_row(3, scan, seq.pose(3), bev, pyramid, cfg.s2m.angle_step)
root = Path(lidarloc.__file__).parent
files = [getattr(m, "__file__", None) for n, m in list(sys.modules.items()) if n.startswith("lidarloc.")]
print(json.dumps({"row": row, "loaded": sorted(Path(f).relative_to(root).as_posix() for f in files if f)}))
"""


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_a_global_match_row_never_reads_the_code_its_fingerprint_leaves_out(cache_root):
    """Rows resume across changes to the lookup table's modules only because no row reads them:
    preparing, searching (tiled and whole-map) and judging a scan, in a fresh process, imports
    none of them, and every file left out still exists (a renamed one would be fingerprinted)."""
    import json
    import os
    import subprocess
    import sys
    from pathlib import Path

    import lidarloc
    from lidarloc.app.bench.city_rows import ROW_CODE_EXCLUDED

    env = {**os.environ, "LIDARLOC_CACHE": str(cache_root)}
    done = subprocess.run([sys.executable, "-c", _ROW_MODULES], env=env, capture_output=True, text=True, timeout=280)
    assert done.returncode == 0, done.stderr[-2000:]
    got = json.loads(done.stdout.strip().splitlines()[-1])
    assert got["row"]["tiled_success"] and got["row"]["same_as_whole"]  # a real row was made
    assert "core/maps/tiled_bev.py" in got["loaded"] and "core/matching/tiled_search.py" in got["loaded"]
    assert not set(ROW_CODE_EXCLUDED) & set(got["loaded"])
    root = Path(lidarloc.__file__).parent
    assert all((root / f).is_file() for f in ROW_CODE_EXCLUDED)


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_a_stopped_bench_city_resumes_at_the_next_scan(cache_root, tmp_path, monkeypatch):
    """With ``rows_dir`` each global match is kept as it is done: a longer run in the same
    directory matches only the scans it does not hold (once more to compile, off the clock)."""
    from lidarloc.app.bench import city_rows

    cfg = load_config(overrides=["town.extent_m=150", "town.n_scans=40"])
    kw = dict(cache_root=cache_root, peer_scans=0, tile_m=50.0, bev_tile_m=32.0, whole_map=False)
    first = run(SourceSpec(), cfg, global_scans=2, rows_dir=tmp_path, **kw)
    assert first["global_scans_resumed"] == 0 and len(first["rows"]) == 2
    searched = []
    search = city_rows.match_global_tiled

    def counted(bev, pts, step):
        searched.append(len(pts))
        return search(bev, pts, step)

    monkeypatch.setattr(city_rows, "match_global_tiled", counted)
    longer = run(SourceSpec(), cfg, global_scans=3, rows_dir=tmp_path, **kw)
    assert longer["global_scans_resumed"] == 2 and len(searched) == 2  # the warm-up and the new scan
    assert longer["rows"][:2] == first["rows"] and longer["rows"][2]["scan"] == scan_order(40, 3, cfg.seed)[2]
    assert longer["global_scans"] == 3 and longer["whole_map_ms_median"] is None


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_bench_city_reports_every_figure(cache_root, monkeypatch):
    import numpy as np
    from lidarloc.app.bench import city
    from lidarloc.core.maps import mapping

    # the candidates asked for: on a city this small "auto" searches it whole
    cfg = load_config(overrides=["town.extent_m=150", "town.n_scans=40", "s2m.global=candidates"])
    spec = SourceSpec()
    out = run(spec, cfg, cache_root=cache_root, global_scans=3, peer_scans=1, tile_m=50.0, bev_tile_m=32.0)
    for key in KEYS:
        assert key in out
    assert out["tiled_score_equals_whole_map"] == 1.0
    assert out["exact_success"] == out["whole_map_success"]
    # lidarloc's answer (the candidates) beside the exact search's, and the second opinion
    assert out["exact_agrees_with_candidates"] == 1.0 and out["global_confident_wrong"] == 0
    assert out["second_opinion_agrees"] == 1.0 and out["places"] > 0
    assert all(r["global_search"] == "candidates" for r in out["rows"])
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
    assert out["fpfh_ransac_status"] == "done" and out["fpfh_ransac_scans_done"] == 1
    assert out["fpfh_feature_points"] > 0 and out["fpfh_peak_rss_mb"] > 0


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_fpfh_ransac_takes_its_scans_in_the_seeded_order_so_a_stopped_run_kept_a_sample(cache_root, monkeypatch):
    """FPFH + RANSAC registers the first scans of the global matches' seeded order, in that order:
    the registrations a run stopped part-way kept are spread over the drive, not its start."""
    from lidarloc.app.bench import city
    from lidarloc.app.bench.city_rows import scan_order

    cfg = load_config(overrides=["town.extent_m=150", "town.n_scans=40"])
    handed = []
    monkeypatch.setattr(city, "peers", lambda seq, map_file, cfg, idx, *rest: handed.append((len(seq), idx)) or {})
    run(SourceSpec(), cfg, cache_root=cache_root, global_scans=6, peer_scans=4, tile_m=50.0, bev_tile_m=32.0)
    [(n, idx)] = handed
    assert idx == scan_order(n, 6, cfg.seed)[:4] and idx != sorted(idx)


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_localize_runs_give_localize_success(cache_root, tmp_path):
    """``--localize-runs``: seeded runs of full localization on the city's drive, summed up as
    bench localize sums them (the share of runs localized and within 5 m to the end), on the
    real-time clock when asked: the first fix's wait in the drive's seconds."""
    import json

    cfg = load_config(overrides=["town.extent_m=150", "town.n_scans=40", "localize.clock=realtime"])
    out = tmp_path / "localize"
    got = localize_figures(SourceSpec(scans=30), cfg, runs=1, workers=1, out_dir=out, cache_root=cache_root)
    summary = json.loads((out / "summary.json").read_text())
    run = json.loads((out / "runs" / "seed_000" / "summary.json").read_text())
    assert got["localize_runs"] == 1 and got["localize_success"] in (0.0, 1.0)
    assert got["localize_success"] == summary["within_5m_to_end_ratio"]
    assert got["localize_false_fire_rate"] == summary["false_fire_rate"]
    assert run["clock"] == "realtime" and got["localize_clock"] == "realtime"
    # paced as `lidarloc run` paces it: the scans arrive at 10 Hz, each step's lag counted
    assert run["late_scans"] is not None and run["scans_per_second"] <= 10.5
    assert got["first_fix_s_median"] == run["localized_at_s"]
    if run["localized_at_s"] is not None:  # the drive's own seconds: scans 0.1 s apart
        assert run["localized_at_s"] == pytest.approx(0.1 * run["localized_at_scan"])


class _Drive:
    """Two scans of random points around the origin, their truth the identity."""

    def scan(self, k):
        import numpy as np

        rng = np.random.default_rng(k)
        return np.c_[rng.uniform(-30, 30, (2000, 3)), np.zeros(2000)]

    def pose(self, k):
        import numpy as np

        return np.eye(4)


def test_fpfh_ransac_is_stopped_at_its_budget_and_says_where(tmp_path, monkeypatch):
    """FPFH + RANSAC runs in a process of its own: past its time or memory budget it is killed,
    and the bench says which budget stopped it, where, and what it had finished; a process
    that fails says why in one line. None is left running."""
    import numpy as np
    import psutil
    from lidarloc.app.bench.city import peers

    cfg = load_config()
    map_file = tmp_path / "map.npy"
    # a million feature points: seconds of features, where the budgets below stop it within one
    np.save(map_file, np.random.default_rng(0).uniform(-50, 50, (2_000_000, 3)).astype(np.float32))
    before = {p.pid for p in psutil.Process().children(recursive=True)}
    quiet = lambda what, f: None  # noqa: E731

    timed = peers(_Drive(), map_file, cfg, [0, 1], quiet, budget_s=0.0, budget_mb=1e9)
    assert timed["fpfh_ransac_status"] == "stopped at the time budget (0 min) while building the map's features"
    assert timed["fpfh_ransac_scans_done"] == 0 and timed["fpfh_ransac_scans"] == 2
    assert timed["fpfh_ransac_ms_median"] is None and timed["fpfh_ransac_success"] is None
    assert timed["fpfh_map_build_s"] is None

    full = peers(_Drive(), map_file, cfg, [0, 1], quiet, budget_s=600.0, budget_mb=1.0)
    assert full["fpfh_ransac_status"].startswith("stopped at the memory budget (")
    assert full["fpfh_peak_own_mb"] > 1.0 and full["fpfh_peak_rss_mb"] >= full["fpfh_peak_own_mb"]

    # whatever else runs beside it, the machine is never run out of memory: it stops at the reserve
    from lidarloc.app.bench import city

    monkeypatch.setattr(city, "memory_reserve", lambda: psutil.virtual_memory().total)
    short = peers(_Drive(), map_file, cfg, [0, 1], quiet, budget_s=600.0, budget_mb=1e9)
    assert short["fpfh_ransac_status"].startswith("stopped at the machine's memory (")
    assert " GB left, at " in short["fpfh_ransac_status"] and short["fpfh_ransac_scans_done"] == 0
    monkeypatch.undo()
    assert 0 < city.default_peer_budget_mb() * 2**20 <= 0.75 * psutil.virtual_memory().total

    failed = peers(_Drive(), tmp_path / "no-map.npy", cfg, [0], quiet, budget_s=600.0, budget_mb=1e9)
    status = failed["fpfh_ransac_status"]
    assert status.startswith("failed (exit code 1): FileNotFoundError") and "no-map.npy" in status
    assert "\n" not in status and failed["fpfh_ransac_scans_done"] == 0

    assert {p.pid for p in psutil.Process().children(recursive=True)} <= before


# ``lidarloc bench city`` whose second global match is a stand-in that spins inside numba for many
# minutes, releasing the GIL, as a search over a city does: Python runs no signal handler there.
_SPINNING_BENCH = """
import os, sys
import numba
import numpy as np
from lidarloc.app.bench import city
from lidarloc.app.cli import main

@numba.njit(nogil=True)
def spin(n):
    x = np.uint64(88172645463325252)
    for _ in range(n):
        x ^= x << np.uint64(13)
        x ^= x >> np.uint64(7)
        x ^= x << np.uint64(17)
    return x

spin(1)
real, calls = city.match_row, []

def match_row(*args):
    calls.append(args[0])
    if len(calls) == 1:
        return real(*args)
    open(os.environ["SPIN_MARK"], "w").close()
    spin(10**13)
    raise AssertionError("the stand-in search ended")

city.match_row = match_row
sys.argv = ["lidarloc", *sys.argv[1:]]
main()
"""


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_a_stop_during_a_long_search_ends_bench_city_at_once_and_keeps_its_rows(cache_root, tmp_path):
    """SIGTERM (as Ctrl-C) in the middle of a global search that would run for many minutes ends
    the command within seconds, exit code 130, with one line that says how many matches are kept
    and where; the rows done before it are on disk for the next run to resume from."""
    import json
    import os
    import signal
    import subprocess
    import sys
    import time

    from helpers import wait_for

    mark, out = tmp_path / "spinning", tmp_path / "bench"
    cmd = [sys.executable, "-c", _SPINNING_BENCH, "bench", "city", "--set", "town.extent_m=150"]
    cmd += ["--set", "town.n_scans=40", "--global-scans", "3", "--peer-scans", "0", "--no-whole-map"]
    cmd += ["--tile-m", "50", "--out", str(out), "--cache", str(cache_root), "--json"]
    proc = subprocess.Popen(
        cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env={**os.environ, "SPIN_MARK": str(mark)}
    )
    try:
        wait_for(lambda: mark.exists() or proc.poll() is not None, timeout=300, what="the second search")
        assert proc.poll() is None, proc.communicate()[1]
        t0 = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        stdout, stderr = proc.communicate(timeout=120)
        stop_s = time.monotonic() - t0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 130, stderr
    assert stop_s < 3.0  # the search itself would have run on for many minutes
    rows = out / "global" / "rows.json"
    assert stderr.strip().splitlines()[-1] == (
        f"stopped: 1 global matches kept in {rows}; the same command resumes at the next scan"
    )
    assert stdout == ""  # no figures from a stopped bench
    kept = json.loads(rows.read_text())["rows"]
    assert [r["scan"] for r in kept] == scan_order(40, 1, load_config().seed)


def test_fpfh_features_are_kept_beside_the_map_and_rebuilt_when_cut_short_or_foreign(tmp_path, caplog):
    """The feature map a city takes ~40 minutes to compute is kept in the map's directory and
    read back exactly; a file cut short, or features of another voxel, are computed again."""
    import json

    import numpy as np
    from lidarloc.app.bench.peers_global import FeatureMap

    points = np.random.default_rng(1).uniform(-40, 40, (60_000, 3)).astype(np.float32)
    built = FeatureMap(points, cache_dir=tmp_path)
    read = FeatureMap(points, cache_dir=tmp_path)
    assert not built.cached and read.cached and read.build_s == built.build_s
    assert np.array_equal(np.asarray(read.cloud.points), np.asarray(built.cloud.points))
    assert np.array_equal(np.asarray(read.fpfh.data), np.asarray(built.fpfh.data))

    fpfh = tmp_path / "fpfh-1m" / "fpfh.npy"
    fpfh.write_bytes(fpfh.read_bytes()[: fpfh.stat().st_size // 2])
    again = FeatureMap(points, cache_dir=tmp_path)
    assert not again.cached and "unreadable cache entry" in caplog.text
    assert np.array_equal(np.asarray(again.fpfh.data), np.asarray(built.fpfh.data))
    assert FeatureMap(points, cache_dir=tmp_path).cached  # written whole again

    record = tmp_path / "fpfh-1m" / "features.json"
    record.write_text(json.dumps({**json.loads(record.read_text()), "voxel": 2.0}))
    assert not FeatureMap(points, cache_dir=tmp_path).cached


def test_fpfh_ransac_with_its_feature_index_built_once_registers_exactly_as_open3d_s_one_call():
    """The map's feature index built once and the reverse check asked only of the map points a scan
    point chose: the same correspondences reach the same RANSAC, so the same pose as open3d's
    registration_ransac_based_on_feature_matching (which builds the index on every call)."""
    import numpy as np
    from lidarloc.app.bench.peers_global import FeatureMap

    rng = np.random.default_rng(1)
    g = rng.uniform(-40, 40, (30_000, 2))
    parts = [np.c_[g, rng.normal(0, 0.03, len(g))]]
    for _ in range(20):  # boxes' walls on the ground
        corner, size = rng.uniform(-35, 35, 2), rng.uniform(2, 8, 3)
        p = rng.uniform(0, 1, (2_500, 3)) * size + [*corner, 0]
        side = rng.integers(0, 4, len(p))
        p[side == 0, 0], p[side == 1, 0] = corner[0], corner[0] + size[0]
        p[side == 2, 1], p[side == 3, 1] = corner[1], corner[1] + size[1]
        parts.append(p)
    world = np.vstack(parts)
    features = FeatureMap(world)
    right = 0
    for k in range(3):
        yaw, centre = rng.uniform(-np.pi, np.pi), rng.uniform(-15, 15, 2)
        c, s = np.cos(yaw), np.sin(yaw)
        scan = world[np.linalg.norm(world[:, :2] - centre, axis=1) < 25] - [*centre, 0]
        scan = scan @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) + rng.normal(0, 0.02, scan.shape)
        T = features.ransac(scan, 7 + k)
        assert np.array_equal(T, features.ransac_open3d(scan, 7 + k))
        right += bool(np.abs(T[:2, 3] - centre).max() < 0.5)
    assert right >= 1  # a registration that finds the place, not only two that agree on nothing
    assert features.index_s > 0


def test_fpfh_ransac_registrations_are_kept_and_a_longer_run_registers_only_the_new_scans(tmp_path, monkeypatch):
    """With rows kept, each registration is on disk as it ends; a run over more scans reads the
    kept ones and the kept feature map and registers only the scans it lacks; a run with nothing
    left to do starts no process at all."""
    import numpy as np
    import psutil
    from lidarloc.app.bench import city
    from lidarloc.app.bench.city import peers

    cfg = load_config()
    map_file = tmp_path / "map.npy"
    np.save(map_file, np.random.default_rng(0).uniform(-50, 50, (40_000, 3)).astype(np.float32))
    quiet = lambda what, f: None  # noqa: E731
    rows = tmp_path / "fpfh-ransac"
    identity = {"method": "FPFH + RANSAC", "map": "random"}
    before = {p.pid for p in psutil.Process().children(recursive=True)}

    first = peers(_Drive(), map_file, cfg, [0], quiet, 600.0, 1e9, GlobalRows(rows, identity))
    assert first["fpfh_ransac_status"] == "done" and first["fpfh_ransac_scans_resumed"] == 0
    assert first["fpfh_features_cached"] is False and first["fpfh_map_build_s"] > 0
    assert [r["scan"] for r in GlobalRows(rows, identity).rows.values()] == [0]

    longer = peers(_Drive(), map_file, cfg, [0, 1], quiet, 600.0, 1e9, GlobalRows(rows, identity))
    assert longer["fpfh_ransac_status"] == "done" and longer["fpfh_ransac_scans_done"] == 2
    assert longer["fpfh_ransac_scans_resumed"] == 1 and longer["fpfh_features_cached"] is True
    assert longer["fpfh_map_build_s"] == first["fpfh_map_build_s"]
    assert longer["fpfh_ransac_rows"][0] == first["fpfh_ransac_rows"][0]  # read back, not run again
    assert [r["scan"] for r in longer["fpfh_ransac_rows"]] == [0, 1]

    started, real = [], city._PeerChild
    monkeypatch.setattr(city, "_PeerChild", lambda *a: started.append(a) or real(*a))
    nothing = peers(_Drive(), map_file, cfg, [1, 0], quiet, 600.0, 1e9, GlobalRows(rows, identity))
    assert started == [] and nothing["fpfh_ransac_status"] == "done"
    assert nothing["fpfh_ransac_scans_resumed"] == 2 and nothing["fpfh_ransac_success"] == longer["fpfh_ransac_success"]
    assert nothing["fpfh_feature_points"] == longer["fpfh_feature_points"]
    assert {p.pid for p in psutil.Process().children(recursive=True)} <= before


def test_a_stopped_bench_city_names_the_fpfh_ransac_registrations_it_keeps(tmp_path):
    from lidarloc.app.bench.city import stopped_line

    GlobalRows(tmp_path / "global", {"a": 1}).add({"scan": 3})
    line = f"stopped: 1 global matches kept in {tmp_path / 'global' / 'rows.json'}"
    assert stopped_line(tmp_path / "global", tmp_path / "fpfh-ransac") == (
        line + "; the same command resumes at the next scan"
    )
    for k in (3, 5):
        GlobalRows(tmp_path / "fpfh-ransac", {"b": 1}).add({"scan": k})
    assert stopped_line(tmp_path / "global", tmp_path / "fpfh-ransac") == (
        f"{line} and 2 FPFH + RANSAC registrations in {tmp_path / 'fpfh-ransac' / 'rows.json'}; "
        "the same command resumes at the next scan"
    )
