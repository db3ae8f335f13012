"""A simulated spinning LiDAR (Velodyne HDL-64E by default): rays cast into a triangle world
with open3d's Embree scene.

The sensor model is deliberately simple but keeps what a scan matcher notices:

- the beams' elevations, ``n_azimuth`` firings per revolution and a maximum range; rays that
  hit nothing within range produce no return (like a real sensor, which reports no point for a
  miss). :data:`SENSORS` holds the HDL-64E (64 beams from +2° to −24.8° in two laser blocks, the
  upper one denser), the VLP-16, the VLP-32C and the OS1-128 with their datasheets' figures;
- Gaussian range noise, random dropouts, and more dropouts for weak far returns;
- intensity = material reflectivity × |cos(incidence)|, the Lambertian falloff a real return has;
- by default one scan is an instantaneous snapshot from one pose (no motion skew), so the
  ground-truth pose describes every point exactly; with a :class:`Sweep` each firing column is
  cast from the sensor's pose at its own firing time (see :mod:`lidarloc.core.odometry.deskew`);
- things that move (traffic) come as extra mesh parts per scan: a second, tiny scene is cast
  and the nearer hit of the two is kept per ray.

The ray direction table is computed once; a scan is one ``cast_rays`` call plus a handful of
vectorised numpy operations, and everything random comes from the generator the caller passes
(so a scan is a pure function of the pose and that generator's seed).
"""

from __future__ import annotations

import functools
import math
import threading
from collections.abc import Callable
from dataclasses import dataclass

import numba as nb
import numpy as np

from ..o3d import open3d
from ..odometry.deskew import sweep_fraction
from .lidar_models import N_PHASES, SENSORS, LidarModel  # noqa: F401  (SENSORS: what a scan can be cast with)


@nb.njit(cache=True, nogil=True)
def _fill_rays(dirs, R, origin, rays):
    """rays[k] = [origin, R @ dirs[k]]: the sensor-frame ray table turned into the world."""
    for k in range(dirs.shape[0]):
        dx, dy, dz = dirs[k, 0], dirs[k, 1], dirs[k, 2]
        rays[k, 0] = origin[0]
        rays[k, 1] = origin[1]
        rays[k, 2] = origin[2]
        rays[k, 3] = R[0, 0] * dx + R[0, 1] * dy + R[0, 2] * dz
        rays[k, 4] = R[1, 0] * dx + R[1, 1] * dy + R[1, 2] * dz
        rays[k, 5] = R[2, 0] * dx + R[2, 1] * dy + R[2, 2] * dz


@nb.njit(cache=True, nogil=True)
def _fill_rays_per_column(dirs, n_azimuth, R, origin, rays):
    """rays[k] = [origin[c], R[c] @ dirs[k]] with c = k mod n_azimuth, the ray's firing column
    (the tables are beam-major): each column cast from its own sensor pose."""
    for k in range(dirs.shape[0]):
        c = k % n_azimuth
        dx, dy, dz = dirs[k, 0], dirs[k, 1], dirs[k, 2]
        rays[k, 0] = origin[c, 0]
        rays[k, 1] = origin[c, 1]
        rays[k, 2] = origin[c, 2]
        rays[k, 3] = R[c, 0, 0] * dx + R[c, 0, 1] * dy + R[c, 0, 2] * dz
        rays[k, 4] = R[c, 1, 0] * dx + R[c, 1, 1] * dy + R[c, 1, 2] * dz
        rays[k, 5] = R[c, 2, 0] * dx + R[c, 2, 1] * dy + R[c, 2, 2] * dz


AZIMUTH_BINS = 1440  # 0.25°: the azimuth histogram that picks the rays worth casting at movers


@nb.njit(cache=True, nogil=True)
def _rays_toward(rays, n_azimuth, origin, centres, radii, bottoms, tops):
    """Indices of the rays that may hit one of the movers bounded by vertical cylinders
    (centres (m, 2), radii (m,), bottom and top heights (m,)) seen from ``origin``: the rays
    within a mover's azimuth span (plus 0.06 rad for the sensor's tilt) whose rise (dz per metre
    across) keeps them between its bottom and its top somewhere across it (plus 0.05). Per
    azimuth bin (AZIMUTH_BINS of them) the span of rises of all its movers is kept; a ray's
    azimuth is its firing column's (read off the middle beam: the tables are beam-major)."""
    two_pi = 2.0 * np.pi
    low = np.full(AZIMUTH_BINS, np.inf)
    high = np.full(AZIMUTH_BINS, -np.inf)
    for a in range(centres.shape[0]):
        dx, dy = centres[a, 0] - origin[0], centres[a, 1] - origin[1]
        d = np.sqrt(dx * dx + dy * dy)
        r = radii[a] + 1.0  # the sweep moves the sensor by up to ±0.7 m
        if d <= r:  # around the sensor: every ray may hit it
            low[:] = -np.inf
            high[:] = np.inf
            break
        half = np.arcsin(r / d) + 0.06
        rise_high = (tops[a] - origin[2]) / (d - r) + 0.05
        rise_low = (bottoms[a] - origin[2]) / (d + r) - 0.05
        az = np.arctan2(dy, dx)
        b0 = int(np.floor((az - half) / two_pi * AZIMUTH_BINS))
        b1 = int(np.floor((az + half) / two_pi * AZIMUTH_BINS))
        for b in range(b0, b1 + 1):
            bb = b % AZIMUTH_BINS
            low[bb] = min(low[bb], rise_low)
            high[bb] = max(high[bb], rise_high)
    column_bin = np.empty(n_azimuth, np.int64)
    middle = (rays.shape[0] // n_azimuth // 2) * n_azimuth
    for c in range(n_azimuth):
        az = np.arctan2(rays[middle + c, 4], rays[middle + c, 3])
        column_bin[c] = int(np.floor(az / two_pi * AZIMUTH_BINS)) % AZIMUTH_BINS
    out = np.empty(rays.shape[0], np.int64)
    m = 0
    for k in range(rays.shape[0]):
        b = column_bin[k % n_azimuth]
        if low[b] == np.inf:
            continue
        h = np.sqrt(rays[k, 3] * rays[k, 3] + rays[k, 4] * rays[k, 4])
        if low[b] * h <= rays[k, 5] <= high[b] * h:
            out[m] = k
            m += 1
    return out[:m]


@nb.njit(cache=True, nogil=True)
def _returns(
    hit,
    t_hit,
    geometry,
    primitive,
    normals,
    rays,
    dirs,
    reflectivity,
    offsets,
    intensity_noise,
    drop_draw,
    range_noise,
    max_range,
    range_sigma,
    intensity_sigma,
    dropout,
    weak_dropout,
):
    """The returned points of one sweep, in the sensor frame: (M, 4) x, y, z, intensity.

    For hit k: intensity = reflectivity × |cos incidence| × (1 + noise), in [0, 1]; the return is
    dropped with probability dropout + weak_dropout · (range/max_range)² · (1 − intensity);
    its range gets Gaussian noise (capped at max_range, the sensor reports nothing farther).
    """
    out = np.empty((hit.shape[0], 4), dtype=np.float32)
    m = 0
    for k in range(hit.shape[0]):
        r = hit[k]
        t = t_hit[r]
        cos_inc = abs(normals[r, 0] * rays[r, 3] + normals[r, 1] * rays[r, 4] + normals[r, 2] * rays[r, 5])
        refl = reflectivity[offsets[geometry[r]] + primitive[r]]
        intensity = refl * cos_inc * (1.0 + intensity_sigma * intensity_noise[k])
        intensity = min(max(intensity, 0.0), 1.0)
        rel = t / max_range
        if drop_draw[k] < dropout + weak_dropout * rel * rel * (1.0 - intensity):
            continue
        rng_m = min(t + range_sigma * range_noise[k], max_range)
        out[m, 0] = dirs[r, 0] * rng_m
        out[m, 1] = dirs[r, 1] * rng_m
        out[m, 2] = dirs[r, 2] * rng_m
        out[m, 3] = intensity
        m += 1
    return out[:m]


@functools.cache
def _compile_kernels() -> None:
    """Run both kernels once on tiny inputs: numba compiles them (or loads its on-disk cache)."""
    dirs = np.array([[1.0, 0.0, 0.0]], np.float32)
    rays = np.empty((1, 6), np.float32)
    _fill_rays(dirs, np.eye(3, dtype=np.float32), np.zeros(3, np.float32), rays)
    _fill_rays_per_column(dirs, 1, np.eye(3, dtype=np.float32)[None], np.zeros((1, 3), np.float32), rays)
    _rays_toward(rays, 1, np.zeros(3), np.ones((1, 2)), np.ones(1), np.zeros(1), np.ones(1))
    one_f = np.ones(1, np.float32)
    one_u = np.zeros(1, np.uint32)
    _returns(
        np.zeros(1, np.int64),
        one_f,
        one_u,
        one_u,
        np.ones((1, 3), np.float32),
        rays,
        dirs,
        one_f,
        np.zeros(1, np.int64),
        one_f,
        one_f,
        one_f,
        np.float32(1),
        np.float32(0),
        np.float32(0),
        np.float32(0),
        np.float32(0),
    )


@dataclass
class MeshPart:
    """One material's triangles: vertices (V, 3), triangle vertex indices (T, 3) and the
    reflectivity of each triangle (T,) in [0, 1] (or one value for all)."""

    name: str
    vertices: np.ndarray
    triangles: np.ndarray
    reflectivity: np.ndarray | float

    def __post_init__(self):
        self.vertices = np.ascontiguousarray(self.vertices, dtype=np.float32).reshape(-1, 3)
        self.triangles = np.ascontiguousarray(self.triangles, dtype=np.uint32).reshape(-1, 3)
        refl = np.asarray(self.reflectivity, dtype=np.float32)
        if refl.ndim == 0:
            refl = np.full(len(self.triangles), float(refl), dtype=np.float32)
        if refl.shape != (len(self.triangles),):
            raise ValueError(f"{self.name}: {refl.shape[0]} reflectivities for {len(self.triangles)} triangles")
        self.reflectivity = refl

    @property
    def n_triangles(self) -> int:
        return len(self.triangles)


@dataclass(frozen=True)
class Sweep:
    """Motion during one sweep: ``period`` s, and ``poses(offsets)``, the sensor's world poses
    (m, 4, 4) at time offsets (m,) s from mid-sweep (see :mod:`lidarloc.core.odometry.deskew`)."""

    period: float
    poses: Callable[[np.ndarray], np.ndarray]


@dataclass
class Movers:
    """Things that are there for one scan only (traffic): their triangles, and a vertical
    cylinder around each (centres (m, 2), radii (m,), bottom and top heights (m,), world frame)
    that picks the rays worth casting at them."""

    parts: list[MeshPart]
    centres: np.ndarray
    radii: np.ndarray
    bottoms: np.ndarray
    tops: np.ndarray


class _Scene:
    """Triangles of a fixed set of mesh parts and their lazily built Embree scene, shared by
    every sensor model that scans them."""

    def __init__(self, parts: list[MeshPart]):
        self.parts = [p for p in parts if p.n_triangles > 0]
        # One flat reflectivity table: geometry g's triangle k is at offsets[g] + k. Geometry ids
        # are assigned by open3d in insertion order starting at 0, which build() checks.
        counts = np.array([p.n_triangles for p in self.parts], dtype=np.int64)
        self.offsets = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
        self.reflectivity = (
            np.concatenate([p.reflectivity for p in self.parts]) if self.parts else np.zeros(0, np.float32)
        )
        self.scene = None
        self._lock = threading.Lock()

    def __getstate__(self):
        state = self.__dict__.copy()
        state["scene"] = None
        state["_lock"] = None
        return state

    def __setstate__(self, state):
        self.__dict__.update(state)
        self._lock = threading.Lock()

    def get(self):
        if self.scene is not None:
            return self.scene
        with self._lock:
            if self.scene is None:
                self.scene = raycasting_scene(self.parts, commit=True)
        return self.scene


def raycasting_scene(parts: list[MeshPart], commit: bool = True):
    """An open3d RaycastingScene of ``parts`` (geometry id = index in ``parts``); ``commit``
    builds its BVH now rather than at the first query."""
    o3d = open3d()
    scene = o3d.t.geometry.RaycastingScene()
    for expected_id, part in enumerate(parts):
        gid = scene.add_triangles(o3d.core.Tensor(part.vertices), o3d.core.Tensor(part.triangles))
        if gid != expected_id:
            raise RuntimeError(f"open3d gave geometry id {gid} to mesh part {expected_id}")
    if commit:
        # Embree commits (builds the BVH) on the first query; do it here, not mid-drive.
        probe = np.zeros((1, 6), np.float32)
        probe[0, 5] = -1.0
        scene.cast_rays(o3d.core.Tensor(probe), nthreads=0)
    return scene


class RaycastLidar:
    """Casts the sensor's rays into a fixed set of mesh parts.

    The Embree scene is built lazily (and not pickled): open3d scenes cannot be copied between
    processes, but the mesh parts can, and rebuilding from them gives the identical scene.
    :meth:`with_model` gives another sensor over the same scene (built once for both).
    """

    def __init__(self, parts: list[MeshPart], model: LidarModel | None = None, *, _scene: _Scene | None = None):
        self.model = model or LidarModel()
        self._world = _scene if _scene is not None else _Scene(parts)
        self._tables = self._ray_tables(self.model)

    def with_model(self, model: LidarModel) -> RaycastLidar:
        """The same world scanned by another sensor (sharing its triangles and scene)."""
        return self if model == self.model else RaycastLidar([], model, _scene=self._world)

    def __getstate__(self):
        state = self.__dict__.copy()
        state["_tables"] = None  # 12 MB that the model recomputes in milliseconds
        return state

    def __setstate__(self, state):
        self.__dict__.update(state)
        self._tables = self._ray_tables(self.model)

    @staticmethod
    def _ray_tables(model: LidarModel) -> list[np.ndarray]:
        return [model.ray_directions(k / N_PHASES) for k in range(N_PHASES)]

    @property
    def parts(self) -> list[MeshPart]:
        return self._world.parts

    @property
    def n_triangles(self) -> int:
        return int(self._world.reflectivity.size)

    def build(self) -> None:
        """Build the scene and its BVH, and compile the scan kernels, now rather than in the
        first scan (which a caller may be timing)."""
        self._world.get()
        _compile_kernels()

    def _column_poses(self, phase: int, sweep: Sweep) -> tuple[np.ndarray, np.ndarray]:
        """Rotation (n_azimuth, 3, 3) and origin (n_azimuth, 3), float32, of each firing column."""
        n = self.model.n_azimuth
        first_beam = self._tables[phase][:n].astype(np.float64)  # one direction per column
        offsets = (sweep_fraction(np.arctan2(first_beam[:, 1], first_beam[:, 0])) - 0.5) * sweep.period
        T = np.asarray(sweep.poses(offsets), np.float64)
        return (
            np.ascontiguousarray(T[:, :3, :3], dtype=np.float32),
            np.ascontiguousarray(T[:, :3, 3], dtype=np.float32),
        )

    def scan(
        self,
        T_world_sensor: np.ndarray,
        rng: np.random.Generator,
        sweep: Sweep | None = None,
        moving: Movers | None = None,
    ) -> np.ndarray:
        """One sweep from the sensor pose ``T_world_sensor`` (4×4): float32 (N, 4) x, y, z,
        intensity in the sensor frame. Only rays that hit something within max_range return.

        ``sweep``: cast each firing column from the pose at its firing time and report its
        points in that column's sensor frame (a skewed scan; ``T_world_sensor`` is then unused).
        ``moving``: things that are there for this scan only (traffic); per ray the nearer of
        the world's and their hit returns. The random draws of the rays that hit the world come
        first and in the same order as without ``moving``, so both scans agree point for point
        wherever the moving things are not in the way."""
        o3d = open3d()
        world = self._world
        scene = world.get()
        model = self.model
        phase = int(rng.integers(N_PHASES))
        dirs = self._tables[phase]
        rays = np.empty((len(dirs), 6), dtype=np.float32)
        if sweep is None:
            T = np.asarray(T_world_sensor, dtype=np.float64)
            _fill_rays(dirs, T[:3, :3].astype(np.float32), T[:3, 3].astype(np.float32), rays)
        else:
            R_col, origin_col = self._column_poses(phase, sweep)
            _fill_rays_per_column(dirs, model.n_azimuth, R_col, origin_col, rays)
        rays_tensor = o3d.core.Tensor.from_numpy(rays)
        result = scene.cast_rays(rays_tensor, nthreads=0)
        t_hit = result["t_hit"].numpy()
        geometry, primitive = result["geometry_ids"].numpy(), result["primitive_ids"].numpy()
        normals = result["primitive_normals"].numpy()
        reflectivity, offsets = world.reflectivity, world.offsets
        hit = np.flatnonzero(t_hit <= model.max_range)
        n = len(hit)
        # Intensity noise need not be Gaussian: uniform with the same σ costs a sixth of the time.
        intensity_noise = (rng.random(n, dtype=np.float32) - np.float32(0.5)) * np.float32(math.sqrt(12.0))
        drop_draw = rng.random(n, dtype=np.float32)
        range_noise = rng.standard_normal(n, dtype=np.float32)
        parts = [p for p in (moving.parts if moving is not None else []) if p.n_triangles > 0]
        if parts:
            origin = rays[len(rays) // 2, :3].astype(np.float64)
            cast = _rays_toward(
                rays,
                model.n_azimuth,
                origin,
                np.asarray(moving.centres, np.float64),
                np.asarray(moving.radii, np.float64),
                np.asarray(moving.bottoms, np.float64),
                np.asarray(moving.tops, np.float64),
            )
            t2 = raycasting_scene(parts, commit=False).cast_rays(o3d.core.Tensor.from_numpy(rays[cast]), nthreads=0)
            t_near = t2["t_hit"].numpy()
            closer = t_near < t_hit[cast]
            nearer = cast[closer]
            if len(nearer):  # (the cast's own result arrays: changed in place)
                t_hit[nearer] = t_near[closer]
                geometry[nearer] = t2["geometry_ids"].numpy()[closer] + len(world.parts)
                primitive[nearer] = t2["primitive_ids"].numpy()[closer]
                normals[nearer] = t2["primitive_normals"].numpy()[closer]
                counts = np.array([p.n_triangles for p in parts], np.int64)
                offsets = np.concatenate(
                    [offsets, world.reflectivity.size + np.concatenate([[0], np.cumsum(counts)[:-1]])]
                ).astype(np.int64)
                reflectivity = np.concatenate([reflectivity] + [p.reflectivity for p in parts])
                was_hit = np.zeros(len(t_hit), bool)
                was_hit[hit] = True
                extra = nearer[~was_hit[nearer] & (t_hit[nearer] <= model.max_range)]
                if len(extra):  # rays that return only because a mover is in their way
                    m = len(extra)
                    drawn = [intensity_noise, drop_draw, range_noise]
                    more = [
                        (rng.random(m, dtype=np.float32) - np.float32(0.5)) * np.float32(math.sqrt(12.0)),
                        rng.random(m, dtype=np.float32),
                        rng.standard_normal(m, dtype=np.float32),
                    ]
                    was_hit[extra] = True
                    all_hit = np.flatnonzero(was_hit)  # in ray order, as without movers
                    for k in range(3):
                        full = np.empty(len(t_hit), np.float32)
                        full[hit] = drawn[k]
                        full[extra] = more[k]
                        drawn[k] = full[all_hit]
                    hit = all_hit
                    intensity_noise, drop_draw, range_noise = drawn
        return _returns(
            hit,
            t_hit,
            geometry,
            primitive,
            normals,
            rays,
            dirs,
            reflectivity,
            offsets,
            intensity_noise,
            drop_draw,
            range_noise,
            np.float32(model.max_range),
            np.float32(model.range_sigma),
            np.float32(model.intensity_noise),
            np.float32(model.dropout),
            np.float32(model.weak_dropout),
        )
