"""Constants of the generated town: its scale, the drive's limits, the sensor's height and the
seeds of the random streams everything is drawn from."""

from __future__ import annotations

import math

from ...config import TOWN_MAX_EXTENT as CITY_MAX_EXTENT  # noqa: F401  (m, the largest extent)

#: Bump whenever the generated geometry, the drive or the sensor model changes: it is part of
#: :meth:`TownSequence.identity`, which keys the prior-map cache.
TOWN_VERSION = 3

SENSOR_HEIGHT = 1.73  # m, KITTI's Velodyne above the road
LANE_OFFSET = 1.75  # m, right-hand traffic: the car drives this far right of the centre line
CELL = 0.5  # m, raster of the ground plan
NODE_CELLS = 4  # height-field node spacing in cells (2 m); road-level ground quads
BLOCK_CELLS = 8  # full raised ground quads are 8×8 cells (4 m)
CURB = 0.15  # m, sidewalks and lots above the road
GROUND_MARGIN = 40.0  # m of bare ground beyond the built area
BUILD_REACH = 70.0  # m, trajectory mode: buildings at most this far from a street
SIDEWALK_MIN = 2.5  # m, nothing built closer to the road than this
EGO_CLEARANCE = 1.3  # m, parked cars keep this far from the driven path's centre line
EGO_CLEARANCE_STATIC = 2.5  # m, poles, trees and walls keep this far
JUNCTION_CLEAR = 14.0  # m, no parking or centre-line dashes this close to a junction centre

# Driving (grid mode).
A_ACCEL = 1.5  # m/s², gentle urban acceleration
A_BRAKE = 2.5  # m/s²
A_LATERAL = 2.0  # m/s², comfortable cornering: v ≤ sqrt(a·R)
R_LEFT = 9.0  # m, turn radii of the lane path (left turns sweep wider)
R_RIGHT = 5.0
SPEED_CHOICES_KMH = (30.0, 40.0, 50.0)
STOP_PROB = 0.35  # chance of a full stop (sign, red light) at an intersection
DS = 0.1  # m, arc-length step of the dense drive path

# Seeds of independent random streams: the town from [seed, TOWN_STREAM], scan i from [seed, i],
# the body's sway on its suspension from [seed, SWAY_STREAM]; the world options draw from their
# own streams, so that each leaves the mapped town and every other option's draws unchanged.
TOWN_STREAM = (0x7A11, 0x70)
SWAY_STREAM = (0x7A11, 0x5A)
CHANGES_STREAM = (0x7A11, 0xC4)  # what changed since the mapping drive
TRAFFIC_STREAM = (0x7A11, 0x7F)  # the traffic
ROUTE2_STREAM = (0x7A11, 0x72)  # the second route and its speeds
SWAY2_STREAM = (0x7A11, 0x5B)  # the second route's body sway
SWAY_STD = 0.13 * math.pi / 180  # rad, pitch and roll of the body on its suspension at speed
SWAY_TIME = 0.35  # s, correlation time of the sway
SWAY_FULL_SPEED = 5.0  # m/s; the sway grows linearly up to this speed (none at a stop)

# The city: a town this large or larger (town.extent_m) is laid out in districts of their own
# style (see :mod:`.districts`); below it the town keeps its single style, bit for bit.
CITY_EXTENT = 1000.0  # m
#: Bump whenever the city's generated geometry changes: it keys the city's world and map caches.
CITY_VERSION = 1
CITY_STREAM = (0x7A11, 0xC1)  # the city's world: streets, districts, objects (not its drives)
CITY_ROUTE_STREAM = (0x7A11, 0xC2)  # route 1 through a city
TILE = 128.0  # m, the side of the squares the city's triangles are sorted into
