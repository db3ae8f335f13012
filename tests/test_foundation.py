"""Foundation: configuration, KITTI readers, prior map, and every bad input named in the issue."""

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from lidarloc.core.config import DEG, Config, load_config
from lidarloc.core.errors import DataError, LidarlocError
from lidarloc.core.geometry import pose_matrix
from lidarloc.core.mapping import VoxelAccumulator, flat_surface_mask, load_or_build_map
from lidarloc.core.config import MapConfig
from lidarloc.core.sequences.kitti_odometry import KittiOdometry

Tr_KITTI = np.array([[4.276802385584e-04, -9.999672484946e-01, -8.084491683471e-03, -1.198459927713e-02],
                     [-7.210626507497e-03, 8.081198471645e-03, -9.999413164504e-01, -5.403984729748e-02],
                     [9.999738645903e-01, 4.859485810390e-04, -7.206933692422e-03, -2.921968648686e-01],
                     [0, 0, 0, 1]])


# ------------------------------------------------------------------------------ configuration
def test_config_defaults_are_the_papers():
    cfg = Config()
    assert cfg.pf.n_particles == 1000 and cfg.pf.scan_voxel == 0.5
    assert cfg.pf.d_max == 5.0 and cfg.pf.sigma == 0.5
    expected_deg = [None, None, None, 5, 2, 0.1, None, 0.05, 0.05, 0.02, None]
    for q, deg in zip(cfg.pf.q_std, expected_deg):
        if deg is not None:
            assert q == pytest.approx(deg * math.pi / 180)
    assert cfg.pf.q_std[:3] == (0.5, 0.5, 0.1) and cfg.pf.q_std[6] == 0.1 and cfg.pf.q_std[10] == 0.001
    assert cfg.pf.init_yaw == pytest.approx(math.pi) and cfg.pf.init_pitch == pytest.approx(30 * DEG)
    assert cfg.s2m.match_resolution == 1.0 and cfg.s2m.angle_step == pytest.approx(2.5 * DEG)
    assert cfg.map.road_normal_z == 0.75
    lc = cfg.localize
    assert (lc.std_threshold, lc.min_consecutive, lc.min_moved, lc.loss_std) == (10.0, 10, 10.0, 50.0)
    assert lc.min_turned == pytest.approx(30 * DEG)


def test_config_yaml_toml_and_overrides(tmp_path):
    y = tmp_path / "c.yaml"
    y.write_text("pf:\n  sigma: 0.7\n  n_particles: 500\ns2m:\n  enabled: false\n")
    cfg = load_config(y, ["pf.d_max=4", "s2m.region_x=30"])
    assert (cfg.pf.sigma, cfg.pf.n_particles, cfg.s2m.enabled, cfg.pf.d_max, cfg.s2m.region_x) == (0.7, 500, False, 4.0, 30.0)
    t = tmp_path / "c.toml"
    t.write_text("[pf]\nsigma = 0.9\n")
    assert load_config(t).pf.sigma == 0.9


@pytest.mark.parametrize("text,needle", [("pf: [1, 2", "unreadable config"), ("pf:\n  sigmaa: 1\n", "unknown key"),
                                         ("pf:\n  sigma: -1\n", "sigma must be > 0"), ("pf:\n  sigma: abc\n", "not a valid")])
def test_config_errors_are_one_line(tmp_path, text, needle):
    y = tmp_path / "bad.yaml"
    y.write_text(text)
    with pytest.raises(LidarlocError) as info:
        load_config(y)
    assert needle in str(info.value) and "\n" not in str(info.value)


# ------------------------------------------------------------------------------ KITTI odometry
def make_odometry(root: Path, n_scans=3, n_poses=None, n_points=500, seq="00"):
    """A tiny KITTI odometry tree; the scans are random points (content does not matter here)."""
    rng = np.random.default_rng(0)
    d = root / "sequences" / seq / "velodyne"
    d.mkdir(parents=True)
    for i in range(n_scans):
        pts = rng.normal(0, 10, (n_points, 4)).astype(np.float32)
        pts.tofile(d / f"{i:06d}.bin")
    P = "P{}: 7.0e+02 0 6.0e+02 0 0 7.0e+02 1.8e+02 0 0 0 1 0"
    lines = [P.format(i) for i in range(4)] + ["Tr: " + " ".join(f"{v:.12e}" for v in Tr_KITTI[:3].ravel())]
    (root / "sequences" / seq / "calib.txt").write_text("\n".join(lines) + "\n")
    (root / "sequences" / seq / "times.txt").write_text("".join(f"{0.1 * i:.6e}\n" for i in range(n_scans)))
    (root / "poses").mkdir()
    n_poses = n_scans if n_poses is None else n_poses
    with open(root / "poses" / f"{seq}.txt", "w") as f:
        for i in range(n_poses):
            T = pose_matrix(i * 1.0, 0.1 * i, 0, 0.01 * i, 0, 0)
            f.write(" ".join(f"{v:.9e}" for v in T[:3].ravel()) + "\n")
    return root


def test_kitti_odometry_reader_converts_cam0_to_lidar(tmp_path):
    make_odometry(tmp_path, n_scans=3)
    seq = KittiOdometry(tmp_path, "00")
    assert len(seq) == 3 and seq.scan(1).dtype == np.float32 and seq.scan(1).shape == (500, 4)
    assert np.allclose(seq.poses[0], np.eye(4))
    cam = [pose_matrix(i * 1.0, 0.1 * i, 0, 0.01 * i, 0, 0) for i in range(3)]
    lidar = [np.linalg.inv(Tr_KITTI) @ c @ Tr_KITTI for c in cam]
    expected = np.linalg.inv(lidar[0]) @ lidar[2]
    assert np.allclose(seq.poses[2], expected, atol=1e-9)
    assert np.allclose(seq.timestamps, [0, 0.1, 0.2])


# ------------------------------------------------------------------------------ bad input, via the CLI
def cli(*args, env_cache):
    env = {"LIDARLOC_CACHE": str(env_cache), "PATH": "/usr/bin:/bin"}
    return subprocess.run([sys.executable, "-m", "lidarloc.app.cli", *args], capture_output=True, text=True,
                          env=env, timeout=300)


def assert_one_line_error(result, *needles):
    assert result.returncode == 2, result.stderr
    lines = [ln for ln in result.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, result.stderr
    assert "Traceback" not in result.stderr
    for needle in needles:
        assert needle in lines[0], lines[0]


def corrupt(root: Path, how: str):
    d = root / "sequences" / "00" / "velodyne"
    if how == "size":
        with open(d / "000001.bin", "ab") as f:
            f.write(b"\0\0\0")
        return "000001.bin", "not a multiple of 16"
    if how == "empty":
        (d / "000001.bin").write_bytes(b"")
        return "000001.bin", "empty scan"
    if how == "nan":
        pts = np.fromfile(d / "000002.bin", dtype=np.float32).reshape(-1, 4)
        pts[5, 1] = np.nan
        pts.tofile(d / "000002.bin")
        return "000002.bin", "NaN"
    raise ValueError(how)


@pytest.mark.parametrize("how", ["size", "empty", "nan"])
def test_bad_scan_files_give_one_line_and_no_half_written_cache(tmp_path, how):
    root = make_odometry(tmp_path / "kitti")
    fname, needle = corrupt(root, how)
    cache = tmp_path / "cache"
    r = cli("map", "build", "--kitti-odometry", str(root), "--sequence", "00", env_cache=cache)
    assert_one_line_error(r, fname, needle)
    # nothing half-written: no map entry, and no temporary directory left behind
    assert not cache.exists() or not any(cache.iterdir())


@pytest.mark.parametrize("n_poses,word", [(5, "more poses"), (2, "fewer poses")])
def test_pose_count_mismatch(tmp_path, n_poses, word):
    root = make_odometry(tmp_path / "kitti", n_scans=3, n_poses=n_poses)
    r = cli("map", "build", "--kitti-odometry", str(root), "--sequence", "00", env_cache=tmp_path / "c")
    assert_one_line_error(r, "00.txt", word)


def test_missing_directory_and_unknown_sequence(tmp_path):
    r = cli("map", "build", "--kitti-odometry", str(tmp_path / "nope"), "--sequence", "00", env_cache=tmp_path / "c")
    assert_one_line_error(r, str(tmp_path / "nope"), "not found")
    root = make_odometry(tmp_path / "kitti")
    r = cli("map", "build", "--kitti-odometry", str(root), "--sequence", "42", env_cache=tmp_path / "c")
    assert_one_line_error(r, "unknown sequence id '42'", "found: 00")
    r = cli("map", "build", "--kitti-raw", str(tmp_path / "nope"), "--date", "2011_09_26", "--drive", "0013",
            env_cache=tmp_path / "c")
    assert_one_line_error(r, "not found")


def test_unreadable_config_via_cli(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("pf: {sigma: [")
    r = cli("map", "build", "--config", str(bad), "--scans", "1", env_cache=tmp_path / "c")
    assert_one_line_error(r, "bad.yaml", "unreadable config")
    r = cli("map", "build", "--set", "pf.sigma=0", "--scans", "1", env_cache=tmp_path / "c")
    assert_one_line_error(r, "sigma must be > 0")


def test_map_build_json_and_cache(tmp_path):
    root = make_odometry(tmp_path / "kitti", n_scans=3, n_points=3000)
    args = ("map", "build", "--kitti-odometry", str(root), "--sequence", "00", "--json")
    first = cli(*args, env_cache=tmp_path / "c")
    assert first.returncode == 0, first.stderr
    a = json.loads(first.stdout)
    assert a["points"] > 0 and 0 < a["points_road_removed"] <= a["points"] and a["cached"] is False
    assert a["peak_rss_mb"] > 0 and a["seconds"] >= 0
    b = json.loads(cli(*args, env_cache=tmp_path / "c").stdout)
    assert b["cached"] is True and b["points"] == a["points"]


# ------------------------------------------------------------------------------ prior map
def test_voxel_accumulator_centroids_and_growth():
    acc = VoxelAccumulator(1.0, capacity=16)   # tiny capacity forces several table growths
    rng = np.random.default_rng(1)
    cells = rng.integers(-50, 50, size=(400, 3))
    pts = np.repeat(cells, 3, axis=0) + rng.uniform(0.01, 0.99, size=(1200, 3))
    acc.add(pts[:600])
    acc.add(pts[600:])
    out = acc.points()
    uniq = np.unique(cells, axis=0)
    assert len(out) == len(uniq)
    # each output point is the centroid of the inputs in its voxel
    keys = np.floor(pts).astype(int)
    for c in uniq[:20]:
        mask = (keys == c).all(axis=1)
        centroid = pts[mask].mean(axis=0)
        assert np.min(np.linalg.norm(out - centroid, axis=1)) < 1e-5


def test_kitti_raw_consecutive_scans_agree(kitti_raw_seq):
    """Consecutive real scans aligned with the OXTS poses agree on non-ground points."""
    seq = kitti_raw_seq
    cfg = MapConfig()
    medians = []
    for i in (0, 30, 60, 90):
        a, b = seq.scan(i)[:, :3].astype(float), seq.scan(i + 1)[:, :3].astype(float)
        a = a[(a[:, 2] > -1.2) & (np.linalg.norm(a, axis=1) < 40)]   # non-ground, near
        b = b[(b[:, 2] > -1.2) & (np.linalg.norm(b, axis=1) < 40)]
        rel = np.linalg.inv(seq.poses[i]) @ seq.poses[i + 1]
        b_in_a = b @ rel[:3, :3].T + rel[:3, 3]
        d, _ = cKDTree(a).query(b_in_a)
        medians.append(np.median(d))
    assert max(medians) < 0.3, medians


def test_road_removal_keeps_walls_drops_road(kitti_raw_seq):
    pts = kitti_raw_seq.scan(10)[:, :3]
    pts = pts[np.linalg.norm(pts, axis=1) < 30]
    flat = flat_surface_mask(pts, MapConfig())
    road = (pts[:, 2] < -1.4) & (np.linalg.norm(pts[:, :2], axis=1) < 12)   # sensor is 1.73 m above the road
    tall = pts[:, 2] > 0.5                                                    # above the car roofs: walls, trees
    assert flat[road].mean() > 0.8, "most road points should be removed"
    assert (~flat[tall]).mean() > 0.7, "most wall/tree points should be kept"


def test_real_map_build_and_cache(kitti_raw_seq, tmp_path):
    from lidarloc.core.sequences.base import Limited

    seq = Limited(kitti_raw_seq, 20)
    m1, d, cached = load_or_build_map(seq, MapConfig(), tmp_path)
    assert not cached and len(m1.points) > 100_000 and len(m1.points_bev) < len(m1.points)
    m2, d2, cached2 = load_or_build_map(seq, MapConfig(), tmp_path)
    assert cached2 and d2 == d and np.array_equal(m1.points, m2.points)
    # one point per 0.2 m voxel (centroids are stored as float32, so a handful that sit on a
    # voxel boundary may round into the neighbouring cell)
    keys = np.floor(m1.points.astype(np.float64) / 0.2).astype(np.int64)
    assert len(np.unique(keys, axis=0)) >= 0.9999 * len(keys)


def test_scan_index_errors(kitti_raw_seq):
    with pytest.raises(IndexError):
        kitti_raw_seq.scan(100)
    with pytest.raises(DataError):
        from lidarloc.core.sequences.base import validate_scan
        validate_scan(np.zeros((0, 4), np.float32), "x.bin")


def test_example_config_is_the_defaults():
    """assets/example-config.yaml says it lists the defaults: it loads, and every value matches."""
    import math
    from pathlib import Path

    from lidarloc.core.config import Config, load_config

    asset = Path(__file__).resolve().parents[1] / "assets" / "example-config.yaml"
    loaded, default = load_config(asset, []).to_dict(), Config().to_dict()
    for section, values in loaded.items():
        if not isinstance(values, dict):
            continue
        for key, value in values.items():
            expected = default[section][key]
            if isinstance(expected, float):
                assert math.isclose(value, expected, rel_tol=1e-6), (section, key)
            else:
                assert value == expected, (section, key)
