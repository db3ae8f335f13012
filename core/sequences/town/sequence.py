"""The town as a :class:`~..base.Sequence`: lay it out, drive through it, and scan it on demand."""

from __future__ import annotations

import functools
import hashlib
import time
from pathlib import Path

import numpy as np
from scipy import ndimage

from ...config import TownConfig
from ...errors import DataError
from ...geometry import inv_pose, rotation_zyx
from ..base import Sequence, check_poses, rebase_poses
from ..kitti_io import cam0_to_lidar_poses, read_pose_lines, read_tr
from ..lidar_sim import LidarModel, RaycastLidar
from .constants import BUILD_REACH, CELL, GROUND_MARGIN, SENSOR_HEIGHT, SWAY_STREAM, TOWN_STREAM, TOWN_VERSION
from .drive import body_sway, grid_drive, vehicle_poses
from .layout import centre_lines, grid_streets, heights_from_track, make_plan, plan_grid, trajectory_streets
from .meshes import ground_parts, object_parts
from .objects import populate
from .raster import HeightField, Raster


def _file_digest(path: Path) -> str:
    return hashlib.sha1(path.read_bytes()).hexdigest()[:12]


class TownSequence(Sequence):
    """A generated town and a drive through it, scanned on demand by a simulated HDL-64E.

    ``TownSequence(seed)`` lays out a ``size`` × ``size`` m grid town and drives ``n_scans`` scans
    at ``rate_hz``; with ``trajectory`` (a KITTI odometry poses file of cam0 poses) and ``calib``
    (its calib with the ``Tr:`` line), the drive is that trajectory and the town is grown around
    it (one scan per pose; ``size`` and ``n_scans`` are then ignored).
    """

    def __init__(self, seed: int = 0, size: float = 400.0, n_scans: int = 1200, rate_hz: float = 10.0,
                 trajectory: str | Path | None = None, calib: str | Path | None = None,
                 lidar: LidarModel | None = None):
        t_start = time.perf_counter()
        self.seed = int(seed)
        self.size = float(size)
        self.rate_hz = float(rate_hz)
        self.trajectory = Path(trajectory) if trajectory is not None else None
        self.calib = Path(calib) if calib is not None else None
        if (self.trajectory is None) != (self.calib is None):
            raise DataError("town: a trajectory needs its calib (the Tr line converts cam0 poses to LiDAR poses)")
        if self.size < 100.0:
            raise DataError(f"town: size must be ≥ 100 m, got {self.size:g}")
        if n_scans < 1:
            raise DataError(f"town: n_scans must be ≥ 1, got {n_scans}")
        if not self.rate_hz > 0:
            raise DataError(f"town: rate_hz must be > 0, got {self.rate_hz:g}")
        rng = np.random.default_rng([self.seed, *TOWN_STREAM])
        self.stats: dict = {}

        if self.trajectory is None:
            self.name = f"town-seed{self.seed}"
            poses_town, times, plan = self._build_grid(rng, int(n_scans))
        else:
            self.name = f"town-seed{self.seed}-{self.trajectory.stem}"
            poses_town, times, plan = self._build_along_trajectory(rng)
        self.n_scans = len(poses_town)
        self.poses_town = poses_town
        self._times = times - times[0]
        self.town_to_world = inv_pose(poses_town[0])
        self._poses = rebase_poses(poses_town)

        solids = populate(plan, rng)
        parts = ground_parts(plan, rng) + object_parts(solids, plan.ground, rng)
        self.ground = plan.ground
        self.raster = plan.raster
        self.road = plan.road
        self.streets = plan.streets
        self.lidar = RaycastLidar(parts, lidar)
        self.lidar.build()
        self.stats.update(dict(solids.counts), triangles=self.lidar.n_triangles, streets=len(plan.streets),
                              build_seconds=time.perf_counter() - t_start)

    # -------------------------------------------------------------- construction
    def _build_grid(self, rng, n_scans):
        size = self.size
        grid = plan_grid(rng, size, loop_distance=6.5 * n_scans / self.rate_hz)
        streets, junctions = grid_streets(grid, size)
        times, x, y, yaw, driven, n_stops = grid_drive(rng, grid, n_scans, self.rate_hz)
        raster = Raster.covering(-GROUND_MARGIN, -GROUND_MARGIN, size + GROUND_MARGIN, size + GROUND_MARGIN)

        # Rolling hills: a few long plane waves, scaled to 3–6 m from lowest to highest point.
        X, Y = HeightField.node_coordinates(raster)
        z = np.zeros(X.shape)
        for _ in range(4):
            wavelength = rng.uniform(0.9, 2.2) * size
            ang, phase = rng.uniform(0, 2 * np.pi, 2)
            z += rng.uniform(0.4, 1.0) * np.sin(2 * np.pi * (X * np.cos(ang) + Y * np.sin(ang)) / wavelength + phase)
        in_town = (X >= 0) & (X <= size) & (Y >= 0) & (Y <= size)
        z *= rng.uniform(3.0, 6.0) / max(np.ptp(z[in_town]), 1e-9)
        ground = HeightField(raster, z)

        xs, ys = raster.centres()
        build_area = ((xs >= 0) & (xs <= size))[:, None] & ((ys >= 0) & (ys <= size))[None, :]
        downtown = (rng.uniform(0.3, 0.7) * size, rng.uniform(0.3, 0.7) * size, 0.28 * size)
        plan = make_plan(rng, raster, ground, streets, junctions, build_area, driven, downtown)
        poses = vehicle_poses(x, y, yaw, ground)
        speed = np.hypot(np.gradient(x, times), np.gradient(y, times)) if len(times) > 1 else np.zeros(1)
        pitch, roll = body_sway(np.random.default_rng([self.seed, *SWAY_STREAM]), times, speed)
        poses[:, :3, :3] = poses[:, :3, :3] @ rotation_zyx(0.0, pitch, roll)   # about the sensor
        self.stats.update(stops=n_stops, route_loop=grid.loop)
        return poses, times, plan

    def _build_along_trajectory(self, rng):
        cam0 = read_pose_lines(self.trajectory)
        Tr = read_tr(self.calib)
        poses = rebase_poses(cam0_to_lidar_poses(cam0, Tr))
        poses = check_poses(poses, len(cam0), str(self.trajectory))
        if len(poses) < 2:
            raise DataError(f"{self.trajectory}: a trajectory needs at least 2 poses")
        times = self._trajectory_times(len(poses))
        xy = poses[:, :2, 3]
        streets, junctions, path = trajectory_streets(rng, xy)
        lo = xy.min(axis=0) - BUILD_REACH - GROUND_MARGIN
        hi = xy.max(axis=0) + BUILD_REACH + GROUND_MARGIN
        raster = Raster.covering(lo[0], lo[1], hi[0], hi[1])
        # The ground passes SENSOR_HEIGHT below each LiDAR pose, along the car's own up axis.
        under = poses[:, :3, 3] - SENSOR_HEIGHT * poses[:, :3, 2]
        step = np.linalg.norm(np.diff(under[:, :2], axis=0), axis=1)
        cum = np.concatenate([[0.0], np.cumsum(step)])
        s = np.arange(0.0, cum[-1] + 1e-9, 1.0)
        moving = np.concatenate([[True], step > 1e-3])
        samples = np.stack([np.interp(s, cum[moving], under[moving, k]) for k in range(3)], axis=1)
        ground = HeightField(raster, heights_from_track(raster, samples))
        centre_dist = ndimage.distance_transform_edt(~centre_lines(raster, streets), sampling=CELL)
        build_area = centre_dist <= BUILD_REACH
        plan = make_plan(rng, raster, ground, streets, junctions, build_area, path)
        # Sensor height above the ground minus SENSOR_HEIGHT: ≈ 0, > 0 where the drive's own
        # heights disagree between passes (see heights_from_track), < 0 would be a sunken car.
        residual = samples[:, 2] - ground(samples[:, 0], samples[:, 1])
        self.stats.update(ground_residual_median=float(np.median(np.abs(residual))),
                          ground_residual_min=float(residual.min()), ground_residual_max=float(residual.max()))
        return poses, times, plan

    def _trajectory_times(self, n):
        """Timestamps from the times file beside the poses (``…/times/SS.txt`` as in
        kitti_odometry_poses, or ``sequences/SS/times.txt``), else ``rate_hz``."""
        candidates = [self.trajectory.parent.parent / "times" / self.trajectory.name,
                      self.trajectory.parent.parent / "sequences" / self.trajectory.stem / "times.txt"]
        for path in candidates:
            if path.is_file():
                try:
                    times = np.loadtxt(path, dtype=np.float64, ndmin=1)
                except ValueError:
                    raise DataError(f"{path}: not a column of numbers") from None
                if len(times) != n:
                    raise DataError(f"{path}: {len(times)} timestamps for {n} poses in {self.trajectory}")
                self._times_source = str(path)
                return times
        self._times_source = f"{self.rate_hz:g} Hz"
        return np.arange(n) / self.rate_hz

    @classmethod
    def from_config(cls, cfg: TownConfig, seed: int | None = None, trajectory: Path | None = None,
                    calib: Path | None = None) -> "TownSequence":
        """The town of ``cfg`` (``seed`` overrides ``cfg.seed``), optionally along a trajectory."""
        return cls(seed=cfg.seed if seed is None else seed, size=cfg.size, n_scans=cfg.n_scans,
                   rate_hz=cfg.rate_hz, trajectory=trajectory, calib=calib)

    # -------------------------------------------------------------- Sequence interface
    def __len__(self) -> int:
        return self.n_scans

    def _read_scan(self, i: int) -> np.ndarray:
        rng = np.random.default_rng([self.seed, int(i)])
        return self.lidar.scan(self.poses_town[i], rng)

    def _describe_scan(self, i: int) -> str:
        return f"town seed {self.seed} scan {i}"

    @property
    def timestamps(self) -> np.ndarray:
        return self._times

    @property
    def poses(self) -> np.ndarray:
        return self._poses

    def identity(self) -> str:
        parts = [f"town|v{TOWN_VERSION}", f"seed={self.seed}", f"size={self.size:g}", f"n_scans={self.n_scans}",
                 f"rate={self.rate_hz:g}", f"lidar={self.lidar.model}"]
        if self.trajectory is not None:
            parts += [f"trajectory={self.trajectory.resolve()}#{_file_digest(self.trajectory)}",
                      f"calib={self.calib.resolve()}#{_file_digest(self.calib)}", f"times={self._times_source}"]
        return "|".join(parts)

    # -------------------------------------------------------------- extras for display and tests
    @property
    def speeds(self) -> np.ndarray:
        """(len,) m/s, ground-truth speed between consecutive scans (last one repeated)."""
        d = np.linalg.norm(np.diff(self._poses[:, :3, 3], axis=0), axis=1)
        dt = np.diff(self._times)
        v = d / np.maximum(dt, 1e-9)
        return np.concatenate([v, v[-1:]]) if len(v) else np.zeros(1)

    def world_mesh(self) -> list[tuple[str, np.ndarray, np.ndarray]]:
        """The town's triangles in the world frame: [(material, vertices (V, 3) float32, triangles
        (T, 3) uint32)], for display."""
        R, t = self.town_to_world[:3, :3], self.town_to_world[:3, 3]
        return [(p.name, (p.vertices.astype(np.float64) @ R.T + t).astype(np.float32), p.triangles)
                for p in self.lidar.parts]

    @functools.cached_property
    def extent(self) -> np.ndarray:
        """(2, 3) world-frame bounding box [min, max] of everything the sensor can hit."""
        lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
        for _, vertices, triangles in self.world_mesh():
            used = vertices[np.unique(triangles)]
            lo, hi = np.minimum(lo, used.min(axis=0)), np.maximum(hi, used.max(axis=0))
        return np.stack([lo, hi]).astype(np.float64)

    def ground_height_world(self, xy: np.ndarray) -> np.ndarray:
        """Approximate world-frame z of the road surface under world-frame points (N, 2); exact
        when the first pose is level, off by the first pose's tilt times the distance otherwise."""
        xy = np.atleast_2d(np.asarray(xy, float))
        world_to_town = inv_pose(self.town_to_world)
        p = np.concatenate([xy, np.zeros((len(xy), 1))], axis=1) @ world_to_town[:3, :3].T + world_to_town[:3, 3]
        ground_town = np.stack([p[:, 0], p[:, 1], self.ground(p[:, 0], p[:, 1])], axis=1)
        return (ground_town @ self.town_to_world[:3, :3].T + self.town_to_world[:3, 3])[:, 2]
