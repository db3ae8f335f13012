"""What a scan-to-map match is made from and what it gives: the scan in the forms S2M needs
(:class:`PreparedScan`) and the match's verdict with what each stage did (:class:`S2MOutcome`)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .gicp import GICPResult
from .m3rsm import MatchResult


@dataclass(frozen=True)
class PreparedScan:
    """One scan in the forms S2M needs (all sensor frame)."""

    points: np.ndarray  # (N, 3) float64, range-filtered full scan (GICP source)
    road_removed: np.ndarray  # (M, 3) float64, flat surfaces removed (the BEV scan before projection)
    ground_z: float  # median z of the scan's flat points near the sensor (nan if none)
    ms: float


@dataclass(frozen=True)
class S2MOutcome:
    accepted: bool
    pose: np.ndarray  # 4×4 world ← LiDAR: refined match if accepted, else the start pose
    score: float  # BEV score of the accepted pose: the 2D match's, or for
    # stage "refined_start" the GICP-refined start's; = start_score
    # when rejected because nothing beat the start
    start_score: float  # BEV score of the start pose (nan in global mode)
    region: tuple  # (x_min, y_min, x_max, y_max) sensor positions searched, world m
    ms: float  # wall time of preparation + match + GICP
    reason: str = ""  # why rejected ("" if accepted)
    match: MatchResult | None = None
    match_pose: np.ndarray | None = None  # 4×4 pose of the 2D match (GICP's initial guess)
    gicp: GICPResult | None = None
    scan_world: np.ndarray | None = None  # (M, 3) float32 road-removed scan at ``pose``
    timings: dict = field(default_factory=dict)  # ms per stage: prepare, m3rsm, gicp
    stage: str = "m3rsm"  # what GICP refined, and if accepted what was accepted: "m3rsm"
    # (the 2D match) or "refined_start" (the start itself); "" when
    # rejected before GICP ran
    search: str = ""  # a whole-map match: "candidates" (the place index's places, verified) or
    # "exact" (the whole-map branch and bound); "" for a local match
    ambiguous: bool = False  # distinct places verified with close scores: rejected, not moved
    alternatives: tuple = ()  # ((x, y, yaw, score), …) the other distinct places verified, best first
