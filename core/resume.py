"""What a recording keeps of a localizer so that it can be resumed at any recorded step, and
putting a localizer back into that state.

After each step a :class:`~lidarloc.core.recording.RecordingWriter` asks
:meth:`Localizer.resume_payload <lidarloc.core.localizer.Localizer.resume_payload>`, which is
:func:`resume_payload` here, for:

- per-step fields (one row per step): the odometry poses of the step's scan and of the scan before
  it as the filter used them (T_odom←scan, float64, NaN where not registered yet), with their path
  lengths and rotation sums, the odometry run's first scan (``odom_origin``: a kidnap restarts
  it), the rules' last odometry scan (``odom_used``), and the scan an S2M match that landed in this
  step started at (``s2m_landed_started``, −1: none). About 0.3 kB per step.
- a ``checkpoint`` file every :data:`CHECKPOINT_EVERY` steps and after the first step that follows
  any control (restart, reset, kidnap, a live parameter change, tracking entry, re-initialisation):
  the filter's exact state (particles, log-weights and log-likelihoods in float64, the random
  generator's state, the protected particle, the dynamic-point history, the KLD bin count), the
  rules, the confidence and frame checks, the scan counters, the odometry buffer, the S2M
  scheduler (the match in flight, its settings and start pose; the counts) and the live
  configuration. Between a checkpoint and any later step up to the next checkpoint no control
  happened, so replaying the steps between them needs nothing but the source, the per-step
  odometry and the recorded S2M outcomes.
- an ``s2m_outcome`` file at every step where a match landed: everything the landing reads of the
  matcher's outcome, with the match's start scan, start pose, settings and ``level``. The
  road-removed scan at the match is not repeated: the step's S2M view in the recording has it.

:func:`restore` puts a freshly built localizer (same source, same configuration as the checkpoint)
into a checkpoint's state; :mod:`lidarloc.core.branch` then replays the steps after it.

Sizes per 1000 steps (``lidarloc bench branch``, the built-in town's first 1000 scans, 1000
particles): checkpoints 1.5 MB, per-step fields 0.3 MB (budget for both: 10 MB), S2M outcomes
2.4 MB (a few kB each, stored uncompressed: compressing them cost more time than it saved space). A checkpoint is small because a resampled cloud holds runs of identical particles, which
the compression folds; 1000 distinct particles would take ~0.1 MB per checkpoint, still within
the budget.
"""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np

from .config import Config, S2MConfig, update_from_dict
from .errors import LidarlocError
from .recording import ResumePayload

__all__ = ["CHECKPOINT_EVERY", "ResumePayload", "resume_payload", "restore", "checkpoint_config",
           "recorded_outcome"]

#: Steps between two checkpoints: a branch replays at most this many − 1 steps.
CHECKPOINT_EVERY = 10


def resume_payload(loc, step: int) -> ResumePayload:
    """The resume payload of the step ``loc`` just made, the ``step``-th row of its recording
    (module docstring). Call it with the localizer's lock held, before the next control."""
    k = int(loc.snapshot().scan_index)
    per_step = loc.odometry.pose_record(k)
    files: dict[str, dict[str, np.ndarray]] = {}
    landing = getattr(loc.s2m, "last_landing", None)
    landed_here = landing is not None and landing[0] == k
    per_step["s2m_landed_started"] = np.int64(landing[1].started_at if landed_here else -1)
    if landed_here:
        files["s2m_outcome"] = _outcome_arrays(landing[1], landing[2])
    if step % CHECKPOINT_EVERY == 0 or getattr(loc, "_controls_checkpointed", None) != loc.controls:
        files["checkpoint"] = _checkpoint(loc)
        loc._controls_checkpointed = loc.controls
    return ResumePayload(per_step=per_step, files=files)


# ---------------------------------------------------------------------------------------- S2M
def _outcome_arrays(job, outcome) -> dict[str, np.ndarray]:
    """An ``s2m_outcome`` file's arrays: few of them (each array of an .npz costs ~0.2 kB)."""
    match = getattr(outcome, "match", None)
    gicp = getattr(outcome, "gicp", None)
    match_pose = getattr(outcome, "match_pose", None)
    candidates = None if match is None else getattr(match, "candidates", None)
    text = {
        "cfg": None if job.cfg is None else dataclasses.asdict(job.cfg), "level": bool(job.level),
        "started_at": int(job.started_at), "accepted": bool(outcome.accepted), "reason": str(outcome.reason or ""),
        "stage": str(getattr(outcome, "stage", "") or ""),
        "timings": {k: float(v) for k, v in (getattr(outcome, "timings", None) or {}).items()},
        "match": None if match is None else {"nodes_per_level": [int(v) for v in
                                                                 (getattr(match, "nodes_per_level", ()) or ())],
                                             "candidates": candidates is not None,
                                             "found": bool(np.isfinite(getattr(match, "x", 0.0)))},
        "match_pose": match_pose is not None,
        "gicp": None if gicp is None else {"converged": bool(gicp.converged), "iterations": int(gicp.iterations)},
    }
    poses = [job.start_pose, outcome.pose]
    poses += [match_pose] if match_pose is not None else []
    poses += [gicp.pose] if gicp is not None else []
    numbers = [outcome.score, outcome.start_score, outcome.ms, *tuple(outcome.region)]
    if gicp is not None:
        numbers += [gicp.inlier_ratio, gicp.correction_m, gicp.correction_rad, gicp.ms]
    d = {"text": np.array(json.dumps(text)), "poses": np.asarray(poses, np.float64),
         "numbers": np.asarray(numbers, np.float64)}
    if candidates is not None:
        d["candidates"] = np.asarray(candidates, np.float64).reshape(-1, 4)
    return d


@dataclasses.dataclass(frozen=True)
class RecordedMatch:
    """What the landing and the S2M view read of a recorded branch-and-bound result."""

    candidates: np.ndarray | None
    nodes_per_level: tuple
    x: float = 0.0      # NaN: the search found no pose scoring higher than its start


def recorded_outcome(d: dict[str, np.ndarray], scan_world: np.ndarray | None, start_pose, cfg,
                     level: bool):
    """The matcher's outcome saved in an ``s2m_outcome`` file, if it is the outcome of exactly this
    match (bit-identical start pose, the same S2M settings and ``level``); else None."""
    from .gicp import GICPResult
    from .s2m import S2MOutcome

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
        match = RecordedMatch(d["candidates"] if text["match"]["candidates"] else None,
                              tuple(text["match"]["nodes_per_level"]),
                              0.0 if text["match"].get("found", True) else math.nan)
    i = 2
    match_pose = None
    if text["match_pose"]:
        match_pose, i = poses[i], i + 1
    gicp = None
    if text["gicp"] is not None:
        ratio, corr_m, corr_rad, gicp_ms = (float(v) for v in numbers[7:11])
        gicp = GICPResult(pose=poses[i], converged=text["gicp"]["converged"], iterations=text["gicp"]["iterations"],
                          inlier_ratio=ratio, ms=gicp_ms, correction_m=corr_m, correction_rad=corr_rad)
    return S2MOutcome(
        accepted=bool(text["accepted"]), pose=poses[1], score=score, start_score=start_score, region=region, ms=ms,
        reason=text["reason"], match=match, match_pose=match_pose, gicp=gicp, scan_world=scan_world,
        timings=text["timings"], stage=text["stage"])


# ---------------------------------------------------------------------------------------- checkpoints
def _checkpoint(loc) -> dict[str, np.ndarray]:
    s2m = loc.s2m
    job = getattr(s2m, "job", None)
    state = {
        "k": loc.k, "steps": loc.steps, "prev_t": loc._prev_t,
        "n_events": len(loc.events) - loc.recorded_events_base,
        "rules": {"localized": loc.rules.localized, "localized_since": loc.rules.localized_since,
                  "streak_start": loc.rules.streak_start, "streak_path": loc.rules.streak_path,
                  "streak_yaw0": float(loc.rules.streak_yaw0),
                  "awaiting_confirmation": bool(loc.rules.awaiting_confirmation)},
        "integrity": loc.integrity.state(), "alarm_on": bool(loc._alarm_on),
        "confidence_armed": loc._confidence.armed, "frame_best_share": float(loc._frame_check.best_share),
        "s2m": {"pending": bool(loc.s2m_pending) or not hasattr(s2m, "_generation"),
                "generation": getattr(s2m, "_generation", 0), "last_start": getattr(s2m, "_last_start", None),
                "n_landed": getattr(s2m, "n_landed", 0), "n_accepted": getattr(s2m, "n_accepted", 0),
                "job": None if job is None else {
                    "started_at": job.started_at, "particle": job.particle, "generation": job.generation,
                    "deferrals": job.deferrals, "mode": job.mode, "level": bool(job.level),
                    "cfg": None if job.cfg is None else dataclasses.asdict(job.cfg)}},
        "config": loc.cfg.to_dict(),
    }
    out = {"state": np.array(json.dumps(state))}
    if job is not None:
        out["s2m_job_start_pose"] = np.asarray(job.start_pose, np.float64)
        out["s2m_job_estimate_pose"] = np.asarray(job.estimate_pose, np.float64)
    out.update({f"pf_{k}": v for k, v in loc.pf.checkpoint().items()})
    out.update({f"odometry_{k}": v for k, v in loc.odometry.checkpoint().items()})
    return out


def checkpoint_state(data: dict[str, np.ndarray]) -> dict:
    """The JSON part of a checkpoint file."""
    try:
        return json.loads(str(data["state"]))
    except (KeyError, ValueError) as exc:
        raise LidarlocError(f"no readable state: {exc}") from None


def checkpoint_config(data: dict[str, np.ndarray]) -> Config:
    """The live configuration the localizer had at a checkpoint."""
    return update_from_dict(Config(), checkpoint_state(data)["config"])


def restore(loc, data: dict[str, np.ndarray]) -> dict:
    """Put ``loc`` (built on the same source with :func:`checkpoint_config`'s configuration, no
    step made yet) into the state of a checkpoint. Events, per-scan records and the snapshot are
    the caller's (they live in the recording). Returns the checkpoint's JSON state."""
    from .s2m_schedule import S2MJob

    state = checkpoint_state(data)
    with loc._lock:
        loc.pf.restore({k[3:]: v for k, v in data.items() if k.startswith("pf_")})
        loc.odometry.restore({k[9:]: v for k, v in data.items() if k.startswith("odometry_")})
        rules = loc.rules
        for name, value in state["rules"].items():
            setattr(rules, name, value)
        loc._confidence.armed = bool(state["confidence_armed"])
        loc._frame_check.best_share = float(state["frame_best_share"])
        loc.integrity.load(state.get("integrity", {}))     # absent in recordings made before the checks
        loc._alarm_on = bool(state.get("alarm_on", False))
        loc.k, loc.steps, loc._prev_t = int(state["k"]), int(state["steps"]), state["prev_t"]
        loc.odometry.catch_up(loc.k, loc.seq.scan, loc.seq.timestamp)
        s2m, saved = loc.s2m, state["s2m"]
        s2m.restart()
        s2m._generation, s2m._last_start = int(saved["generation"]), saved["last_start"]
        s2m.n_landed, s2m.n_accepted = int(saved["n_landed"]), int(saved["n_accepted"])
        job = saved["job"]
        if job is not None:
            cfg = S2MConfig(**job["cfg"]) if job["cfg"] is not None else loc.cfg.s2m
            start_pose = np.array(data["s2m_job_start_pose"], np.float64)
            k0 = int(job["started_at"])
            future = s2m.submit(k0, lambda: loc._odometry_scan(k0), start_pose, cfg, bool(job["level"]))
            s2m.job = S2MJob(k0, int(job["particle"]), int(job["generation"]), start_pose, future,
                             deferrals=int(job["deferrals"]), mode=str(job["mode"]), cfg=cfg, level=bool(job["level"]),
                             estimate_pose=np.array(data.get("s2m_job_estimate_pose", start_pose), np.float64))
        loc._controls_checkpointed = loc.controls
    return state
