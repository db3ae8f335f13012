"""Scan-to-map matching (paper, "Scan-to-map matching" and "Particle state correction").

Two stages: M3RSM on the bird's-eye view (road-removed scan against the road-removed map, see
:mod:`lidarloc.core.matching.m3rsm`) finds x, y, yaw on a d_m / d_θ lattice; GICP against the full 3D
map (:mod:`lidarloc.core.matching.gicp`) then corrects all six degrees of freedom, starting from the 2D
match with z, pitch and roll taken from the start pose.

Acceptance (paper): a local match is accepted only if its BEV score is strictly greater than the
score of the pose it started from (computed the same way, :func:`m3rsm.score_pose`). The search
is told to report only strictly better poses, so blocks that cannot beat the start are pruned
from the outset and a start that nothing beats is rejected quickly. The translation lattice is
anchored at the start, the yaw lattice is the paper's world-fixed θ_r = −π + r·d_θ (see
:func:`m3rsm.match` for why that matters for starts already near the truth).

Beyond the paper (``s2m.refine_unbeaten_start``, on by default; off in the ``paper`` preset): a
start within the BEV's resolution of the
truth is usually not beaten by any lattice pose — on the built-in town a best particle 0.3 m and
0.2° from the truth scored 3405, the best lattice pose 3373 (exhaustive search agrees) — so the
paper's rule rejects it and GICP never gets to refine it. Then the start itself is refined by
GICP, and accepted if the refined pose's BEV score beats the start's (the same acceptance test,
applied to the refined start instead of a lattice pose); ``stage`` says which one was accepted.

Whole-map matches may go through the place index first (:mod:`.candidate_match`); a match that
lands at a later scan is carried there by :mod:`.carry`. The outcome types are in :mod:`.outcome`,
the ground height a match without a start z takes in :mod:`.ground`.
"""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

from ..config import MapConfig, PFConfig, S2MConfig
from ..errors import LidarlocError
from ..geometry import levelled, pose_matrix, pose_to_xyz_ypr, transform_points
from ..maps.bev import BEVPyramid
from ..maps.mapping import flat_surface_mask, range_filter
from ..o3d import open3d
from . import m3rsm
from .candidate_match import CandidateMatchMixin
from .candidates import window_of
from .gicp import GICPRefiner, LocalGICPRefiner
from .ground import GroundGrid, TiledGround
from .outcome import PreparedScan, S2MOutcome
from .tiled_search import match_global_tiled

#: Voxel (m) the scan is down-sampled to before its normals are estimated for road removal.
#: 0.3 m keeps the scan's near-range density close to the 0.2 m map's (so the |n_z| test behaves
#: alike on both) at half the normal-estimation cost of 0.2 m (~45 ms vs ~70 ms per scan).
ROAD_REMOVAL_VOXEL = 0.3

#: A GICP refinement that moves the pose farther than this from the 2D match is not a local
#: correction of it (the BEV lattice error is at most ~0.7·d_m and d_θ/2): the match is rejected.
GICP_MAX_SHIFT_CELLS = 2.0  # × d_m
GICP_MAX_TURN_STEPS = 3.0  # × d_θ
GICP_MIN_INLIERS = 0.3  # fraction of scan points with a map correspondence after GICP
#: Fewer occupied d_m cells than this in the road-removed scan: nothing to match (an empty road,
#: a scan of the sky); the search would return an arbitrary pose.
MIN_BEV_CELLS = 20
#: A start pose pitched or rolled more than this is not a road vehicle's attitude (the steepest
#: streets are ~19°) but a particle that tumbled where the likelihood does not hold pitch and
#: roll (the paper's, once its weights collapse): the local search then levels it, as for
#: ``level``. Trusting it cost GICP 2.5 s at 34° and 9 s at 120° (the town, VLP-16), and the
#: match was refused all the same; levelled, GICP takes ~30 ms and may succeed.
MAX_TRUSTED_TILT = math.radians(20.0)


class ScanToMapMatcher(CandidateMatchMixin):
    """The S2M block for one prior map: BEV pyramid + GICP target, both built once."""

    def __init__(
        self,
        prior_map,
        pyramid: BEVPyramid,
        s2m_cfg: S2MConfig | None = None,
        map_cfg: MapConfig | None = None,
        gicp_backend: str = "small_gicp",
        refine_unbeaten: bool | None = None,
        places=None,
    ):
        """``refine_unbeaten``: when no lattice pose beats the start (the start is already within the
        BEV's d_m / d_θ of the best it can tell), refine the start itself by GICP and accept that
        if its BEV score beats the start's — see the module docstring. False = the paper's rule
        only. None (default): as the settings in use say (``s2m.refine_unbeaten_start`` of
        ``self.cfg``, which the localizer replaces with its live settings at every match)."""
        self.refine_unbeaten = None if refine_unbeaten is None else bool(refine_unbeaten)
        self.cfg = s2m_cfg or S2MConfig()
        self.map_cfg = map_cfg or MapConfig()
        if abs(pyramid.resolution - self.cfg.match_resolution) > 1e-9:
            raise LidarlocError(
                f"BEV pyramid resolution {pyramid.resolution} m differs from "
                f"s2m.match_resolution {self.cfg.match_resolution} m"
            )
        self.prior_map = prior_map
        self.pyramid = pyramid
        # the place index (core/maps/places.py) for whole-map matches by candidates: given by the
        # caller from the map's cache, or built here on first use (uncached)
        self.places = places
        self._l0 = None  # the finest level whole, for the look-up's re-ranking (see _finest)
        # the map side is finer than the scan (but no finer than the map itself): see gicp.py
        gicp_args = dict(
            voxel=self.cfg.gicp_voxel,
            max_corr=self.cfg.gicp_max_corr,
            backend=gicp_backend,
            target_voxel=max(float(prior_map.voxel_size), self.cfg.gicp_voxel / 2.0),
        )
        tiles = getattr(prior_map, "tiles", None)
        if tiles is None:
            self.gicp = GICPRefiner(prior_map.points, **gicp_args)
            self._ground = GroundGrid(prior_map.points, pyramid.resolution)
        else:  # a map held as point tiles (a city): the map is read only near each match
            # what a scan point can pair with: the scan's range and the correspondence distance
            reach = float(self.map_cfg.scan_max_range) + self.cfg.gicp_max_corr
            self.gicp = LocalGICPRefiner(tiles, reach_m=reach, **gicp_args)
            self._ground = TiledGround(tiles, pyramid.resolution)

    def map_points_near(self, x: float, y: float, radius: float) -> np.ndarray:
        """The map's points within ``radius`` of (x, y) in x-y, (n, 3) float64 (from the point
        tiles on a tiled map: never the whole map)."""
        tiles = getattr(self.prior_map, "tiles", None)
        if tiles is not None:
            return tiles.points_near(x, y, radius).astype(np.float64)
        pts = np.asarray(self.prior_map.points, dtype=np.float64)
        return pts[np.hypot(pts[:, 0] - x, pts[:, 1] - y) <= radius]

    # ------------------------------------------------------------------------- scan preparation
    def prepare(self, scan_sensor: np.ndarray) -> PreparedScan:
        """Range-filter the scan and remove its flat surfaces (the paper's RS block)."""
        t0 = time.perf_counter()
        pts = np.asarray(scan_sensor)
        if pts.ndim != 2 or pts.shape[1] < 3 or len(pts) == 0:
            raise LidarlocError(f"scan must be (N, 3|4) with N > 0; got shape {pts.shape}")
        pts = range_filter(pts[:, :3].astype(np.float64), self.map_cfg)
        o3d = open3d()
        down = np.asarray(
            o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts)).voxel_down_sample(ROAD_REMOVAL_VOXEL).points
        )
        if len(down) < 3:
            return PreparedScan(pts, down, math.nan, (time.perf_counter() - t0) * 1e3)
        flat = flat_surface_mask(down, self.map_cfg)
        near_flat = down[flat & (np.hypot(down[:, 0], down[:, 1]) < 15.0)]
        ground_z = float(np.median(near_flat[:, 2])) if len(near_flat) >= 10 else math.nan
        return PreparedScan(pts, down[~flat], ground_z, (time.perf_counter() - t0) * 1e3)

    @staticmethod
    def _bev(road_removed: np.ndarray, pitch: float, roll: float) -> np.ndarray:
        """Project the road-removed scan to the ground plane: level it with the pose's pitch and
        roll (yaw is what the search finds), then drop z."""
        return levelled(road_removed, pitch, roll)[:, :2]

    # ------------------------------------------------------------------------------- matching
    def match_local(
        self,
        scan_sensor: np.ndarray,
        start_pose: np.ndarray,
        road_removed: bool = False,
        bev_scan: np.ndarray | None = None,
        prepared: PreparedScan | None = None,
        level: bool = False,
    ) -> S2MOutcome:
        """Match around ``start_pose`` (4×4 world ← LiDAR): translations ± (region_x, region_y), yaws
        within ± yaw_window.

        ``level``: do not trust the start pose's z, pitch and roll (a particle before localization:
        its attitude is as random as its position, up to ±30° of pitch). The scan is then levelled
        with pitch = roll = 0 and GICP starts at the map's ground height under the match, as in
        :meth:`match_global`. Measured: a filter collapsed on a wrong particle had every whole-map
        match refused because GICP had to fix 8–14° of the particle's pitch and roll. A start
        tilted more than :data:`MAX_TRUSTED_TILT` is levelled too.

        ``scan_sensor`` is the full scan (sensor frame); its flat surfaces are removed here. To skip
        that, pass the road-removed scan as ``bev_scan`` (the full scan still feeds GICP), or pass a
        road-removed scan as ``scan_sensor`` with ``road_removed=True`` (GICP then aligns only what
        survived road removal: kerbs, cars and trees still hold z. On the KITTI drive, 13 scans from
        starts ±8 m / ±57° / ±0.3 m in z: same median error, 0.04 m, 2× faster, but one 0.46 m
        outlier where the full scan gave 0.05 m)."""
        t0 = time.perf_counter()
        cfg = self.cfg
        start_pose = np.asarray(start_pose, dtype=np.float64)
        x, y, z, yaw, pitch, roll = pose_to_xyz_ypr(start_pose)
        if level or max(abs(pitch), abs(roll)) > MAX_TRUSTED_TILT:
            z, pitch, roll = math.nan, 0.0, 0.0
        prep = prepared or self._prepare_with(scan_sensor, bev_scan, road_removed)
        B = self._bev(prep.road_removed, pitch, roll)
        start_score = m3rsm.score_pose(self._near(x, y, 0.0), B, x, y, yaw)
        d = self.cfg.match_resolution
        region = (x - cfg.region_x, y - cfg.region_y, x + cfg.region_x, y + cfg.region_y)
        if len(m3rsm.scan_cells(B, d)) < MIN_BEV_CELLS:
            return self._reject(
                start_pose,
                start_score,
                start_score,
                None,
                prep,
                t0,
                {"prepare": prep.ms},
                "too few road-removed scan points to match",
                region=region,
            )
        timings = {"prepare": prep.ms}
        whole_map = self.covers_map(x, y, cfg.region_x, cfg.region_y)
        search = "exact" if whole_map else ""
        result = None
        if whole_map and self.by_candidates:
            decided, result = self._by_candidates(prep, B, z, pitch, roll, start_pose, start_score, t0, timings)
            if decided is not None:
                return decided
            if result is not None:  # no place beat the start: the start is refined below
                search = "candidates"
        if result is None and whole_map and not isinstance(self.pyramid, BEVPyramid):
            result = match_global_tiled(self.pyramid, B, cfg.angle_step)  # a city held in tiles
            if not result.score > start_score:  # as the search below reports an unbeaten start
                result = dataclasses.replace(result, x=math.nan, y=math.nan, yaw=math.nan, score=start_score)
            timings["m3rsm"] = timings.get("m3rsm", 0.0) + result.ms
        if result is None:  # a local match, the exact whole-map search, or its fallback
            result = m3rsm.match(
                self._near(x, y, max(cfg.region_x, cfg.region_y)),
                B,
                (x, y),
                (cfg.region_x, cfg.region_y),
                yaw,
                cfg.yaw_window,
                cfg.angle_step,
                min_score=start_score,
            )
            timings["m3rsm"] = timings.get("m3rsm", 0.0) + result.ms
        if math.isfinite(result.x):
            if not math.isfinite(z):
                z = self._height_under(result.x, result.y, prep)
            init = pose_matrix(result.x, result.y, z, result.yaw, pitch, roll)
            return dataclasses.replace(
                self._refine(init, prep, result, start_score, start_pose, t0, timings, whole_map), search=search
            )
        reason = "no pose in the search region scores higher than the start pose"
        refine = cfg.refine_unbeaten_start if self.refine_unbeaten is None else self.refine_unbeaten
        if refine:
            refined = self._refine(start_pose, prep, result, start_score, start_pose, t0, timings, whole_map)
            if refined.accepted:
                rx, ry, _, ryaw, _, _ = pose_to_xyz_ypr(refined.pose)
                score = m3rsm.score_pose(self._near(rx, ry, 0.0), B, rx, ry, ryaw)
                if score > start_score:
                    return dataclasses.replace(
                        refined, score=score, stage="refined_start", ms=(time.perf_counter() - t0) * 1e3, search=search
                    )
                reason += f", nor does the start refined by GICP (score {score:.0f})"
            else:
                reason += f"; refining the start failed: {refined.reason}"
            # what GICP did to the start stays in the outcome: the inspection shows it
            out = self._reject(
                start_pose,
                start_score,
                start_score,
                result,
                prep,
                t0,
                timings,
                reason,
                init=refined.match_pose,
                gicp=refined.gicp,
                stage="refined_start",
            )
            return dataclasses.replace(out, search=search)
        out = self._reject(start_pose, start_score, start_score, result, prep, t0, timings, reason)
        return dataclasses.replace(out, search=search)

    def match_global(
        self,
        scan_sensor: np.ndarray,
        road_removed: bool = False,
        bev_scan: np.ndarray | None = None,
        prepared: PreparedScan | None = None,
        start_pose: np.ndarray | None = None,
    ) -> S2MOutcome:
        """Match against the whole map (θ_r = −π + r·d_θ). z, pitch and roll for GICP come from
        ``start_pose`` if given; otherwise pitch = roll = 0 and z = map ground height under the
        match minus the scan's own ground height (its flat points within 15 m); for a scan given
        already road-removed, whose ground is gone, the configured sensor height above the map's
        ground instead."""
        t0 = time.perf_counter()
        prep = prepared or self._prepare_with(scan_sensor, bev_scan, road_removed)
        if start_pose is not None:
            _, _, z, _, pitch, roll = pose_to_xyz_ypr(np.asarray(start_pose, float))
        else:
            z, pitch, roll = math.nan, 0.0, 0.0
        B = self._bev(prep.road_removed, pitch, roll)
        if len(m3rsm.scan_cells(B, self.cfg.match_resolution)) < MIN_BEV_CELLS:
            identity = np.eye(4) if start_pose is None else np.asarray(start_pose, float)
            return self._reject(
                identity,
                math.nan,
                math.nan,
                None,
                prep,
                t0,
                {"prepare": prep.ms},
                "too few road-removed scan points to match",
                region=self.pyramid.extent,
            )
        timings = {"prepare": prep.ms}
        if self.by_candidates:
            decided, _ = self._by_candidates(prep, B, z, pitch, roll, None, math.nan, t0, timings)
            if decided is not None:
                return decided
        if isinstance(self.pyramid, BEVPyramid):
            result = m3rsm.match_global(self.pyramid, B, self.cfg.angle_step)
        else:  # a city held in tiles
            result = match_global_tiled(self.pyramid, B, self.cfg.angle_step)
        timings["m3rsm"] = timings.get("m3rsm", 0.0) + result.ms
        if not math.isfinite(z):
            z = self._height_under(result.x, result.y, prep)
        init = pose_matrix(result.x, result.y, z, result.yaw, pitch, roll)
        return dataclasses.replace(self._refine(init, prep, result, math.nan, init, t0, timings, True), search="exact")

    def _near(self, x: float, y: float, half: float):
        """The pyramid a search within ``half`` m of (x, y) reads: the map's own, or on a city held
        in tiles (:class:`~lidarloc.core.maps.tiled_bev.TiledBEV`) a window of them wide enough for
        every scan point (the same cells, so the same scores)."""
        return window_of(self.pyramid, x, y, half + float(self.map_cfg.scan_max_range))

    def covers_map(self, x: float, y: float, half_x: float, half_y: float) -> bool:
        """Whether ± (half_x, half_y) around (x, y) covers the whole pyramid: a whole-map match."""
        x0, y0, x1, y1 = self.pyramid.extent
        d = self.pyramid.resolution
        return x - half_x <= x0 + d and x + half_x >= x1 - d and y - half_y <= y0 + d and y + half_y >= y1 - d

    def _height_under(self, x: float, y: float, prep: PreparedScan) -> float:
        """Sensor z at (x, y): the map's ground height there minus the scan's own ground height
        (or the configured sensor height when the scan's ground is gone)."""
        ground = self._ground.height(x, y)
        scan_ground = prep.ground_z if math.isfinite(prep.ground_z) else -PFConfig().sensor_height
        return ground - scan_ground if math.isfinite(ground) else 0.0

    # -------------------------------------------------------------------------------- helpers
    def _prepare_with(self, scan_sensor, bev_scan, road_removed: bool) -> PreparedScan:
        if bev_scan is None and not road_removed:
            return self.prepare(scan_sensor)
        t0 = time.perf_counter()
        pts = range_filter(np.asarray(scan_sensor)[:, :3].astype(np.float64), self.map_cfg)
        bev = pts if bev_scan is None else np.asarray(bev_scan, np.float64)[:, :3]
        return PreparedScan(pts, bev, math.nan, (time.perf_counter() - t0) * 1e3)

    def _refine(self, init, prep, result, start_score, start_pose, t0, timings, whole_map=False) -> S2MOutcome:
        # a whole-map answer on a city held in tiles: GICP against a target built for that place
        verify = getattr(self.gicp, "verify", None) if whole_map else None
        g = verify(prep.points, init) if verify is not None else self.gicp.refine(prep.points, init)
        timings["gicp"] = g.ms
        cfg = self.cfg
        reason = ""
        if not np.isfinite(g.pose).all():
            reason = "GICP diverged (non-finite pose)"
        elif g.correction_m > GICP_MAX_SHIFT_CELLS * cfg.match_resolution * math.sqrt(2.0):
            reason = f"GICP moved the 2D match by {g.correction_m:.2f} m: not a local correction"
        elif g.correction_rad > GICP_MAX_TURN_STEPS * cfg.angle_step:
            reason = f"GICP turned the 2D match by {math.degrees(g.correction_rad):.1f}°: not a local correction"
        elif g.inlier_ratio < GICP_MIN_INLIERS:
            reason = f"GICP left only {100 * g.inlier_ratio:.0f}% of the scan with map correspondences"
        if reason:
            return self._reject(
                start_pose,
                result.score,
                start_score,
                result,
                prep,
                t0,
                timings,
                reason,
                init=init,
                gicp=g,
                stage="m3rsm",
            )
        pose = g.pose
        return S2MOutcome(
            accepted=True,
            pose=pose,
            score=result.score,
            start_score=start_score,
            region=result.region,
            ms=(time.perf_counter() - t0) * 1e3,
            match=result,
            match_pose=init,
            gicp=g,
            scan_world=transform_points(pose, prep.road_removed).astype(np.float32),
            timings=timings,
        )

    def _reject(
        self,
        start_pose,
        score,
        start_score,
        result,
        prep,
        t0,
        timings,
        reason,
        init=None,
        gicp=None,
        region=None,
        stage="",
    ):
        return S2MOutcome(
            accepted=False,
            pose=np.asarray(start_pose, float).copy(),
            score=float(score),
            start_score=float(start_score),
            region=tuple(region if result is None else result.region),
            ms=(time.perf_counter() - t0) * 1e3,
            reason=reason,
            match=result,
            match_pose=init,
            gicp=gicp,
            scan_world=transform_points(start_pose, prep.road_removed).astype(np.float32),
            timings=timings,
            stage=stage,
        )
