"""A user's own data end to end: a map file (``--map``), a recording (``--bag``, ``--scans-dir``),
ground truth (``--gt``) and an initial guess (``--init``) on the command line and in ``run``.

Everything is made at test time from the real KITTI raw drive (tests/bagfixtures.py): its first
scans as bags and a .pcd folder, its truth as TUM, and its whole-drive map as a .pcd file (also
shifted to UTM-sized coordinates). Localizing from a recording must give the trajectory the KITTI
raw reader gives with the same map file and seed (replay clock)."""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest
from bagfixtures import N_SCANS, write_pcd_folder, write_tum
from helpers import UTM_SHIFT
from lidarloc.core.config import Config
from lidarloc.core.sequences.factory import SourceSpec, open_sequence

PARTICLES = 300


def small_cfg(seed: int = 0) -> Config:
    """300 particles, and the S2M process at the PF's priority: the replay clock waits for every
    match, and a niced S2M beside busy processes gets a sliver of a core (12 town scans: 55 s
    niced against 7 s, load ~15); the priority never changes a replay's result."""
    cfg = Config()
    cfg.pf.n_particles = PARTICLES
    cfg.s2m.replay_process_nice = 0
    cfg.seed = seed
    return cfg


@pytest.fixture(scope="session")
def utm_truth(kitti_drive, tmp_path_factory):
    """The drive's truth shifted like the UTM map."""
    _, times, poses = kitti_drive
    shifted = poses.copy()
    shifted[:, :3, 3] += UTM_SHIFT
    return write_tum(tmp_path_factory.mktemp("utm") / "gt_utm.tum", times, shifted)


def run(spec: SourceSpec, out, cache_root, seed: int = 0) -> dict:
    from lidarloc.app.headless import run_headless

    summary, interrupted = run_headless(spec, small_cfg(seed), out, cache_root=cache_root)
    assert not interrupted
    return summary


@pytest.fixture(scope="session")
def reference(kitti_raw_dir, drive_maps, cache_root, tmp_path_factory):
    """The KITTI raw reader's run over the recordings' scans, in the drive's map file."""
    out = tmp_path_factory.mktemp("reference")
    spec = SourceSpec(kitti_raw=kitti_raw_dir, date="2011_09_26", drive="0013", scans=N_SCANS, map=drive_maps["local"])
    return run(spec, out, cache_root), out


def trajectory(out, name="trajectory_kitti.txt") -> np.ndarray:
    return np.loadtxt(out / name, ndmin=2)


@pytest.mark.slow
# ------------------------------------------------------------------------- same trajectory
@pytest.mark.slow
@pytest.mark.parametrize("kind", ["ros1", "sqlite3", "pcd"])
def test_recordings_localize_like_the_kitti_reader(kind, kitti_recordings, drive_maps, reference, cache_root, tmp_path):
    ref_summary, ref_out = reference
    source = {"scans_dir": kitti_recordings["pcd"]} if kind == "pcd" else {"bag": kitti_recordings[kind]}
    spec = SourceSpec(**source, gt=kitti_recordings["tum"], map=drive_maps["local"])
    summary = run(spec, tmp_path, cache_root)
    assert summary["scans"] == N_SCANS
    np.testing.assert_allclose(trajectory(tmp_path), trajectory(ref_out), atol=1e-6)
    np.testing.assert_allclose(
        trajectory(tmp_path, "groundtruth_kitti.txt"), trajectory(ref_out, "groundtruth_kitti.txt"), atol=1e-5
    )
    assert summary["localized_at_scan"] == ref_summary["localized_at_scan"]
    assert summary["rmse_after_localized_m"] == pytest.approx(ref_summary["rmse_after_localized_m"], abs=1e-6)


@pytest.mark.slow
def test_lidarloc_run_from_an_mcap_bag(kitti_recordings, drive_maps, reference, cache_root, tmp_path):
    """The command line as a user types it: ``lidarloc run --bag … --map … --gt …``."""
    import subprocess

    ref_summary, ref_out = reference
    out = tmp_path / "run"
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "lidarloc.app.cli",
            "run",
            "--bag",
            str(kitti_recordings["mcap"]),
            "--map",
            str(drive_maps["local"]),
            "--gt",
            str(kitti_recordings["tum"]),
            "--out",
            str(out),
            "--set",
            f"pf.n_particles={PARTICLES}",
            "--set",
            "s2m.replay_process_nice=0",
            "--cache",
            str(cache_root),
            "--json",
        ],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout)
    assert summary["scans"] == N_SCANS and summary["frame_mismatch"] == []
    np.testing.assert_allclose(trajectory(out), trajectory(ref_out), atol=1e-6)
    assert summary["rmse_after_localized_m"] == pytest.approx(ref_summary["rmse_after_localized_m"], abs=1e-6)


@pytest.mark.slow
def test_a_utm_map_localizes_with_the_same_error_and_utm_results(
    kitti_recordings, drive_maps, utm_truth, reference, cache_root, tmp_path
):
    ref_summary, ref_out = reference
    spec = SourceSpec(bag=kitti_recordings["mcap"], gt=utm_truth, map=drive_maps["utm"])
    summary = run(spec, tmp_path, cache_root)
    origin = np.array(summary["map_origin_m"])
    assert np.abs(origin[:2]).min() > 1e5  # the localizer worked in a local frame
    assert summary["localized_at_scan"] is not None
    # the local frame is the file's minus a rounded origin: float32 map points land on other
    # roundings and lookup cells than in the drive's frame, so the run differs a little
    assert summary["rmse_after_localized_m"] == pytest.approx(ref_summary["rmse_after_localized_m"], abs=0.1)
    tum, ref_tum = trajectory(tmp_path, "trajectory_tum.txt"), trajectory(ref_out, "trajectory_tum.txt")
    assert (tum[:, 1] > 4.9e5).all() and (tum[:, 2] > 3.9e6).all()
    np.testing.assert_allclose(tum[:, 1:4] - UTM_SHIFT, ref_tum[:, 1:4], atol=0.5)
    kitti = trajectory(tmp_path)
    np.testing.assert_allclose(kitti[:, [3, 7, 11]], tum[:, 1:4], atol=1e-5)  # full precision in both
    # the truth goes back out in the map's frame at full precision
    gt = trajectory(tmp_path, "groundtruth_tum.txt")
    np.testing.assert_allclose(gt[:, 1:4] - UTM_SHIFT, trajectory(ref_out, "groundtruth_tum.txt")[:, 1:4], atol=1e-5)


@pytest.mark.slow
def test_without_truth_run_writes_no_errors(kitti_recordings, drive_maps, reference, cache_root, tmp_path):
    spec = SourceSpec(bag=kitti_recordings["mcap"], map=drive_maps["local"])
    summary = run(spec, tmp_path, cache_root)
    assert summary["scans"] == N_SCANS
    assert summary["rmse_after_localized_m"] is None and summary["final_error_m"] is None
    assert not list(tmp_path.glob("groundtruth_*"))
    np.testing.assert_allclose(trajectory(tmp_path), trajectory(reference[1]), atol=1e-6)
    with open(tmp_path / "scans.csv") as f:
        header = f.readline().strip().split(",")
        col = header.index("error_m")
        assert all(line.strip().split(",")[col] == "" for line in f)


# ------------------------------------------------------------------------------ --init
@pytest.mark.slow
@pytest.mark.parametrize("frame", ["local", "utm"])
def test_init_starts_the_particles_around_the_given_pose(
    frame, kitti_recordings, kitti_drive, utm_truth, drive_maps, cache_root
):
    from lidarloc.core.localizer import Localizer

    pose = kitti_drive[2][0]
    x, y = pose[:2, 3] + (1.0, -0.5)  # a guess a metre or so off, in the map's frame
    if frame == "utm":
        x, y = x + UTM_SHIFT[0], y + UTM_SHIFT[1]
    yaw_deg = np.degrees(np.arctan2(pose[1, 0], pose[0, 0])) + 3.0
    gt = kitti_recordings["tum"] if frame == "local" else utm_truth
    spec = SourceSpec(bag=kitti_recordings["mcap"], gt=gt, map=drive_maps[frame], init=f"{x},{y},{yaw_deg},1.5,4")
    seq = open_sequence(spec, small_cfg())
    with Localizer(seq, small_cfg(), cache_root) as loc:
        origin = loc.prior_map.origin
        states = loc.pf.states
        assert np.linalg.norm(states[:, :2].mean(axis=0) - (np.array([x, y]) - origin[:2])) < 0.3
        assert 1.2 < states[:, 0].std() < 1.8 and 1.2 < states[:, 1].std() < 1.8
        yaw_err = np.degrees(np.angle(np.exp(1j * (states[:, 3] - np.radians(yaw_deg)))))
        assert abs(np.mean(yaw_err)) < 1.0 and 3.0 < np.std(yaw_err) < 5.0
        # the height is the ground's under the guess plus the sensor's: the truth's, within the spread
        assert abs(np.median(states[:, 2]) - seq.pose(0)[2, 3]) < 1.0
        assert [e.kind for e in loc.events] == ["initial_guess"]
        snap = loc.run(N_SCANS)
        assert snap.error_m is not None and snap.error_m < 1.5
        loc.restart()  # every start is around the guess
        assert np.linalg.norm(loc.pf.states[:, :2].mean(axis=0) - (np.array([x, y]) - origin[:2])) < 0.3


# ----------------------------------------------------------------------------- bad input
def lidarloc(capsys, monkeypatch, *args) -> tuple[int, str]:
    """``lidarloc ARGS`` in this process: (exit status, stderr)."""
    from lidarloc.app.cli import main

    monkeypatch.setattr(sys, "argv", ["lidarloc", *map(str, args)])
    with pytest.raises(SystemExit) as exit_:
        main()
    return exit_.value.code, capsys.readouterr().err


def test_bad_combinations_are_one_line_each(kitti_recordings, drive_maps, cache_root, capsys, monkeypatch, tmp_path):
    bag, tum, pcd = kitti_recordings["mcap"], kitti_recordings["tum"], kitti_recordings["pcd"]
    out = tmp_path / "out"
    cases = [
        (["run", "--topic", "/velodyne_points"], "--topic names a PointCloud2 topic of --bag"),
        (["run", "--gt", tum], "--gt applies to a recording"),
        (["run", "--extrinsic", tum], "--extrinsic applies to a recording"),
        (["run", "--bag", bag], "a prior map needs --map FILE or ground truth (--gt) to fuse the scans"),
        (["inspect", "--scan", 1, "--scans-dir", pcd], "a prior map needs --map FILE or ground truth (--gt)"),
        (["run", "--bag", bag, "--scans-dir", pcd, "--gt", tum], "choose one source: --bag or --scans-dir"),
        (["run", "--bag", bag, "--gt-times", tum, "--map", drive_maps["local"]], "--gt-times"),
        (["run", "--bag", bag, "--map", tmp_path / "nope.pcd"], "no such map file"),
        (["run", "--bag", bag, "--map", tum], "cannot read a map of this type"),
        (["run", "--bag", bag, "--gt", tum, "--init", "1,2"], "--init takes x,y,yaw"),
        (["run", "--bag", bag, "--gt", tum, "--init", "1,2,3,0,5"], "σ_xy and σ_yaw must be > 0"),
        (
            ["run", "--bag", bag, "--map", drive_maps["local"], "--init", "5000,5000,0", "--cache", cache_root],
            "no map point within",
        ),
        (
            ["map", "build", "--bag", bag, "--map", drive_maps["local"], "--out", tmp_path / "m.pcd"],
            "no ground-truth poses",
        ),
    ]
    for args, needle in cases:
        if args[0] in ("run", "inspect"):
            args = args + ["--out", out]
        code, err = lidarloc(capsys, monkeypatch, *args)
        lines = [ln for ln in err.splitlines() if ln.strip()]
        assert code == 2 and len(lines) == 1 and needle in lines[0], (args, err)
    assert not (tmp_path / "m.pcd").exists()


# ------------------------------------------------------------------------------ map build
def test_map_build_writes_a_map_file_and_its_road_removed_layer(
    kitti_recordings, cache_root, capsys, monkeypatch, tmp_path
):
    from lidarloc.core.maps.mapfile import read_map

    out = tmp_path / "built.pcd"
    code, err = lidarloc(
        capsys,
        monkeypatch,
        "map",
        "build",
        "--bag",
        kitti_recordings["ros1"],
        "--gt",
        kitti_recordings["tum"],
        "--out",
        out,
        "--cache",
        cache_root,
    )
    assert code in (0, None), err
    both = read_map(out).points
    road_removed = read_map(tmp_path / "built_road_removed.pcd").points
    assert 10_000 < len(road_removed) < len(both)
    # fused in the truth's frame: the first scan's points lie around the first pose (the origin)
    assert np.linalg.norm(np.median(both[:, :2], axis=0)) < 200
    # the file is a map source like any other: the scan folder localizes in it
    seq = open_sequence(SourceSpec(scans_dir=kitti_recordings["pcd"], map=out), small_cfg())
    assert len(seq) == N_SCANS and seq.map_source.path == out.resolve()


# ------------------------------------------------------------------------------ frames
@pytest.mark.slow
def test_scans_in_another_frame_are_reported(kitti_drive, drive_maps, cache_root, tmp_path, capsys):
    """Scans in millimetres: no scan point comes near the map at any particle."""
    from lidarloc.app.headless import run_headless

    scans, times, _ = kitti_drive
    folder = write_pcd_folder(tmp_path / "mm", [np.c_[s[:, :3] * 1000.0, s[:, 3:]] for s in scans[:12]], times[:12])
    cfg = small_cfg()
    cfg.s2m.enabled = False
    summary, _ = run_headless(
        SourceSpec(scans_dir=folder, map=drive_maps["local"]), cfg, tmp_path / "out", cache_root=cache_root
    )
    assert len(summary["frame_mismatch"]) == 1 and "different frames" in summary["frame_mismatch"][0]
    assert "warning: over the first 10 scans" in capsys.readouterr().err


def test_truth_outside_the_map_is_reported(kitti_recordings, drive_maps, cache_root):
    """Truth in the drive's frame with the UTM map: the first pose is kilometres outside it."""
    from lidarloc.core.localizer import Localizer

    spec = SourceSpec(bag=kitti_recordings["mcap"], gt=kitti_recordings["tum"], map=drive_maps["utm"])
    with Localizer(open_sequence(spec, small_cfg()), small_cfg(), cache_root) as loc:
        mismatch = [e for e in loc.events if e.kind == "frame_mismatch"]
        assert len(mismatch) == 1 and "outside the map" in mismatch[0].detail


# ------------------------------------------------------------------------------ 16 beams
def kitti_rings(points: np.ndarray) -> np.ndarray:
    """Each point's ring (laser) in a KITTI raw scan, top laser first.

    KITTI raw has no ring field, but its .bin files hold one laser's sweep after the other, each
    turning counter-clockwise from the rear (a file starts mid-sweep, at the cut the recording
    made): a point's ring is the number of times the azimuth wrapped from +180° to −180° before it.
    The elevation angle checks the derivation (the test asserts that the rings' median elevations
    fall from the top laser to the bottom one)."""
    azimuth = np.arctan2(points[:, 1], points[:, 0])
    return np.concatenate([[0], np.cumsum(np.diff(azimuth) < -np.pi)])


@pytest.mark.slow
def test_a_16_beam_lidar_localizes_on_the_real_drive(kitti_raw_seq, kitti_drive, drive_maps, cache_root, tmp_path):
    """Every 4th ring of the HDL-64E's scans (a VLP-16-like sensor) over the whole drive, in the
    64-beam drive's map file: it localizes as the full scans do (BENCHMARKS.md has the numbers)."""
    from bagfixtures import absolute_stamps_ns

    scans = [kitti_raw_seq.scan(i) for i in range(len(kitti_raw_seq))]
    rings = kitti_rings(scans[0])
    elevation = np.arctan2(scans[0][:, 2], np.hypot(scans[0][:, 0], scans[0][:, 1]))
    medians = np.array([np.median(elevation[rings == r]) for r in range(rings.max() + 1)])
    assert 64 <= len(medians) <= 65 and (np.diff(medians) < 0).mean() > 0.95
    thinned = [s[kitti_rings(s) % 4 == 0] for s in scans]
    assert 0.2 < len(thinned[0]) / len(scans[0]) < 0.3
    stamps = absolute_stamps_ns(kitti_raw_seq)
    folder = write_pcd_folder(tmp_path / "vlp16", thinned, stamps)
    gt = write_tum(tmp_path / "gt.tum", stamps, np.asarray(kitti_raw_seq.poses))
    summary = run(SourceSpec(scans_dir=folder, gt=gt, map=drive_maps["local"]), tmp_path / "out", cache_root)
    assert summary["scans"] == len(scans)
    assert summary["localized_at_scan"] is not None and summary["localized_at_scan"] < 30
    assert summary["rmse_after_localized_m"] < 0.5 and summary["false_positives"] == 0


def test_kitti_format_truth_with_its_times_file(kitti_recordings, kitti_drive, drive_maps, tmp_path):
    """``--gt poses.txt --gt-times times.txt`` gives the scans the poses TUM truth gives them."""
    from bagfixtures import seconds_text

    _, times, poses = kitti_drive
    np.savetxt(tmp_path / "poses.txt", poses[:, :3, :4].reshape(len(poses), 12), fmt="%.15e")
    (tmp_path / "times.txt").write_text("".join(seconds_text(t) + "\n" for t in times))
    kitti = open_sequence(
        SourceSpec(
            bag=kitti_recordings["mcap"],
            gt=tmp_path / "poses.txt",
            gt_times=tmp_path / "times.txt",
            map=drive_maps["local"],
        )
    )
    tum = open_sequence(SourceSpec(bag=kitti_recordings["mcap"], gt=kitti_recordings["tum"], map=drive_maps["local"]))
    kitti.use_map_origin(np.zeros(3))
    tum.use_map_origin(np.zeros(3))
    # a KITTI times file in Unix seconds holds ~0.2 µs steps as float64: micrometres of pose
    np.testing.assert_allclose(kitti.poses, tum.poses, atol=1e-5)
    np.testing.assert_allclose(kitti.poses, poses, atol=1e-5)
