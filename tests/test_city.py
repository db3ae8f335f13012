"""The generated city (core/sim/town/ from town.extent_m = 1000 m): districts of their own
style, streets of several classes, drives across districts that stay on the road, scans that
lie on the survey map, every world option, one world per (seed, extent) cached, and one-line
errors for impossible extents."""

from __future__ import annotations

import numpy as np
import pytest
from lidarloc.core.config import TownConfig, load_config
from lidarloc.core.errors import DataError, LidarlocError
from lidarloc.core.sim.town import SENSOR_HEIGHT, TownSequence
from lidarloc.core.sim.town.city_layout import ARTERIAL, CLASS_SPEED_KMH, RING
from lidarloc.core.sim.town.districts import DOWNTOWN, INDUSTRIAL, PARK, STYLE_NAMES, SUBURB
from lidarloc.core.sim.town.survey import BURIED, survey_points
from lidarloc.core.sim.town.survey_sight import height
from scipy.spatial import cKDTree

EXTENT = 1200.0  # the smallest city worth testing: all five district styles already


@pytest.fixture(scope="module")
def city_cache(tmp_path_factory):
    """The city's world cache for this module (not the user's)."""
    path = tmp_path_factory.mktemp("city-cache")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("LIDARLOC_CACHE", str(path))
        yield path


@pytest.fixture(scope="module")
def city(city_cache) -> TownSequence:
    return TownSequence.from_config(TownConfig(extent_m=EXTENT, n_scans=2000), seed=0)


def _to_world(T: np.ndarray, pts: np.ndarray) -> np.ndarray:
    return pts[:, :3].astype(np.float64) @ T[:3, :3].T + T[:3, 3]


# ------------------------------------------------------------------------------ the world
def test_city_has_districts_of_their_own_style(city):
    town = city.town
    assert town.is_city and city.name == "city-seed0"
    shares = town.stats["districts"]
    assert set(shares) == set(STYLE_NAMES) and all(shares[name] > 0.005 for name in STYLE_NAMES), shares
    # the styles build differently: tall downtown, low suburbs, big industrial halls, leafy parks
    b = np.asarray(town.solids.boxes["building"], float)
    style = town.districts.style_at(b[:, 0], b[:, 1])
    height = b[:, 6] - town.ground(b[:, 0], b[:, 1])
    footprint = b[:, 3] * b[:, 4]
    assert np.median(height[style == DOWNTOWN]) > 2.5 * np.median(height[style == SUBURB])
    assert np.median(footprint[style == INDUSTRIAL]) > 5 * np.median(footprint[style == SUBURB])
    trees = np.asarray([(it.x, it.y) for it in town.solids.items if it.kind == "tree"])
    tree_style = town.districts.style_at(trees[:, 0], trees[:, 1])
    per_area = {k: np.sum(tree_style == k) / max(shares[STYLE_NAMES[k]], 1e-9) for k in (PARK, DOWNTOWN)}
    assert per_area[PARK] > 3 * per_area[DOWNTOWN]


def test_city_streets_have_classes_and_speed_limits(city):
    town = city.town
    kinds = {st.kind for st in town.streets}
    assert kinds == {"local", "arterial", "highway"}
    widths = {kind: {st.half_width for st in town.streets if st.kind == kind} for kind in kinds}
    assert min(widths["highway"]) > max(widths["arterial"]) > min(widths["local"])
    g = town.grid
    speeds = {
        k: np.unique(np.concatenate([g.h_speed[g.h_edge & (g.h_kind == k)], g.v_speed[g.v_edge & (g.v_kind == k)]]))
        for k in (RING, ARTERIAL)
    }
    assert np.allclose(speeds[RING], CLASS_SPEED_KMH[RING] / 3.6)
    assert np.allclose(speeds[ARTERIAL], CLASS_SPEED_KMH[ARTERIAL] / 3.6)
    # every junction on the network has a way on (no dead ends for a drive)
    for node in g.present():
        assert len(g.neighbours(node)) >= 2


def test_city_drive_crosses_districts_on_the_road(city):
    xy = city.poses_town[:, :2, 3]
    assert np.sum(np.linalg.norm(np.diff(xy, axis=0), axis=1)) >= 1000.0
    assert city.raster.lookup(city.road, xy[:, 0], xy[:, 1]).all()
    styles = set(city.town.districts.style_at(xy[:, 0], xy[:, 1]).tolist())
    assert len(styles) >= 2, styles
    assert city.speeds.max() <= CLASS_SPEED_KMH[RING] / 3.6 + 0.5
    # the sensor rides SENSOR_HEIGHT above the road; the city's frame is its own
    under = city.poses_town[:, :3, 3] - SENSOR_HEIGHT * city.poses_town[:, :3, 2]
    np.testing.assert_allclose(under[:, 2], city.ground(under[:, 0], under[:, 1]), atol=0.02)
    np.testing.assert_array_equal(city.poses, city.poses_town)


def test_city_scan_lies_on_the_survey_map(city):
    """A simulated scan placed by its ground-truth pose lands on the surveyed surfaces: the map
    sampled from the triangles the scan was cast into, as a survey sees them."""
    for i in (150, 1500):
        T = city.poses[i]
        x, y = T[0, 3], T[1, 3]
        points, bev = survey_points(city.town, 0.2, 0.75, region=(x - 60.0, y - 60.0, x + 60.0, y + 60.0))
        assert len(bev) < len(points)
        pts = city.scan(i)
        near = np.hypot(pts[:, 0], pts[:, 1]) < 40.0
        d, _ = cKDTree(points).query(_to_world(T, pts[near]), distance_upper_bound=2.0)
        assert np.median(d) < 0.1 and np.mean(d > 0.5) < 0.03, (i, np.median(d), np.mean(d > 0.5))
        upright = pts[near, 2] > -1.0  # walls, trees, cars … (the road removal keeps them)
        d_bev, _ = cKDTree(bev).query(_to_world(T, pts[near][upright]), distance_upper_bound=2.0)
        assert np.mean(d_bev > 0.5) < 0.05, (i, np.mean(d_bev > 0.5))
        # nothing below the ground surface, where no scanner sees (a wall's foot on a slope)
        g = city.town.plan.ground
        above = points[:, 2] - np.array([height(px, py, g.z, g.x0, g.y0, g.spacing) for px, py in points[:, :2]])
        assert above.min() >= -BURIED - 0.05, (i, above.min())


# ------------------------------------------------------------------------------ world options
def test_every_world_option_works_in_the_city(city):
    second = city.with_world(route=2)
    xy2 = second.poses_town[:, :2, 3]
    assert not np.allclose(xy2[:50], city.poses_town[:50, :2, 3])
    assert city.raster.lookup(city.road, xy2[:, 0], xy2[:, 1]).all()
    assert second.map_source is city.map_source  # one survey map for every drive
    lived_in = city.with_world(changes=0.3, traffic=True, skew=True, sensor="vlp16", mount_height=2.0)
    assert lived_in.changes_made.counts()["moved"] > 0
    assert len(lived_in.traffic_boxes(300)) > 0
    pts = lived_in.scan(300)
    assert len(pts) > 10_000 and pts.shape[1] == 4
    r = np.linalg.norm(pts[:, :3], axis=1)
    assert np.degrees(np.arcsin(pts[:, 2] / r)).max() < 15.5  # the VLP-16's rings
    np.testing.assert_allclose(
        lived_in.poses[:, :3, 3] - city.poses[:, :3, 3], (2.0 - SENSOR_HEIGHT) * city.poses[:, :3, 2], atol=1e-9
    )


def test_city_world_is_cached_and_deterministic(city, city_cache):
    again = TownSequence(seed=0, extent_m=EXTENT, n_scans=2000)
    assert again.stats["world_cached"] is True
    assert again.identity() == city.identity()
    np.testing.assert_array_equal(again.poses, city.poses)
    np.testing.assert_array_equal(again.scan(40), city.scan(40))
    shorter = TownSequence(seed=0, extent_m=EXTENT, n_scans=300)  # another drive, the same world and map
    assert shorter.map_source.identity() == city.map_source.identity()
    np.testing.assert_array_equal(shorter.poses[0], city.poses[0])
    assert shorter.stats["world_cached"] is True


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_another_seed_is_another_city(city_cache):
    other = TownSequence(seed=1, extent_m=EXTENT, n_scans=200)
    base = TownSequence(seed=0, extent_m=EXTENT, n_scans=200)
    assert other.identity() != base.identity()
    assert other.map_source.identity() != base.map_source.identity()
    assert not np.allclose(other.poses[0], base.poses[0])


# ------------------------------------------------------------------------------ bad extents
@pytest.mark.parametrize("value", ["50", "-1", "1e6", "abc", "nan", "inf"])
def test_bad_extents_are_one_line_config_errors(value):
    with pytest.raises(LidarlocError) as info:
        load_config(None, [f"town.extent_m={value}"])
    message = str(info.value)
    assert "\n" not in message and ("extent_m" in message or "not" in message), message


def test_bad_extents_are_one_line_errors_where_a_town_is_built():
    for value in (50.0, 1e6, float("nan")):
        with pytest.raises(DataError) as info:
            TownSequence(extent_m=value, n_scans=10)
        assert "\n" not in str(info.value) and "extent_m" in str(info.value)
