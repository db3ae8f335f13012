"""The map's layers of the scene: the prior map and its road-removed copy thinned for display, and
the BEV pyramid's cells at one level.

A map that fits in ``DISPLAY_MAX_POINTS`` at the display voxel is sent whole, as one node. A
bigger one (a city) is sent in tiles (:mod:`.map_tiles`): a coarse layer of the whole map,
always there, and the tiles nearest the estimate at the display voxel in place of their coarse
points, swapped as the vehicle moves; its road-removed copy stays coarse. Every map layer
together never sends more than ``DISPLAY_BUDGET`` points."""

from __future__ import annotations

import time

import numpy as np

from ...core.maps.voxel_grid import voxel_centroids
from .ground import GroundHeight
from .map_tiles import NearTiles, TiledMap, TileSettings, thin
from .minimap import Footprint
from .style import (
    BEV_COLOR,
    DISPLAY_MAX_POINTS,
    DISPLAY_VOXEL,
    height_colors,
)


class MapLayers:
    """A part of :class:`SceneView` (see the module docstring)."""

    # -------------------------------------------------------------------- static content
    def set_map(
        self,
        prior_map,
        voxel: float = DISPLAY_VOXEL,
        max_points: int = DISPLAY_MAX_POINTS,
        tiles: TileSettings | None = None,
    ) -> None:
        """The map, down-sampled for display and coloured by height: whole when it fits in
        ``max_points`` at ``voxel``, else in tiles (``tiles``: how; default the viewer's).
        float32 positions: viser's default float16 is off by ~0.25 m a few hundred metres out."""
        with self._lock:
            self._set_map(prior_map, voxel, max_points, tiles if tiles is not None else TileSettings())

    def _cloud(self, name: str, pts: np.ndarray, point_size: float, visible: bool, span=None):
        return self.scene.add_point_cloud(
            name,
            pts,
            height_colors(pts[:, 2], span),
            point_size=point_size,
            precision="float32",
            point_shape="square",
            point_shading="flat",
            visible=visible,
        )

    def _set_map(self, prior_map, voxel: float, max_points: int, settings: TileSettings) -> None:
        self._drop_map()
        voxel = max(voxel, prior_map.voxel_size)
        self.display_voxel = voxel
        self._source_voxel = float(prior_map.voxel_size)
        self._tile_settings = settings
        self._max_points = max_points
        # whole, if it leaves room for the road-removed layer in the budget
        pts = voxel_centroids(prior_map.points, voxel, cap=min(max_points, settings.budget - settings.road_removed_max))
        if pts is not None:  # one node
            self._map = self._cloud("/map/full", pts, voxel * 0.8, self.layers.map)
            self._map_points = len(pts)
            self.ground = GroundHeight(pts)
            lo, hi, shown = pts.min(axis=0), pts.max(axis=0), pts
        else:
            tiled = self._tiled = TiledMap(prior_map.points, prior_map.voxel_size, voxel, settings)
            self._map = self.scene.add_frame("/map/full", show_axes=False, visible=self.layers.map)
            size = tiled.coarse_voxel * 0.8
            for t, part in tiled.coarse_tiles.items():
                name = f"/map/full/coarse/{tiled.grid.name(t)}"
                self._coarse_nodes[t] = self._cloud(name, part, size, True, tiled.z_span)
            self._map_points = len(tiled.coarse)
            budget = settings.budget - len(tiled.coarse) - settings.road_removed_max
            self._near = NearTiles(tiled, budget, settings, on_ready=self._map_tiles_ready)
            self.ground = tiled.ground
            lo, hi, shown = tiled.lo, tiled.hi, tiled.coarse
        self.footprint = Footprint.of_points(shown, lo, hi)
        self._map_bev = None
        self._map_bev_points = 0
        if prior_map.points_bev is not None:  # else it is still being built: set_map_bev adds it
            self._set_map_bev(prior_map.points_bev)
        self.map_center = (np.asarray(lo, float) + np.asarray(hi, float)) / 2.0
        self.map_center[2] = self.ground.z_default
        self.map_extent = float(max(hi[0] - lo[0], hi[1] - lo[1], 20.0))
        self._check_budget()

    def _drop_map(self) -> None:
        """Another map is shown: the tiles of the one before go (a whole map's node is replaced
        by name)."""
        if self._near is not None:
            self._near.cancelled = True
        for node in [*self._near_nodes.values(), *self._coarse_nodes.values()]:
            node.remove()
        if self._tiled is not None and self._map is not None:
            self._map.remove()
            self._map = None
        self._near_nodes, self._coarse_nodes = {}, {}
        self._tiled = self._near = None

    def _map_tiles_ready(self) -> None:
        callback = self.on_map_tiles
        if callback is not None:
            callback()

    @property
    def tiled(self) -> bool:
        """Whether the map is sent in tiles (too big to send whole)."""
        return self._tiled is not None

    @property
    def map_points_sent(self) -> int:
        """Points of every map layer sent to the browser (the map and its road-removed copy)."""
        near = 0 if self._near is None else self._near.points
        return self._map_points + near + self._map_bev_points

    def _check_budget(self) -> None:
        budget = self._tile_settings.budget
        assert self.map_points_sent <= budget, f"{self.map_points_sent} map points sent, budget {budget}"

    @property
    def near_tiles(self) -> tuple:
        """The tiles shown at full density, as (x0, y0, x1, y1) each, sorted (none for a map
        sent whole)."""
        with self._lock:
            if self._tiled is None:
                return ()
            return tuple(self._tiled.grid.rect(t) for t in sorted(self._near_nodes))

    def near_tile_node(self, rect):
        """The node of the full-density tile at ``rect`` (one of :attr:`near_tiles`), or None."""
        with self._lock:
            if self._tiled is None:
                return None
            t = int(self._tiled.grid.tiles_of(np.array([[rect[0], rect[1]]]) + 1e-6)[0])
            return self._near_nodes.get(t)

    def follow_map(self, pose, now: float | None = None) -> None:
        """Display thread: the full-density tiles of a map sent in tiles follow ``pose`` (4×4,
        the estimate). Swaps in the tiles read since the last call, and at most every
        ``interval_s`` asks for a new choice (read on a thread of its own: nothing here waits)."""
        with self._lock:
            near = self._near
            if near is None:
                return
            change = near.take()
            if change is not None:
                self._swap_tiles(*change)
            if pose is None:
                return
            p = np.asarray(pose, float)[:3, 3]
            if np.isfinite(p).all():
                near.request(float(p[0]), float(p[1]), time.monotonic() if now is None else now)

    def wait_map_tiles(self, timeout: float | None = None) -> None:
        """Until the tiles being read (if any) are read: the next :meth:`follow_map` shows them."""
        near = self._near
        if near is not None:
            near.wait(timeout)

    def _swap_tiles(self, added: dict, removed: list) -> None:
        tiled = self._tiled
        assert tiled is not None
        for t in removed:
            self._near_nodes.pop(t).remove()
            if t in self._coarse_nodes:
                self._coarse_nodes[t].visible = True
        for t, pts in added.items():
            name = f"/map/full/near/{tiled.grid.name(t)}"
            self._near_nodes[t] = self._cloud(name, pts, self.display_voxel * 0.8, True, tiled.z_span)
            if t in self._coarse_nodes:
                self._coarse_nodes[t].visible = False
        self._check_budget()

    @property
    def has_map_bev(self) -> bool:
        """Whether the road-removed map is drawn (it can arrive after the map: see set_map_bev)."""
        return self._map_bev is not None

    def set_map_bev(self, points_bev) -> None:
        """The road-removed map, when it was built after the map was shown (a first start: road
        removal runs in the background while the filter already plays)."""
        with self._lock:
            if self._map_bev is None:
                self._set_map_bev(points_bev)

    def _set_map_bev(self, points_bev) -> None:
        s = self._tile_settings
        if self._tiled is None:  # as the map: at the display voxel, within what the budget leaves
            room = min(self._max_points, s.budget - self._map_points)
            bev = voxel_centroids(points_bev, self.display_voxel, cap=room)
            size = self.display_voxel
            if bev is None:
                bev, size = thin(points_bev, room, self.display_voxel, self._source_voxel)
            span = None
        else:  # coarse, in the share of the budget kept for it
            bev, size = thin(points_bev, s.road_removed_max, self.display_voxel, self._source_voxel)
            span = self._tiled.z_span
        self._map_bev = self._cloud("/map/road_removed", bev, size * 0.8, self.layers.map_bev, span)
        self._map_bev_points = len(bev)
        self._check_budget()

    def set_pyramid(self, pyramid, level: int) -> None:
        """Show one BEV pyramid level as a flat image on the ground (cells with map points in
        yellow, the paper's colour, brighter for larger values; empty cells transparent)."""
        if pyramid is None:
            return
        with self._lock:
            self._set_pyramid(pyramid, level)

    def _set_pyramid(self, pyramid, level: int) -> None:
        level = int(np.clip(level, 0, len(pyramid.levels) - 1))
        if pyramid is self._pyramid and level == self._bev_level_shown:
            return
        grid = np.asarray(pyramid.levels[level], np.float32)  # [ix, iy]
        cell = pyramid.resolution * 2**level
        vmax = float(grid.max()) if grid.size and grid.max() > 0 else 1.0
        value = np.clip(grid / vmax, 0, 1)
        # image rows run top (max y) to bottom, columns along +x
        value = value.T[::-1]
        rgba = np.zeros(value.shape + (4,), np.uint8)
        rgba[..., :3] = BEV_COLOR
        rgba[..., 3] = np.where(value > 0, (90 + 140 * np.sqrt(value)).astype(np.uint8), 0)
        nx, ny = grid.shape
        x0, y0 = (float(v) for v in pyramid.origin)
        w, h = nx * cell, ny * cell
        z = (self.ground.z_default if self.ground is not None else 0.0) - 0.3
        if self._bev_image is not None:
            self._bev_image.remove()
        # Nearest-neighbour look: upsample small levels so the image filter keeps the cells crisp.
        rep = max(1, int(np.ceil(256 / max(value.shape))))
        if rep > 1:
            rgba = np.repeat(np.repeat(rgba, rep, axis=0), rep, axis=1)
        self._bev_image = self.scene.add_image(
            "/map/bev_level",
            rgba,
            w,
            h,
            format="png",
            position=(x0 + w / 2, y0 + h / 2, z),
            cast_shadow=False,
            receive_shadow=False,
            visible=self.layers.bev_level,
        )
        self._pyramid, self._bev_level_shown = pyramid, level
