"""The stale places of ``lidarloc corpus staleness`` as a layer of the recorded-run viewer
(``lidarloc view --run RUN --staleness DIR``): their points in magenta over the map, and where
the grid has stale cells without points, a dot per cell; toggled in the Layers folder."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..corpus.staleness_out import read_grid

STALE_COLOR = (230, 40, 200)
NODE = "/staleness"


def stale_layer_points(folder: Path) -> np.ndarray:
    """(N, 3) float32: the stale places' points, or each stale cell's centre on the map's
    ground (z 0) where the output holds no points. One-line errors for a folder that is not a
    staleness output."""
    grid = read_grid(folder)
    if grid["points"] is not None and len(grid["points"]):
        return np.asarray(grid["points"], np.float32)
    cells = np.argwhere(grid["stale"])
    xy = np.asarray(grid["origin"]) + (cells + 0.5) * float(grid["resolution"])
    return np.column_stack([xy, np.zeros(len(xy))]).astype(np.float32)


def show_staleness(viewer, folder: Path):
    """Add the layer to ``viewer`` (its checkbox shown and followed); returns the node."""
    points = stale_layer_points(folder)
    box = viewer.controls.layers["staleness"]
    node = viewer.scene.scene.add_point_cloud(
        NODE, points, STALE_COLOR, point_size=0.5, precision="float32", point_shading="flat", visible=bool(box.value)
    )
    box.visible = True

    def follow(_event=None) -> None:
        node.visible = bool(box.value)

    box.on_update(follow)
    return node
