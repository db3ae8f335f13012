"""KITTI odometry: ``--kitti-odometry DIR --sequence SS``."""

from __future__ import annotations

from pathlib import Path

from ..registry import Option, Source, as_path


def _open(spec, cfg, progress=None):
    from ..kitti_odometry import KittiOdometry

    return KittiOdometry(as_path(spec.kitti_odometry), spec.sequence)


SOURCE = Source(
    name="kitti_odometry",
    title="KITTI odometry (sequences/SS/velodyne/*.bin, calib.txt, times.txt, poses/SS.txt)",
    options=(
        Option("kitti_odometry", Path, "KITTI odometry root (holds sequences/ and poses/).", metavar="DIR"),
        Option("sequence", str, "KITTI odometry sequence id, e.g. 05.", metavar="SS", required=True),
    ),
    open=_open,
    describe=lambda spec: f"KITTI odometry {spec.kitti_odometry} seq {spec.sequence}",
)
