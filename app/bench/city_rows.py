"""bench city's global-match rows: how a scan is prepared, searched over the whole city and judged,
and the rows kept on disk so that a stopped run resumes (200 searches over 16 km² take hours).

A row depends only on the code fingerprinted in :data:`ROW_CODE`: the world and its scans, the
map and its bird's-eye-view pyramid, the searches and this file. The lookup table's modules are
left out on purpose (the global search never reads the lookup table), so that work on the
particle filter's tables does not throw away hours of kept rows; a test checks that preparing,
searching and judging a row never imports them.
"""

from __future__ import annotations

import json
import math
from functools import partial
from pathlib import Path

import numpy as np

from ...core.cache import atomic_write_file
from ...core.config import Config
from ...core.errors import LidarlocError
from ...core.geometry import pose_matrix, pose_to_xyz_ypr
from ...core.maps.mapping import flat_surface_mask, range_filter
from ...core.matching import m3rsm
from ...core.matching.tiled_search import match_global_tiled
from ...core.o3d import open3d

SUCCESS_M, SUCCESS_DEG = 2.0, 5.0
ROAD_REMOVAL_VOXEL = 0.3  # as the scan-to-map matcher prepares a scan
ROW_CODE = ("core/matching", "core/maps", "core/sequences", "core/config", "core/geometry.py", "app/bench/city_rows.py")
# The lookup table and what only a run on tiles reads (the particle filter's window follower): no
# row reads them.
ROW_CODE_EXCLUDED = (
    "core/maps/lookup.py",
    "core/maps/distance_transform.py",
    "core/maps/bricks.py",
    "core/maps/tiled_lookup.py",
    "core/maps/follow.py",
)
#: A confident answer farther than this from the truth is a wrong place (the metrics' "within 5 m").
WRONG_PLACE_M = 5.0
#: The second opinion's estimate: the truth moved this much, as a filter localized near it has it.
ESTIMATE_OFFSET = (0.4, -0.3, math.radians(1.5))


def prepare(scan: np.ndarray, cfg: Config) -> np.ndarray:
    """The scan's road-removed points (sensor frame), as the scan-to-map matcher prepares them."""
    pts = range_filter(np.asarray(scan)[:, :3].astype(np.float64), cfg.map)
    o3d = open3d()
    down = np.asarray(
        o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts)).voxel_down_sample(ROAD_REMOVAL_VOXEL).points
    )
    return down[~flat_surface_mask(down, cfg.map)] if len(down) >= 3 else down


def judge(x: float, y: float, yaw: float, truth: np.ndarray) -> tuple[bool, float]:
    """(within 2 m and 5°, metres off) of a 2D pose against a 4 × 4 true pose."""
    if not math.isfinite(x):
        return False, math.inf
    m = math.hypot(x - truth[0, 3], y - truth[1, 3])
    dyaw = abs((yaw - math.atan2(truth[1, 0], truth[0, 0]) + math.pi) % (2 * math.pi) - math.pi)
    return m <= SUCCESS_M and math.degrees(dyaw) <= SUCCESS_DEG, m


def missed(row: dict, truth: np.ndarray, district_at=None) -> dict:
    """A scan the search placed elsewhere, named: where it is, where it matched, how far off and
    at what score; with ``district_at(x, y)`` (a generated city) the districts of both places."""
    x, y, yaw = row["tiled_pose"]
    out = {
        "scan": row["scan"],
        "err_m": row["tiled_err_m"],
        "truth_xy": [float(truth[0, 3]), float(truth[1, 3])],
        "matched_xy_yaw_deg": [x, y, math.degrees(yaw) if math.isfinite(yaw) else yaw],
        "score": row["tiled_score"],
    }
    if district_at is not None:
        out["truth_district"] = district_at(truth[0, 3], truth[1, 3])
        out["matched_district"] = district_at(x, y) if math.isfinite(x) else None
    return out


def warm_up(bev, pyramid, scan: np.ndarray, angle_step: float, tiled: bool = True, shards=None) -> None:
    """Both searches once, so that numba's kernels are compiled off the clock (on the shards too)."""
    if tiled:
        _tiled(shards)(bev, scan[:, :2], angle_step)
    if pyramid is not None:
        m3rsm.match_global(pyramid, scan[:, :2], angle_step)


def _tiled(shards):
    """The tiled search, on this machine or over ``shards`` (the same answer either way)."""
    return match_global_tiled if shards is None else partial(match_global_tiled, shards=shards)


def match_row(k: int, scan: np.ndarray, truth: np.ndarray, bev, pyramid, angle_step: float, shards=None) -> dict:
    """Scan ``k``'s row: the tiled search over the whole city (``bev``; over ``shards`` where
    given, :mod:`lidarloc.core.matching.shards`), and beside it the whole-map search when its
    ``pyramid`` is given, each timed and judged against ``truth``."""
    row: dict = {"scan": int(k)}
    res = _tiled(shards)(bev, scan[:, :2], angle_step)
    row["tiled_ms"], (row["tiled_success"], row["tiled_err_m"]) = res.ms, judge(res.x, res.y, res.yaw, truth)
    # where it matched, so that a scan the search placed elsewhere can be named and looked at
    row["tiled_pose"], row["tiled_score"] = [res.x, res.y, res.yaw], res.score
    row["tiled_tiles_searched"] = res.nodes_per_level[0] if res.nodes_per_level else 0
    row["tiled_nodes"] = res.nodes_expanded
    if pyramid is not None:
        whole = m3rsm.match_global(pyramid, scan[:, :2], angle_step)
        row["whole_ms"], (row["whole_success"], _) = whole.ms, judge(whole.x, whole.y, whole.yaw, truth)
        row["same_as_whole"] = bool(whole.score == res.score)
        # best first over the whole map expands only the nodes whose bound beats the optimum:
        # what any exact search with these bounds must expand, whatever its order
        row["whole_nodes"] = whole.nodes_expanded
    return row


def candidate_row(k: int, prep, truth: np.ndarray, matcher, whole_cfg) -> dict:
    """Scan ``k``'s global localization as lidarloc runs it (``matcher``: the scan-to-map matcher
    on the city's tiles and place index; ``prep`` its prepared scan): the whole-map match from no
    start, judged (within 2 m and 5°, and a confident answer farther than 5 m is a wrong place),
    and the whole-map second opinion from an estimate near the truth (``whole_cfg``: the S2M
    settings with a region over the whole city), as a localized filter asks for it."""
    row: dict = {"scan": int(k), "prepare_ms": float(prep.ms)}
    out = matcher.match_global(None, prepared=prep)
    x, y, _, yaw, _, _ = pose_to_xyz_ypr(out.pose)
    ok, err = judge(x, y, yaw, truth) if out.accepted else (False, math.inf)
    row["global_ms"], row["global_search"] = float(out.ms), out.search
    row["global_accepted"], row["global_ambiguous"] = bool(out.accepted), bool(out.ambiguous)
    row["global_success"], row["global_err_m"] = bool(ok), float(err)
    row["global_confident_wrong"] = bool(out.accepted and err > WRONG_PLACE_M)
    row["global_pose"], row["global_score"] = [x, y, yaw], float(out.score)
    row["global_alternatives"] = [[float(v) for v in a] for a in out.alternatives]
    row["global_reason"] = out.reason
    row["global_timings"] = {key: float(v) for key, v in out.timings.items()}
    dx, dy, dyaw = ESTIMATE_OFFSET
    tx, ty, tz, tyaw, tpitch, troll = pose_to_xyz_ypr(truth)
    estimate = pose_matrix(tx + dx, ty + dy, tz, tyaw + dyaw, tpitch, troll)
    saved, matcher.cfg = matcher.cfg, whole_cfg
    try:
        check = matcher.match_local(None, estimate, prepared=prep, level=True)
    finally:
        matcher.cfg = saved
    cx, cy, _, cyaw, _, _ = pose_to_xyz_ypr(check.pose)
    row["second_ms"], row["second_search"] = float(check.ms), check.search
    row["second_agrees"] = bool(check.accepted and judge(cx, cy, cyaw, truth)[0])
    return row


class GlobalRows:
    """The global matches done so far, one row a scan, kept in ``directory/rows.json`` (rewritten
    whole after each scan, atomically) so that a run stopped at any moment resumes at the next
    scan: 200 searches over a 16 km² city take hours. A directory holding another source's,
    configuration's or code's rows is refused, never mixed in."""

    def __init__(self, directory: Path, identity: dict):
        self.path = Path(directory) / "rows.json"
        self.identity = json.loads(json.dumps(identity, sort_keys=True, default=str))
        self.rows: dict[int, dict] = {}
        if self.path.is_file():
            try:
                kept = json.loads(self.path.read_text())
                rows = {int(r["scan"]): r for r in kept["rows"]}
                theirs = kept["identity"]
            except (ValueError, KeyError, TypeError) as exc:
                raise LidarlocError(
                    f"{self.path}: not a bench city rows file ({exc}); remove it or use another --out"
                ) from None
            if theirs != self.identity:
                raise LidarlocError(
                    f"{self.path}: holds the global matches of another source, configuration or version of "
                    "lidarloc's code; use another --out"
                )
            self.rows = rows

    def add(self, row: dict) -> None:
        self.rows[int(row["scan"])] = row
        data = {"identity": self.identity, "rows": list(self.rows.values())}
        text = json.dumps(data, indent=1, default=lambda v: v.item())  # numpy scalars as plain numbers
        atomic_write_file(self.path, lambda tmp: tmp.write_text(text))


def scan_order(n: int, count: int, seed: int) -> list[int]:
    """``count`` scans of ``n`` in a seeded random order: the first ones of a longer list are the
    same scans, so rows kept from a shorter or stopped run are a fair sample of the longer one."""
    return [int(k) for k in np.random.default_rng(seed).permutation(n)[: min(count, n)]]
