"""Recordings made at test time from the real KITTI raw drive (never stored in the project):
ROS 1 / ROS 2 (sqlite3, MCAP) bags of sensor_msgs/PointCloud2, .pcd scan folders and TUM truth.

Test files import the builders and the fixtures they need (``from bagfixtures import …``). The
fixtures use the drive's first :data:`N_SCANS` scans; header stamps are the drive's absolute
times (Unix time, whole nanoseconds), and each message is recorded :data:`RECORD_DELAY_S` later, as a recorder
does, so a reader that took the recorded time for the scan's time would be caught.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

N_SCANS = 20
TOPIC = "/velodyne_points"
FRAME = "velodyne"
RECORD_DELAY_S = 0.031
#: Ouster-like point: x y z, 4 bytes of padding, intensity, t, reflectivity, ring; 48 bytes
OUSTER_DTYPE = np.dtype(
    {
        "names": ["x", "y", "z", "intensity", "t", "reflectivity", "ring"],
        "formats": ["<f4", "<f4", "<f4", "<f4", "<u4", "<u2", "<u2"],
        "offsets": [0, 4, 8, 16, 20, 24, 26],
        "itemsize": 48,
    }
)
TFMESSAGE_DEF = "geometry_msgs/TransformStamped[] transforms\n"


def typestore(ros1: bool):
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    ts.register(get_types_from_msg(TFMESSAGE_DEF, "tf2_msgs/msg/TFMessage"))
    return ts


def absolute_stamps_ns(seq) -> np.ndarray:
    """The drive's scan times as Unix nanoseconds (int64): its first OXTS time + the sequence's
    times, each rounded to the nanosecond, so that differences of stamps are the sequence's
    times exactly (both have microsecond resolution)."""
    t0 = int(round(seq._kitti.timestamps[0].timestamp() * 1e6)) * 1000
    return t0 + np.round(np.asarray(seq.timestamps) * 1e9).astype(np.int64)


def stamp_ns(t) -> int:
    """Nanoseconds from integer nanoseconds or float seconds."""
    return int(t) if isinstance(t, (int, np.integer)) else int(round(t * 1e9))


def seconds_text(t) -> str:
    """``t`` (integer nanoseconds or float seconds) as seconds with 9 decimals, exactly for integers."""
    if isinstance(t, (int, np.integer)):
        t = int(t)
        sign, t = ("-", -t) if t < 0 else ("", t)
        return f"{sign}{t // 10**9}.{t % 10**9:09d}"
    return f"{t:.9f}"


# --------------------------------------------------------------------------------- PointCloud2
def cloud_layout(points: np.ndarray, layout: str, rng) -> dict:
    """The PointCloud2 fields and bytes of ``points`` (N, 4) in one of the layouts:

    - ``xyzi``: dense, 16-byte float32 x, y, z, intensity (what the KITTI driver publishes);
    - ``ouster``: organised 64 × W, 48-byte padded points (OUSTER_DTYPE), a tenth of the cells
      without a return (half NaN, half x = y = z = 0), 16 bytes of padding after each row."""
    if layout == "xyzi":
        data = np.ascontiguousarray(points[:, :4], dtype="<f4")
        fields = [(c, 4 * k, 7, 1) for k, c in enumerate(("x", "y", "z", "intensity"))]
        n = len(points)
        return dict(
            fields=fields,
            point_step=16,
            height=1,
            width=n,
            row_step=16 * n,
            data=data.view(np.uint8).reshape(-1),
            is_dense=True,
        )
    assert layout == "ouster"
    n = len(points)
    n_missing = n // 10
    height = 64
    width = -(-(n + n_missing) // height)
    cells = np.zeros(height * width, dtype=OUSTER_DTYPE)
    valid = np.zeros(height * width, dtype=bool)
    valid[np.sort(rng.choice(n + n_missing, n, replace=False))] = True
    cells["x"][valid], cells["y"][valid], cells["z"][valid] = points[:, 0], points[:, 1], points[:, 2]
    cells["intensity"][valid] = points[:, 3]
    cells["t"] = np.arange(height * width) % width * 48828
    cells["reflectivity"][valid] = (points[:, 3] * 255).astype(np.uint16)
    cells["ring"] = np.repeat(np.arange(height), width)
    missing = np.flatnonzero(~valid)
    nan = missing[rng.random(len(missing)) < 0.5]
    for c in ("x", "y", "z"):
        cells[c][nan] = np.nan  # the others stay 0 (Ouster's "no return")
    row_step = width * 48 + 16
    buf = np.full((height, row_step), 0xAB, dtype=np.uint8)  # padding bytes are garbage, not zeros
    buf[:, : width * 48] = cells.view(np.uint8).reshape(height, width * 48)
    fields = [
        (name, OUSTER_DTYPE.fields[name][1], code, 1)
        for name, code in (("x", 7), ("y", 7), ("z", 7), ("intensity", 7), ("t", 6), ("reflectivity", 4), ("ring", 4))
    ]
    return dict(
        fields=fields,
        point_step=48,
        height=height,
        width=width,
        row_step=row_step,
        data=buf.reshape(-1),
        is_dense=False,
    )


def pointcloud2(ts, points, t, layout: str = "xyzi", rng=None, seq: int = 0, frame: str = FRAME):
    """A sensor_msgs/PointCloud2 of the typestore ``ts`` (ROS 1 headers carry ``seq``)."""
    rng = rng or np.random.default_rng(0)
    lay = cloud_layout(points, layout, rng)
    T = ts.types
    ns = stamp_ns(t)
    stamp = T["builtin_interfaces/msg/Time"](sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
    hdr_fields = T["std_msgs/msg/Header"].__dataclass_fields__
    header = T["std_msgs/msg/Header"](**({"seq": seq} if "seq" in hdr_fields else {}), stamp=stamp, frame_id=frame)
    PF = T["sensor_msgs/msg/PointField"]
    return T["sensor_msgs/msg/PointCloud2"](
        header=header,
        height=lay["height"],
        width=lay["width"],
        fields=[PF(name=n, offset=o, datatype=d, count=c) for n, o, d, c in lay["fields"]],
        is_bigendian=False,
        point_step=lay["point_step"],
        row_step=lay["row_step"],
        data=lay["data"],
        is_dense=lay["is_dense"],
    )


def tf_static_message(ts, t, parent: str, child: str, T_parent_child: np.ndarray):
    from scipy.spatial.transform import Rotation

    T = ts.types
    ns = stamp_ns(t)
    stamp = T["builtin_interfaces/msg/Time"](sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
    hdr_fields = T["std_msgs/msg/Header"].__dataclass_fields__
    header = T["std_msgs/msg/Header"](**({"seq": 0} if "seq" in hdr_fields else {}), stamp=stamp, frame_id=parent)
    q = Rotation.from_matrix(T_parent_child[:3, :3]).as_quat()
    x, y, z = T_parent_child[:3, 3]
    tf = T["geometry_msgs/msg/TransformStamped"](
        header=header,
        child_frame_id=child,
        transform=T["geometry_msgs/msg/Transform"](
            translation=T["geometry_msgs/msg/Vector3"](x=x, y=y, z=z),
            rotation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
        ),
    )
    return T["tf2_msgs/msg/TFMessage"](transforms=[tf])


# --------------------------------------------------------------------------------- bags
def write_bag(
    path: Path,
    kind: str,
    scans,
    times,
    layout: str = "xyzi",
    topic: str = TOPIC,
    extra_topics: dict | None = None,
    tf_static: tuple | None = None,
    record_times=None,
) -> Path:
    """Write ``scans`` (list of (N, 4)) stamped ``times`` (integer ns, or float seconds) as a bag.

    ``kind``: ``ros1`` (``path`` is the .bag file), ``mcap`` or ``sqlite3`` (``path`` is the ROS 2
    bag folder). ``extra_topics``: more topics → msgtype (PointCloud2 or std_msgs/String), one
    message each. ``tf_static``: (parent, child, T_parent_child) published once.
    ``record_times``: the recorder's times (int ns) instead of the stamps + RECORD_DELAY_S."""
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import StoragePlugin
    from rosbags.rosbag2 import Writer as Writer2

    ros1 = kind == "ros1"
    ts = typestore(ros1)
    ser = ts.serialize_ros1 if ros1 else ts.serialize_cdr
    if ros1:
        writer = Writer1(path)
    else:
        plugin = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}[kind]
        writer = Writer2(path, version=9, storage_plugin=plugin)
    rng = np.random.default_rng(7)
    PC2 = "sensor_msgs/msg/PointCloud2"
    with writer:
        conn = writer.add_connection(topic, PC2, typestore=ts)
        t_first = stamp_ns(times[0])
        if tf_static is not None:
            tf_conn = writer.add_connection("/tf_static", "tf2_msgs/msg/TFMessage", typestore=ts)
            msg = tf_static_message(ts, t_first, *tf_static)
            writer.write(tf_conn, stamp_ns(t_first), ser(msg, "tf2_msgs/msg/TFMessage"))
        for name, msgtype in (extra_topics or {}).items():
            c = writer.add_connection(name, msgtype, typestore=ts)
            msg = (
                pointcloud2(ts, scans[0], t_first, "xyzi", rng)
                if msgtype == PC2
                else ts.types["std_msgs/msg/String"](data="not a scan")
            )
            writer.write(c, stamp_ns(t_first), ser(msg, msgtype))
        for i, (pts, t) in enumerate(zip(scans, times)):
            msg = pointcloud2(ts, pts, stamp_ns(t), layout, rng, seq=i)
            recorded = stamp_ns(t) + stamp_ns(RECORD_DELAY_S) if record_times is None else int(record_times[i])
            writer.write(conn, recorded, ser(msg, PC2))
    return path


# --------------------------------------------------------------------------------- folders, truth
def write_pcd_folder(directory: Path, scans, times=None) -> Path:
    """One binary .pcd per scan (x, y, z, intensity float32) named 000000.pcd…, and times.txt."""
    from lidarloc.core.o3d import open3d

    o3d = open3d()
    directory.mkdir(parents=True, exist_ok=True)
    for i, pts in enumerate(scans):
        pc = o3d.t.geometry.PointCloud()
        pc.point.positions = o3d.core.Tensor(np.ascontiguousarray(pts[:, :3], dtype=np.float32))
        pc.point.intensity = o3d.core.Tensor(np.ascontiguousarray(pts[:, 3:4], dtype=np.float32))
        assert o3d.t.io.write_point_cloud(str(directory / f"{i:06d}.pcd"), pc, write_ascii=False)
    if times is not None:
        (directory / "times.txt").write_text("".join(seconds_text(t) + "\n" for t in times))
    return directory


def write_tum(path: Path, times, poses) -> Path:
    """TUM truth with more digits than evo writes, so a comparison tests the reader, not rounding."""
    from scipy.spatial.transform import Rotation

    with open(path, "w") as f:
        f.write("# timestamp tx ty tz qx qy qz qw\n")
        for t, T in zip(times, poses):
            q = Rotation.from_matrix(T[:3, :3]).as_quat()
            f.write(
                f"{seconds_text(t)} {T[0, 3]:.12f} {T[1, 3]:.12f} {T[2, 3]:.12f} "
                f"{q[0]:.15f} {q[1]:.15f} {q[2]:.15f} {q[3]:.15f}\n"
            )
    return path


# --------------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="session")
def kitti_drive(kitti_raw_seq):
    """The drive's first N_SCANS scans, absolute stamps (int ns) and LiDAR poses, read by the KITTI reader."""
    n = min(N_SCANS, len(kitti_raw_seq))
    scans = [kitti_raw_seq.scan(i) for i in range(n)]
    return scans, absolute_stamps_ns(kitti_raw_seq)[:n], np.asarray(kitti_raw_seq.poses[:n])


@pytest.fixture(scope="session")
def kitti_recordings(kitti_drive, tmp_path_factory):
    """The drive written as every recording kind: name → path, plus the truth as TUM."""
    scans, times, poses = kitti_drive
    root = tmp_path_factory.mktemp("recordings")
    out = {
        "mcap": write_bag(root / "drive_mcap", "mcap", scans, times),
        "sqlite3": write_bag(root / "drive_sqlite3", "sqlite3", scans, times),
        "ros1": write_bag(root / "drive.bag", "ros1", scans, times),
        "ouster_mcap": write_bag(root / "drive_ouster", "mcap", scans, times, layout="ouster"),
        "pcd": write_pcd_folder(root / "pcd", scans, times),
        "tum": write_tum(root / "gt.tum", times, poses),
    }
    return out
