"""Reading and writing the KITTI file formats shared by the odometry and raw layouts, and the
base class of the two KITTI readers."""

from __future__ import annotations

import contextlib
import io
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import DataError
from .base import RecordedSequence


def read_velodyne_bin(path: str | os.PathLike) -> np.ndarray:
    """A KITTI ``.bin`` scan: float32 x, y, z, reflectance records of 16 bytes."""
    path = Path(path)
    try:
        size = path.stat().st_size
    except FileNotFoundError:
        raise DataError(f"{path}: scan file not found") from None
    if size % 16 != 0:
        raise DataError(f"{path}: corrupt scan file (size {size} bytes is not a multiple of 16)")
    return np.fromfile(path, dtype=np.float32).reshape(-1, 4)


def write_velodyne_bin(path: str | os.PathLike, points: np.ndarray) -> None:
    np.ascontiguousarray(points[:, :4], dtype=np.float32).tofile(path)


def read_pose_lines(path: str | os.PathLike) -> np.ndarray:
    """KITTI odometry poses: one row-major 3×4 matrix (12 numbers) per line → (N, 4, 4)."""
    path = Path(path)
    rows = []
    with open(path) as f:
        for lineno, line in enumerate(f, 1):
            if not line.strip():
                continue
            try:
                values = np.array([float(v) for v in line.split()])
            except ValueError:
                raise DataError(f"{path}:{lineno}: not a line of 12 numbers") from None
            if values.size != 12:
                raise DataError(f"{path}:{lineno}: expected 12 numbers, got {values.size}")
            rows.append(values)
    if not rows:
        raise DataError(f"{path}: no poses in file")
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3, :4] = np.asarray(rows).reshape(-1, 3, 4)
    return poses


def write_pose_lines(path: str | os.PathLike, poses: np.ndarray) -> None:
    with open(path, "w") as f:
        for T in poses:
            f.write(" ".join(f"{v:.9e}" for v in np.asarray(T)[:3, :4].reshape(-1)) + "\n")


def read_tr(path: str | os.PathLike) -> np.ndarray:
    """The ``Tr:`` (velodyne → rectified cam0) line of a KITTI odometry calib file, as 4×4."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: calibration file not found")
    for line in path.read_text().splitlines():
        if line.startswith("Tr:"):
            values = np.array([float(v) for v in line.split()[1:]])
            if values.size != 12:
                raise DataError(f"{path}: Tr line must hold 12 numbers")
            T = np.eye(4)
            T[:3, :4] = values.reshape(3, 4)
            return T
    raise DataError(f"{path}: no 'Tr:' line")


def cam0_to_lidar_poses(poses_cam0: np.ndarray, Tr: np.ndarray) -> np.ndarray:
    """KITTI odometry ground truth is the cam0 pose; the LiDAR pose is inv(Tr) · P · Tr."""
    return np.linalg.inv(Tr)[None] @ poses_cam0 @ Tr[None]


def lidar_to_cam0_poses(poses_lidar: np.ndarray, Tr: np.ndarray) -> np.ndarray:
    return Tr[None] @ poses_lidar @ np.linalg.inv(Tr)[None]


class FileBackedSequence(RecordedSequence):
    """A sequence of scan files, one file per scan, read when the scan is asked for; timestamps
    and poses read once when the sequence is opened.

    A subclass sets ``_files``, ``_times`` and, where it has ground truth, ``_poses``. The KITTI
    readers open their layout with :meth:`_open_pykitti` (which sets ``_kitti`` and ``_files``) and
    read KITTI ``.bin`` scans; a reader of other files overrides :meth:`_read_scan`.
    """

    _files: list

    def _open_pykitti(
        self, opener: Callable[[], Any], errors: tuple[type[Exception], ...], failure: str, velodyne_dir: Path
    ) -> None:
        """Run ``opener`` (a pykitti reader) and list its scan files. pykitti prints when poses are
        absent, so its output is swallowed; ``errors`` it raises become a DataError starting with
        ``failure``, and a layout without scans one naming ``velodyne_dir``."""
        try:
            with contextlib.redirect_stdout(io.StringIO()):
                self._kitti = opener()
        except errors as exc:
            raise DataError(f"{failure} ({exc})") from None
        self._files = list(self._kitti.velo_files)
        if not self._files:
            raise DataError(f"{velodyne_dir}: no .bin scans")

    def __len__(self) -> int:
        return len(self._files)

    def _read_scan(self, i: int) -> np.ndarray:
        return read_velodyne_bin(self._files[i])

    def describe_scan(self, i: int) -> str:
        return str(self._files[i])
