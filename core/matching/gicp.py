"""6-DoF refinement of a scan-to-map match by Generalized ICP against the 3D prior map
(paper, "Scan-to-map matching": the 2D BEV match fixes x, y, yaw to d_m / d_θ; GICP then corrects
the full pose in 3D).

The map side (down-sampled map, per-point covariances, KD-tree) is built once per map in
:class:`GICPRefiner`'s constructor; each refinement only pre-processes the scan.

Library choice: small_gicp. Measured on the KITTI raw drive 0013 (``lidarloc bench s2m``,
``gicp_comparison``: 25 scans, start = ground truth perturbed by up to ±0.5 m in x, y and ±1.25°
in yaw — the 2D lattice error —, scan voxel 0.5 m, 20 neighbours, 2 m correspondence distance,
30 iterations, one thread; medians (max); 2 cores shared with other jobs, load ≈ 1.5–2):

======================  ==========  ==============  ==============  ===========  ===========
backend / map voxel     ms / call   error m         error °         map build s  GIL
======================  ==========  ==============  ==============  ===========  ===========
small_gicp / 0.25 m     142         0.046 (0.14)    0.052 (0.21)    1.1          held
small_gicp / 0.5 m       91         0.075 (0.40)    0.092 (0.23)    0.4          held
open3d / 0.25 m         590         0.039 (0.08)    0.063 (0.17)    2.6          released
======================  ==========  ==============  ==============  ===========  ===========

* small_gicp with a prebuilt target (``preprocess_points`` once, then ``align(target, source,
  tree, …)``) does no per-call map work. With the map as coarse as the scan (0.5 m) it converged
  0.2–0.4 m off the ground truth on scans 20–36 of the drive, even when started *at* the truth
  (open3d with a 0.5 m map did not); a map twice as fine as the scan removes that bias for
  ~1.5× the time, hence ``target_voxel`` defaults to voxel / 2. (A 1.0 m scan voxel against the
  0.25 m map was as accurate again and ~40 % faster: s2m.gicp_voxel is worth revisiting.)
* open3d ``registration_generalized_icp`` builds a KD-tree of the target inside every call, so
  the map is cropped to the scan's reach first (covariances are precomputed once and survive the
  crop). It is slightly more accurate, and it releases the GIL, but costs ~4× the CPU per call.

On two cores CPU time is the scarce resource: an S2M match every n_s2m = 2 scans (200 ms) fits
with small_gicp, not with open3d. The price is that small_gicp holds the GIL for the 60–150 ms
of a refinement (``gil_hold_ms`` in the bench): Python threads such as the particle filter's
stall meanwhile; numba ``nogil`` kernels already running do not. The localizer therefore runs
the S2M block in a child process (:mod:`lidarloc.core.matching.worker`). ``backend="open3d"`` remains
available.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from ..errors import LidarlocError
from ..maps.tiling import usable_cores


@dataclass(frozen=True)
class GICPResult:
    pose: np.ndarray  # 4×4 refined world ← LiDAR
    converged: bool
    iterations: int
    inlier_ratio: float  # source points with a correspondence within max_corr at the end
    ms: float
    correction_m: float  # |translation change| from the initial guess
    correction_rad: float  # rotation angle of the change from the initial guess


def _rot_angle(R: np.ndarray) -> float:
    return float(math.acos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)))


def _result(
    init: np.ndarray, pose: np.ndarray, converged: bool, iterations: int, inlier_ratio: float, t0: float
) -> GICPResult:
    delta = np.linalg.inv(init) @ pose
    return GICPResult(
        pose=pose,
        converged=bool(converged),
        iterations=int(iterations),
        inlier_ratio=float(inlier_ratio),
        ms=(time.perf_counter() - t0) * 1e3,
        correction_m=float(np.linalg.norm(delta[:3, 3])),
        correction_rad=_rot_angle(delta[:3, :3]),
    )


class GICPRefiner:
    """GICP of scans against one prior map, small_gicp backend (the default) or open3d."""

    def __init__(
        self,
        map_points: np.ndarray,
        voxel: float = 0.5,
        max_corr: float = 2.0,
        num_neighbors: int = 20,
        max_iterations: int = 30,
        backend: str = "small_gicp",
        crop_radius: float = 90.0,
        target_voxel: float | None = None,
        thinned: bool = False,
    ):
        """``voxel``: scan (source) down-sampling; ``target_voxel``: map down-sampling, default
        voxel / 2 (a target as coarse as the scan biased small_gicp by 0.2–0.4 m on part of the
        KITTI drive, see the module docstring). ``thinned``: ``map_points`` are already one
        centroid per ``target_voxel`` (:meth:`~lidarloc.core.maps.point_tiles.PointTiles.thinned`),
        so only the target's k-d tree and covariances are made (small_gicp)."""
        if backend not in ("small_gicp", "open3d"):
            raise LidarlocError(f"unknown GICP backend '{backend}': expected small_gicp or open3d")
        pts = np.ascontiguousarray(np.asarray(map_points)[:, :3], dtype=np.float64)
        if len(pts) == 0:
            raise LidarlocError("cannot register against an empty map")
        self.backend = backend
        self.voxel = float(voxel)
        self.target_voxel = float(target_voxel if target_voxel is not None else voxel / 2.0)
        self.max_corr = float(max_corr)
        self.num_neighbors = int(num_neighbors)
        self.max_iterations = int(max_iterations)
        self.crop_radius = float(crop_radius)
        t0 = time.perf_counter()
        if backend == "small_gicp":
            import small_gicp

            self._sg = small_gicp
            if thinned:
                # Each point's covariance is its own (no sum across threads), so the target is the
                # same on any number of threads: all the cores for the ~70 % of a verification
                # target's build that these two take. The down-sampling stays on one thread, where
                # small_gicp's is deterministic.
                self._target = small_gicp.PointCloud(pts)
                self._tree = small_gicp.KdTree(self._target, num_threads=TARGET_THREADS)
                small_gicp.estimate_covariances(self._target, self._tree, self.num_neighbors, TARGET_THREADS)
            else:
                self._target, self._tree = small_gicp.preprocess_points(
                    pts, downsampling_resolution=self.target_voxel, num_neighbors=self.num_neighbors, num_threads=1
                )
            self.n_target = int(self._target.size())
        else:
            from ..o3d import open3d

            o3d = open3d()
            self._o3d = o3d
            pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts)).voxel_down_sample(self.target_voxel)
            pcd.estimate_covariances(o3d.geometry.KDTreeSearchParamKNN(self.num_neighbors))
            self._target = pcd
            self.n_target = len(pcd.points)
        self.build_ms = (time.perf_counter() - t0) * 1e3

    def refine(self, scan_points: np.ndarray, init: np.ndarray) -> GICPResult:
        """Align ``scan_points`` (sensor frame, (N, ≥3)) to the map starting from ``init``
        (world ← LiDAR); returns the refined pose and diagnostics."""
        t0 = time.perf_counter()
        init = np.asarray(init, dtype=np.float64)
        pts = np.ascontiguousarray(np.asarray(scan_points)[:, :3], dtype=np.float64)
        if len(pts) < 10:
            return _result(init, init.copy(), False, 0, 0.0, t0)
        if self.backend == "small_gicp":
            src, _ = self._sg.preprocess_points(
                pts, downsampling_resolution=self.voxel, num_neighbors=self.num_neighbors, num_threads=1
            )
            res = self._sg.align(
                self._target,
                src,
                self._tree,
                init,
                registration_type="GICP",
                max_correspondence_distance=self.max_corr,
                num_threads=1,
                max_iterations=self.max_iterations,
            )
            n_src = max(int(src.size()), 1)
            return _result(
                init, np.array(res.T_target_source), res.converged, res.iterations, res.num_inliers / n_src, t0
            )
        o3d = self._o3d
        reg = o3d.pipelines.registration
        src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts)).voxel_down_sample(self.voxel)
        src.estimate_covariances(o3d.geometry.KDTreeSearchParamKNN(self.num_neighbors))
        c = init[:3, 3]
        r = np.array([self.crop_radius, self.crop_radius, self.crop_radius])
        target = self._target.crop(o3d.geometry.AxisAlignedBoundingBox(c - r, c + r))
        crit = reg.ICPConvergenceCriteria(max_iteration=self.max_iterations)
        res = reg.registration_generalized_icp(
            src, target, self.max_corr, init, reg.TransformationEstimationForGeneralizedICP(), crit
        )
        # open3d does not report convergence; fitness is its inlier ratio
        return _result(init, np.array(res.transformation), True, self.max_iterations, res.fitness, t0)


#: Threads a thinned target's k-d tree and covariances are made on (see GICPRefiner): the cores
#: this process may use. On a quiet 2-core machine the second core takes about half of the
#: covariances; beside other jobs it gives nothing (a target near a 1 km² city scan: 328 ms on 2
#: threads, 296 ms on 1, at load 15).
TARGET_THREADS = usable_cores()
#: m, the map's down-sampling in a target built to verify one whole-map answer (the tracking
#: target's is half the scan's 0.5 m voxel): a quarter of the points, built ~4× faster.
VERIFY_TARGET_VOXEL = 0.5
#: m, a verification target serves later answers within this distance of its guess.
VERIFY_RECENTRE_M = 10.0
#: m, the map around a guess a verification target holds: most of a scan's points lie within it,
#: and a disc of 60 m holds half the points of the tracking target's 82 m.
VERIFY_REACH_M = 60.0


class LocalGICPRefiner:
    """GICP against the map near each match, for a map held as point tiles (a city). The target is
    the map within ``reach_m`` (the scan's range plus the correspondence distance: everything a
    scan point can pair with) plus ``recentre_m`` of the match's initial guess in x-y, and serves
    every later match whose guess stays within ``recentre_m`` of its centre; a guess farther off
    builds the next one around itself. One target is held at a time: small_gicp keeps ~210 bytes
    per target point, so a disc of 142 m on the 4 × 4 km city holds 0.87–1.6 M points and
    186–344 MB (measured in four districts). A target took 2.1–4.1 s to build there (2 shared
    cores at load ~6): once per ``recentre_m`` or more of driving, in the S2M process, whose
    matches wait meanwhile."""

    def __init__(self, tiles, reach_m: float = 82.0, recentre_m: float = 60.0, **gicp_args):
        self.tiles = tiles
        self.reach_m = float(reach_m)
        self.recentre_m = float(recentre_m)
        self.gicp_args = gicp_args
        self.centre: tuple[float, float] | None = None
        self._target: GICPRefiner | None = None
        self._verify_target: tuple[tuple[float, float], GICPRefiner] | None = None
        self.builds = 0  # targets built so far
        # the map thinned for verification targets: made once per map (cached with its tiles) now,
        # not at the first whole-map answer, which would wait for it
        self._verify_tiles = tiles.thinned(max(VERIFY_TARGET_VOXEL, gicp_args.get("target_voxel") or 0.0))

    def target_for(self, x: float, y: float) -> GICPRefiner:
        """The GICP target for a guess at (x, y): the current one while (x, y) is within
        ``recentre_m`` of its centre, else one built around (x, y)."""
        if self._target is not None and self.centre is not None:
            if math.hypot(x - self.centre[0], y - self.centre[1]) <= self.recentre_m:
                return self._target
        half = self.reach_m + self.recentre_m
        pts = self.tiles.points_near(x, y, half)
        if len(pts) == 0:
            raise LidarlocError(f"no map points within {half:.0f} m of ({x:.1f}, {y:.1f}): nothing to register against")
        self._target = None  # the old target goes before the new one is built: never two resident
        self._target = GICPRefiner(pts, **self.gicp_args)
        self.centre = (x, y)
        self.builds += 1
        return self._target

    def refine(self, scan_points: np.ndarray, init: np.ndarray) -> GICPResult:
        init = np.asarray(init, dtype=np.float64)
        try:
            target = self.target_for(float(init[0, 3]), float(init[1, 3]))
        except LidarlocError:  # off the map: nothing converges there
            return _result(init, init.copy(), False, 0, 0.0, time.perf_counter())
        return target.refine(scan_points, init)

    def verify(self, scan_points: np.ndarray, init: np.ndarray) -> GICPResult:
        """GICP for a whole-map answer anywhere in the city: against the tracking target where the
        guess lies within it, else against a target built for this guess only — the map within
        :data:`VERIFY_REACH_M` (not the tracking target's reach plus ``recentre_m``), down-sampled to
        :data:`VERIFY_TARGET_VOXEL` — so that checking a place costs a fraction of a second, not the
        seconds of a tracking target (measured on the 16 km² city: docs/global-localization.md).
        The down-sampled map is read from the point tiles thinned once per map
        (:meth:`~lidarloc.core.maps.point_tiles.PointTiles.thinned`): a sixth of the points, and no
        down-sampling per answer, which with the raw points took 80–160 ms of a 460 ms match on
        the 1 km² city (docs/benchmarks/city.md). The last such target is kept for the next answer
        at the same place."""
        init = np.asarray(init, dtype=np.float64)
        x, y = float(init[0, 3]), float(init[1, 3])
        if self._target is not None and self.centre is not None:
            if math.hypot(x - self.centre[0], y - self.centre[1]) <= self.recentre_m:
                return self._target.refine(scan_points, init)
        quick = self._verify_target
        if quick is None or math.hypot(x - quick[0][0], y - quick[0][1]) > VERIFY_RECENTRE_M:
            # the map near the guess, already down-sampled tile by tile (once per map)
            pts = self._verify_tiles.points_near(x, y, min(self.reach_m, VERIFY_REACH_M))
            if len(pts) == 0:  # off the map: nothing converges there
                return _result(init, init.copy(), False, 0, 0.0, time.perf_counter())
            args = {**self.gicp_args, "target_voxel": self._verify_tiles.voxel, "thinned": True}
            self._verify_target = None  # the old one goes first: never two resident
            self._verify_target = quick = ((x, y), GICPRefiner(pts, **args))
        return quick[1].refine(scan_points, init)
