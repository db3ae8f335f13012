"""The map's layers of the scene: the prior map and its road-removed copy thinned for display, and the BEV pyramid's cells at one level."""

from __future__ import annotations

import numpy as np

from .ground import GroundHeight
from .shapes import (
    downsample_for_display,
)
from .style import (
    BEV_COLOR,
    DISPLAY_MAX_POINTS,
    DISPLAY_VOXEL,
    height_colors,
)


class MapLayers:
    """A part of :class:`SceneView` (see the module docstring)."""

    # -------------------------------------------------------------------- static content
    def set_map(self, prior_map, voxel: float = DISPLAY_VOXEL, max_points: int = DISPLAY_MAX_POINTS) -> None:
        """The map, down-sampled for display and coloured by height; sent once (static scene state).
        float32 positions: viser's default float16 is off by ~0.25 m a few hundred metres out."""
        with self._lock:
            self._set_map(prior_map, voxel, max_points)

    def _set_map(self, prior_map, voxel: float, max_points: int) -> None:
        pts, self.display_voxel = downsample_for_display(prior_map.points, max(voxel, prior_map.voxel_size), max_points)
        self._map = self.scene.add_point_cloud(
            "/map/full",
            pts,
            height_colors(pts[:, 2]),
            point_size=self.display_voxel * 0.8,
            precision="float32",
            point_shape="square",
            point_shading="flat",
            visible=self.layers.map,
        )
        self._max_points = max_points
        self._map_bev = None
        if prior_map.points_bev is not None:  # else it is still being built: set_map_bev adds it
            self._set_map_bev(prior_map.points_bev)
        self.ground = GroundHeight(pts)
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        self.map_center = (lo + hi) / 2.0
        self.map_center[2] = self.ground.z_default
        self.map_extent = float(max(hi[0] - lo[0], hi[1] - lo[1], 20.0))

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
        bev, _ = downsample_for_display(points_bev, self.display_voxel, self._max_points)
        self._map_bev = self.scene.add_point_cloud(
            "/map/road_removed",
            bev,
            height_colors(bev[:, 2]),
            point_size=self.display_voxel * 0.8,
            precision="float32",
            point_shape="square",
            point_shading="flat",
            visible=self.layers.map_bev,
        )

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
