"""A folder of scan files as a Sequence: ``.pcd``, ``.ply`` (open3d), ``.bin`` (KITTI: float32
x, y, z, intensity records) or ``.npy`` ((N, 3) or (N, ≥ 4) arrays, x, y, z[, intensity, …]).

Scans are the folder's files of one of those kinds, sorted by name with numbers compared as
numbers (``scan_2`` before ``scan_10``); a folder mixing kinds is an error, as it is almost
always a mistake. Times: ``times.txt`` in the folder (one per line, seconds, one per scan;
KITTI's convention), else 10 Hz from 0 with a note in :attr:`notes`. Intensity: a .pcd/.ply
``intensity`` field, else 0.

Frames and ground truth work as for a bag (:mod:`lidarloc.core.sequences.rosbag`): scans stay in
the LiDAR frame, the truth (``gt``: TUM matched by time against ``times.txt``, or KITTI one pose
per scan or with its own times file) is moved to the LiDAR with ``extrinsic`` (base ← LiDAR, a
4×4 array, a text file or "identity"; default identity), scans outside its span are left out,
and :attr:`truth_origin` is the first LiDAR pose in the truth's frame.
"""

from __future__ import annotations

import hashlib
import os
import re
from pathlib import Path

import numpy as np

from ..cache import array_digest
from ..errors import DataError
from .extrinsic import resolve_extrinsic
from .groundtruth import MATCH_TOL_S, read_times_precise, truth_of_recording
from .kitti_io import FileBackedSequence, read_velodyne_bin

SCAN_SUFFIXES = (".pcd", ".ply", ".bin", ".npy")
#: scan period assumed without times.txt: the rate of nearly every spinning LiDAR's default
DEFAULT_PERIOD_S = 0.1


def natural_key(name: str):
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", name)]


def read_scan_file(path: Path) -> np.ndarray:
    """(N, 4) float32 x, y, z, intensity of one scan file (intensity 0 where the file has none)."""
    suffix = path.suffix.lower()
    if suffix == ".bin":
        return read_velodyne_bin(path)
    if suffix == ".npy":
        try:
            arr = np.load(path, allow_pickle=False)
        except Exception as exc:  # numpy's header parser raises ValueError, SyntaxError, TokenError, …
            detail = " ".join(str(exc).split()) or type(exc).__name__
            raise DataError(f"{path}: unreadable .npy ({detail[:200]})") from None
        if arr.ndim != 2 or arr.shape[1] < 3 or arr.dtype.kind not in "fiu":
            raise DataError(
                f"{path}: a .npy scan must be a numeric (N, 3) or (N, ≥4) array; got {arr.dtype} {arr.shape}"
            )
        out = np.zeros((len(arr), 4), dtype=np.float32)
        with np.errstate(over="ignore", invalid="ignore"):  # beyond float32: inf, refused by validate_scan
            out[:, : min(arr.shape[1], 4)] = arr[:, :4]
        return out
    from ..o3d import open3d

    o3d = open3d()
    if not path.is_file():
        raise DataError(f"{path}: scan file not found")
    cloud = o3d.t.io.read_point_cloud(str(path))  # an unreadable file gives an empty cloud
    if "positions" not in cloud.point or len(cloud.point.positions) == 0:
        raise DataError(f"{path}: no points (empty or unreadable {suffix} file)")
    xyz = cloud.point.positions.numpy()
    out = np.zeros((len(xyz), 4), dtype=np.float32)
    out[:, :3] = xyz
    if "intensity" in cloud.point:
        out[:, 3] = cloud.point.intensity.numpy().reshape(len(xyz), -1)[:, 0]
    return out


class ScanFolderSequence(FileBackedSequence):
    """The scans of a folder, one file each (the module docstring)."""

    def __init__(
        self,
        directory: str | os.PathLike,
        gt=None,
        extrinsic=None,
        gt_times: str | os.PathLike | None = None,
        match_tol: float = MATCH_TOL_S,
    ):
        self.directory = Path(directory)
        self.name = f"scans {self.directory.name}"
        self.notes: list[str] = []
        if not self.directory.is_dir():
            raise DataError(f"{self.directory}: scan folder not found")
        files = [p for p in self.directory.iterdir() if p.is_file() and p.suffix.lower() in SCAN_SUFFIXES]
        if not files:
            raise DataError(f"{self.directory}: no scans (.pcd, .ply, .bin or .npy files)")
        kinds = sorted({p.suffix.lower() for p in files})
        if len(kinds) > 1:
            raise DataError(f"{self.directory}: scans of several kinds ({', '.join(kinds)}); keep one kind per folder")
        files.sort(key=lambda p: natural_key(p.name))

        times_file = self.directory / "times.txt"
        if times_file.is_file():
            stamps, since_first = read_times_precise(times_file)
            if len(stamps) != len(files):
                raise DataError(f"{times_file}: {len(stamps)} times for {len(files)} scans")
            if (np.diff(stamps) <= 0).any():
                k = int(np.argmax(np.diff(stamps) <= 0))
                raise DataError(f"{times_file}:{k + 2}: times must increase (scan order is by file name)")
        else:
            stamps = DEFAULT_PERIOD_S * np.arange(len(files), dtype=np.float64)
            since_first = stamps.copy()
            self.notes.append(f"{self.directory}: no times.txt; scans taken as {1 / DEFAULT_PERIOD_S:g} Hz from 0 s")

        self.T_base_lidar = resolve_extrinsic(extrinsic)
        self._poses = None
        self.truth_origin = None
        self._gt_identity = ""
        if gt is not None:
            matched = truth_of_recording(gt, gt_times, stamps, self.T_base_lidar, match_tol)
            self.notes += matched.notes
            files = [files[k] for k in matched.keep]
            stamps, since_first = stamps[matched.keep], since_first[matched.keep]
            self.truth_origin = matched.origin
            self._poses = matched.rebased
            self._gt_identity = matched.identity
        self._files = files
        self.stamps = stamps
        self._times = since_first - since_first[0]

    def _read_scan(self, i: int) -> np.ndarray:
        return read_scan_file(self._files[i])

    def identity(self) -> str:
        stats = [(p.name, p.stat().st_size, p.stat().st_mtime_ns) for p in self._files]
        digest = hashlib.sha1(repr(stats).encode()).hexdigest()[:12]
        return (
            f"scan-folder|{self.directory.resolve()}|{digest}|gt={self._gt_identity}"
            f"|ext={array_digest(self.T_base_lidar)}"
        )
