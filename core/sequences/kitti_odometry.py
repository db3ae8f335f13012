"""KITTI odometry layout: ``sequences/SS/velodyne/*.bin``, ``calib.txt``, ``times.txt`` and
``poses/SS.txt`` (cam0 poses, converted to the LiDAR frame with Tr), read through pykitti."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import DataError
from .base import check_poses, rebase_poses
from .kitti_io import FileBackedSequence, cam0_to_lidar_poses, read_pose_lines


class KittiOdometry(FileBackedSequence):
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
        self._open_pykitti(
            lambda: pykitti.odometry(str(self.root), self.sequence),
            (KeyError, ValueError, OSError),
            f"{seq_dir / 'calib.txt'}: unreadable calibration or times",
            seq_dir / "velodyne",
        )
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

    def identity(self) -> str:
        return f"kitti-odometry|{self.root.resolve()}|{self.sequence}"
