"""An S2M outcome as a recording keeps it, and back: everything a landing reads of the matcher's
outcome, with the match's start scan, start pose, settings and ``level`` (the road-removed scan
at the match is not repeated: the step's S2M view in the recording has it). A resumed run uses a
recorded outcome instead of running the matcher again when the match is exactly the same."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np

from .gicp import GICPResult
from .outcome import S2MOutcome


def outcome_arrays(job, outcome) -> dict[str, np.ndarray]:
    """An ``s2m_outcome`` file's arrays: few of them (each array of an .npz costs ~0.2 kB)."""
    match = getattr(outcome, "match", None)
    gicp = getattr(outcome, "gicp", None)
    match_pose = getattr(outcome, "match_pose", None)
    candidates = None if match is None else getattr(match, "candidates", None)
    text = {
        "cfg": None if job.cfg is None else dataclasses.asdict(job.cfg),
        "level": bool(job.level),
        "started_at": int(job.started_at),
        "accepted": bool(outcome.accepted),
        "reason": str(outcome.reason or ""),
        "stage": str(getattr(outcome, "stage", "") or ""),
        "search": str(getattr(outcome, "search", "") or ""),
        "ambiguous": bool(getattr(outcome, "ambiguous", False)),
        "alternatives": [[float(v) for v in a] for a in (getattr(outcome, "alternatives", ()) or ())],
        "timings": {k: float(v) for k, v in (getattr(outcome, "timings", None) or {}).items()},
        "match": None
        if match is None
        else {
            "nodes_per_level": [int(v) for v in (getattr(match, "nodes_per_level", ()) or ())],
            "candidates": candidates is not None,
            "found": bool(np.isfinite(getattr(match, "x", 0.0))),
        },
        "match_pose": match_pose is not None,
        "gicp": None if gicp is None else {"converged": bool(gicp.converged), "iterations": int(gicp.iterations)},
    }
    poses = [job.start_pose, outcome.pose]
    poses += [match_pose] if match_pose is not None else []
    poses += [gicp.pose] if gicp is not None else []
    numbers = [outcome.score, outcome.start_score, outcome.ms, *tuple(outcome.region)]
    if gicp is not None:
        numbers += [gicp.inlier_ratio, gicp.correction_m, gicp.correction_rad, gicp.ms]
    d = {
        "text": np.array(json.dumps(text)),
        "poses": np.asarray(poses, np.float64),
        "numbers": np.asarray(numbers, np.float64),
    }
    if candidates is not None:
        d["candidates"] = np.asarray(candidates, np.float64).reshape(-1, 4)
    return d


@dataclasses.dataclass(frozen=True)
class RecordedMatch:
    """What the landing and the S2M view read of a recorded branch-and-bound result."""

    candidates: np.ndarray | None
    nodes_per_level: tuple
    x: float = 0.0  # NaN: the search found no pose scoring higher than its start


def recorded_outcome(d: dict[str, np.ndarray], scan_world: np.ndarray | None, start_pose, cfg, level: bool):
    """The matcher's outcome saved in an ``s2m_outcome`` file, if it is the outcome of exactly this
    match (bit-identical start pose, the same S2M settings and ``level``); else None."""
    text = json.loads(str(d["text"]))
    poses, numbers = d["poses"], d["numbers"]
    if not np.array_equal(poses[0], np.asarray(start_pose, np.float64)):
        return None
    cfg_now = None if cfg is None else dataclasses.asdict(cfg)
    if bool(text["level"]) != bool(level) or text["cfg"] != cfg_now:
        return None
    score, start_score, ms = (float(v) for v in numbers[:3])
    region = tuple(float(v) for v in numbers[3:7])
    match = None
    if text["match"] is not None:
        match = RecordedMatch(
            d["candidates"] if text["match"]["candidates"] else None,
            tuple(text["match"]["nodes_per_level"]),
            0.0 if text["match"].get("found", True) else math.nan,
        )
    i = 2
    match_pose = None
    if text["match_pose"]:
        match_pose, i = poses[i], i + 1
    gicp = None
    if text["gicp"] is not None:
        ratio, corr_m, corr_rad, gicp_ms = (float(v) for v in numbers[7:11])
        gicp = GICPResult(
            pose=poses[i],
            converged=text["gicp"]["converged"],
            iterations=text["gicp"]["iterations"],
            inlier_ratio=ratio,
            ms=gicp_ms,
            correction_m=corr_m,
            correction_rad=corr_rad,
        )
    return S2MOutcome(
        accepted=bool(text["accepted"]),
        pose=poses[1],
        score=score,
        start_score=start_score,
        region=region,
        ms=ms,
        reason=text["reason"],
        match=match,
        match_pose=match_pose,
        gicp=gicp,
        scan_world=scan_world,
        timings=text["timings"],
        stage=text["stage"],
        search=text.get("search", ""),
        ambiguous=bool(text.get("ambiguous", False)),
        alternatives=tuple(tuple(a) for a in text.get("alternatives", ())),
    )
