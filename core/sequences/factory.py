"""Build a Sequence from the source options every command shares."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from ..config import Config
from ..errors import DataError
from .base import Limited, Sequence


@dataclass
class SourceSpec:
    """Where scans come from. Exactly one of: KITTI odometry, KITTI raw, or the built-in town."""

    kitti_odometry: Path | None = None
    sequence: str | None = None
    kitti_raw: Path | None = None
    date: str | None = None
    drive: str | None = None
    town_seed: int = 0
    trajectory: Path | None = None     # lay the town along a KITTI poses file …
    calib: Path | None = None          # … whose calib (Tr line) converts cam0 → LiDAR
    scans: int | None = None           # keep only the first N scans

    def describe(self) -> str:
        if self.kitti_odometry is not None:
            return f"KITTI odometry {self.kitti_odometry} seq {self.sequence}"
        if self.kitti_raw is not None:
            return f"KITTI raw {self.kitti_raw} {self.date} drive {self.drive}"
        along = f" along {self.trajectory}" if self.trajectory else ""
        return f"built-in town (seed {self.town_seed}){along}"


def open_sequence(spec: SourceSpec, cfg: Config | None = None) -> Sequence:
    cfg = cfg or Config()
    if spec.kitti_odometry is not None and spec.kitti_raw is not None:
        raise DataError("choose one source: --kitti-odometry or --kitti-raw, not both")
    if spec.kitti_odometry is not None:
        if not spec.sequence:
            raise DataError("--kitti-odometry needs --sequence SS")
        from .kitti_odometry import KittiOdometry

        seq: Sequence = KittiOdometry(spec.kitti_odometry, spec.sequence)
    elif spec.kitti_raw is not None:
        if not spec.date or not spec.drive:
            raise DataError("--kitti-raw needs --date YYYY_MM_DD and --drive NNNN")
        from .kitti_raw import KittiRaw

        seq = KittiRaw(spec.kitti_raw, spec.date, spec.drive)
    else:
        if (spec.trajectory is None) != (spec.calib is None):
            raise DataError("--trajectory and --calib go together (the calib's Tr converts cam0 poses to LiDAR)")
        from .town import TownSequence

        seq = TownSequence.from_config(cfg.town, seed=spec.town_seed, trajectory=spec.trajectory, calib=spec.calib)
    if spec.scans is not None:
        seq = Limited(seq, spec.scans)
    return seq
