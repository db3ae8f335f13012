"""A ROS 1 .bag, a ROS 2 bag folder, a .db3 or an .mcap file with PointCloud2 scans: ``--bag``
(``--topic`` when it has several)."""

from __future__ import annotations

from pathlib import Path

from ..registry import Option, Source, as_path, truth_options


def _open(spec, cfg, progress=None):
    from ..rosbag import BagSequence

    return BagSequence(as_path(spec.bag), topic=spec.topic, progress=progress, **truth_options(spec))


SOURCE = Source(
    name="bag",
    title="a ROS 1 .bag, a ROS 2 bag folder, .db3 or .mcap with sensor_msgs/PointCloud2 scans",
    options=(
        Option(
            "bag",
            Path,
            "ROS 1 .bag, ROS 2 bag folder, .db3 or .mcap with PointCloud2 scans.",
            metavar="FILE_OR_DIR",
        ),
        Option("topic", str, "PointCloud2 topic of --bag (default: its only one).", what="names a PointCloud2 topic"),
    ),
    open=_open,
    describe=lambda spec: f"bag {spec.bag}{' ' + spec.topic if spec.topic else ''}",
    recording=True,
    indexes=True,
)
