"""KITTI raw: ``--kitti-raw DIR --date YYYY_MM_DD --drive NNNN`` (velodyne + OXTS)."""

from __future__ import annotations

from pathlib import Path

from ..registry import Option, Source, as_path


def _open(spec, cfg, progress=None):
    from ..kitti_raw import KittiRaw

    return KittiRaw(as_path(spec.kitti_raw), spec.date, spec.drive)


SOURCE = Source(
    name="kitti_raw",
    title="KITTI raw (YYYY_MM_DD/..._drive_NNNN_sync: velodyne + OXTS)",
    options=(
        Option("kitti_raw", Path, "KITTI raw root (holds YYYY_MM_DD/).", metavar="DIR"),
        Option("date", str, "KITTI raw date, YYYY_MM_DD.", metavar="YYYY_MM_DD", required=True),
        Option("drive", str, "KITTI raw drive number, NNNN.", metavar="NNNN", required=True),
    ),
    open=_open,
    describe=lambda spec: f"KITTI raw {spec.kitti_raw} {spec.date} drive {spec.drive}",
)
