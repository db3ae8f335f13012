"""KITTI raw layout (velodyne + OXTS), read through pykitti.

The LiDAR pose is ``T_w_imu · inv(T_velo_imu)`` (pykitti's OXTS pose of the IMU, moved to the
Velodyne), re-based so that the world frame is the first LiDAR pose.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import DataError
from .base import check_poses, rebase_poses
from .kitti_io import FileBackedSequence


class KittiRaw(FileBackedSequence):
    def __init__(self, root: str | Path, date: str, drive: str):
        import pykitti

        self.root = Path(root)
        self.date, self.drive = str(date), str(drive).zfill(4)
        self.name = f"kitti-raw {self.date}/{self.drive}"
        if not self.root.is_dir():
            raise DataError(f"{self.root}: KITTI raw directory not found")
        date_dir = self.root / self.date
        drive_dir = date_dir / f"{self.date}_drive_{self.drive}_sync"
        if not drive_dir.is_dir():
            raise DataError(f"{drive_dir}: drive not found")
        for needed in ("calib_imu_to_velo.txt", "calib_velo_to_cam.txt", "calib_cam_to_cam.txt"):
            if not (date_dir / needed).is_file():
                raise DataError(f"{date_dir / needed}: calibration file not found")
        if not (drive_dir / "oxts" / "timestamps.txt").is_file():
            raise DataError(f"{drive_dir / 'oxts' / 'timestamps.txt'}: file not found")
        self._open_pykitti(
            lambda: pykitti.raw(str(self.root), self.date, self.drive),
            (KeyError, ValueError, OSError, IndexError),
            f"{drive_dir}: unreadable OXTS or calibration",
            drive_dir / "velodyne_points" / "data",
        )
        n = len(self._files)
        oxts = self._kitti.oxts
        T_velo_imu = np.asarray(self._kitti.calib.T_velo_imu, dtype=np.float64)
        T_w_imu = np.array([o.T_w_imu for o in oxts], dtype=np.float64).reshape(-1, 4, 4)
        where = str(drive_dir / "oxts" / "data")
        lidar = check_poses(T_w_imu @ np.linalg.inv(T_velo_imu)[None], n, where)
        self._poses = rebase_poses(lidar)
        stamps = self._kitti.timestamps
        if len(stamps) != n:
            raise DataError(f"{drive_dir / 'oxts' / 'timestamps.txt'}: {len(stamps)} timestamps for {n} scans")
        t0 = stamps[0]
        self._times = np.array([(t - t0).total_seconds() for t in stamps], dtype=np.float64)

    def identity(self) -> str:
        return f"kitti-raw|{self.root.resolve()}|{self.date}|{self.drive}"
