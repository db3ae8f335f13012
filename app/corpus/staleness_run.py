"""The staleness of each map a corpus run's drives were localized in (:mod:`.staleness`), and,
where the world's changes are known (the built-in town with ``town.changes``), how well the stale
places find them.

Known changes are scored per changed object (a moved object is one change, at its old and its new
place): it was *in range* when an analysed scan's estimate came within the staleness range of it
and at least ``min_drives`` drives observed a cell of its footprint (one behind a building is in
no drive's sight; one seen by a single drive cannot recur), and *found* when a stale cell lies
within its footprint (half its length, at least 1 m; a tree's crown: 4.5 m) plus one cell. ``recall`` = found / in range; ``precision`` = stale places within one
cell of any changed object's footprint / all stale places. A stale place that is no change but lies
within :data:`TRAFFIC_NEAR_M` of where traffic was during an analysed scan counts as
``traffic_flagged``.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..bench.localize import bench_sequence
from .staleness import MapGrid, MapPoints, Settings, corpus_drives, judge_drive, localized_scans, stale_places

TREE_RADIUS_M = 4.5  # a grown crown reaches ~5 m
TRAFFIC_NEAR_M = 2.0


def corpus_staleness(
    folder: Path, s: Settings, cache_root: Path | None, progress: Callable[[str, int, int], None] | None = None
) -> list[dict]:
    """Per map of the corpus run in ``folder``: {name, grid, places, labels, truth}."""
    from ...core.maps.world import open_world

    report = progress or (lambda label, i, n: None)
    drives = corpus_drives(folder)
    maps: dict[str, dict] = {}
    for drive in drives:
        seq = bench_sequence(drive.spec, drive.cfg, cache_root)
        world = open_world(seq.map_source, drive.cfg, cache_root, pyramid=False, road_removal=False)
        entry = maps.get(world.map_dir.name)
        if entry is None:
            points = np.asarray(world.prior_map.points)[:, :3]
            grid = MapGrid.over(points, s.cell_m)
            entry = maps[world.map_dir.name] = dict(
                name=world.map_dir.name, grid=grid, map_points=MapPoints(points, grid), known=[], traffic=[], poses=[]
            )
        scans, poses, times = localized_scans(drive.folder, s.every)
        tick = functools.partial(report, drive.name)
        judge_drive(entry["grid"], entry["map_points"], world.lookup, seq, scans, poses, s, drive.name, tick)
        entry["poses"].append(poses[:, :2, 3])
        _known_world(entry, seq, poses, times, s)
    out = []
    for entry in maps.values():
        labels, places = stale_places(entry["grid"], s)
        truth = _score(entry, labels, places, s) if entry["known"] else None
        known = [c["xy"] for c in entry["known"]]
        out.append(
            dict(
                name=entry["name"],
                grid=entry["grid"],
                places=places,
                labels=labels,
                truth=truth,
                known=np.concatenate(known) if known else None,
            )
        )
    return out


def _to_map(seq, xy: np.ndarray) -> np.ndarray:
    T = np.asarray(seq.town_to_world)
    return xy @ T[:2, :2].T + T[:2, 3]


def _known_world(entry: dict, seq, poses: np.ndarray, times: np.ndarray, s: Settings) -> None:
    """The town's changes (once per map) and its traffic at the analysed scans' times."""
    record = getattr(seq, "changes_made", None)
    if record is None:
        return
    if not entry["known"]:
        changes = [("moved", [a, b]) for a, b in zip(record.moved, record.moved_to, strict=True)]
        changes += [(kind, [it]) for kind in ("removed", "added", "cut", "grown") for it in getattr(record, kind)]
        for kind, items in changes:
            xy = _to_map(seq, np.array([[it.x, it.y] for it in items]))
            radius = [TREE_RADIUS_M if it.kind == "tree" else max(1.0, 0.5 * max(it.length, it.width)) for it in items]
            entry["known"].append(dict(kind=kind, object=items[0].kind, xy=xy, radius=np.array(radius)))
    traffic = getattr(seq, "traffic", None)
    if traffic is None:
        return
    for T, t in zip(poses, times, strict=True):
        at = traffic.agents_at(float(t))["xy"]
        if len(at):
            xy = _to_map(seq, at)
            entry["traffic"].append(xy[np.hypot(*(xy - T[:2, 3]).T) <= s.range_m])


def _score(entry: dict, labels: np.ndarray, places: list[dict], s: Settings) -> dict:
    grid: MapGrid = entry["grid"]
    poses = np.concatenate(entry["poses"]) if entry["poses"] else np.zeros((0, 2))
    stale_xy = grid.origin + (np.argwhere(labels > 0) + 0.5) * grid.cell_m
    stale_label = labels[labels > 0]
    seen_xy = grid.origin + (np.argwhere(grid.drives_observed >= s.min_drives) + 0.5) * grid.cell_m
    in_range = found = 0
    matched_places: set[int] = set()
    by_kind: dict[str, list[int]] = {}
    for change in entry["known"]:
        d_pose = np.min(np.hypot(*(poses[:, None, :] - change["xy"][None]).T)) if len(poses) else np.inf
        seen = any(
            np.any(np.hypot(*(seen_xy - xy).T) <= r) for xy, r in zip(change["xy"], change["radius"], strict=True)
        )
        if d_pose > s.range_m or not seen:
            continue
        in_range += 1
        hit = False
        for xy, r in zip(change["xy"], change["radius"], strict=True):
            near = np.hypot(*(stale_xy - xy).T) <= r + grid.cell_m
            matched_places.update(int(k) for k in stale_label[near])
            hit |= bool(near.any())
        found += hit
        kind = by_kind.setdefault(f"{change['kind']} {change['object']}", [0, 0])
        kind[0] += hit
        kind[1] += 1
    traffic = np.concatenate(entry["traffic"]) if entry["traffic"] else np.zeros((0, 2))
    traffic_places = []
    for place in places:
        if place["place"] in matched_places:
            continue
        cells = stale_xy[stale_label == place["place"]]
        if len(traffic) and np.min(np.hypot(*(traffic[:, None, :] - cells[None]).T)) <= TRAFFIC_NEAR_M:
            traffic_places.append(place["place"])
    return {
        "changes_in_range": in_range,
        "changes_found": found,
        "recall": round(found / in_range, 3) if in_range else None,
        "stale_places": len(places),
        "places_on_changes": len(matched_places),
        "precision": round(len(matched_places) / len(places), 3) if places else None,
        "traffic_flagged": len(traffic_places) > 0,
        "traffic_places": traffic_places,
        "by_kind": {k: f"{v[0]}/{v[1]}" for k, v in sorted(by_kind.items())},
    }
