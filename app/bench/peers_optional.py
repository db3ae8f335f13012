"""The optional global-localization peers of ``lidarloc bench peers``: KISS-Matcher
(:mod:`.peers_kiss_matcher`) and MapClosures (:mod:`.peers_mapclosures`), installed with
``pip install 'lidarloc[peers]'``. Each registers the same scans of a global part as M3RSM and
FPFH + RANSAC did, against the same map, on the same machine, judged by the same rule (2 m and 5°
of the truth); a peer whose package is absent is skipped with a one-line reason.

Fields per peer ``P`` of a global part (and over both parts in the headline), as FPFH + RANSAC's:
``P_success`` (the share of scans within 2 m / 5°), ``P_success_count``, ``P_ms_median``,
``P_err_m_median``, ``P_accepted`` (the share the peer itself called good: KISS-Matcher's
``valid``, a MapClosures closure above its inlier threshold); besides, ``P_repeatable`` (the first
scan registered twice gave the same pose) and ``P_settings``. MapClosures adds
``mapclosures_stitch_ms_median`` (its query's local map) and ``mapclosures_single_*`` (one scan as
the query). What each builds once per map (MapClosures' tile database) is off the clock and
reported beside (``mapclosures_build_s``).
"""

from __future__ import annotations

import importlib
import math
import time
from pathlib import Path

import numpy as np

from ...core.config import Config
from ...core.maps.mapping import load_or_build_map, range_filter
from ...core.sequences.factory import SourceSpec
from . import peers_kiss_matcher, peers_mapclosures
from .common import median, open_source, pose_error

SUCCESS_M, SUCCESS_DEG = 2.0, 5.0  # as FPFH + RANSAC's (peers_global)
#: peer → (module imported, pip name)
PACKAGES = {
    "kiss_matcher": (peers_kiss_matcher.MODULE, peers_kiss_matcher.PIP_NAME),
    "mapclosures": (peers_mapclosures.MODULE, peers_mapclosures.PIP_NAME),
}
REPEAT_ATOL = 1e-9  # two poses of one scan whose entries differ by no more are the same


def missing(peer: str) -> str | None:
    """Why ``peer`` cannot run here (one line), or None where its package imports."""
    module, pip_name = PACKAGES[peer]
    try:
        importlib.import_module(module)
    except ImportError as exc:
        return f"{pip_name} is not installed ({exc}); pip install 'lidarloc[peers]'"
    return None


def _judge(T: np.ndarray | None, truth: np.ndarray) -> tuple[bool, float, float]:
    if T is None or not np.isfinite(T).all():
        return False, math.inf, math.inf
    m, deg = pose_error(T, truth)
    return m <= SUCCESS_M and deg <= SUCCESS_DEG, m, deg


def _timed(row: dict, name: str, call, truth: np.ndarray) -> None:
    t = time.perf_counter()
    T, accepted = call()
    row[f"{name}_ms"] = (time.perf_counter() - t) * 1e3
    row[f"{name}_accepted"] = bool(accepted)
    row[f"{name}_success"], row[f"{name}_err_m"], row[f"{name}_err_deg"] = _judge(T, truth)


def _repeat(first: np.ndarray | None, again: np.ndarray | None) -> tuple[bool, float]:
    """Whether two poses of the same scan are the same, and how far apart their positions are (m;
    inf where only one of them is a pose)."""
    if first is None or again is None:
        return first is None and again is None, 0.0 if first is None and again is None else math.inf
    gap = float(np.linalg.norm(first[:3, 3] - again[:3, 3]))
    return bool(np.allclose(first, again, rtol=0.0, atol=REPEAT_ATOL)), gap


def summarize(rows: list[dict], name: str) -> dict:
    """A peer's figures over the rows, the shape of FPFH + RANSAC's."""
    ok = [bool(r[f"{name}_success"]) for r in rows]
    return {
        f"{name}_success": float(np.mean(ok)) if ok else 0.0,
        f"{name}_success_count": int(sum(ok)),
        f"{name}_ms_median": median(r[f"{name}_ms"] for r in rows),
        f"{name}_err_m_median": median(r[f"{name}_err_m"] for r in rows),
        f"{name}_accepted": float(np.mean([r[f"{name}_accepted"] for r in rows])) if rows else 0.0,
    }


def add_optional_peers(
    part: dict, spec: SourceSpec, cfg: Config, cache_root: Path | None = None, progress=None
) -> dict[str, str]:
    """Register the scans of ``part`` (a global part: its ``rows``' ``scan``) by each optional
    peer whose package imports, adding its fields to the rows and to ``part``; returns the peers
    skipped, each with its reason. The scans are those of ``spec``, the map the one the part ran on."""
    skipped = {peer: reason for peer in PACKAGES if (reason := missing(peer)) is not None}
    running = [peer for peer in PACKAGES if peer not in skipped]
    if not running:
        return skipped
    seq = open_source(spec, cfg, "peers", need_poses=True)
    prior, map_dir, _ = load_or_build_map(seq.map_source, cfg.map, cache_root)
    rows = part["rows"]
    scans = [int(r["scan"]) for r in rows]

    def prepared(k: int) -> np.ndarray:
        return range_filter(seq.scan(k), cfg.map)[:, :3]

    if "kiss_matcher" in running:
        peer = peers_kiss_matcher.KissMatcherPeer(prior.points)
        # the first scan twice, off the clock: a warm-up, and whether it answers the same twice
        first, again = peer.register(prepared(scans[0]))[0], peer.register(prepared(scans[0]))[0]
        for j, (row, k) in enumerate(zip(rows, scans)):
            pts = prepared(k)
            _timed(row, "kiss_matcher", lambda: peer.register(pts), seq.pose(k))
            if progress is not None:
                progress("kiss_matcher", j + 1, len(rows))
        part.update(summarize(rows, "kiss_matcher"))
        same, gap = _repeat(first, again)
        part.update(
            kiss_matcher_repeatable=same,
            kiss_matcher_repeat_gap=gap,
            kiss_matcher_settings=peers_kiss_matcher.settings(),
        )
    if "mapclosures" in running:
        part.update(_mapclosures(seq, prior, map_dir, rows, scans, prepared, progress))
    return skipped


def _mapclosures(seq, prior, map_dir, rows: list[dict], scans: list[int], prepared, progress) -> dict:
    """MapClosures on the rows' scans: a 10-scan local map as the query (its figure) and the scan
    alone (``mapclosures_single_*``), each on a tile database of its own."""
    from ...core.odometry.rpe import load_or_build_odometry

    odometry = load_or_build_odometry(seq, map_dir).value
    t0 = time.perf_counter()
    local_db = peers_mapclosures.MapClosuresDatabase(prior.points)
    build_s = time.perf_counter() - t0
    single_db = peers_mapclosures.MapClosuresDatabase(prior.points)
    # the same first query of a database built the same way: whether MapClosures answers the same
    # (asked twice of one database, the second would meet the first, which it adds to it)
    twin_db = peers_mapclosures.MapClosuresDatabase(prior.points)
    first = again = None
    for j, (row, k) in enumerate(zip(rows, scans)):
        poses = peers_mapclosures.local_poses(odometry, k)
        clouds = [prepared(i) for i in poses]  # read from disk before the clock starts
        t = time.perf_counter()
        query = local_db.local_map(clouds, list(poses.values()))
        row["mapclosures_stitch_ms"] = (time.perf_counter() - t) * 1e3
        row["mapclosures_local_scans"] = len(clouds)
        if j == 0:  # the first query, off the clock: a warm-up, and whether the twin answers the same
            first, again = local_db.query(query)[0], twin_db.query(query)[0]

        def closure(db, cloud):
            T, inliers = db.query(cloud)
            return T, inliers > peers_mapclosures.CONFIG["inliers_threshold"]

        single = single_db.local_map(clouds[-1:], [np.eye(4)])  # the scan alone, in the same voxel map
        truth = seq.pose(k)
        _timed(row, "mapclosures", lambda: closure(local_db, query), truth)
        _timed(row, "mapclosures_single", lambda: closure(single_db, single), truth)
        if progress is not None:
            progress("mapclosures", j + 1, len(rows))
    same, gap = _repeat(first, again)
    return {
        **summarize(rows, "mapclosures"),
        "mapclosures_stitch_ms_median": median(r["mapclosures_stitch_ms"] for r in rows),
        **summarize(rows, "mapclosures_single"),
        "mapclosures_repeatable": same,
        "mapclosures_repeat_gap": gap,
        "mapclosures_tiles": len(local_db.tiles),
        "mapclosures_build_s": build_s,
        "mapclosures_settings": peers_mapclosures.settings(),
    }


def notes(result: dict) -> list[str]:
    """The one-line notices ``bench peers`` prints beside its figures: each peer skipped and why,
    each peer that did not answer the same twice."""
    lines = [f"bench peers: {peer} skipped: {reason}" for peer, reason in result.get("skipped", {}).items()]
    for part in ("global_town", "global_real"):
        for peer in PACKAGES:
            if result.get(part, {}).get(f"{peer}_repeatable") is False:
                gap = result[part][f"{peer}_repeat_gap"]
                lines.append(
                    f"bench peers: {peer} is not deterministic: the same scan twice gave poses {gap:.3g} m apart "
                    f"({part}; its API takes no seed)"
                )
    return lines
