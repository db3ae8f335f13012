"""The built-in world: a generated town, drives through it, and a simulated LiDAR scanning it.

Two ways to lay out the town:

- **grid** (default): an irregular street grid (block sides from a few standard lengths, some
  street segments missing so blocks merge), a drive that first closes one loop around a group of
  blocks (so the start is revisited) and then wanders on, right-hand traffic, stops at some
  intersections and a speed profile with 30–50 km/h cruising and braking for turns;
- **trajectory**: the drive is a real KITTI odometry ground truth (cam0 poses + Tr), and the town
  is grown around it at true scale: the road follows the trajectory's footprint, side streets
  branch off it, and buildings, trees, etc. are placed beside the road, never on it.

Both share one pipeline on a 0.5 m raster of the ground plan: street centrelines → road mask
(with rounded curb corners) → distance fields → buildings along the street frontages (varied
footprints, setbacks and heights driven by a smooth "urban density" field), back buildings,
parks, trees whose crowns are clouds of small triangles (rays pass through the gaps, so crowns
return scattered points as real foliage does), street lights and sign poles, walls, fences and
hedges on property lines, parked cars in the parking lanes, dashed centre lines, and a smooth
height field under everything with sidewalks and lots raised by a curb.

**A city**: from ``extent_m`` ≥ 1000 m (``--set town.extent_m=4000``: 16 km²) the grid grows
into a city of districts, each built in its own style: downtown (tall, dense, narrow lots),
suburbs (detached houses, gardens, hedges, trees), an industrial strip (large low halls, fences,
yards), parks (trees, paths, few buildings) and a highway ring (wide, fast, guard rails and noise
walls, nothing built near it); streets come in classes (local, arterial, highway) with their
own widths and speed limits, and drives pick routes across districts. Below 1000 m a town keeps
its single style, bit for bit. A city's world does not depend on any drive: it is built once per
(seed, extent) and cached, its frame is its own (the drives' poses are in it), its triangles are
cast tile by tile, and its prior map is not fused from a mapping drive but sampled from its
surfaces as a survey of every street sees them (``docs/city.md``).

Scans are simulated on demand from (seed, index) and nothing is written to disk (a city caches
its world). The town is
built in its own frame ("town frame"); the world frame of every drive through a town is the
mapping drive's first LiDAR pose (for the mapping drive, its own first pose, as for every
:class:`~..base.Sequence`); :attr:`TownSequence.town_to_world` maps one to the other.

A town's prior map always comes from the **mapping drive** (route 1, the town as it was mapped,
HDL-64E at 1.73 m, no motion skew, no traffic: :attr:`TownSequence.map_source`); a city's from
its survey (:mod:`.survey`). The drive being
localized may differ from it in its world options (``town.*`` in the configuration): changes
since mapping, traffic, another sensor or mounting height, motion skew, a second route.

The package, in the order a town is made:

- :mod:`.constants`: scale, driving limits, sensor height, random-stream seeds;
- :mod:`.raster`: the ground plan's raster and height field;
- :mod:`.layout`: streets (grid or along a trajectory) and the ground plan;
- :mod:`.drive`: the drive through the streets and the LiDAR poses along it;
- :mod:`.objects`: buildings, trees, poles, cars … placed on the plan;
- :mod:`.meshes`: triangles of the ground and the objects for the ray caster;
- :mod:`.world`: :class:`~.world.Town`, the town as mapped and its mapping drive, built once;
- :mod:`.changes`: what changed since the mapping drive (``town.changes``);
- :mod:`.traffic`: cars, cyclists and pedestrians moving through it (``town.traffic``);
- :mod:`.routes`: the second drive through the same streets (``town.route = 2``);
- :mod:`.sequence`: :class:`TownSequence`, a drive through a town, scanned on demand;

and for a city:

- :mod:`.districts`: the district map and what each style builds;
- :mod:`.city_layout`: the city's streets by class, and its compact ground plan;
- :mod:`.city_objects`: the objects, district by district, and the highway's own;
- :mod:`.city_route`: drives across districts;
- :mod:`.city`: the city's world, built once per (seed, extent) and cached;
- :mod:`.tiles`: its ray caster, tile by tile;
- :mod:`.survey`: its prior map, sampled from its surfaces.
"""

from .constants import SENSOR_HEIGHT, SWAY_STD, TOWN_VERSION
from .sequence import TownSequence

__all__ = ["SENSOR_HEIGHT", "SWAY_STD", "TOWN_VERSION", "TownSequence"]
