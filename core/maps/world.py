"""The world a localizer works in, opened in one place: the prior map (with its road-removed copy),
the nearest-distance lookup table the particle filter reads, and the BEV pyramid the scan-to-map
matcher searches — each loaded from the map's cache directory, or built and cached there once.

The prior map always comes from the sequence's ``map_source`` (the whole mapping drive, or a map
file), never from the scans being localized alone: ``--scans N`` plays N scans inside the whole
drive's map, and the town's drive with changes, traffic or another sensor is localized inside the
town as it was mapped. The localizer, the viewer's recorded runs and the benchmarks all open their
world here.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..config import Config
from .bev import BEVPyramid, load_or_build_pyramid
from .follow import TileFollower
from .lookup import LookupTable, load_or_build_lookup
from .mapping import PriorMap, load_or_build_map
from .places import PlaceIndex, places_for_pyramid, uses_places
from .point_tiles import PointTiles
from .tiled_lookup import TiledLookup


@dataclass
class World:
    """The prior map and what is precomputed from it, all in ``map_dir``. ``lookup`` and
    ``pyramid`` are None where they were not asked for; ``pyramid`` also while the road-removed
    copy is still to be built (``open_world(road_removal=False)``)."""

    prior_map: PriorMap
    map_dir: Path
    lookup: LookupTable | None = None
    pyramid: BEVPyramid | None = None
    tiles: TileFollower | None = None
    places: PlaceIndex | None = None  # the place index of whole-map matches by candidates

    @property
    def origin(self) -> np.ndarray:
        """The map's frame in the frame of the file it came from (float64, metres)."""
        return self.prior_map.origin

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(min, max) corners of the map's points (float64, metres, the map's local frame)."""
        lo, hi = self.prior_map.bounds
        return np.asarray(lo, float), np.asarray(hi, float)


def open_world(
    map_source,
    cfg: Config,
    cache_root: Path | None = None,
    *,
    lookup: bool = True,
    pyramid: bool = True,
    road_removal: bool = True,
    progress: Callable[[str, float], None] | None = None,
    on_map: Callable[[PriorMap], None] | None = None,
) -> World:
    """The world of ``map_source`` with ``cfg``'s map, lookup and S2M settings.

    ``road_removal=False``: the map may come without its road-removed copy (then no pyramid): a
    viewer's first start plays on the particle filter while it is built in the background.
    ``progress(stage, fraction)`` reports "map", "point tiles" (a large map cut into tiles),
    "lookup", "pyramid" and "places" (the place index, with the pyramid where
    ``s2m.global_search`` is "candidates"); ``on_map(prior_map)`` is called as soon as the map is there, before its
    tables (a viewer shows it meanwhile)."""
    report = progress or (lambda stage, fraction: None)
    tiled = cfg.pf.lookup_tile_m > 0  # a large map in a tiled run (a city) stays on disk, never read whole
    prior_map, map_dir, _ = load_or_build_map(
        map_source,
        cfg.map,
        cache_root,
        progress=lambda i, n: report("map", i / n),
        road_removal=road_removal,
        memory_map=tiled,
    )
    if prior_map.on_disk:
        report("point tiles", 0.0)
        prior_map.use_tiles(
            PointTiles.load_or_build(
                prior_map.points, map_dir / "tiles-points", map_dir.name, progress=lambda f: report("point tiles", f)
            )
        )
    if on_map is not None:
        on_map(prior_map)
    world = World(prior_map, map_dir)
    if lookup and cfg.pf.lookup_tile_m > 0:
        report("lookup", 0.0)
        tiled = TiledLookup.load_or_build(
            prior_map.points, map_dir / "tiles-lookup", map_dir.name, cfg.pf.lookup_resolution, cfg.pf.d_max,
            cfg.pf.lookup_tile_m, progress=lambda f: report("lookup", f),
        )  # fmt: skip
        # until the particles are there: the whole map (a start may be spread over all of it)
        world.tiles = TileFollower(tiled)
        world.lookup = world.tiles.follow(np.asarray(prior_map.bounds)[:, :2], 0.0)
    elif lookup:
        report("lookup", 0.0)
        world.lookup = load_or_build_lookup(
            prior_map, map_dir, cfg.pf.lookup_resolution, cfg.pf.d_max, progress=lambda f: report("lookup", f)
        ).value
    if pyramid and prior_map.points_bev is not None:
        report("pyramid", 0.0)
        world.pyramid = load_or_build_pyramid(prior_map, map_dir, cfg.s2m).value
        if uses_places(cfg.s2m, world.pyramid.shape):
            report("places", 0.0)
            world.places = places_for_pyramid(world.pyramid, prior_map.points, map_dir, cfg.s2m)
    return world
