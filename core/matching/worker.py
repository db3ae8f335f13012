"""The RS and S2M blocks in their own process.

small_gicp holds the GIL for the 60–150 ms of a refinement (``gil_hold_ms`` in
``lidarloc bench s2m``), and road removal's normal estimation is ~45 ms of mostly GIL-holding work:
on threads they stall the particle filter (measured: the PF step took ~150 ms inside the
localizer against 35 ms alone). Here a child process loads the prior map and the BEV pyramid
from the map cache, builds its own GICP target once, and answers "match this scan from this
pose" requests with an :class:`~lidarloc.core.matching.outcome.S2MOutcome`. The outcome comes back pickled
whole: beside the road-removed scan it carries only what the viewer's inspection shows (the
search's best candidates and nodes per level, the 2D match, GICP's pose and figures), a few
hundred bytes.

In the replay clock the child runs at a lower priority (``s2m.replay_process_nice``, default
10, its scheduler autogroup too: see :func:`~lidarloc.core.worker_process.lower_priority`). The
parent waits for each match at k + n_s2m anyway, so the priority changes no result, only who
waits for the CPU: measured with two town runs side by side on 2 cores (one PF thread each), PF
median 80 ms with the child at nice 0, 43 ms at nice 10. The real-time clock keeps it at nice 0.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..worker_process import WorkerProxy, lower_priority, serve


def _make_handler(init: tuple):
    from ..maps.bev import load_or_build_pyramid
    from ..maps.mapping import PriorMap
    from ..maps.places import places_for_pyramid, uses_places
    from ..maps.point_tiles import PointTiles
    from .s2m import ScanToMapMatcher

    map_dir, map_cfg, s2m_cfg, nice, point_tiles = init
    if nice > 0:
        lower_priority(nice)
    map_dir = Path(map_dir)
    # a map held as point tiles (a city) stays on disk: mapped, read only near each match
    meta = json.loads((map_dir / "meta.json").read_text())
    prior_map = PriorMap.load(map_dir, meta, memory_map=bool(point_tiles), large=0)  # the parent chose
    if point_tiles:
        prior_map.use_tiles(PointTiles.open(Path(point_tiles), prior_map.points))

    def places(pyramid, cfg):
        # the parent's open_world built it into the map's cache with the pyramid: read here
        return places_for_pyramid(pyramid, prior_map.points, map_dir, cfg) if uses_places(cfg, pyramid.shape) else None

    pyramid = load_or_build_pyramid(prior_map, map_dir, s2m_cfg).value
    state = {"matcher": ScanToMapMatcher(prior_map, pyramid, s2m_cfg, map_cfg, places=places(pyramid, s2m_cfg))}
    _warm_up(state["matcher"])

    def handle(request):
        kind, scan, start_pose, cfg, level = request
        matcher = state["matcher"]
        if abs(cfg.match_resolution - matcher.pyramid.resolution) > 1e-9:
            # the parent rebuilt the pyramid for a new d_m before asking: it is in the cache
            matcher.pyramid = load_or_build_pyramid(prior_map, map_dir, cfg).value
            matcher.places = places(matcher.pyramid, cfg)
        elif matcher.places is None and uses_places(cfg, matcher.pyramid.shape):
            matcher.places = places(matcher.pyramid, cfg)
        matcher.cfg = cfg  # live region / angle-step changes
        return matcher.match_local(np.asarray(scan), np.asarray(start_pose), prepared=None, level=level)

    return handle


def _warm_up(matcher) -> None:
    """One small match during set-up, so the first real one does not pay the one-off costs
    (importing open3d, loading the numba kernels from their cache): measured on the real drive,
    the first whole-map match took 1.1 s against 0.3 s for the next ones, 0.6 s of it in open3d's
    import. The scan is the map's own points within 20 m of one of them, seen from 1.7 m above it;
    the result is thrown away."""
    from dataclasses import replace

    from ..geometry import pose_matrix

    pts = matcher.prior_map.points
    centre = np.asarray(pts[len(pts) // 2], np.float64) + np.array([0.0, 0.0, 1.7])
    near = matcher.map_points_near(centre[0], centre[1], 20.0)[::4]
    if len(near) < 100:
        return
    saved, matcher.cfg = matcher.cfg, replace(matcher.cfg, region_x=5.0, region_y=5.0)
    try:
        matcher.match_local(near - centre, pose_matrix(*centre, 0.0, 0.0, 0.0), level=True)
    except Exception:
        pass  # a warm-up failure is no set-up failure: the real match reports its own
    finally:
        matcher.cfg = saved


class S2MProcess(WorkerProxy):
    """Parent side: ``match_local(scan, start_pose, s2m_cfg)`` → S2MOutcome, computed in the child
    (RS, M3RSM and GICP). Set-up starts at construction and overlaps with the caller's work."""

    def __init__(self, map_dir: Path, map_cfg, s2m_cfg, nice: int = 0, point_tiles: Path | None = None):
        """``point_tiles``: the directory of the map's point tiles, for a map too big to load
        whole (:mod:`~lidarloc.core.maps.point_tiles`); the child then maps the map's files."""
        self.nice = int(nice)
        tiles = None if point_tiles is None else str(point_tiles)
        super().__init__("lidarloc.core.matching.worker", (str(map_dir), map_cfg, s2m_cfg, self.nice, tiles), "S2M")

    def match_local(self, scan: np.ndarray, start_pose: np.ndarray, s2m_cfg, level: bool = False):
        pts = np.ascontiguousarray(np.asarray(scan)[:, :3], dtype=np.float32)
        return self._worker.call(("match", pts, np.asarray(start_pose, np.float64), s2m_cfg, bool(level)))


if __name__ == "__main__":
    serve(_make_handler)
