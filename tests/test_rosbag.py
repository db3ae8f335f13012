"""Bags as sources: the real KITTI drive written at test time as ROS 1, ROS 2 sqlite3 and ROS 2
MCAP bags (and an Ouster-like organised, padded variant) reads back as the KITTI reader's scans,
times and poses; every bad bag is one line naming the file."""

import pickle
import shutil
import threading

import numpy as np
import pytest
from bagfixtures import FRAME, N_SCANS, TOPIC, write_bag, write_tum
from lidarloc.core.errors import DataError, LidarlocError
from lidarloc.core.geometry import inv_pose, pose_matrix
from lidarloc.core.sequences.base import Limited
from lidarloc.core.sequences.rosbag import BagSequence

KINDS = ["mcap", "sqlite3", "ros1", "ouster_mcap"]


def one_line(exc) -> str:
    text = str(exc.value)
    assert "\n" not in text, text
    return text


@pytest.mark.parametrize("kind", KINDS)
def test_bag_reads_the_kitti_readers_scans_times_and_poses(kind, kitti_drive, kitti_recordings, kitti_raw_seq):
    scans, _, poses = kitti_drive
    seq = BagSequence(kitti_recordings[kind], gt=kitti_recordings["tum"])
    assert len(seq) == len(scans) == N_SCANS
    assert seq.topic == TOPIC and seq.frame_id == FRAME
    for i in range(len(seq)):
        np.testing.assert_array_equal(seq.scan(i), scans[i])  # same points, same order, same bits
    # header stamps, not the recorder's times (written RECORD_DELAY_S later)
    np.testing.assert_array_equal(seq.timestamps, kitti_raw_seq.timestamps[:N_SCANS])
    np.testing.assert_allclose(seq.poses, poses, atol=1e-6)
    assert seq.notes == []


def test_random_access_jumps_and_returns(kitti_drive, kitti_recordings):
    scans = kitti_drive[0]
    for kind in ("mcap", "sqlite3", "ros1"):
        calls = []
        seq = BagSequence(kitti_recordings[kind], progress=lambda i, n: calls.append((i, n)))
        assert calls[0] == (0, N_SCANS) and calls[-1] == (N_SCANS, N_SCANS)
        for i in (7, 3, 4, 5, N_SCANS - 1, 0, 12, 11):
            np.testing.assert_array_equal(seq.scan(i), scans[i], err_msg=f"{kind} scan {i}")
        assert not seq.has_poses


@pytest.mark.parametrize("kind", ["mcap", "sqlite3", "ros1"])
def test_scans_recorded_at_the_same_instant(kind, kitti_drive, tmp_path):
    """A recorder may write several scans with one time: each is still found by its index."""
    scans, stamps = kitti_drive[0][:6], kitti_drive[1][:6]
    recorded = np.repeat(stamps[::2], 2) + 50_000_000  # pairs share a recorded time
    bag = write_bag(tmp_path / ("b.bag" if kind == "ros1" else "b"), kind, scans, stamps, record_times=recorded)
    seq = BagSequence(bag)
    for i in (1, 3, 2, 5, 4, 0, 1):
        np.testing.assert_array_equal(seq.scan(i), scans[i], err_msg=f"{kind} scan {i}")


def test_scans_are_ordered_by_their_header_stamps(kitti_drive, tmp_path):
    scans, stamps = kitti_drive[0][:4], kitti_drive[1][:4]
    recorded = stamps[[1, 0, 3, 2]] + 50_000_000  # the recorder got them out of order
    seq = BagSequence(write_bag(tmp_path / "b", "mcap", scans, stamps, record_times=recorded))
    for i in range(4):
        np.testing.assert_array_equal(seq.scan(i), scans[i])
    assert (np.diff(seq.timestamps) > 0).all() and seq.notes == []


def test_unset_header_stamps_fall_back_to_the_recorders_times(kitti_drive, tmp_path):
    scans, stamps = kitti_drive[0][:4], kitti_drive[1][:4]
    recorded = stamps + 50_000_000
    seq = BagSequence(write_bag(tmp_path / "b.bag", "ros1", scans, np.zeros(4, dtype=np.int64), record_times=recorded))
    np.testing.assert_allclose(seq.timestamps, (stamps - stamps[0]) / 1e9, atol=1e-9)
    np.testing.assert_array_equal(seq.scan(2), scans[2])
    assert len(seq.notes) == 1 and "recorder's times" in seq.notes[0]


def test_bench_bag_reads_every_scan(kitti_raw_dir):
    from lidarloc.app.bench.bag import run
    from lidarloc.core.config import Config
    from lidarloc.core.sequences.factory import SourceSpec

    spec = SourceSpec(kitti_raw=kitti_raw_dir, date="2011_09_26", drive="0013", scans=2)
    result = run(spec, Config(), total=5, repeats=1, random_reads=3)
    assert result["scans"] == 5 and result["storage"] == "mcap"
    assert result["points_per_scan_median"] > 100_000  # the 64-beam scans came through
    assert result["scans_per_s"] > 0 and result["bag_mb"] > 5
    with pytest.raises(LidarlocError):
        run(spec, Config(), storage="rosbag3")


def test_lone_storage_files(kitti_drive, kitti_recordings, tmp_path):
    """A .mcap / .db3 is read through its folder's metadata.yaml when there is one, else alone."""
    scans = kitti_drive[0]
    for kind, suffix in (("mcap", ".mcap"), ("sqlite3", ".db3")):
        inside = next(kitti_recordings[kind].glob(f"*{suffix}"))
        lone = tmp_path / f"copy{suffix}"
        shutil.copy(inside, lone)
        for path in (inside, lone):
            seq = BagSequence(path)
            assert len(seq) == N_SCANS
            np.testing.assert_array_equal(seq.scan(N_SCANS - 2), scans[N_SCANS - 2])


def test_sequence_is_shared_by_threads_and_pickled(kitti_drive, kitti_recordings):
    scans = kitti_drive[0]
    seq = BagSequence(kitti_recordings["mcap"])
    wrong = []

    def read(order):
        for i in order:
            if not np.array_equal(seq.scan(i), scans[i]):
                wrong.append(i)

    threads = [
        threading.Thread(target=read, args=(range(N_SCANS),)),
        threading.Thread(target=read, args=(range(N_SCANS - 1, -1, -1),)),
    ]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert wrong == []
    copy = pickle.loads(pickle.dumps(seq))
    np.testing.assert_array_equal(copy.scan(9), scans[9])
    np.testing.assert_array_equal(copy.timestamps, seq.timestamps)


def test_truth_of_the_base_moves_to_the_lidar(kitti_drive, tmp_path):
    """Truth recorded for base_link: the bag's /tf_static (or --extrinsic) gives base ← LiDAR."""
    scans, times, poses = kitti_drive[0][:5], kitti_drive[1][:5], kitti_drive[2][:5]
    T_base_lidar = pose_matrix(0.81, 0.32, 1.73, 0.02, -0.01, 0.005)
    base_tum = write_tum(tmp_path / "base.tum", times, poses @ inv_pose(T_base_lidar)[None])
    bag = write_bag(tmp_path / "tf.bag", "ros1", scans, times, tf_static=("base_link", FRAME, T_base_lidar))
    seq = BagSequence(bag, gt=base_tum)
    np.testing.assert_allclose(seq.T_base_lidar, T_base_lidar, atol=1e-9)
    np.testing.assert_allclose(seq.poses, poses, atol=1e-6)
    np.testing.assert_allclose(seq.truth_origin, poses[0] @ inv_pose(T_base_lidar) @ T_base_lidar, atol=1e-6)
    assert any("base_link ← velodyne from /tf_static" in n for n in seq.notes)
    # an explicit extrinsic wins over /tf_static
    ext = tmp_path / "identity.txt"
    ext.write_text(" ".join(map(str, np.eye(4).ravel())))
    plain = BagSequence(bag, gt=base_tum, extrinsic=ext)
    base = poses @ inv_pose(T_base_lidar)[None]
    np.testing.assert_allclose(plain.poses, inv_pose(base[0])[None] @ base, atol=1e-6)


def test_scans_outside_the_truth_are_left_out(kitti_drive, kitti_recordings, tmp_path):
    scans, times, poses = kitti_drive
    partial = write_tum(tmp_path / "partial.tum", times[3:15], poses[3:15])
    seq = BagSequence(kitti_recordings["sqlite3"], gt=partial)
    assert len(seq) == 12 and seq.timestamps[0] == 0
    np.testing.assert_array_equal(seq.scan(0), scans[3])
    np.testing.assert_allclose(seq.poses, np.linalg.inv(poses[3])[None] @ poses[3:15], atol=1e-6)
    assert len(seq.notes) == 1 and "8 of 20 scans" in seq.notes[0]
    relative = write_tum(tmp_path / "relative.tum", times - times[0], poses)
    with pytest.raises(DataError) as exc:
        BagSequence(kitti_recordings["sqlite3"], gt=relative)
    assert "do not overlap" in one_line(exc)


# ------------------------------------------------------------------------------- bad input
@pytest.fixture(scope="module")
def small_drive(kitti_drive):
    scans, times, _ = kitti_drive
    return scans[:3], times[:3]


def test_topic_choice(small_drive, tmp_path):
    scans, times = small_drive
    bag = write_bag(
        tmp_path / "two",
        "mcap",
        scans,
        times,
        extra_topics={"/os_cloud_node/points": "sensor_msgs/msg/PointCloud2", "/status": "std_msgs/msg/String"},
    )
    with pytest.raises(DataError) as exc:
        BagSequence(bag)
    text = one_line(exc)
    assert text.startswith(str(bag)) and "--topic" in text and TOPIC in text and "/os_cloud_node/points" in text
    assert len(BagSequence(bag, topic="velodyne_points")) == 3  # the leading slash may be left out
    with pytest.raises(DataError) as exc:
        BagSequence(bag, topic="/points_raw")
    text = one_line(exc)
    assert "no topic /points_raw" in text and TOPIC in text and "/os_cloud_node/points" in text
    with pytest.raises(DataError) as exc:
        BagSequence(bag, topic="/status")
    assert "std_msgs/msg/String, not a sensor_msgs/PointCloud2" in one_line(exc)


def test_bag_without_pointcloud2(tmp_path):
    from bagfixtures import typestore
    from rosbags.rosbag1 import Writer

    only = tmp_path / "strings.bag"
    ts = typestore(True)
    with Writer(only) as w:
        c = w.add_connection("/status", "std_msgs/msg/String", typestore=ts)
        w.write(c, 1, ts.serialize_ros1(ts.types["std_msgs/msg/String"](data="x"), "std_msgs/msg/String"))
    with pytest.raises(DataError) as exc:
        BagSequence(only)
    text = one_line(exc)
    assert (
        text.startswith(str(only))
        and "no sensor_msgs/PointCloud2 topic" in text
        and "/status (std_msgs/msg/String)" in text
    )


def test_cloud_without_xyz(small_drive, tmp_path):
    from bagfixtures import pointcloud2, stamp_ns, typestore
    from rosbags.rosbag2 import StoragePlugin, Writer

    scans, times = small_drive
    ts = typestore(False)
    msg = pointcloud2(ts, scans[0], times[0])
    for f, name in zip(msg.fields, ("u", "v", "w", "intensity")):
        f.name = name
    bag = tmp_path / "noxyz"
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        c = w.add_connection(TOPIC, "sensor_msgs/msg/PointCloud2", typestore=ts)
        w.write(c, stamp_ns(times[0]), ts.serialize_cdr(msg, "sensor_msgs/msg/PointCloud2"))
    with pytest.raises(DataError) as exc:
        BagSequence(bag)
    text = one_line(exc)
    assert "no x/y/z fields" in text and "u, v, w, intensity" in text and text.startswith(str(bag))


@pytest.mark.parametrize("kind", ["ros1", "mcap", "sqlite3"])
def test_truncated_or_corrupt_bags(kind, small_drive, tmp_path):
    scans, times = small_drive
    target = tmp_path / ("b.bag" if kind == "ros1" else "b")
    write_bag(target, kind, scans, times)
    storage = target if kind == "ros1" else next(p for p in target.iterdir() if p.suffix in (".mcap", ".db3"))
    data = storage.read_bytes()
    for label, damaged in (
        ("truncated", data[: len(data) * 2 // 3]),
        ("corrupt", data[:1000] + bytes(len(data) - 2000) + data[-1000:]),
        ("empty", b""),
    ):
        storage.write_bytes(damaged)
        with pytest.raises(DataError) as exc:
            seq = BagSequence(target)
            for i in range(len(seq)):  # damage the index did not see shows on reading
                seq.scan(i)
        text = one_line(exc)
        assert str(target) in text, f"{kind} {label}: {text}"


def test_not_a_bag(tmp_path):
    folder = tmp_path / "folder"
    folder.mkdir()
    (folder / "drive.mcap").write_bytes(b"")
    with pytest.raises(DataError) as exc:
        BagSequence(folder)
    assert "no metadata.yaml" in one_line(exc) and "drive.mcap" in str(exc.value)
    with pytest.raises(DataError) as exc:
        BagSequence(tmp_path / "missing.bag")
    assert "bag not found" in one_line(exc)
    other = tmp_path / "scan.pcd"
    other.write_text("x")
    with pytest.raises(DataError) as exc:
        BagSequence(other)
    assert "not a bag" in one_line(exc)


# ------------------------------------------------------------------------------- replay
class _Drive(Limited):
    """The first scans of a sequence as a drive of its own (mapped from those scans), with the
    KITTI reader's poses: a TUM file cannot carry them bit for bit (KITTI raw's rotations are
    orthonormal only to ~1e-7), and a particle filter amplifies any difference in its map."""

    def __init__(self, inner, n, poses, tag):
        super().__init__(inner, n)
        self._kitti_poses, self._tag = poses, tag

    @property
    def poses(self):
        return self._kitti_poses

    @property
    def map_source(self):
        return self

    def identity(self):
        return f"{self.inner.identity()}|{self._tag}"


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_localizing_from_a_bag_or_a_folder_replays_the_kitti_trajectory(kitti_raw_seq, kitti_recordings, cache_root):
    from helpers import make_localizer
    from lidarloc.core.sequences.scan_folder import ScanFolderSequence

    poses = np.asarray(kitti_raw_seq.poses[:N_SCANS])
    runs = {}
    for name, seq in (
        ("kitti", kitti_raw_seq),
        ("mcap", BagSequence(kitti_recordings["mcap"])),
        ("pcd", ScanFolderSequence(kitti_recordings["pcd"])),
    ):
        with make_localizer(_Drive(seq, N_SCANS, poses, f"replay-{name}"), cache_root) as loc:
            loc.run(N_SCANS)
            runs[name] = [(r.x, r.y, r.z, r.yaw, r.n_eff) for r in loc.records]
    assert len(runs["kitti"]) == N_SCANS
    assert runs["mcap"] == runs["kitti"]
    assert runs["pcd"] == runs["kitti"]


def test_bench_bag_command_line(kitti_raw_dir, tmp_path):
    import json
    import os
    import subprocess
    import sys

    env = {**os.environ, "LIDARLOC_DATA": str(kitti_raw_dir.parent), "LIDARLOC_CACHE": str(tmp_path / "cache")}
    run = subprocess.run(
        [
            sys.executable,
            "-m",
            "lidarloc.app.cli",
            "bench",
            "bag",
            "--total",
            "4",
            "--repeats",
            "1",
            "--scans",
            "2",
            "--storage",
            "ros1",
            "--json",
        ],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )
    assert run.returncode == 0, run.stderr
    result = json.loads(run.stdout)
    assert result["storage"] == "ros1" and result["scans"] == 4 and result["source"].startswith("kitti-raw")
    bad = subprocess.run(
        [sys.executable, "-m", "lidarloc.app.cli", "bench", "bag", "--storage", "rosbag3"],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )
    assert bad.returncode == 2 and bad.stderr.strip().count("\n") == 0 and "--storage" in bad.stderr
