"""KITTI odometry layout: ``sequences/SS/velodyne/*.bin``, ``calib.txt``, ``times.txt`` and
``poses/SS.txt`` (cam0 poses, converted to the LiDAR frame with Tr), read through pykitti."""

from __future__ import annotations

import contextlib
import io
from pathlib import Path

import numpy as np

from ..errors import DataError
from .base import Sequence, check_poses, rebase_poses
from .kitti_io import cam0_to_lidar_poses, read_pose_lines, read_velodyne_bin


class KittiOdometry(Sequence):
    def __init__(self, root: str | Path, sequence: str):
        import pykitti

        self.root = Path(root)
        self.sequence = str(sequence)
        self.name = f"kitti-odometry {self.sequence}"
        if not self.root.is_dir():
            raise DataError(f"{self.root}: KITTI odometry directory not found")
        seq_dir = self.root / "sequences" / self.sequence
        if not seq_dir.is_dir():
            known = sorted(p.name for p in (self.root / "sequences").glob("*") if p.is_dir())
            raise DataError(f"{seq_dir}: unknown sequence id '{self.sequence}' (found: {', '.join(known) or 'none'})")
        for needed in ("calib.txt", "times.txt"):
            if not (seq_dir / needed).is_file():
                raise DataError(f"{seq_dir / needed}: file not found")
        try:
            with contextlib.redirect_stdout(io.StringIO()):  # pykitti prints when poses are absent
                self._kitti = pykitti.odometry(str(self.root), self.sequence)
        except (KeyError, ValueError, OSError) as exc:
            raise DataError(f"{seq_dir / 'calib.txt'}: unreadable calibration or times ({exc})") from None
        self._files = list(self._kitti.velo_files)
        if not self._files:
            raise DataError(f"{seq_dir / 'velodyne'}: no .bin scans")
        n = len(self._files)
        times = np.array([t.total_seconds() for t in self._kitti.timestamps], dtype=np.float64)
        if len(times) != n:
            raise DataError(f"{seq_dir / 'times.txt'}: {len(times)} timestamps for {n} scans")
        self._times = times - times[0]
        self.Tr = np.asarray(self._kitti.calib.T_cam0_velo, dtype=np.float64)
        pose_file = self.root / "poses" / f"{self.sequence}.txt"
        self._poses = None
        if pose_file.is_file():
            cam0 = check_poses(read_pose_lines(pose_file), n, str(pose_file))
            self._poses = rebase_poses(cam0_to_lidar_poses(cam0, self.Tr))

    def __len__(self) -> int:
        return len(self._files)

    def _read_scan(self, i: int) -> np.ndarray:
        return read_velodyne_bin(self._files[i])

    def _describe_scan(self, i: int) -> str:
        return str(self._files[i])

    @property
    def timestamps(self) -> np.ndarray:
        return self._times

    @property
    def poses(self):
        return self._poses

    def identity(self) -> str:
        return f"kitti-odometry|{self.root.resolve()}|{self.sequence}"
