"""Views of the localizer's state, handed to the viewer and to result writers.

A snapshot is built by the localizer after each scan and never mutated afterwards, so a reader
on another thread (the viewer) needs no lock to use it. A :class:`ScanRecord` is the scan's row
of the per-scan log, made from its snapshot.

Both carry the scan's confidence, what a user without ground truth can read to tell a good
estimate from a bad one: ``n_particles`` (the particles that weighed the scan), ``n_eff_share``
(N_eff / N), ``converged`` (every position std below ``localize.std_threshold``),
``inlier_share`` and ``mean_residual_m`` (the share of the prepared scan's points within d_max of
the map at the estimate, and their mean distance to it), ``cov_xx``, ``cov_xy``, ``cov_yy`` (m²,
the particles' x-y position covariance), and, where the truth is known, ``inside_2sigma`` (the
true x-y position inside the estimate's 2σ ellipse: Mahalanobis distance ≤ 2).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .geometry import pose_to_xyz_ypr


@dataclass(frozen=True)
class Event:
    scan: int  # scan index at which it happened
    kind: str  # "localized", "false_positive", "loss", "relocalized", "false_fire", "reset",
    # "kidnap", "tracking", "confidence_low", "unconfirmed" (localized withdrawn: S2M no
    # longer confirms the estimate), "s2m_started", "s2m_accepted",
    # "s2m_rejected", "s2m_cancelled", "s2m_agrees" (real time: a match agreed with the estimate
    # before it could land), "s2m_ready", "restarted", "error"
    detail: str = ""


@dataclass(frozen=True)
class S2MView:
    started_at: int  # scan k whose scan was matched
    landed_at: int  # scan k' at which the result was applied
    accepted: bool
    score: float  # M3RSM score of the match (L0 cells hit, weighted)
    start_score: float  # score of the particle's own pose it started from
    pose: np.ndarray  # 4×4 matched pose carried forward to k' (world ← LiDAR)
    scan_world: np.ndarray  # (M, 3) float32 road-removed scan at the matched pose
    region: tuple  # (x_min, y_min, x_max, y_max) search rectangle, world metres
    ms: float  # wall time of match + refinement
    reason: str = ""  # why rejected, if it was
    # what the match did, for the viewer's S2M inspection (empty/None where not known)
    mode: str = ""  # "global" (whole map) or "local" (region around the particle)
    start_pose: np.ndarray | None = None  # 4×4 the particle's pose the match started from (scan started_at)
    candidates: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    # (K, 4) x, y, yaw (rad), score: the best poses BnB scored at the
    # finest level, best first (at most 10)
    nodes_per_level: tuple = ()  # BnB nodes expanded per pyramid level (index = level)
    match_pose: np.ndarray | None = None  # 4×4 the 2D match (GICP's initial guess), scan started_at
    gicp_pose: np.ndarray | None = None  # 4×4 after GICP, scan started_at
    gicp_fitness: float | None = None  # GICP inlier share (source points with a correspondence)
    gicp_correction: tuple = ()  # (metres, radians) GICP moved the 2D match
    stage: str = ""  # what GICP refined: "m3rsm" (the 2D match) or "refined_start" (the
    # start itself); "" if GICP never ran
    carried_through: int | None = None  # real time: the scan whose odometry carried the match,
    # when landed_at's own was not registered yet (then on at the odometry's last motion)
    search: str = ""  # a whole-map match: "candidates" (the place index's places, verified) or
    # "exact" (the whole-map branch and bound); "" for a local match
    ambiguous: bool = False  # distinct places verified with close scores: refused, the filter not moved
    alternatives: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    # (K, 4) x, y, yaw (rad), score of the other distinct places a whole-map match verified, best first


@dataclass(frozen=True)
class Snapshot:
    scan_index: int  # index of the scan just processed (-1 before the first)
    n_scans: int
    timestamp: float
    particles: np.ndarray  # (N, 11) state, see config.STATE_NAMES
    weights: np.ndarray  # (N,) normalised weights
    best_index: int
    mean_pose: np.ndarray  # 4×4 estimate (weighted mean; circular mean for angles)
    cov_xyz: np.ndarray  # (3, 3)
    std_xyz: np.ndarray  # (3,)
    ellipse_xy: tuple  # 2σ ellipse: (semi-axis a, semi-axis b, angle rad)
    n_eff: float
    localized: bool
    localized_since: int | None
    scan_world: np.ndarray  # (M, 3) float32 current prepared scan at the estimate
    gt_pose: np.ndarray | None  # 4×4 ground truth at this scan, where known
    error_m: float | None  # |estimate − truth| in 3D, where known
    pf_ms: float
    s2m: S2MView | None  # last S2M result that landed
    s2m_running: bool
    s2m_acceptance: float  # accepted / landed so far
    # confidence (module docstring); None where unknown: before the first scan, after a reset,
    # inside_2sigma without truth
    n_particles: int | None = None  # particles that weighed this scan (None: len(weights))
    converged: bool = False  # every position std < localize.std_threshold
    inlier_share: float | None = None  # share of scan points within d_max of the map at the estimate
    mean_residual_m: float | None = None  # their mean distance to the map (m)
    inside_2sigma: bool | None = None  # truth inside the 2σ x-y ellipse
    rpe_ms: float | None = None  # KISS-ICP registration time of the newest registered scan
    s2m_pending: bool = False  # S2M waits for its tables, built in the background
    log_weights: np.ndarray | None = None  # (N,) log-weights (their order survives when the weights underflow to 0)
    events: tuple = field(default_factory=tuple)
    paused: bool = False
    done: bool = False
    # Whether the filter's word can be trusted (see :mod:`lidarloc.core.rules.integrity`):
    s2m_status: str = "ready"  # "ready", "building" (its tables, in the background),
    # "held" (s2m.join_at_scan), "off" (switched off)
    s2m_status_detail: str = ""  # e.g. "road removal 40 %", "held back until scan 100"
    awaiting_confirmation: bool = False  # the PF alone meets the rule; no S2M match has agreed yet
    confirmed_at: int | None = None  # scan at which an S2M match last agreed with the estimate
    truth_alarm: str | None = None  # localized while the truth is farther than FALSE_FIRE_M:
    # "the rule says localized; the truth is 102 m away"

    @property
    def n_eff_share(self) -> float:
        """N_eff / N of the weights the estimate was computed from."""
        n = self.n_particles if self.n_particles else len(self.weights)
        return float(self.n_eff) / max(n, 1)

    @property
    def cov_xx(self) -> float:
        return float(self.cov_xyz[0, 0])

    @property
    def cov_xy(self) -> float:
        return float(self.cov_xyz[0, 1])

    @property
    def cov_yy(self) -> float:
        return float(self.cov_xyz[1, 1])


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
    n_particles: int
    n_eff_share: float
    converged: bool
    inlier_share: float | None
    mean_residual_m: float | None
    cov_xx: float
    cov_xy: float
    cov_yy: float
    inside_2sigma: bool | None

    @classmethod
    def from_snapshot(cls, snap: Snapshot, s2m_ms: float | None, reinit: bool) -> ScanRecord:
        """The row of the scan a snapshot was taken after: its estimate, and what the snapshot
        says about localization and the truth."""
        xyz_ypr = pose_to_xyz_ypr(snap.mean_pose)
        gt = snap.gt_pose
        gt_xyz_ypr = pose_to_xyz_ypr(gt) if gt is not None else [None] * 6
        std = snap.std_xyz
        return cls(
            scan=snap.scan_index,
            time=snap.timestamp,
            x=xyz_ypr[0],
            y=xyz_ypr[1],
            z=xyz_ypr[2],
            yaw=xyz_ypr[3],
            pitch=xyz_ypr[4],
            roll=xyz_ypr[5],
            std_x=float(std[0]),
            std_y=float(std[1]),
            std_z=float(std[2]),
            n_eff=snap.n_eff,
            localized=snap.localized,
            error_m=snap.error_m,
            gt_x=gt_xyz_ypr[0],
            gt_y=gt_xyz_ypr[1],
            gt_z=gt_xyz_ypr[2],
            gt_yaw=gt_xyz_ypr[3],
            pf_ms=snap.pf_ms,
            s2m_ms=s2m_ms,
            reinit=reinit,
            n_particles=int(snap.n_particles if snap.n_particles else len(snap.weights)),
            n_eff_share=snap.n_eff_share,
            converged=bool(snap.converged),
            inlier_share=snap.inlier_share,
            mean_residual_m=snap.mean_residual_m,
            cov_xx=snap.cov_xx,
            cov_xy=snap.cov_xy,
            cov_yy=snap.cov_yy,
            inside_2sigma=snap.inside_2sigma,
        )
