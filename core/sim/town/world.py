"""The town as it was mapped: streets, ground, objects and the mapping drive (route 1), built once
from the seed and shared by every drive through it (:class:`~.sequence.TownSequence`)."""

from __future__ import annotations

import hashlib
import time
from pathlib import Path

import numpy as np
from scipy import ndimage

from ...errors import DataError
from ...geometry import inv_pose, rotation_zyx
from ...sequences.base import check_poses, rebase_poses
from ...sequences.kitti_io import cam0_to_lidar_poses, read_pose_lines, read_tr
from ..lidar_models import LidarModel
from ..lidar_sim import RaycastLidar
from .constants import (
    BUILD_REACH,
    CELL,
    CITY_EXTENT,
    CITY_MAX_EXTENT,
    CITY_ROUTE_STREAM,
    GROUND_MARGIN,
    SENSOR_HEIGHT,
    SWAY_STREAM,
    TOWN_STREAM,
    TOWN_VERSION,
)
from .drive import body_sway, grid_drive, vehicle_poses
from .layout import centre_lines, grid_streets, heights_from_track, make_plan, plan_grid, trajectory_streets
from .meshes import ground_parts, object_parts
from .objects import populate
from .raster import HeightField, Raster


def _file_digest(path: Path) -> str:
    return hashlib.sha1(path.read_bytes()).hexdigest()[:12]


class Town:
    """A generated town and its mapping drive.

    Grid mode (no ``trajectory``): an ``extent_m`` × ``extent_m`` m street grid and a drive of
    ``n_scans`` scans at ``rate_hz``; from ``extent_m`` ≥ CITY_EXTENT a city of districts
    (:mod:`.city`), its world shared by all its drives and cached, its frame its own (not the
    first pose's), its triangles cast tile by tile (:mod:`.tiles`). Trajectory mode: the drive is a KITTI odometry poses file
    (cam0 poses, converted to LiDAR poses with ``calib``'s Tr), one scan per pose, and the town is
    grown around it. ``lidar`` is the mapping drive's sensor (HDL-64E by default).

    Kept after construction: ``plan`` (the ground plan, for placing changes and traffic; not
    pickled), ``solids`` (the objects' parameters), ``parts`` (their triangles), ``lidar``
    (the mapping sensor over them, its scene built on first use), ``poses_town`` and ``times``
    of the mapping drive, ``town_to_world`` (the world frame is the mapping drive's first pose),
    ``grid`` and ``route_edges`` (grid mode) and ``stats``; a city also keeps ``districts`` and
    ``cover`` (what hides what from the street, for its survey map).
    """

    is_city = False

    def __init__(
        self,
        seed: int = 0,
        extent_m: float = 400.0,
        n_scans: int = 1200,
        rate_hz: float = 10.0,
        trajectory: str | Path | None = None,
        calib: str | Path | None = None,
        lidar: LidarModel | None = None,
    ):
        t_start = time.perf_counter()
        self.seed = int(seed)
        self.extent_m = float(extent_m)
        self.rate_hz = float(rate_hz)
        self.trajectory = Path(trajectory) if trajectory is not None else None
        self.calib = Path(calib) if calib is not None else None
        if (self.trajectory is None) != (self.calib is None):
            raise DataError("town: a trajectory needs its calib (the Tr line converts cam0 poses to LiDAR poses)")
        for path in (self.trajectory, self.calib):
            if path is not None and not path.is_file():
                raise DataError(f"{path}: no such file")
        if not 100.0 <= self.extent_m <= CITY_MAX_EXTENT:
            raise DataError(f"town: extent_m must be in 100..{CITY_MAX_EXTENT:g} m, got {self.extent_m:g}")
        if n_scans < 1:
            raise DataError(f"town: n_scans must be ≥ 1, got {n_scans}")
        if not self.rate_hz > 0:
            raise DataError(f"town: rate_hz must be > 0, got {self.rate_hz:g}")
        rng = np.random.default_rng([self.seed, *TOWN_STREAM])
        self.stats: dict = {}
        self.grid = None
        self.route_edges: list = []
        if self.trajectory is None and self.extent_m >= CITY_EXTENT:
            self._build_city(int(n_scans), lidar)
            self.build_seconds = time.perf_counter() - t_start
            return

        if self.trajectory is None:
            self.name = f"town-seed{self.seed}"
            poses_town, times, plan = self._build_grid(rng, int(n_scans))
        else:
            self.name = f"town-seed{self.seed}-{self.trajectory.stem}"
            poses_town, times, plan = self._build_along_trajectory(rng)
        self.n_scans = len(poses_town)
        self.poses_town = poses_town
        self.times = times - times[0]
        self.town_to_world = inv_pose(poses_town[0])

        self.solids = populate(plan, rng)
        self.parts = ground_parts(plan, rng) + object_parts(self.solids, plan.ground, rng)
        self.plan = plan
        self.ground = plan.ground
        self.raster = plan.raster
        self.road = plan.road
        self.streets = plan.streets
        self.lidar = RaycastLidar(self.parts, lidar)
        self.stats.update(dict(self.solids.counts), triangles=self.lidar.n_triangles, streets=len(plan.streets))
        self.build_seconds = time.perf_counter() - t_start

    def __getstate__(self):
        state = self.__dict__.copy()
        state["plan"] = None  # ~50 MB of rasters, only needed to place changes and traffic
        state.pop("cover", None)  # a city's: only its survey map needs it
        state.pop("_survey", None)
        return state

    def lidar_of(self, parts):
        """This town's kind of ray caster over ``parts``, with its mapping sensor."""
        if self.is_city:
            from .tiles import TiledLidar

            return TiledLidar(parts, self.lidar.model)
        return RaycastLidar(parts, self.lidar.model)

    @property
    def survey(self):
        """A city's prior-map source: its surfaces sampled at survey density (:mod:`.survey`)."""
        if "_survey" not in self.__dict__:
            from .survey import CitySurvey

            self._survey = CitySurvey(self)
        return self._survey

    def identity(self) -> str:
        """The mapping drive's identity (keys the prior-map cache); a city's drive's."""
        if self.is_city:
            from .city import city_identity

            return "|".join(
                [
                    city_identity(self.seed, self.extent_m),
                    f"n_scans={self.n_scans}",
                    f"rate={self.rate_hz:g}",
                    f"lidar={self.lidar.model}",
                ]
            )
        # "size=" is the extent's key as it always was: maps and tables cached before stay valid
        parts = [
            f"town|v{TOWN_VERSION}",
            f"seed={self.seed}",
            f"size={self.extent_m:g}",
            f"n_scans={self.n_scans}",
            f"rate={self.rate_hz:g}",
            f"lidar={self.lidar.model}",
        ]
        if self.trajectory is not None:
            parts += [
                f"trajectory={self.trajectory.resolve()}#{_file_digest(self.trajectory)}",
                f"calib={self.calib.resolve()}#{_file_digest(self.calib)}",
                f"times={self._times_source}",
            ]
        return "|".join(parts)

    # -------------------------------------------------------------- construction
    def _build_grid(self, rng, n_scans):
        size = self.extent_m
        grid = plan_grid(rng, size, loop_distance=6.5 * n_scans / self.rate_hz)
        streets, junctions = grid_streets(grid, size)
        drive = grid_drive(rng, grid, n_scans, self.rate_hz)
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
        plan = make_plan(rng, raster, ground, streets, junctions, build_area, drive.driven, downtown)
        poses = drive_poses(drive, ground, np.random.default_rng([self.seed, *SWAY_STREAM]))
        self.grid, self.route_edges = grid, drive.edges
        self.stats.update(stops=drive.n_stops, route_loop=grid.loop)
        return poses, drive.times, plan

    def _build_city(self, n_scans, lidar):
        from .city import load_or_build_city
        from .city_route import city_route
        from .tiles import TiledLidar

        world, cached = load_or_build_city(self.seed, self.extent_m)
        self.is_city = True
        self.name = f"city-seed{self.seed}"
        self.grid, self.districts, self.cover = world.grid, world.districts, world.cover
        self.plan, self.solids, self.parts = world.plan, world.solids, world.parts
        self.ground, self.raster, self.road, self.streets = (
            world.plan.ground,
            world.plan.raster,
            world.plan.road,
            world.plan.streets,
        )
        drive = grid_drive(
            np.random.default_rng([self.seed, *CITY_ROUTE_STREAM]),
            self.grid,
            n_scans,
            self.rate_hz,
            plan_route=city_route(self.grid, self.districts, self.extent_m),
        )
        self.poses_town = drive_poses(drive, self.ground, np.random.default_rng([self.seed, *SWAY_STREAM]))
        self.n_scans = len(self.poses_town)
        self.times = drive.times - drive.times[0]
        self.route_edges = drive.edges
        self.town_to_world = np.eye(4)  # the city's own frame: its drives and its map share it
        self.lidar = TiledLidar(self.parts, lidar)
        self.stats.update(
            world.stats, stops=drive.n_stops, world_cached=cached, world_build_seconds=round(world.build_seconds, 2)
        )

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
        self.stats.update(
            ground_residual_median=float(np.median(np.abs(residual))),
            ground_residual_min=float(residual.min()),
            ground_residual_max=float(residual.max()),
        )
        return poses, times, plan

    def _trajectory_times(self, n):
        """Timestamps from the times file beside the poses (``…/times/SS.txt`` as in
        kitti_odometry_poses, or ``sequences/SS/times.txt``), else ``rate_hz``."""
        candidates = [
            self.trajectory.parent.parent / "times" / self.trajectory.name,
            self.trajectory.parent.parent / "sequences" / self.trajectory.stem / "times.txt",
        ]
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


def drive_poses(drive, ground: HeightField, sway_rng: np.random.Generator) -> np.ndarray:
    """LiDAR poses (town frame) of a grid drive: the body on the ground, swaying on its suspension."""
    x, y, times = drive.x, drive.y, drive.times
    poses = vehicle_poses(x, y, drive.yaw, ground)
    speed = np.hypot(np.gradient(x, times), np.gradient(y, times)) if len(times) > 1 else np.zeros(1)
    pitch, roll = body_sway(sway_rng, times, speed)
    poses[:, :3, :3] = poses[:, :3, :3] @ rotation_zyx(0.0, pitch, roll)  # about the sensor
    return poses
