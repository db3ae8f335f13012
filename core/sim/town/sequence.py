"""The town as a :class:`~..base.Sequence`: a drive through a :class:`~.world.Town`, scanned on
demand, and the mapping drive its prior map comes from."""

from __future__ import annotations

import functools
import time
from pathlib import Path

import numpy as np

from ...config import TOWN_SENSORS, TownConfig
from ...errors import DataError
from ...sequences.base import Sequence, rebase_poses
from ..lidar_models import SENSORS, LidarModel
from ..lidar_sim import Sweep
from .constants import SENSOR_HEIGHT
from .drive import interpolate_poses
from .world import Town

#: The world options of the mapping drive (the town as it was mapped), in TownConfig's names.
MAPPING_OPTIONS = dict(
    changes=0.0, traffic=False, sensor="hdl64e", mount_height=SENSOR_HEIGHT, skew=False, route=1, traffic_seed=0
)


class TownSequence(Sequence):
    """A generated town and a drive through it, scanned on demand by a simulated LiDAR.

    ``TownSequence(seed)`` lays out an ``extent_m`` × ``extent_m`` m grid town (from 1000 m a city
    of districts, see the package) and drives ``n_scans`` scans at ``rate_hz``; with
    ``trajectory`` (a KITTI odometry poses file of cam0 poses) and ``calib`` (its calib with the
    ``Tr:`` line), the drive is that trajectory and the town is grown around it (one scan per
    pose; ``extent_m`` and ``n_scans`` are then ignored).

    The world options describe the drive being localized (see :class:`~lidarloc.core.config.TownConfig`):
    ``changes`` (share of movable objects and trees changed since mapping, :mod:`.changes`),
    ``traffic`` (:mod:`.traffic`), ``sensor`` (:data:`~..lidar_models.SENSORS`), ``mount_height``
    (m above the road), ``skew`` (each scan swept over 1/rate_hz while moving, not de-skewed;
    :mod:`lidarloc.core.odometry.deskew`) and ``route`` (1, or 2: :mod:`.routes`). At their defaults the
    sequence *is* the mapping drive. Otherwise :attr:`map_source` is the mapping drive — route 1,
    the town as mapped, HDL-64E (or ``lidar``) at SENSOR_HEIGHT, no skew, no traffic — sharing
    this sequence's streets, ground and objects (the town is laid out once). Every drive of one
    town has the same world frame: the mapping drive's first LiDAR pose. A city's map source is
    its survey and its world frame its own, for every drive.
    """

    def __init__(
        self,
        seed: int = 0,
        extent_m: float = 400.0,
        n_scans: int = 1200,
        rate_hz: float = 10.0,
        trajectory: str | Path | None = None,
        calib: str | Path | None = None,
        lidar: LidarModel | None = None,
        *,
        changes: float = 0.0,
        traffic: bool = False,
        sensor: str = "hdl64e",
        mount_height: float = SENSOR_HEIGHT,
        skew: bool = False,
        route: int = 1,
        traffic_seed: int = 0,
    ):
        t_start = time.perf_counter()
        options = _check_options(
            dict(
                changes=changes,
                traffic=traffic,
                sensor=sensor,
                mount_height=mount_height,
                skew=skew,
                route=route,
                traffic_seed=traffic_seed,
            )
        )
        self._setup(Town(seed, extent_m, n_scans, rate_hz, trajectory, calib, lidar), options)
        self.lidar.build()
        self.stats["build_seconds"] = time.perf_counter() - t_start

    @classmethod
    def _of_town(cls, town: Town, options: dict) -> TownSequence:
        seq = cls.__new__(cls)
        seq._setup(town, options)
        return seq

    def with_world(self, **options) -> TownSequence:
        """Another drive through this same town (no new layout): this drive's world options
        with ``options`` (changes, traffic, sensor, mount_height, skew, route, traffic_seed) replaced."""
        unknown = set(options) - set(MAPPING_OPTIONS)
        if unknown:
            raise DataError(f"town: unknown world option(s) {', '.join(sorted(unknown))}")
        if self.town.plan is None and (options.get("changes") or options.get("traffic")):
            raise DataError("town: a copied town cannot add changes or traffic; build it anew")
        seq = TownSequence._of_town(self.town, _check_options(dict(self.options, **options)))
        if not seq.is_mapping_drive and not self.town.is_city:
            seq.__dict__["_mapping_drive"] = self.map_source  # one mapping drive per town
        seq.lidar.build()
        return seq

    def _setup(self, town: Town, options: dict) -> None:
        self.town = town
        self.options = options
        self.seed, self.extent_m, self.rate_hz = town.seed, town.extent_m, town.rate_hz
        self.trajectory, self.calib, self.name = town.trajectory, town.calib, town.name
        self.ground, self.raster, self.road, self.streets = town.ground, town.raster, town.road, town.streets
        self.town_to_world = town.town_to_world
        self.stats = dict(town.stats)
        self.is_mapping_drive = options == MAPPING_OPTIONS
        self.changes_made = None

        lidar = town.lidar
        if options["changes"] > 0:
            from .changes import changed_world

            parts, self.changes_made, _ = changed_world(town, options["changes"])
            lidar = town.lidar_of(parts)
            self.stats.update(changes=self.changes_made.counts())
        if options["sensor"] != MAPPING_OPTIONS["sensor"]:
            lidar = lidar.with_model(SENSORS[options["sensor"]])
        self.lidar = lidar

        if options["route"] == 1:
            poses_town, times = town.poses_town, town.times
        else:
            from .routes import second_route

            poses_town, times = second_route(town)
        lift = options["mount_height"] - SENSOR_HEIGHT
        if lift != 0.0:  # the sensor higher or lower on the same car, along the car's up axis
            poses_town = poses_town.copy()
            poses_town[:, :3, 3] += lift * poses_town[:, :3, 2]
        self.poses_town = poses_town
        self.n_scans = len(poses_town)
        self._times = times
        if options["route"] == 1 and lift == 0.0 and not town.is_city:
            self._poses = rebase_poses(poses_town)
        else:
            self._poses = town.town_to_world[None] @ poses_town

        self._traffic = None
        if options["traffic"]:
            from .traffic import Traffic

            self._traffic = Traffic(town, poses_town, times, options["traffic_seed"])

    @classmethod
    def from_config(
        cls, cfg: TownConfig, seed: int | None = None, trajectory: Path | None = None, calib: Path | None = None
    ) -> TownSequence:
        """The town of ``cfg`` (``seed`` overrides ``cfg.seed``), optionally along a trajectory,
        driven with ``cfg``'s world options."""
        return cls(
            seed=cfg.seed if seed is None else seed,
            extent_m=cfg.extent_m,
            n_scans=cfg.n_scans,
            rate_hz=cfg.rate_hz,
            trajectory=trajectory,
            calib=calib,
            changes=cfg.changes,
            traffic=cfg.traffic,
            sensor=cfg.sensor,
            mount_height=cfg.mount_height,
            skew=cfg.skew,
            route=cfg.route,
            traffic_seed=cfg.traffic_seed,
        )

    def world_options(self) -> dict:
        """The world options of this drive (changes, traffic, sensor, mount_height, skew, route,
        traffic_seed)."""
        return dict(self.options)

    @functools.cached_property
    def _mapping_drive(self) -> TownSequence:
        return TownSequence._of_town(self.town, dict(MAPPING_OPTIONS))

    @property
    def map_source(self):
        """The mapping drive (this sequence itself at the default world options); a city's
        survey map (:class:`~.survey.CitySurvey`) for every drive through it."""
        if self.town.is_city:
            return self.town.survey
        return self if self.is_mapping_drive else self._mapping_drive

    # -------------------------------------------------------------- Sequence interface
    def __len__(self) -> int:
        return self.n_scans

    def _read_scan(self, i: int) -> np.ndarray:
        rng = np.random.default_rng([self.seed, int(i)])
        if self.is_mapping_drive or not (self.options["skew"] or self._traffic is not None):
            return self.lidar.scan(self.poses_town[i], rng)
        sweep = None
        if self.options["skew"]:
            t_i = float(self._times[i])
            sweep = Sweep(
                1.0 / self.rate_hz, lambda offsets: interpolate_poses(self._times, self.poses_town, t_i + offsets)
            )
        moving = None
        if self._traffic is not None:
            moving = self._traffic.movers_at(
                float(self._times[i]), self.poses_town[i, :2, 3], self.lidar.model.max_range + 5.0
            )
        return self.lidar.scan(self.poses_town[i], rng, sweep=sweep, moving=moving)

    def describe_scan(self, i: int) -> str:
        return f"town seed {self.seed} scan {i}"

    @property
    def timestamps(self) -> np.ndarray:
        return self._times

    @property
    def poses(self) -> np.ndarray:
        return self._poses

    def identity(self) -> str:
        ident = self.town.identity()
        if self.is_mapping_drive:
            return ident
        # (the town's own traffic, seed 0, is named as before there were others: its scans' caches stay)
        named = {k: v for k, v in self.options.items() if not (k == "traffic_seed" and v == 0)}
        return ident + "|world=" + ",".join(f"{k}={v}" for k, v in named.items())

    # -------------------------------------------------------------- extras for display and tests
    @property
    def speeds(self) -> np.ndarray:
        """(len,) m/s, ground-truth speed between consecutive scans (last one repeated)."""
        d = np.linalg.norm(np.diff(self._poses[:, :3, 3], axis=0), axis=1)
        dt = np.diff(self._times)
        v = d / np.maximum(dt, 1e-9)
        return np.concatenate([v, v[-1:]]) if len(v) else np.zeros(1)

    @property
    def traffic(self):
        """The drive's :class:`~.traffic.Traffic`, or None without traffic."""
        return self._traffic

    def traffic_boxes(self, i: int) -> np.ndarray:
        """The traffic's boxes (k, 8) at scan i in the town frame (cx, cy, yaw, length, width,
        z0, z1, reflectivity), as scanned; empty without traffic."""
        if self._traffic is None:
            return np.zeros((0, 8))
        return self._traffic.boxes_at(
            float(self._times[i]), self.poses_town[i, :2, 3], self.lidar.model.max_range + 5.0
        )

    def world_mesh(self) -> list[tuple[str, np.ndarray, np.ndarray]]:
        """The triangles this drive scans (the changed town, without traffic) in the world
        frame: [(material, vertices (V, 3) float32, triangles (T, 3) uint32)], for display."""
        R, t = self.town_to_world[:3, :3], self.town_to_world[:3, 3]
        return [
            (p.name, (p.vertices.astype(np.float64) @ R.T + t).astype(np.float32), p.triangles)
            for p in self.lidar.parts
        ]

    @functools.cached_property
    def extent(self) -> np.ndarray:
        """(2, 3) world-frame bounding box [min, max] of everything the sensor can hit."""
        lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
        for _, vertices, triangles in self.world_mesh():
            used = vertices[np.unique(triangles)]
            lo, hi = np.minimum(lo, used.min(axis=0)), np.maximum(hi, used.max(axis=0))
        return np.stack([lo, hi]).astype(np.float64)


def _check_options(options: dict) -> dict:
    """The world options as plain values; DataError (one line) on an impossible one."""
    changes = float(options["changes"])
    if not 0.0 <= changes <= 1.0:
        raise DataError(f"town: changes must be in [0, 1], got {changes:g}")
    if options["sensor"] not in SENSORS or options["sensor"] not in TOWN_SENSORS:
        raise DataError(f"town: sensor must be one of {'|'.join(TOWN_SENSORS)}, got {options['sensor']!r}")
    mount = float(options["mount_height"])
    if not 0.3 <= mount <= 5.0:
        raise DataError(f"town: mount_height must be in 0.3..5 m, got {mount:g}")
    if options["route"] not in (1, 2):
        raise DataError(f"town: route must be 1 or 2, got {options['route']!r}")
    traffic_seed = int(options.get("traffic_seed", 0))
    if traffic_seed < 0:
        raise DataError(f"town: traffic_seed must be ≥ 0, got {traffic_seed}")
    return dict(
        changes=changes,
        traffic=bool(options["traffic"]),
        sensor=str(options["sensor"]),
        mount_height=mount,
        skew=bool(options["skew"]),
        route=int(options["route"]),
        # another day's traffic means nothing without traffic: such a drive is the one without
        traffic_seed=traffic_seed if options["traffic"] else 0,
    )
