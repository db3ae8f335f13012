"""A simulated Velodyne HDL-64E: rays cast into a triangle world with open3d's Embree scene.

The sensor model is deliberately simple but keeps what a scan matcher notices:

- 64 beams from +2° to −24.8° elevation in the HDL-64E's two laser blocks (the upper block is
  denser), ``n_azimuth`` steps per revolution, 120 m maximum range; rays that hit nothing within
  range produce no return (like the real sensor, which reports no point for a miss);
- Gaussian range noise, random dropouts, and more dropouts for weak far returns;
- intensity = material reflectivity × |cos(incidence)|, the Lambertian falloff a real return has;
- one scan is an instantaneous snapshot from one pose (no motion skew within the sweep), so the
  ground-truth pose describes every point of the scan exactly.

The ray direction table is computed once; a scan is one ``cast_rays`` call plus a handful of
vectorised numpy operations, and everything random comes from the generator the caller passes
(so a scan is a pure function of the pose and that generator's seed).
"""

from __future__ import annotations

import functools
import math
import threading
from dataclasses import dataclass

import numba as nb
import numpy as np

from ..o3d import open3d

DEG = np.pi / 180.0

# HDL-64E S2 layout: the upper block's 32 lasers span +2° … −8.33° (≈1/3° apart), the lower
# block's 32 span −8.83° … −24.8° (≈1/2° apart).
HDL64E_UPPER_DEG = (2.0, -8.33)
HDL64E_LOWER_DEG = (-8.83, -24.8)
HDL64E_MIN_ELEVATION_DEG = HDL64E_LOWER_DEG[1]
HDL64E_MAX_ELEVATION_DEG = HDL64E_UPPER_DEG[0]
# The firing phase is not locked to the frame: each scan uses one of this many ray tables, each
# turned by a fraction of one azimuth step, so two scans from one pose sample different spots.
N_PHASES = 8


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
def _returns(hit, t_hit, geometry, primitive, normals, rays, dirs, reflectivity, offsets,
             intensity_noise, drop_draw, range_noise, max_range, range_sigma, intensity_sigma,
             dropout, weak_dropout):
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


@functools.lru_cache(maxsize=None)
def _compile_kernels() -> None:
    """Run both kernels once on tiny inputs: numba compiles them (or loads its on-disk cache)."""
    dirs = np.array([[1.0, 0.0, 0.0]], np.float32)
    rays = np.empty((1, 6), np.float32)
    _fill_rays(dirs, np.eye(3, dtype=np.float32), np.zeros(3, np.float32), rays)
    one_f = np.ones(1, np.float32)
    one_u = np.zeros(1, np.uint32)
    _returns(np.zeros(1, np.int64), one_f, one_u, one_u, np.ones((1, 3), np.float32), rays, dirs, one_f,
             np.zeros(1, np.int64), one_f, one_f, one_f, np.float32(1), np.float32(0), np.float32(0),
             np.float32(0), np.float32(0))


@dataclass(frozen=True)
class LidarModel:
    """Parameters of the simulated sensor."""

    n_azimuth: int = 2000              # firings per revolution and laser (0.18° apart)
    max_range: float = 120.0           # m
    range_sigma: float = 0.02          # m, Gaussian range noise
    dropout: float = 0.02              # probability that any return is lost
    weak_dropout: float = 0.4          # extra loss probability of a zero-intensity return at max range
    intensity_noise: float = 0.05      # relative (multiplicative) intensity noise, standard deviation

    def elevations(self) -> np.ndarray:
        """(64,) beam elevations in radians, top beam first."""
        upper = np.linspace(*HDL64E_UPPER_DEG, 32)
        lower = np.linspace(*HDL64E_LOWER_DEG, 32)
        return np.concatenate([upper, lower]) * DEG

    def ray_directions(self, phase: float = 0.0) -> np.ndarray:
        """(64 · n_azimuth, 3) float32 unit directions in the sensor frame, beam-major (ring order),
        the first firing of each beam ``phase`` azimuth steps after the x axis."""
        elevation = self.elevations()[:, None]
        azimuth = (np.arange(self.n_azimuth)[None, :] + phase) * (2.0 * np.pi / self.n_azimuth)
        dirs = np.stack(
            np.broadcast_arrays(np.cos(elevation) * np.cos(azimuth),
                                np.cos(elevation) * np.sin(azimuth),
                                np.sin(elevation)),
            axis=-1,
        )
        return dirs.reshape(-1, 3).astype(np.float32)


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

    @staticmethod
    def _ray_tables(model: LidarModel) -> list[np.ndarray]:
        return [model.ray_directions(k / N_PHASES) for k in range(N_PHASES)]

    @property
    def n_triangles(self) -> int:
        return len(self.triangles)


class RaycastLidar:
    """Casts the sensor's rays into a fixed set of mesh parts.

    The Embree scene is built lazily (and not pickled): open3d scenes cannot be copied between
    processes, but the mesh parts can, and rebuilding from them gives the identical scene.
    """

    def __init__(self, parts: list[MeshPart], model: LidarModel | None = None):
        self.model = model or LidarModel()
        self.parts = [p for p in parts if p.n_triangles > 0]
        self._tables = self._ray_tables(self.model)
        # One flat reflectivity table: geometry g's triangle k is at offsets[g] + k. Geometry ids
        # are assigned by open3d in insertion order starting at 0, which _build checks.
        counts = np.array([p.n_triangles for p in self.parts], dtype=np.int64)
        self._offsets = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
        self._reflectivity = (np.concatenate([p.reflectivity for p in self.parts])
                              if self.parts else np.zeros(0, np.float32))
        self._scene = None
        self._lock = threading.Lock()

    def __getstate__(self):
        state = self.__dict__.copy()
        state["_scene"] = None
        state["_lock"] = None
        state["_tables"] = None  # 12 MB that the model recomputes in milliseconds
        return state

    def __setstate__(self, state):
        self.__dict__.update(state)
        self._lock = threading.Lock()
        self._tables = self._ray_tables(self.model)

    @staticmethod
    def _ray_tables(model: LidarModel) -> list[np.ndarray]:
        return [model.ray_directions(k / N_PHASES) for k in range(N_PHASES)]

    @property
    def n_triangles(self) -> int:
        return int(self._reflectivity.size)

    def build(self) -> None:
        """Build the scene and its BVH, and compile the scan kernels, now rather than in the
        first scan (which a caller may be timing)."""
        self._scene_or_build()
        _compile_kernels()

    def _scene_or_build(self):
        if self._scene is not None:
            return self._scene
        with self._lock:
            if self._scene is None:
                o3d = open3d()
                scene = o3d.t.geometry.RaycastingScene()
                for expected_id, part in enumerate(self.parts):
                    gid = scene.add_triangles(o3d.core.Tensor(part.vertices), o3d.core.Tensor(part.triangles))
                    if gid != expected_id:
                        raise RuntimeError(f"open3d gave geometry id {gid} to mesh part {expected_id}")
                # Embree commits (builds the BVH) on the first query; do it here, not mid-drive.
                probe = np.zeros((1, 6), np.float32)
                probe[0, 5] = -1.0
                scene.cast_rays(o3d.core.Tensor(probe), nthreads=0)
                self._scene = scene
        return self._scene

    def scan(self, T_world_sensor: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """One sweep from the sensor pose ``T_world_sensor`` (4×4): float32 (N, 4) x, y, z,
        intensity in the sensor frame. Only rays that hit something within max_range return."""
        o3d = open3d()
        scene = self._scene_or_build()
        model = self.model
        dirs = self._tables[int(rng.integers(N_PHASES))]
        T = np.asarray(T_world_sensor, dtype=np.float64)
        rays = np.empty((len(dirs), 6), dtype=np.float32)
        _fill_rays(dirs, T[:3, :3].astype(np.float32), T[:3, 3].astype(np.float32), rays)
        result = scene.cast_rays(o3d.core.Tensor.from_numpy(rays), nthreads=0)
        t_hit = result["t_hit"].numpy()
        hit = np.flatnonzero(t_hit <= model.max_range)
        n = len(hit)
        # Intensity noise need not be Gaussian: uniform with the same σ costs a sixth of the time.
        intensity_noise = (rng.random(n, dtype=np.float32) - np.float32(0.5)) * np.float32(math.sqrt(12.0))
        drop_draw = rng.random(n, dtype=np.float32)
        range_noise = rng.standard_normal(n, dtype=np.float32)
        return _returns(hit, t_hit, result["geometry_ids"].numpy(), result["primitive_ids"].numpy(),
                        result["primitive_normals"].numpy(), rays, dirs, self._reflectivity, self._offsets,
                        intensity_noise, drop_draw, range_noise, np.float32(model.max_range),
                        np.float32(model.range_sigma), np.float32(model.intensity_noise),
                        np.float32(model.dropout), np.float32(model.weak_dropout))
