"""Relative pose estimation (paper, "Relative pose estimation"): scan-to-scan odometry from the
LiDAR alone, giving the relative transforms that carry S2M matches forward and the speed and
angular-rate pseudo-measurements of the particle filter.

The paper uses GICP between consecutive scans (with RANSAC); here KISS-ICP does the job:
point-to-point ICP of each scan against a local voxel map of the recent scans, with an adaptive
correspondence threshold and a robust kernel, no tuning. Measured on the KITTI raw drive 0013
(``lidarloc bench s2m``): after 100 scans / 114 m the end point is off by 1.4 % of the distance
and 0.6° against the GPS/INS truth. Motion compensation (deskew) is off: the scans carry no
per-point timestamps. Poses accumulate as in the paper, H_k = H_(k,k−1) ⋯ H_(1,0) H_0 with
H_0 = I: ``odom_pose(k)`` is the pose of scan k in the frame of the first scan registered
(T_odom←k).

Threading: one writer calls :meth:`RelativePoseEstimator.add`; any number of readers may query.
The registration itself runs outside the lock (only the writer touches the KISS-ICP state), so
readers never wait for an ICP; the lock only guards the pose buffer.

The GIL: KISS-ICP's C++ registration does *not* release it. Measured (``lidarloc bench s2m``,
``gil_hold_ms``): while another thread runs ``register_frame``, a Python thread that sleeps 1 ms
in a loop wakes up only every ~50–150 ms (the length of one ICP call), against ~1 ms when idle
or while a numba ``nogil`` kernel runs. So odometry overlaps with numba/NumPy kernels that drop
the GIL, but not with pure-Python work on other threads; to avoid that, pass an odometry running
in another process as ``icp`` (anything with ``register_frame`` and ``last_pose``).
"""

from __future__ import annotations

import math
import threading
from collections import OrderedDict
from pathlib import Path

import numpy as np

from ..cache import Cached, atomic_write_dir, cache_rebuilt
from ..geometry import euler_zyx, inv_pose, wrap_angle
from .kiss import KISS_CONVERGENCE, kiss_config
from .worker import KissICPProcess


def _rotation_angle(R: np.ndarray) -> float:
    return float(math.acos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)))


#: The most scans :meth:`RelativePoseEstimator.keep_from` keeps beyond its buffer: ten minutes at
#: 10 Hz (~2 MB of poses), longer than any match in flight takes, even a whole city's.
MAX_KEPT = 6000


class RelativePoseEstimator:
    """KISS-ICP odometry over a bounded buffer of the most recent scans (and of every scan from
    the one :meth:`keep_from` names on: a scan-to-map match in flight carries its result forward
    from its start scan, however long it took)."""

    def __init__(
        self,
        max_buffer: int = 100,
        max_range: float = 100.0,
        min_range: float = 2.5,
        voxel_size: float | None = None,
        icp=None,
        recorded: np.ndarray | None = None,
        known: dict[int, np.ndarray] | None = None,
        make_icp=None,
    ):
        """``icp``: an object with KissICP's ``register_frame``/``last_pose`` (e.g. the
        process-backed :class:`~lidarloc.core.odometry.worker.KissICPProcess`); default: in-process.
        ``recorded``: (N, 4, 4) odometry poses of every scan of the sequence from an earlier run
        (:func:`load_or_build_odometry`); then no ICP runs, scan k gets inv(P_origin)·P_k with
        origin the first scan added — bit for bit what the live odometry gave when the recording
        started at the same scan (replay benchmarks: the odometry does not depend on the seed).
        ``known``: scan → T_odom←scan of scans whose pose is already known (a recorded run being
        resumed): those are taken as they are, bit for bit, and only the others registered;
        ``make_icp(k)``: builds the ``icp`` when the first scan without a known pose, k, comes
        (warmed up on the scans before it, see :mod:`lidarloc.core.odometry.feed`)."""
        if max_buffer < 2:
            raise ValueError(f"max_buffer must be ≥ 2, got {max_buffer}")
        self.max_buffer = int(max_buffer)
        self._recorded = None if recorded is None else np.asarray(recorded, dtype=np.float64)
        self._origin: int | None = None
        self._known = known
        self._make_icp = make_icp
        if icp is None and self._recorded is None and make_icp is None:
            from kiss_icp.kiss_icp import KissICP

            icp = KissICP(kiss_config(max_range, min_range, voxel_size))
        self._icp = icp
        self._lock = threading.Lock()
        # scan index → (odometry pose 4×4, timestamp, path length at this scan, rotation sum)
        self._buf: OrderedDict[int, tuple[np.ndarray, float, float, float]] = OrderedDict()
        self._latest: int | None = None
        self._keep_from: int | None = None

    # ------------------------------------------------------------------------------- writer
    def registers(self, k: int) -> bool:
        """Whether :meth:`add` of scan k runs the ICP (no recorded or known pose for it)."""
        return self._recorded is None and (self._known is None or int(k) not in self._known)

    @property
    def live_icp(self):
        """The ICP that registers scans (None before a resumed run's first unknown scan); the
        writer may replace it between two :meth:`add` calls (a restarted KISS-ICP child)."""
        return self._icp

    @live_icp.setter
    def live_icp(self, icp) -> None:
        self._icp = icp

    def add(self, k: int, scan_points: np.ndarray, timestamp: float) -> np.ndarray:
        """Register scan k (indices must increase) and return its odometry pose T_odom←k."""
        k = int(k)
        if self._latest is not None and k <= self._latest:
            raise ValueError(f"scan {k} added after scan {self._latest}: indices must increase")
        if self._recorded is not None:
            if self._origin is None:
                self._origin = k
            pose = inv_pose(self._recorded[self._origin]) @ self._recorded[k]
        elif self._known is not None and k in self._known:
            pose = np.array(self._known[k], dtype=np.float64)
        else:
            if self._icp is None:
                self._icp = self._make_icp(k)
            pts = np.ascontiguousarray(np.asarray(scan_points)[:, :3], dtype=np.float64)
            # deskew is off, so KISS-ICP ignores per-point times; it still wants the argument
            self._icp.register_frame(pts, np.zeros(0))
            pose = np.array(self._icp.last_pose, dtype=np.float64)
        with self._lock:
            if self._buf:
                prev_pose, _, path, turned = next(reversed(self._buf.values()))
                step = inv_pose(prev_pose) @ pose
                path += float(np.linalg.norm(step[:3, 3]))
                turned += _rotation_angle(step[:3, :3])
            else:
                path, turned = 0.0, 0.0
            self._buf[k] = (pose, float(timestamp), path, turned)
            self._trim()
            self._latest = k
        return pose.copy()

    def keep_from(self, k: int | None) -> None:
        """Keep every scan from k on, beyond the buffer's ``max_buffer`` most recent (at most
        :data:`MAX_KEPT` more); None: the buffer alone. The scans already dropped stay dropped."""
        with self._lock:
            self._keep_from = None if k is None else int(k)
            self._trim()

    def _trim(self) -> None:
        """Drop the oldest scans beyond the buffer (the lock held)."""
        while len(self._buf) > self.max_buffer:
            oldest = next(iter(self._buf))
            kept = self._keep_from is not None and oldest >= self._keep_from
            if kept and len(self._buf) <= self.max_buffer + MAX_KEPT:
                break
            self._buf.popitem(last=False)

    def restore(self, entries) -> None:
        """Refill the buffer with (scan, T_odom←scan, timestamp, path length, rotation sum) entries
        in scan order, as :meth:`entries` gave them (resuming a recorded run)."""
        with self._lock:
            self._buf.clear()
            for k, pose, t, path, turned in entries:
                self._buf[int(k)] = (np.array(pose, dtype=np.float64), float(t), float(path), float(turned))
            self._trim()
            self._latest = next(reversed(self._buf)) if self._buf else None

    def entries(self, last: int | None = None) -> list[tuple[int, np.ndarray, float, float, float]]:
        """The buffer (its ``last`` newest entries if given), oldest first: (scan, T_odom←scan,
        timestamp, path length, rotation sum)."""
        with self._lock:
            keys = list(self._buf) if last is None else list(self._buf)[-last:]
            return [(k, self._buf[k][0].copy(), *self._buf[k][1:]) for k in keys]

    # ------------------------------------------------------------------------------ readers
    @property
    def latest(self) -> int | None:
        """Index of the last registered scan (None before the first)."""
        with self._lock:
            return self._latest

    def has(self, k: int) -> bool:
        with self._lock:
            return int(k) in self._buf

    def _get(self, k: int):
        entry = self._buf.get(int(k))
        if entry is None:
            raise KeyError(
                f"scan {k} is not in the odometry buffer (not registered yet, or older than the "
                f"last {self.max_buffer} scans)"
            )
        return entry

    def odom_pose(self, k: int) -> np.ndarray:
        """T_odom←k: pose of scan k in the odometry frame (the first registered scan)."""
        with self._lock:
            return self._get(k)[0].copy()

    def relative(self, k_from: int, k_to: int) -> np.ndarray:
        """T_from←to = inv(O_from)·O_to: the pose of scan k_to in the frame of scan k_from, i.e. the
        transform that takes scan k_to's points into scan k_from's frame. Composes in the order
        of the paper's H_(k', k) chain (see :func:`lidarloc.core.matching.carry.carry_forward`)."""
        with self._lock:
            a = self._get(k_from)[0]
            b = self._get(k_to)[0]
        return inv_pose(a) @ b

    def predicted(self, k: int, t: float) -> np.ndarray:
        """T_odom←(the sensor at time t): scan k's odometry pose moved on from its timestamp to t
        at the motion of its last registration, held constant (KISS-ICP's own prediction model):
        that motion repeated once per whole scan period (exact for a constant twist), a fraction
        of a period left scaled to first order (rotation vector and translation)."""
        from scipy.spatial.transform import Rotation

        with self._lock:
            (p0, t0, _, _), (p1, t1, _, _), ok = self._previous(k, 1)
        if not ok or t1 <= t0:
            return p1.copy()  # no motion known yet
        step = inv_pose(p0) @ p1
        scale = max(0.0, (float(t) - t1) / (t1 - t0))
        whole = int(math.floor(scale + 1e-6))
        ahead = np.linalg.matrix_power(step, whole)  # exact for a constant twist
        rest = np.eye(4)  # the fraction of a scan period left (none at a scan's time)
        rest[:3, :3] = Rotation.from_rotvec(
            Rotation.from_matrix(step[:3, :3]).as_rotvec() * (scale - whole)
        ).as_matrix()
        rest[:3, 3] = step[:3, 3] * (scale - whole)
        return p1 @ ahead @ rest

    def _previous(self, k: int, window: int):
        """The entries of k and of the scan ``window`` registrations before it (clamped to the buffer)."""
        keys = list(self._buf.keys())
        i = keys.index(int(k)) if int(k) in self._buf else None
        if i is None:
            self._get(k)  # raises the KeyError
        j = max(0, i - max(1, int(window)))
        return self._buf[keys[j]], self._buf[keys[i]], i != j

    def speed(self, k: int, window: int = 1) -> float:
        """Speed (m/s) at scan k by a backward difference over ``window`` scans (1 = the paper's
        one-step Euler difference; larger windows smooth the noise). 0 for the first scan."""
        with self._lock:
            (p0, t0, _, _), (p1, t1, _, _), ok = self._previous(k, window)
        if not ok or t1 <= t0:
            return 0.0
        return float(np.linalg.norm(p1[:3, 3] - p0[:3, 3]) / (t1 - t0))

    def rates(self, k: int, window: int = 1) -> np.ndarray:
        """[yaw, pitch, roll] rates (rad/s) at scan k: backward difference of the Z-Y-X Euler angles
        of the odometry poses over ``window`` scans, angles wrapped. Zeros for the first scan."""
        with self._lock:
            (p0, t0, _, _), (p1, t1, _, _), ok = self._previous(k, window)
        if not ok or t1 <= t0:
            return np.zeros(3)
        d = wrap_angle(euler_zyx(p1[:3, :3]) - euler_zyx(p0[:3, :3]))
        return np.asarray(d, dtype=np.float64) / (t1 - t0)

    def moved_since(self, k: int, k_to: int | None = None) -> float:
        """Distance travelled along the odometry path from scan k to k_to (default: the latest)."""
        with self._lock:
            a = self._get(k)[2]
            b = self._get(self._latest if k_to is None else k_to)[2]
        return b - a

    def turned_since(self, k: int, k_to: int | None = None) -> float:
        """Rotation accumulated along the path from scan k to k_to (default: the latest): the sum of
        each step's rotation angle, so turning 30° left then 30° right counts 60°."""
        with self._lock:
            a = self._get(k)[3]
            b = self._get(self._latest if k_to is None else k_to)[3]
        return b - a

    def __len__(self) -> int:
        with self._lock:
            return len(self._buf)


def load_or_build_odometry(seq, map_dir, progress=None) -> Cached[np.ndarray]:
    """KISS-ICP odometry poses (N, 4, 4) of every scan of ``seq``, cached beside its prior map.
    Computed exactly as the localizer's live RPE does (the same child process, the same float32
    hand-over), so replaying them changes no number."""
    # keyed by the convergence setting: poses recorded under another one are not reused
    directory = Path(map_dir) / f"odometry-kiss-{KISS_CONVERGENCE:g}"
    path = directory / "poses.npy"
    if path.is_file():
        try:
            poses = np.load(path)
            if poses.shape != (len(seq), 4, 4) or not np.isfinite(poses).all():
                raise ValueError(f"{poses.shape} poses, not ({len(seq)}, 4, 4) finite ones")
            return Cached(poses, directory, True)
        except (OSError, ValueError) as exc:  # recomputed below
            cache_rebuilt(directory, f"{type(exc).__name__}: {exc}")
    icp = KissICPProcess()
    try:
        rpe = RelativePoseEstimator(max_buffer=2, icp=icp)
        poses = np.empty((len(seq), 4, 4))
        for k in range(len(seq)):
            poses[k] = rpe.add(k, seq.scan(k), seq.timestamp(k))
            if progress is not None:
                progress((k + 1) / len(seq))
    finally:
        icp.close()
    atomic_write_dir(directory, lambda d: np.save(Path(d) / "poses.npy", poses))
    return Cached(poses, directory, False)
