"""What a landed S2M match leaves behind: its view for the viewer's inspection (the verdict and
why, the search, GICP, the pose carried forward), and the paper's acceptance test that writes a
match into its particle unless that lowers the particle's weight."""

from __future__ import annotations

import numpy as np

from ..snapshot import S2MView


def landed_view(
    job, k: int, outcome, accepted: bool, pose_k: np.ndarray, reason: str, through: int | None = None
) -> S2MView:
    """What the viewer shows of a landed match: the verdict and why, and what the search and
    GICP did on the way (any of them may be missing: a match refused before the search, or an
    outcome made by a stand-in matcher)."""
    scan_world = outcome.scan_world if outcome.scan_world is not None else np.zeros((0, 3), np.float32)
    result = getattr(outcome, "match", None)
    gicp = getattr(outcome, "gicp", None)
    match_pose = getattr(outcome, "match_pose", None)
    candidates = np.zeros((0, 4))
    if result is not None and getattr(result, "candidates", None) is not None:
        candidates = np.asarray(result.candidates, np.float64).reshape(-1, 4)
    return S2MView(
        started_at=job.started_at,
        landed_at=k,
        accepted=accepted,
        score=float(outcome.score),
        start_score=float(outcome.start_score),
        pose=np.asarray(pose_k),
        scan_world=scan_world,
        region=tuple(outcome.region),
        ms=float(outcome.ms),
        reason=reason or "",
        mode=job.mode,
        start_pose=np.asarray(job.start_pose, np.float64).copy(),
        candidates=candidates,
        nodes_per_level=tuple(getattr(result, "nodes_per_level", ()) or ()) if result is not None else (),
        match_pose=None if match_pose is None else np.asarray(match_pose, np.float64),
        gicp_pose=None if gicp is None else np.asarray(gicp.pose, np.float64),
        gicp_fitness=None if gicp is None else float(gicp.inlier_ratio),
        gicp_correction=() if gicp is None else (float(gicp.correction_m), float(gicp.correction_rad)),
        stage=str(getattr(outcome, "stage", "") or ""),
        carried_through=None if through is None or through == k else int(through),
        search=str(getattr(outcome, "search", "") or ""),
        ambiguous=bool(getattr(outcome, "ambiguous", False)),
        alternatives=np.asarray(getattr(outcome, "alternatives", ()) or (), np.float64).reshape(-1, 4),
    )


def write_unless_weight_drops(pf, j: int, state: np.ndarray, prepared: np.ndarray) -> tuple[bool, str]:
    """The paper's acceptance of a landed match (``s2m.reject_if_weight_drops``): write
    ``state`` into particle j and re-weight it; if its log-likelihood for the current scan is
    lower than that of its own state, the particle, and every weight, is put back as it was.
    Returns (accepted, reason).

    The paper only says a failed match "will significantly lower the weight of the particle"
    and is not accepted; "lower" is taken literally (any drop rejects: no margin), and the
    comparison is between exact log-likelihoods of the same scan, the particle's own one
    recomputed first (the weight update may have floored it, see likelihood.py)."""
    saved = (pf.states[j].copy(), pf.log_weights.copy(), pf.log_likelihoods.copy())
    before = pf.reweight(j, prepared)
    pf.set_particle(j, state)
    after = pf.reweight(j)
    if after >= before:
        return True, ""
    pf.states[j], pf.log_weights, pf.log_likelihoods = saved
    return False, f"lowers the particle's weight: log-likelihood {after:.1f} < {before:.1f}"
