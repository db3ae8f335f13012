"""Views of the localizer's state, handed to the viewer and to result writers.

A snapshot is built by the localizer after each scan and never mutated afterwards, so a reader
on another thread (the viewer) needs no lock to use it. A :class:`ScanRecord` is the scan's row
of the per-scan log, made from its snapshot.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .geometry import pose_to_xyz_ypr


@dataclass(frozen=True)
class Event:
    scan: int          # scan index at which it happened
    kind: str          # "localized", "false_positive", "loss", "reset", "kidnap", "tracking",
                       # "s2m_started", "s2m_accepted", "s2m_rejected", "s2m_cancelled", "error"
    detail: str = ""


@dataclass(frozen=True)
class S2MView:
    started_at: int               # scan k whose scan was matched
    landed_at: int                # scan k' at which the result was applied
    accepted: bool
    score: float                  # M3RSM score of the match (L0 cells hit, weighted)
    start_score: float            # score of the particle's own pose it started from
    pose: np.ndarray              # 4×4 matched pose carried forward to k' (world ← LiDAR)
    scan_world: np.ndarray        # (M, 3) float32 road-removed scan at the matched pose
    region: tuple                 # (x_min, y_min, x_max, y_max) search rectangle, world metres
    ms: float                     # wall time of match + refinement
    reason: str = ""              # why rejected, if it was


@dataclass(frozen=True)
class Snapshot:
    scan_index: int                       # index of the scan just processed (-1 before the first)
    n_scans: int
    timestamp: float
    particles: np.ndarray                 # (N, 11) state, see config.STATE_NAMES
    weights: np.ndarray                   # (N,) normalised weights
    best_index: int
    mean_pose: np.ndarray                 # 4×4 estimate (weighted mean; circular mean for angles)
    cov_xyz: np.ndarray                   # (3, 3)
    std_xyz: np.ndarray                   # (3,)
    ellipse_xy: tuple                     # 2σ ellipse: (semi-axis a, semi-axis b, angle rad)
    n_eff: float
    localized: bool
    localized_since: int | None
    scan_world: np.ndarray                # (M, 3) float32 current prepared scan at the estimate
    gt_pose: np.ndarray | None            # 4×4 ground truth at this scan, where known
    error_m: float | None                 # |estimate − truth| in 3D, where known
    pf_ms: float
    s2m: S2MView | None                   # last S2M result that landed
    s2m_running: bool
    s2m_acceptance: float                 # accepted / landed so far
    events: tuple = field(default_factory=tuple)
    paused: bool = False
    done: bool = False


@dataclass
class ScanRecord:
    """One row of the per-scan log (headless CSV, metrics A–E)."""

    scan: int
    time: float
    x: float
    y: float
    z: float
    yaw: float
    pitch: float
    roll: float
    std_x: float
    std_y: float
    std_z: float
    n_eff: float
    localized: bool
    error_m: float | None
    gt_x: float | None
    gt_y: float | None
    gt_z: float | None
    gt_yaw: float | None
    pf_ms: float
    s2m_ms: float | None
    reinit: bool

    @classmethod
    def from_snapshot(cls, snap: Snapshot, s2m_ms: float | None, reinit: bool) -> ScanRecord:
        """The row of the scan a snapshot was taken after: its estimate, and what the snapshot
        says about localization and the truth."""
        xyz_ypr = pose_to_xyz_ypr(snap.mean_pose)
        gt = snap.gt_pose
        gt_xyz_ypr = pose_to_xyz_ypr(gt) if gt is not None else [None] * 6
        std = snap.std_xyz
        return cls(
            scan=snap.scan_index, time=snap.timestamp, x=xyz_ypr[0], y=xyz_ypr[1], z=xyz_ypr[2], yaw=xyz_ypr[3],
            pitch=xyz_ypr[4], roll=xyz_ypr[5], std_x=float(std[0]), std_y=float(std[1]), std_z=float(std[2]),
            n_eff=snap.n_eff, localized=snap.localized, error_m=snap.error_m,
            gt_x=gt_xyz_ypr[0], gt_y=gt_xyz_ypr[1], gt_z=gt_xyz_ypr[2], gt_yaw=gt_xyz_ypr[3],
            pf_ms=snap.pf_ms, s2m_ms=s2m_ms, reinit=reinit)
