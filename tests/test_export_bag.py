"""A run as a ROS 2 MCAP bag of standard messages (``export --bag``, ``run --write-bag``), read
back with rosbags and with the mcap reader: topics, types, message counts, stamps equal to the
scans', poses equal to trajectory_tum.txt, the map latched; bad names and missing runs are one
line and exit 2."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest
from helpers import cli_here, run_cli
from lidarloc.app.export_bag import (
    DIAGNOSTICS,
    MAP,
    PARTICLE_CLOUD,
    PARTICLES,
    POSE,
    ROSOUT,
    SCAN,
    TF,
    TOPICS,
    TRUTH,
    export_bag,
)
from lidarloc.core.runs import recording
from rich.console import Console
from scipy.spatial.transform import Rotation

QUIET = Console(file=io.StringIO())


def assert_one_line_error(result, *needles):
    assert result.returncode == 2, result.stderr
    lines = [ln for ln in result.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in result.stderr, result.stderr
    for needle in needles:
        assert needle in lines[0], lines[0]


def read_bag(path: Path) -> dict[str, list]:
    """topic → [(recorded time, message)] through rosbags' AnyReader (what the project's own
    reader uses)."""
    from rosbags.highlevel import AnyReader

    out: dict[str, list] = {}
    with AnyReader([path]) as reader:
        for conn, t, raw in reader.messages():
            out.setdefault(conn.topic, []).append((t, reader.deserialize(raw, conn.msgtype)))
        types = {c.topic: c.msgtype for c in reader.connections}
    return out | {"__types__": types}


def stamp(header) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def assert_same_rotation(q_ros, q_file) -> None:
    """Quaternions up to sign."""
    a = np.array([q_ros.x, q_ros.y, q_ros.z, q_ros.w])
    assert min(np.abs(a - q_file).max(), np.abs(a + q_file).max()) < 2e-6


@pytest.fixture(scope="module")
def bag(recorded_town_run, cache_root, tmp_path_factory):
    run, _ = recorded_town_run
    out = tmp_path_factory.mktemp("bag") / "run.mcap"
    return run, out, export_bag(run, out, console=QUIET, cache_root=cache_root)


def test_the_bag_holds_every_topic_with_one_message_per_step(bag):
    run, out, result = bag
    rec = recording.open(run)
    assert out.is_file() and result["bag"] == str(out) and result["steps"] == rec.n
    assert not list(out.parent.glob(".*writing*"))  # no half-written folder left behind
    msgs = read_bag(out)
    types = msgs.pop("__types__")
    assert types == {t: TOPICS[t] for t in (POSE, TF, PARTICLES, PARTICLE_CLOUD, TRUTH, SCAN, MAP, ROSOUT, DIAGNOSTICS)}
    for topic in (POSE, TF, PARTICLES, PARTICLE_CLOUD, TRUTH, SCAN, DIAGNOSTICS):
        assert len(msgs[topic]) == rec.n, topic
    assert len(msgs[MAP]) == 1 and msgs[MAP][0][1].width == result["map_points"] > 1000
    assert len(msgs[ROSOUT]) == len(rec.events) > 0
    assert {m.function for _, m in msgs[ROSOUT]} == {ev.kind for _, ev in rec.events}


def test_stamps_and_poses_equal_the_trajectory_file(bag):
    run, out, _ = bag
    rec = recording.open(run)
    tum = np.loadtxt(run / "trajectory_tum.txt")
    gt = np.loadtxt(run / "groundtruth_tum.txt")
    msgs = read_bag(out)
    poses = msgs[POSE]
    expected_ns = np.round(tum[:, 0] * 1e9).astype(np.int64)
    assert len(gt) == len(tum)
    for (t, m), row in zip(poses, tum):
        # the scans' stamps (this source's times), as the message's stamp and its recorded time
        assert abs(stamp(m.header) - round(row[0] * 1e9)) <= 1000 and t == stamp(m.header)
        assert m.header.frame_id == "map"
        p = m.pose.pose.position
        assert np.allclose([p.x, p.y, p.z], row[1:4], atol=2e-6)
        assert_same_rotation(m.pose.pose.orientation, row[4:8])
        cov = np.asarray(m.pose.covariance).reshape(6, 6)
        assert np.allclose(cov, cov.T) and (np.diag(cov) >= 0).all()
    # the position block of the covariance is the filter's own (the recording's cov_xyz)
    for (_, m), cov_xyz in zip(poses, rec.cov_xyz):
        assert np.allclose(np.asarray(m.pose.covariance).reshape(6, 6)[:3, :3], cov_xyz, rtol=1e-9, atol=1e-12)
    for (_, m), truth in zip(msgs[TRUTH], gt):
        assert np.allclose([m.pose.position.x, m.pose.position.y, m.pose.position.z], truth[1:4], atol=2e-6)
    # /tf: map → lidar is the estimate, map → lidar_truth the truth; the scan in the lidar frame
    for (_, m), row in zip(msgs[TF], tum):
        by_child = {tf.child_frame_id: tf for tf in m.transforms}
        assert set(by_child) == {"lidar", "lidar_truth"} and by_child["lidar"].header.frame_id == "map"
        tr = by_child["lidar"].transform.translation
        assert np.allclose([tr.x, tr.y, tr.z], row[1:4], atol=2e-6)
    scans = [m for _, m in msgs[SCAN]]
    assert [stamp(m.header) for m in scans] == [stamp(m.header) for _, m in poses]
    assert all(m.header.frame_id == "lidar" and m.width > 500 for m in scans)
    assert np.abs(np.array([stamp(m.header) for _, m in poses]) - expected_ns).max() <= 1000


def test_particles_carry_the_recorded_states_and_weights(bag):
    run, out, _ = bag
    rec = recording.open(run)
    msgs = read_bag(out)
    i = rec.n - 1
    parts = rec.particles(i)
    pa = msgs[PARTICLES][i][1]
    assert len(pa.poses) == len(parts)
    xyz = np.array([[p.position.x, p.position.y, p.position.z] for p in pa.poses])
    assert np.allclose(xyz, parts[:, :3], atol=1e-4)
    yaw = Rotation.from_quat(
        [[p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w] for p in pa.poses]
    ).as_euler("ZYX")[:, 0]
    assert np.allclose(np.angle(np.exp(1j * (yaw - parts[:, 3]))), 0, atol=1e-5)
    cloud = msgs[PARTICLE_CLOUD][i][1]
    assert [f.name for f in cloud.fields] == ["x", "y", "z", "weight"]
    data = np.frombuffer(bytes(cloud.data), np.float32).reshape(-1, 4)
    assert np.allclose(data[:, 3], rec.weights(i), rtol=1e-5, atol=1e-9)


def test_the_mcap_reader_sees_the_same_bag_and_the_map_is_latched(bag):
    from mcap.reader import make_reader

    run, out, result = bag
    with open(out, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        channels = {c.id: c for c in summary.channels.values()}
        counts = {channels[cid].topic: n for cid, n in summary.statistics.channel_message_counts.items()}
        assert counts == result["messages"]
        schemas = {s.name: s.encoding for s in summary.schemas.values()}
        assert set(schemas) == set(TOPICS.values())
        assert set(schemas.values()) <= {"ros2msg", "ros2idl"}
        latched = {
            c.topic
            for c in channels.values()
            if "durability: 1" in c.metadata.get("offered_qos_profiles", "")
            or "transient_local" in c.metadata.get("offered_qos_profiles", "")
        }
        assert latched == {MAP}
        times = [m.log_time for _, c, m in reader.iter_messages(topics=[POSE])]
    tum = np.loadtxt(run / "trajectory_tum.txt")
    assert np.abs(np.array(times) - np.round(tum[:, 0] * 1e9)).max() <= 1000


def cli(*args, env_cache):
    return run_cli(*args, cache=env_cache)


def test_bad_names_and_missing_runs_are_one_line(recorded_town_run, tmp_path, cache_root):
    run, _ = recorded_town_run
    assert_one_line_error(
        run_cli("export", str(tmp_path / "nothing"), "--bag", str(tmp_path / "x.mcap"), cache=cache_root),
        "no such run folder",
    )

    def cli(*args, env_cache):  # the other refusals by the entry point in this process
        return cli_here(*args, cache=env_cache)

    assert_one_line_error(cli("export", str(run), "--bag", str(tmp_path / "x.db3"), env_cache=cache_root), ".mcap")
    (tmp_path / "there.mcap").write_bytes(b"")
    assert_one_line_error(
        cli("export", str(run), "--bag", str(tmp_path / "there.mcap"), env_cache=cache_root), "already exists"
    )
    assert_one_line_error(cli("export", str(run), "--bag", "/proc/nope/x.mcap", env_cache=cache_root), "cannot create")
    assert_one_line_error(
        cli("export", str(run), "--bag", str(tmp_path / "y.mcap"), "--with-input", env_cache=cache_root), "--with-input"
    )
    assert_one_line_error(
        cli(
            "run",
            "--out",
            str(tmp_path / "r"),
            "--no-record",
            "--write-bag",
            str(tmp_path / "r.mcap"),
            env_cache=cache_root,
        ),
        "--no-record",
    )
    assert_one_line_error(
        cli(
            "run",
            "--out",
            str(tmp_path / "r"),
            "--write-bag",
            str(tmp_path / "r.mcap"),
            "--with-input",
            env_cache=cache_root,
        ),
        "--bag",
    )


@pytest.mark.slow
def test_a_run_on_a_bag_writes_its_bag_with_the_scans_stamps_and_the_input_beside(tmp_path, cache_root):
    """``run --bag IN --write-bag OUT.mcap --with-input``: stamps are the input's header stamps
    (absolute), and the input's scans are copied in beside the results."""
    from bagfixtures import TOPIC, write_bag, write_tum
    from helpers import short_town

    seq = short_town(12)
    scans = [seq.scan(i) for i in range(len(seq))]
    stamps = 1_700_000_000_000_000_000 + np.round(np.asarray(seq.timestamps) * 1e9).astype(np.int64)
    bag_in = write_bag(tmp_path / "drive", "mcap", scans, stamps)
    gt = write_tum(tmp_path / "gt.tum", stamps, np.asarray(seq.poses))
    out = tmp_path / "out"
    # the world is the truth's first LiDAR pose: start around it
    r = cli(
        "run",
        "--bag",
        str(bag_in),
        "--gt",
        str(gt),
        "--out",
        str(out),
        "--set",
        "pf.n_particles=300",
        "--init",
        "0,0,0",
        "--write-bag",
        str(tmp_path / "results.mcap"),
        "--with-input",
        env_cache=cache_root,
    )
    assert r.returncode == 0, r.stderr[-2000:]
    msgs = read_bag(tmp_path / "results.mcap")
    types = msgs.pop("__types__")
    assert types[TOPIC] == "sensor_msgs/msg/PointCloud2" and len(msgs[TOPIC]) == len(scans)
    assert [stamp(m.header) for _, m in msgs[POSE]] == stamps.tolist()
    assert [stamp(m.header) for _, m in msgs[SCAN]] == [stamp(m.header) for _, m in msgs[TOPIC]]
    tum = np.loadtxt(out / "trajectory_tum.txt")
    for (_, m), row in zip(msgs[POSE], tum):
        p = m.pose.pose.position
        assert np.allclose([p.x, p.y, p.z], row[1:4], atol=2e-6)
