"""The default town stays bit-identical: the same poses, the same triangles, the same scans and
the same prior map for ``--town-seed 0`` and the default configuration, whatever else the town
package learns (the city's districts, tiles and survey map never touch the town's path).

The expected digests were computed from the town's code before the city existed. They hold for
this environment's numpy, scipy and open3d; a library upgrade that changes the numbers shows up
here first (re-derive them only after checking that the town itself did not change)."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest
from lidarloc.core.config import Config, TownConfig
from lidarloc.core.sequences.town import TownSequence


def _digest(array) -> str:
    return hashlib.sha1(np.ascontiguousarray(array).tobytes()).hexdigest()[:16]


POSES = "6522ecc6333b5c65"
POSES_TOWN = "689643a606221d38"
TIMES = "d10e215363082fa0"
SCANS = {0: "4c26eeb93ce0a612", 1: "c521adc64821ac27", 600: "46f945511e29dbf8", 1199: "c47cda34667fa7e1"}
PARTS = {  # material: (triangles, vertices digest, triangles digest, reflectivity digest)
    "road": (23344, "6f5c2c03ac2650f6", "f65253f317cc8055", "e9b51d655b2965b2"),
    "sidewalk_lot": (97144, "fbd3d0560424c2bd", "e7a585feaaa9d6f7", "8c9033e4fc37e78f"),
    "curb": (25728, "726821b2981bbbea", "a1aef8ab9b7016c3", "9818da075427c945"),
    "building": (2400, "0c01ee3b717b47f1", "ca814bec7321ca25", "b49277b3c52d9225"),
    "roof": (240, "33e2971e11cc3286", "e94e0ab83e2f152d", "1d7dd20a185dcea4"),
    "wall": (390, "2c83389bacee64e4", "9a541de3a29c5bbb", "3bc5959c7111b67c"),
    "fence": (2650, "79c5d148b64001ef", "c5c950a8132be34a", "404a0c896b190bd2"),
    "hedge": (2788, "5ac9c5732e113e78", "c8507171e5fa207d", "23f02f5af112219c"),
    "trunk": (11682, "3591fed406249030", "e5c2322956870ec2", "2e23c8f527c2233e"),
    "crown": (89253, "4bc8a746d60f0821", "6308715575c582c3", "48ba5d4f4473d7fc"),
    "bush": (7616, "293fb1e5538de156", "f5c6a2b7509575be", "279b0f3a9cd99653"),
    "pole": (3112, "4aa1956141e5abaa", "efe6c54c23eb10c5", "7501382aabfe4e0f"),
    "sign": (20, "258b2abfc1db5cd8", "e2f66d9b0a6f013b", "ff4bfd8278168848"),
    "car": (2630, "a1df1879d3a1894c", "6313ea04e79d583a", "596a57388746d90b"),
    "glass": (2360, "efcd6a6de86ae330", "ed660e961aa97a8b", "2f505169836e8626"),
    "wheel": (10520, "5ae06062955ad60b", "7ea7ac0f4329252a", "39bc426cb71b36e6"),
    "marking": (602, "0b021316f2e900e2", "d0fe1c49b16f951d", "24445167b4615dde"),
}
COUNTS = dict(
    stops=3,
    walls=39,
    buildings=153,
    hedges=12,
    trees=531,
    poles=81,
    fences=31,
    parked_cars=263,
    bushes=141,
    triangles=282479,
    streets=11,
)
ROUTE_2_POSES = "b8afe06c47dee76c"
ROUTE_2_SCAN_5 = "db3353d3e92347b3"
LIVED_IN_SCAN_50 = "78a45b40422dbc22"  # changes 0.3, traffic, skew, VLP-16
MAP = dict(points=1521629, road_removed=491853, digest="ec2210f10b69b50e")


@pytest.fixture(scope="module")
def town() -> TownSequence:
    return TownSequence.from_config(TownConfig(), seed=0)


def test_default_town_drive_and_triangles_are_unchanged(town):
    assert _digest(town.poses) == POSES
    assert _digest(town.poses_town) == POSES_TOWN
    assert _digest(town.timestamps) == TIMES
    parts = {
        p.name: (p.n_triangles, _digest(p.vertices), _digest(p.triangles), _digest(p.reflectivity))
        for p in town.lidar.parts
    }
    assert parts == PARTS
    assert {k: town.stats[k] for k in COUNTS} == COUNTS


def test_default_town_scans_are_unchanged(town):
    assert {i: _digest(town.scan(i)) for i in SCANS} == SCANS


def test_default_town_world_options_are_unchanged(town):
    second = town.with_world(route=2)
    assert _digest(second.poses) == ROUTE_2_POSES
    assert _digest(second.scan(5)) == ROUTE_2_SCAN_5
    lived_in = town.with_world(changes=0.3, traffic=True, skew=True, sensor="vlp16")
    assert _digest(lived_in.scan(50)) == LIVED_IN_SCAN_50


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_default_town_map_is_unchanged(town, tmp_path):
    from lidarloc.core.maps.mapping import load_or_build_map

    prior = load_or_build_map(town.map_source, Config().map, tmp_path).value
    assert (len(prior.points), len(prior.points_bev)) == (MAP["points"], MAP["road_removed"])
    assert _digest(prior.points) == MAP["digest"]
