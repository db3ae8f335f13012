"""A recorded run's steps in the form the file exports write them (:mod:`.export_bag` for ROS 2,
:mod:`.export_foxglove` for Foxglove's schemas): one place that decides stamps, frames, poses and
the particles' covariance, so that both files say the same thing.

**Stamps.** A step is stamped with its scan's own time: a bag's header stamp (absolute,
nanoseconds) where the run's source is a bag, else the sequence's time of the scan (seconds from
its first scan, as ``trajectory_tum.txt`` has it). Input topics copied beside the results
(``--with-input``) then line up with them.

**Frames.** ``map`` is the frame of ``trajectory_tum.txt``: the map file's own coordinates where
the run had one (``--map``, possibly georeferenced), else the mapping drive's first LiDAR pose.
Poses are float64 there. Point clouds are float32, which cannot hold UTM coordinates to the
centimetre: where the map has an origin, the map and the particles' cloud are written in
``map_local`` (``map`` minus the origin, a static transform), as the localizer works. The scan is
in ``lidar``, the estimate's frame (``map → lidar`` is the estimate, ``map → lidar_truth`` the
ground truth): placed by the estimate, a scan that fits the map shows the estimate is right.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from rich.console import Console

from ..core.errors import LidarlocError
from ..core.geometry import wrap_angle

MAP_FRAME = "map"
LOCAL_FRAME = "map_local"
LIDAR_FRAME = "lidar"
TRUTH_FRAME = "lidar_truth"
#: the map is thinned for display to at most this many points (a voxel grown until it fits)
MAP_POINTS = 400_000

#: event kinds a log reader should not miss (warning) and the ones that are failures (error)
WARN_EVENTS = frozenset(
    {
        "loss",
        "false_positive",
        "unconfirmed",
        "confidence_low",
        "frame_mismatch",
        "relocalized",
        "kidnap",
        "s2m_rejected",
    }
)
ERROR_EVENTS = frozenset({"false_fire", "error"})


def event_level(kind: str) -> str:
    """ "info", "warning" or "error": how a log panel should show an event of ``kind``."""
    return "error" if kind in ERROR_EVENTS else "warning" if kind in WARN_EVENTS else "info"


@dataclass
class Step:
    """One step of the run, in the map's frame (see the module docstring)."""

    index: int
    scan: int
    stamp_ns: int
    pose: np.ndarray  # 4×4 estimate (map ← LiDAR), float64
    truth: np.ndarray | None  # 4×4 ground truth where known
    particles: np.ndarray  # (N, 6) x, y, z (map frame), yaw, pitch, roll
    weights: np.ndarray  # (N,) normalised
    covariance: np.ndarray  # 6×6, ROS order: x, y, z, rotation about X, Y, Z (m², rad²)
    ellipse_xy: tuple  # 2σ ellipse of x-y: (semi-axis a, semi-axis b, angle rad)
    figures: dict  # the per-scan figures the viewer plots (SI units; ms for latencies)
    events: list = field(default_factory=list)  # Event of this step (the first step: also those before it)
    s2m: object | None = None  # the S2MView of a match that landed at this step


def particle_covariance(particles: np.ndarray, weights: np.ndarray, cov_xyz: np.ndarray) -> np.ndarray:
    """6×6 covariance in ROS's order (x, y, z, roll, pitch, yaw): the position block is the
    filter's own (``cov_xyz``, what it judged the scan with); the angles and their cross terms are
    the recorded particles' weighted spread around their own circular mean (a cloud across ±π is
    not 2π wide). The recorded particles are those after the step's resampling, so their position
    spread differs a little from the filter's figure; the filter's is the one the viewer shows."""
    cov = np.zeros((6, 6))
    if len(particles):
        w = np.asarray(weights, float)
        w = w / w.sum() if w.sum() > 0 else np.full(len(w), 1.0 / len(w))
        d = np.empty((len(particles), 6))
        d[:, :3] = particles[:, :3] - w @ particles[:, :3]
        for col, state in ((3, 5), (4, 4), (5, 3)):  # roll, pitch, yaw from states 5, 4, 3
            a = particles[:, state]
            mean = math.atan2(float(w @ np.sin(a)), float(w @ np.cos(a)))
            d[:, col] = wrap_angle(a - mean)
        cov = (d * w[:, None]).T @ d
    cov[:3, :3] = np.asarray(cov_xyz, float)
    return cov


def in_map(T: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """A local-frame pose in the ``map`` frame (the map file's origin added)."""
    T = np.array(T, np.float64)
    T[:3, 3] += origin
    return T


def make_step(
    index: int,
    scan: int,
    stamp_ns: int,
    origin: np.ndarray,
    mean_pose,
    gt_pose,
    particles,
    weights,
    cov_xyz,
    std_xyz,
    ellipse_xy,
    n_eff: float,
    n_particles: int,
    localized: bool,
    latencies: dict,
    events: list,
    s2m,
) -> Step:
    """A :class:`Step` from one step's state in the localizer's local frame (a recording's row or
    a live snapshot); ``latencies``: error_m, pf_ms, rpe_ms, s2m_ms, NaN or None where unknown."""
    parts = np.asarray(particles, np.float64)[:, :6].copy()
    parts[:, :3] += origin
    weights = np.asarray(weights, np.float64)
    gt = None if gt_pose is None else np.asarray(gt_pose, np.float64)
    n = int(n_particles) or len(parts)
    std = np.asarray(std_xyz, float)

    def known(v):
        return None if v is None or not math.isfinite(float(v)) else float(v)

    figures = {
        "std_m": float(max(std[0], std[1])),
        "std_x_m": float(std[0]),
        "std_y_m": float(std[1]),
        "std_z_m": float(std[2]),
        "n_eff": float(n_eff),
        "n_eff_share": float(n_eff) / max(n, 1),
        "particles": n,
        "localized": bool(localized),
        **{k: known(v) for k, v in latencies.items()},
    }
    return Step(
        index=index,
        scan=scan,
        stamp_ns=int(stamp_ns),
        pose=in_map(mean_pose, origin),
        truth=in_map(gt, origin) if gt is not None and np.isfinite(gt).all() else None,
        particles=parts,
        weights=weights,
        covariance=particle_covariance(parts, weights, cov_xyz),
        ellipse_xy=tuple(float(v) for v in ellipse_xy),
        figures=figures,
        events=list(events),
        s2m=s2m,
    )


def display_map(points: np.ndarray, max_points: int = MAP_POINTS, map_voxel: float = 0.1) -> tuple[np.ndarray, float]:
    """The map thinned for display, in the localizer's local frame (float32), and the voxel used
    (at least 0.5 m). Streamed, as the viewer thins a city's coarse layer (``map_voxel``: the
    map's own voxel, from which the first voxel tried is guessed): a whole copy of a 421 M-point
    map and a hash table sized by its points would take tens of GB."""
    from .viewer.map_tiles import thin

    return thin(points, max_points, 0.5, map_voxel)


def stamps_of(seq, scans: np.ndarray, times_s: np.ndarray) -> np.ndarray:
    """Each scan's stamp (int64 ns): a bag's header stamps where the sequence has them, else its
    times (see the module docstring)."""
    stamps = getattr(seq, "stamps_ns", None)
    if stamps is not None:
        return np.asarray(stamps, np.int64)[np.asarray(scans, np.int64)]
    return np.round(np.asarray(times_s, np.float64) * 1e9).astype(np.int64)


class RunSteps:
    """A recorded run opened for export: its sequence, map and steps (one-line errors for a
    missing or empty recording, or a source that moved)."""

    def __init__(self, run_dir, cache_root: Path | None = None, console: Console | None = None):
        from ..core.maps.mapping import load_or_build_map
        from ..core.runs import recording
        from .console import progress_bar

        self.rec = rec = recording.open(run_dir)
        if rec.n == 0:
            raise LidarlocError(f"{rec.path}: the recording has no complete step to export")
        self.seq = rec.open_sequence()
        cfg = rec.config()
        with progress_bar() as bar:  # from the cache; built (minutes) only if the cache lost it
            task = bar.add_task("preparing map", total=100)
            self.prior = load_or_build_map(
                self.seq.map_source,
                cfg.map,
                cache_root,
                progress=lambda i, n: bar.update(task, completed=100 * i / max(n, 1)),
            ).value
        self.origin = np.asarray(self.prior.origin, np.float64).reshape(3)
        self.local_frame = LOCAL_FRAME if self.origin.any() else MAP_FRAME
        self.n = rec.n
        self.stamps_ns = stamps_of(self.seq, rec.scan_index, rec.timestamp)
        self._events: dict[int, list] = {}
        for step, ev in rec.events:
            self._events.setdefault(max(step, 0), []).append(ev)
        self._s2m_steps = set(rec.s2m_steps)

    @property
    def name(self) -> str:
        return str(self.rec.meta.get("sequence", "run"))

    def in_map(self, T: np.ndarray) -> np.ndarray:
        return in_map(T, self.origin)

    def map_points(self, max_points: int = MAP_POINTS) -> tuple[np.ndarray, float]:
        return display_map(self.prior.points, max_points, float(self.prior.voxel_size))

    def scan(self, i: int) -> np.ndarray:
        """(M, 3) float32: step i's scan as the filter weighed it, in the LiDAR's frame."""
        return np.asarray(self.rec.prepared_scan(i, self.seq), np.float32)

    def step(self, i: int) -> Step:
        rec = self.rec
        return make_step(
            i,
            int(rec.scan_index[i]),
            int(self.stamps_ns[i]),
            self.origin,
            rec.mean_pose[i],
            rec.gt_pose[i],
            rec.particles(i),
            rec.weights(i),
            rec.cov_xyz[i],
            rec.std_xyz[i],
            rec.ellipse_xy[i],
            float(rec.n_eff[i]),
            int(rec.n_particles[i]),
            bool(rec.localized[i]),
            {"error_m": rec.error_m[i], "pf_ms": rec.pf_ms[i], "rpe_ms": rec.rpe_ms[i], "s2m_ms": rec.s2m_ms[i]},
            self._events.get(i, []),
            rec.s2m(i) if i in self._s2m_steps else None,
        )

    def __iter__(self):
        return (self.step(i) for i in range(self.n))
