"""A city's world, built once per (seed, extent) and cached: streets and districts, the ground
plan, the objects, their triangles, and what the survey map needs to know about sight lines.

Unlike a town's, a city's world does not depend on any drive through it (nothing is placed
with a particular drive in mind, see :mod:`.city_layout`), so every drive of a city shares one
world, one cache entry and one survey map. The entry is a directory ``city-<key>`` in the cache
root (``$LIDARLOC_CACHE``), keyed by CITY_VERSION, the seed and the extent; generating a 4 km
city takes minutes, loading it seconds.
"""

from __future__ import annotations

import hashlib
import pickle
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ...cache import atomic_write_dir, default_cache_root
from ..lidar_sim import MeshPart
from .city_layout import CityGrid, city_ground, city_raster, city_streets, make_city_plan, plan_city_grid
from .city_objects import populate_city
from .constants import CELL, CITY_STREAM, CITY_VERSION
from .districts import DistrictMap
from .layout import Plan
from .meshes import ground_parts, object_parts
from .solids import Solids

GROUND_WINDOW = 512  # cells (256 m): the ground is meshed window by window
#: materials that hide what is behind them from a street-level sensor (see :mod:`.survey`)
OPAQUE = ("building", "wall", "container")


@dataclass
class CityWorld:
    seed: int
    extent: float
    grid: CityGrid
    districts: DistrictMap
    plan: Plan
    solids: Solids
    parts: list[MeshPart]
    cover: np.ndarray  # (nx, ny) uint8: height of opaque objects above the ground per cell, in 0.25 m
    stats: dict
    build_seconds: float


def city_identity(seed: int, extent: float) -> str:
    return f"city|v{CITY_VERSION}|seed={int(seed)}|extent={float(extent):g}"


def build_city(seed: int, extent: float) -> CityWorld:
    t0 = time.perf_counter()
    rng = np.random.default_rng([int(seed), *CITY_STREAM])
    grid, districts = plan_city_grid(rng, extent)
    streets, junctions = city_streets(grid, extent)
    raster = city_raster(extent)
    ground = city_ground(rng, raster, extent)
    plan = make_city_plan(rng, raster, ground, streets, junctions, districts, extent)
    solids = populate_city(plan, rng)
    parts = _ground_parts(plan, rng) + object_parts(solids, ground, rng, chunk_rows=20_000)
    cover = _cover(plan, solids)
    stats = dict(solids.counts)
    stats.update(
        triangles=int(sum(p.n_triangles for p in parts)),
        streets=len(streets),
        junctions=len(junctions),
        districts=districts.shares(extent),
        street_km=_street_km(streets),
    )
    return CityWorld(
        int(seed), float(extent), grid, districts, plan, solids, parts, cover, stats, time.perf_counter() - t0
    )


def _ground_parts(plan: Plan, rng) -> list[MeshPart]:
    """The ground window by window, joined into one part per material."""
    nx, ny = plan.raster.shape
    pieces: dict[str, list[MeshPart]] = {}
    for i0 in range(0, nx, GROUND_WINDOW):
        for j0 in range(0, ny, GROUND_WINDOW):
            window = (i0, min(i0 + GROUND_WINDOW, nx), j0, min(j0 + GROUND_WINDOW, ny))
            for part in ground_parts(plan, rng, window):
                pieces.setdefault(part.name, []).append(part)
    out = []
    for name, group in pieces.items():
        offsets = np.cumsum([0] + [len(p.vertices) for p in group[:-1]])
        out.append(
            MeshPart(
                name,
                np.concatenate([p.vertices for p in group]),
                np.concatenate([p.triangles.astype(np.int64) + o for p, o in zip(group, offsets)]),
                np.concatenate([p.reflectivity for p in group]),
            )
        )
    return out


def _cover(plan: Plan, solids: Solids) -> np.ndarray:
    """The height of the opaque objects (buildings, walls, containers) above the ground of every
    cell they stand on, in 0.25 m steps (uint8: up to 63 m, enough to hide anything behind)."""
    raster = plan.raster
    cover = np.zeros(raster.shape, np.uint8)
    step = CELL * 0.7
    for material in OPAQUE:
        rows = np.asarray(solids.boxes.get(material, []), float).reshape(-1, 8)
        n_all = (np.ceil(rows[:, 3] / step) + 1) * (np.ceil(rows[:, 4] / step) + 1)
        cum = np.cumsum(n_all)
        k0 = 0
        while k0 < len(rows):  # about 2 M footprint points at a time
            k1 = max(int(np.searchsorted(cum, cum[k0] - n_all[k0] + 2_000_000, side="right")), k0 + 1)
            a = rows[k0:k1]
            k0 = k1
            cx, cy, yaw, L, W, _, z1, _ = a.T
            nu = np.maximum(np.ceil(L / step).astype(int) + 1, 2)
            nv = np.maximum(np.ceil(W / step).astype(int) + 1, 2)
            rep = np.repeat(np.arange(len(a)), nu * nv)
            first = np.repeat(np.cumsum(nu * nv) - nu * nv, nu * nv)
            flat = np.arange(len(rep)) - first
            u = (flat // nv[rep]) / (nu[rep] - 1) - 0.5
            v = (flat % nv[rep]) / (nv[rep] - 1) - 0.5
            c, s = np.cos(yaw[rep]), np.sin(yaw[rep])
            x = cx[rep] + u * L[rep] * c - v * W[rep] * s
            y = cy[rep] + u * L[rep] * s + v * W[rep] * c
            height = z1[rep] - plan.ground(x, y)
            i, j, ok = raster.ij(x, y)
            q = np.clip(np.round(height / 0.25), 0, 255).astype(np.uint8)
            np.maximum.at(cover, (i[ok], j[ok]), q[ok])
    return cover


def _street_km(streets) -> dict[str, float]:
    km: dict[str, float] = {}
    for st in streets:
        km[st.kind] = km.get(st.kind, 0.0) + st.length / 1000.0
    return {k: round(v, 2) for k, v in sorted(km.items())}


# --------------------------------------------------------------------------------- cache
def city_cache_dir(seed: int, extent: float, cache_root: Path | None = None) -> Path:
    key = hashlib.sha1(city_identity(seed, extent).encode()).hexdigest()[:16]
    return Path(cache_root or default_cache_root()) / f"city-{key}"


#: Where the simulator's modules lived before it became ``core/sim/``: a city cached then (minutes
#: to build on a 16 km² city) still loads.
_FORMER_PACKAGES = {
    "lidarloc.core.sequences.town": "lidarloc.core.sim.town",
    "lidarloc.core.sequences.lidar_sim": "lidarloc.core.sim.lidar_sim",
}


class _CityUnpickler(pickle.Unpickler):
    def find_class(self, module, name):
        for old, new in _FORMER_PACKAGES.items():
            if module == old or module.startswith(old + "."):
                module = new + module[len(old) :]
        return super().find_class(module, name)


def load_or_build_city(seed: int, extent: float, cache_root: Path | None = None) -> tuple[CityWorld, bool]:
    """The city's world from the cache, or built and cached; and whether it came from the cache.
    A cache that cannot be written costs only the next build's time: the world is returned."""
    directory = city_cache_dir(seed, extent, cache_root)
    path = directory / "world.pkl"
    if path.is_file():
        try:
            with open(path, "rb") as f:
                stored = _CityUnpickler(f).load()
            if stored.get("identity") == city_identity(seed, extent):
                return _restored(stored["world"]), True
        except (OSError, EOFError, pickle.UnpicklingError, AttributeError, ImportError, KeyError, ValueError):
            pass  # unreadable or from another version of the code: build it again
    world = build_city(seed, extent)

    def write(tmp: Path):
        with open(tmp / "world.pkl", "wb") as f:
            pickle.dump({"identity": city_identity(seed, extent), "world": _storable(world)}, f, protocol=5)

    try:
        atomic_write_dir(directory, write)
    except OSError:
        pass
    return world, False


def _storable(world: CityWorld) -> CityWorld:
    # The distance to a drive is a constant: not worth 67 M cells of a 4 km city on disk.
    return replace(world, plan=replace(world.plan, dist_ego=None))


def _restored(world: CityWorld) -> CityWorld:
    plan = world.plan
    return replace(world, plan=replace(plan, dist_ego=np.broadcast_to(np.float32(np.inf), plan.raster.shape)))
