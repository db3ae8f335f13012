"""One interface for a stream of LiDAR scans, whatever produced it.

A :class:`Sequence` has a length, scan ``i`` as float32 (N, 4) x, y, z, intensity in the sensor
frame, its timestamp (seconds since the first scan) and, where known, the ground-truth LiDAR pose
as a 4×4 matrix in a world frame equal to the first LiDAR pose of its :attr:`~Sequence.map_source`
(the sequence itself, unless a separate mapping drive builds the prior map).
"""

from __future__ import annotations

import hashlib
import os
import threading
from abc import ABC, abstractmethod
from pathlib import Path

import numpy as np

from ..errors import DataError


class Sequence(ABC):
    #: short human name, e.g. "town-seed0" or "kitti-raw 2011_09_26/0013"
    name: str = "sequence"

    @abstractmethod
    def __len__(self) -> int: ...

    @abstractmethod
    def _read_scan(self, i: int) -> np.ndarray:
        """Raw scan i as (N, 4) float32 (validated by :meth:`scan`)."""

    @abstractmethod
    def describe_scan(self, i: int) -> str:
        """Where scan i comes from (a file path, or 'town seed 0 scan 12'), for error messages."""

    @property
    @abstractmethod
    def timestamps(self) -> np.ndarray:
        """(len,) float64 seconds since the first scan."""

    @property
    def poses(self) -> np.ndarray | None:
        """(len, 4, 4) float64 ground-truth LiDAR poses (world = the map source's first LiDAR
        pose), or None."""
        return None

    @property
    def has_poses(self) -> bool:
        return self.poses is not None

    @property
    def map_source(self) -> Sequence:
        """The sequence whose scans and poses build the prior map: this one, unless the source
        knows a separate mapping drive (the generated town's, when its world changed)."""
        return self

    def identity(self) -> str:
        """A string that identifies the source and its parameters (for cache keys)."""
        return self.name

    def cache_key(self) -> str:
        return hashlib.sha1(f"{self.identity()}|n={len(self)}".encode()).hexdigest()[:16]

    # ---------------------------------------------------------------- public accessors
    def scan(self, i: int) -> np.ndarray:
        n = len(self)
        if not -n <= i < n:
            raise IndexError(f"scan index {i} out of range for {self.name} ({n} scans)")
        i = i % n
        return validate_scan(self._read_scan(i), self.describe_scan(i))

    def timestamp(self, i: int) -> float:
        return float(self.timestamps[i])

    def pose(self, i: int) -> np.ndarray | None:
        poses = self.poses
        return None if poses is None else poses[i]

    def __iter__(self):
        for i in range(len(self)):
            yield self.scan(i)


class RecordedSequence(Sequence):
    """A sequence whose times and, where it has ground truth, poses were read when it was opened
    (files, a bag, a capture): a subclass sets ``_times`` and ``_poses``."""

    _times: np.ndarray
    _poses: np.ndarray | None = None

    @property
    def timestamps(self) -> np.ndarray:
        return self._times

    @property
    def poses(self) -> np.ndarray | None:
        return self._poses


def validate_scan(points: np.ndarray, where: str) -> np.ndarray:
    """Check a scan is usable: (N, 4) finite float32 with N > 0. Raises DataError naming ``where``."""
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 4:
        raise DataError(f"{where}: scan must be (N, 4) x, y, z, intensity; got shape {points.shape}")
    if points.shape[0] == 0:
        raise DataError(f"{where}: empty scan (0 points)")
    if not np.isfinite(points).all():
        bad = int((~np.isfinite(points)).any(axis=1).sum())
        raise DataError(f"{where}: {bad} point(s) with NaN or infinite coordinates")
    return points.astype(np.float32, copy=False)


def check_poses(poses: np.ndarray, n_scans: int, where: str) -> np.ndarray:
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise DataError(f"{where}: poses must be 4×4 matrices; got shape {poses.shape}")
    if len(poses) != n_scans:
        more_fewer = "more" if len(poses) > n_scans else "fewer"
        raise DataError(f"{where}: {len(poses)} poses for {n_scans} scans ({more_fewer} poses than scans)")
    if not np.isfinite(poses).all():
        raise DataError(f"{where}: poses contain NaN or infinite values")
    return poses


def rebase_poses(poses: np.ndarray) -> np.ndarray:
    """Express poses in the frame of the first one (world = first LiDAR pose)."""
    from ..geometry import inv_pose

    return inv_pose(poses[0])[None] @ poses


class Limited(Sequence):
    """The first ``n`` scans of another sequence (``--scans N``)."""

    def __init__(self, inner: Sequence, n: int):
        if n < 1:
            raise DataError(f"--scans must be ≥ 1, got {n}")
        self.inner = inner
        self.n = min(n, len(inner))
        self.name = inner.name

    def __len__(self) -> int:
        return self.n

    def _read_scan(self, i: int) -> np.ndarray:
        return self.inner._read_scan(i)

    def describe_scan(self, i: int) -> str:
        return self.inner.describe_scan(i)

    @property
    def timestamps(self) -> np.ndarray:
        return self.inner.timestamps[: self.n]

    @property
    def poses(self) -> np.ndarray | None:
        p = self.inner.poses
        return None if p is None else p[: self.n]

    def identity(self) -> str:
        return self.inner.identity()

    @property
    def map_source(self) -> Sequence:
        """The inner sequence's map source: ``--scans N`` plays N scans inside the whole map."""
        return self.inner.map_source

    def __getattr__(self, item):  # expose source-specific extras (e.g. the town's geometry)
        return getattr(self.__dict__["inner"], item)


class DiskCachedScans(Limited):
    """Another sequence whose scans are stored in ``directory`` (one ``.npy`` per scan) the first
    time they are read, and loaded from there afterwards. For sources that compute their scans
    (the generated town simulates each one, ~20 ms): ``bench localize`` fills the directory once
    and its runs then load the same scans instead of simulating them again. Each file is written
    to a temporary name and renamed, so concurrent readers never see half a scan."""

    def __init__(self, inner: Sequence, directory: Path):
        super().__init__(inner, len(inner))
        self.directory = Path(directory)
        self.directory.mkdir(parents=True, exist_ok=True)

    def _read_scan(self, i: int) -> np.ndarray:
        path = self.directory / f"{i:06d}.npy"
        try:
            return np.load(path)
        except (FileNotFoundError, ValueError, OSError):
            pass
        points = self.inner._read_scan(i)
        self.directory.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f"{path.stem}.{os.getpid()}.{threading.get_ident()}.tmp.npy")
        np.save(tmp, points)
        os.replace(tmp, path)
        return points
