"""A city's ray caster: its triangles sorted into TILE-sized squares, and each scan cast into
the scene of the 4 × 4 tiles around the sensor only.

Why: a 4 km city has tens of millions of triangles; one Embree scene of all of them would take
GBs and tens of seconds to build, while a scan reaches 120 m. The block of a scan is the 4 × 4
tiles around the tile corner nearest the sensor, so the sensor is always at least 1.5 tiles
(192 m) from the block's edge: enough for the sensor's range, the longest triangles (walls of
80 m halls, sorted by their centroid) and the sensor's motion during a skewed sweep. A block's
scene is built when a drive first needs it (about every 128 m of driving, a fraction of a
second) and the last few are kept. A scan depends only on its pose and its random stream, as
in a town: the block is a function of the pose.
"""

from __future__ import annotations

import math
import threading
from collections import OrderedDict

import numpy as np

from ..lidar_models import LidarModel
from ..lidar_sim import MeshPart, RaycastLidar, _compile_kernels, _Scene
from .constants import TILE

_OFFSET = 512  # tile indices are stored shifted by this, so that keys stay ≥ 0
_SPAN = 1024  # int32 key = (ti + _OFFSET) · _SPAN + (tj + _OFFSET)
BLOCK_TILES = 4
KEPT_SCENES = 3


def block_of(x: float, y: float) -> tuple[int, int]:
    """The block of a sensor at (x, y): the index of the tile corner nearest it."""
    return int(math.floor(x / TILE + 0.5)), int(math.floor(y / TILE + 0.5))


class _TileIndex:
    """Each part's triangles in order of their tile (by centroid), and the block scenes."""

    def __init__(self, parts: list[MeshPart]):
        self.parts = [p for p in parts if p.n_triangles > 0]
        self.order, self.keys = [], []
        for p in self.parts:
            key = np.empty(p.n_triangles, np.int32)
            for k in range(0, p.n_triangles, 1 << 20):  # centroids a million at a time
                c = p.vertices[p.triangles[k : k + (1 << 20)]].mean(axis=1)
                ti = np.clip(np.floor(c[:, 0] / TILE), -_OFFSET, _OFFSET - 1).astype(np.int32) + _OFFSET
                tj = np.clip(np.floor(c[:, 1] / TILE), -_OFFSET, _OFFSET - 1).astype(np.int32) + _OFFSET
                key[k : k + len(c)] = ti * _SPAN + tj
            order = np.argsort(key, kind="stable").astype(np.int32)
            self.order.append(order)
            self.keys.append(key[order])
        self._scenes: OrderedDict = OrderedDict()
        self._lock = threading.Lock()

    def __getstate__(self):
        state = self.__dict__.copy()
        state["_scenes"] = OrderedDict()
        state["_lock"] = None
        return state

    def __setstate__(self, state):
        self.__dict__.update(state)
        self._lock = threading.Lock()

    @property
    def n_triangles(self) -> int:
        return int(sum(p.n_triangles for p in self.parts))

    def triangles_in(self, i0: int, i1: int, j0: int, j1: int) -> list[np.ndarray]:
        """Per part, the indices of its triangles whose centroid lies in tiles [i0, i1) × [j0, j1)."""
        out = []
        for order, keys in zip(self.order, self.keys):
            pieces = []
            for ti in range(i0, i1):
                lo = (ti + _OFFSET) * _SPAN + (j0 + _OFFSET)
                a, b = np.searchsorted(keys, [lo, lo + (j1 - j0)])
                if b > a:
                    pieces.append(order[a:b])
            out.append(np.concatenate(pieces) if pieces else np.zeros(0, np.int32))
        return out

    def block_parts(self, block: tuple[int, int]) -> list[MeshPart]:
        """The triangles of the block's 4 × 4 tiles, one part per part, vertices compacted."""
        ci, cj = block
        half = BLOCK_TILES // 2
        out = []
        for p, idx in zip(self.parts, self.triangles_in(ci - half, ci + half, cj - half, cj + half)):
            if not len(idx):
                continue
            used, remap = np.unique(p.triangles[idx], return_inverse=True)
            out.append(MeshPart(p.name, p.vertices[used], remap.reshape(-1, 3), p.reflectivity[idx]))
        return out

    def scene(self, block: tuple[int, int]) -> _Scene:
        with self._lock:
            scene = self._scenes.get(block)
            if scene is None:
                scene = _Scene(self.block_parts(block))
                self._scenes[block] = scene
                while len(self._scenes) > KEPT_SCENES:
                    self._scenes.popitem(last=False)
            else:
                self._scenes.move_to_end(block)
        return scene


class TiledLidar:
    """:class:`~..lidar_sim.RaycastLidar`'s interface over a city's tiles (see the module's
    docstring): ``scan``, ``with_model``, ``parts``, ``n_triangles``, ``build``."""

    def __init__(self, parts: list[MeshPart], model: LidarModel | None = None, *, _index: _TileIndex | None = None):
        self.model = model or LidarModel()
        self._index = _index if _index is not None else _TileIndex(parts)
        self._lidars: OrderedDict = OrderedDict()
        self._lock = threading.Lock()

    def with_model(self, model: LidarModel) -> TiledLidar:
        """The same city scanned by another sensor (sharing its tiles and block scenes)."""
        return self if model == self.model else TiledLidar([], model, _index=self._index)

    def __getstate__(self):
        state = self.__dict__.copy()
        state["_lidars"] = OrderedDict()
        state["_lock"] = None
        return state

    def __setstate__(self, state):
        self.__dict__.update(state)
        self._lock = threading.Lock()

    @property
    def parts(self) -> list[MeshPart]:
        return self._index.parts

    @property
    def n_triangles(self) -> int:
        return self._index.n_triangles

    def build(self) -> None:
        """Compile the scan kernels now; block scenes are built as drives reach them."""
        _compile_kernels()

    def _lidar(self, block) -> RaycastLidar:
        with self._lock:
            lidar = self._lidars.get(block)
            if lidar is not None:
                self._lidars.move_to_end(block)
                return lidar
        lidar = RaycastLidar([], self.model, _scene=self._index.scene(block))
        with self._lock:
            self._lidars[block] = lidar
            while len(self._lidars) > KEPT_SCENES:
                self._lidars.popitem(last=False)
        return lidar

    def scan(self, T_world_sensor: np.ndarray, rng: np.random.Generator, sweep=None, moving=None) -> np.ndarray:
        """One sweep from ``T_world_sensor`` (town frame), as :meth:`RaycastLidar.scan`."""
        T = np.asarray(T_world_sensor, dtype=np.float64)
        return self._lidar(block_of(T[0, 3], T[1, 3])).scan(T, rng, sweep=sweep, moving=moving)
