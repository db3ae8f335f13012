"""``lidarloc bench bag``: how fast scans come out of a bag (index + decode).

The bag is written at benchmark time (the real data is not shipped, and a bag of it would be a
copy): the source's scans (default: the real KITTI drive's 64-beam HDL-64E scans, ~120 k points,
1.9 MB each) as sensor_msgs/PointCloud2 (x, y, z, intensity float32, what the Velodyne driver
publishes), repeated until there are ``total`` of them, stamped at 10 Hz, in ROS 2 MCAP by
default (``--storage sqlite3|ros1`` for the others). Then :class:`BagSequence` opens it (the
index pass over the topic) and reads every scan in order, ``repeats`` times; the figure is scans
per second including the index pass, against the target of 200 scans/s (20× the sensor's rate,
so that reading never limits a replay). A second figure times jumps to random scans (a kidnap,
a seek in the viewer).

The bag has just been written, so it is read from the page cache: the figures measure rosbags'
reading and our decoding, not the disk (a cold read of a 64-beam bag is bounded by the disk at
1.9 MB per scan).
"""

from __future__ import annotations

import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from ...core.config import Config
from ...core.errors import LidarlocError
from ...core.sequences.factory import SourceSpec
from .common import load_avg, open_source

TARGET_SCANS_PER_S = 200.0
STORAGES = ("mcap", "sqlite3", "ros1")
TOPIC = "/velodyne_points"
T0_NS = 1_700_000_000 * 10**9  # an arbitrary Unix time for the header stamps


def _cloud(ts, points: np.ndarray, stamp_ns: int, seq: int):
    T = ts.types
    hdr = T["std_msgs/msg/Header"]
    stamp = T["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9)
    header = hdr(**({"seq": seq} if "seq" in hdr.__dataclass_fields__ else {}), stamp=stamp, frame_id="velodyne")
    PF = T["sensor_msgs/msg/PointField"]
    data = np.ascontiguousarray(points[:, :4], dtype="<f4")
    return T["sensor_msgs/msg/PointCloud2"](
        header=header,
        height=1,
        width=len(data),
        fields=[PF(name=n, offset=4 * k, datatype=7, count=1) for k, n in enumerate(("x", "y", "z", "intensity"))],
        is_bigendian=False,
        point_step=16,
        row_step=16 * len(data),
        data=data.view(np.uint8).reshape(-1),
        is_dense=True,
    )


def write_bag(path: Path, seq, total: int, storage: str) -> Path:
    """``total`` scans of ``seq`` (cycling through it) as a PointCloud2 bag at ``path``."""
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import StoragePlugin
    from rosbags.rosbag2 import Writer as Writer2
    from rosbags.typesys import Stores, get_typestore

    ros1 = storage == "ros1"
    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    serialize = ts.serialize_ros1 if ros1 else ts.serialize_cdr
    if ros1:
        writer = Writer1(path)
    else:
        writer = Writer2(
            path, version=9, storage_plugin=StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
        )
    msgtype = "sensor_msgs/msg/PointCloud2"
    with writer:
        conn = writer.add_connection(TOPIC, msgtype, typestore=ts)
        for i in range(total):
            stamp = T0_NS + i * 100_000_000
            writer.write(conn, stamp, serialize(_cloud(ts, seq.scan(i % len(seq)), stamp, i), msgtype))
    return path


def _size_bytes(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file()) if path.is_dir() else path.stat().st_size


def run(
    spec: SourceSpec,
    cfg: Config,
    total: int = 300,
    storage: str = "mcap",
    repeats: int = 3,
    random_reads: int = 30,
    workdir: Path | None = None,
) -> dict:
    from ...core.sequences.rosbag import BagSequence

    if storage not in STORAGES:
        raise LidarlocError(f"--storage must be one of {', '.join(STORAGES)}; got {storage!r}")
    if total < 1 or repeats < 1:
        raise LidarlocError("--total and --repeats must be ≥ 1")
    seq = open_source(spec, cfg, "bag")
    tmp = Path(tempfile.mkdtemp(prefix="lidarloc-bench-bag-", dir=workdir))
    try:
        path = tmp / ("drive.bag" if storage == "ros1" else "drive")
        t0 = time.perf_counter()
        write_bag(path, seq, total, storage)
        write_s = time.perf_counter() - t0
        load_before = load_avg()
        index_s, read_s, points = [], [], []
        for _ in range(repeats):
            t0 = time.perf_counter()
            bag = BagSequence(path)
            t1 = time.perf_counter()
            for i in range(len(bag)):
                points.append(len(bag.scan(i)))
            t2 = time.perf_counter()
            index_s.append(t1 - t0)
            read_s.append(t2 - t1)
            bag.close()
        rng = np.random.default_rng(0)
        bag = BagSequence(path)
        jumps = []
        for i in rng.integers(0, len(bag), random_reads):
            t0 = time.perf_counter()
            bag.scan(int(i))
            jumps.append(time.perf_counter() - t0)
        bag.close()
        size = _size_bytes(path)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    total_s = float(np.median(np.add(index_s, read_s)))
    scans_per_s = total / total_s
    return {
        "storage": storage,
        "source": seq.name,
        "scans": total,
        "points_per_scan_median": int(np.median(points)),
        "bag_mb": round(size / 1e6, 1),
        "write_s": round(write_s, 2),
        "index_s_median": round(float(np.median(index_s)), 3),
        "read_s_median": round(float(np.median(read_s)), 3),
        "scans_per_s": round(scans_per_s, 1),
        "scans_per_s_read_only": round(total / float(np.median(read_s)), 1),
        "mb_per_s": round(size / 1e6 / total_s, 1),
        "random_scan_ms_median": round(1e3 * float(np.median(jumps)), 2),
        "target_scans_per_s": TARGET_SCANS_PER_S,
        "meets_target": bool(scans_per_s >= TARGET_SCANS_PER_S),
        "repeats": repeats,
        "cpu_count": os.cpu_count(),
        "load_avg_1min_before": round(load_before, 2),
        "load_avg_1min_after": round(load_avg(), 2),
    }
