"""The built-in world: a generated town, a drive through it, and a simulated HDL-64E scanning it.

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

Scans are simulated on demand from (seed, index) and nothing is written to disk. The town is
built in its own frame ("town frame"); the sequence's world frame is the first LiDAR pose, as for
every :class:`~..base.Sequence`; :attr:`TownSequence.town_to_world` maps one to the other.

The package, in the order a town is made:

- :mod:`.constants`: scale, driving limits, sensor height, random-stream seeds;
- :mod:`.raster`: the ground plan's raster and height field;
- :mod:`.layout`: streets (grid or along a trajectory) and the ground plan;
- :mod:`.drive`: the drive through the streets and the LiDAR poses along it;
- :mod:`.objects`: buildings, trees, poles, cars … placed on the plan;
- :mod:`.meshes`: triangles of the ground and the objects for the ray caster;
- :mod:`.sequence`: :class:`TownSequence`, which puts it together and scans on demand.
"""

from .constants import SENSOR_HEIGHT, SWAY_STD, TOWN_VERSION
from .sequence import TownSequence

__all__ = ["SENSOR_HEIGHT", "SWAY_STD", "TOWN_VERSION", "TownSequence"]
