"""The generated town's world options (core/sim/town/): the prior map comes from the
mapping drive whatever is being localized; changes since mapping, traffic, other sensors and
mounting heights, and a second route change only the drive being localized."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
from lidarloc.core.config import Config
from lidarloc.core.errors import DataError
from lidarloc.core.sequences.base import DiskCachedScans, Limited
from lidarloc.core.sequences.factory import SourceSpec, open_sequence
from lidarloc.core.sim.lidar_models import SENSORS, LidarModel
from lidarloc.core.sim.town import SENSOR_HEIGHT, TownSequence
from lidarloc.core.sim.town.objects import MOVABLE_KINDS
from lidarloc.core.sim.town.traffic import CAR, LEADER, LEADER_GAP, PEDESTRIAN
from scipy.spatial import cKDTree


@pytest.fixture(scope="module")
def town(default_town) -> TownSequence:
    return default_town  # the default town: the mapping drive (made once per session)


@pytest.fixture(scope="module")
def changed(town) -> TownSequence:
    return town.with_world(changes=0.3)


@pytest.fixture(scope="module")
def busy(town) -> TownSequence:
    return town.with_world(traffic=True)


def _to_town(T: np.ndarray, pts: np.ndarray) -> np.ndarray:
    return pts[:, :3].astype(np.float64) @ T[:3, :3].T + T[:3, 3]


def _box_frame(boxes: np.ndarray, pts: np.ndarray):
    """Points (n, 3) in each box's frame: (boxes, n) along, across, and height above its base."""
    c, s = np.cos(boxes[:, 2])[:, None], np.sin(boxes[:, 2])[:, None]
    dx, dy = pts[None, :, 0] - boxes[:, 0, None], pts[None, :, 1] - boxes[:, 1, None]
    return dx * c + dy * s, -dx * s + dy * c, pts[None, :, 2] - boxes[:, 5, None]


def _in_boxes(boxes: np.ndarray, pts: np.ndarray, margin: float) -> np.ndarray:
    u, v, h = _box_frame(boxes, pts)
    inside = (
        (np.abs(u) <= boxes[:, 3, None] / 2 + margin)
        & (np.abs(v) <= boxes[:, 4, None] / 2 + margin)
        & (h >= -margin)
        & (h <= (boxes[:, 6] - boxes[:, 5])[:, None] + margin)
    )
    return inside.any(axis=0)


def _behind_boxes(boxes: np.ndarray, origin: np.ndarray, pts: np.ndarray, margin: float) -> np.ndarray:
    """Whether the segment from ``origin`` to each point passes through one of the boxes (slab
    test in each box's frame)."""
    u0, v0, h0 = (a[:, 0] for a in _box_frame(boxes, origin[None]))
    u1, v1, h1 = _box_frame(boxes, pts)
    lo = np.zeros(u1.shape)
    hi = np.ones(u1.shape)
    half = [boxes[:, 3] / 2 + margin, boxes[:, 4] / 2 + margin]
    for a0, a1, low, high in (
        (u0, u1, -half[0], half[0]),
        (v0, v1, -half[1], half[1]),
        (h0, h1, np.full(len(boxes), -margin), boxes[:, 6] - boxes[:, 5] + margin),
    ):
        d = a1 - a0[:, None]
        with np.errstate(divide="ignore", invalid="ignore"):
            t0 = (low[:, None] - a0[:, None]) / d
            t1 = (high[:, None] - a0[:, None]) / d
        parallel = np.abs(d) < 1e-12
        inside = (a0[:, None] >= low[:, None]) & (a0[:, None] <= high[:, None])
        lo = np.where(parallel, np.where(inside, lo, 2.0), np.maximum(lo, np.minimum(t0, t1)))
        hi = np.where(parallel, np.where(inside, hi, -1.0), np.minimum(hi, np.maximum(t0, t1)))
    return (lo <= hi).any(axis=0)


# ------------------------------------------------------------------------------ the map source
def test_mapping_drive_is_its_own_map_source(town):
    assert town.map_source is town
    assert town.world_options() == dict(
        changes=0.0, traffic=False, sensor="hdl64e", mount_height=SENSOR_HEIGHT, skew=False, route=1, traffic_seed=0
    )
    assert "world=" not in town.identity()


def test_map_source_is_the_town_as_mapped():
    """Whatever the world options, the map source is the same mapping drive: same identity and
    cache key as the town built without options, same streets, objects, poses and scans."""
    plain = TownSequence(seed=3, extent_m=150.0, n_scans=120)
    drive = TownSequence(
        seed=3,
        extent_m=150.0,
        n_scans=120,
        changes=0.5,
        traffic=True,
        sensor="vlp16",
        mount_height=2.1,
        skew=True,
        route=2,
    )
    mapping = drive.map_source
    assert mapping is not drive and mapping.map_source is mapping
    assert mapping.identity() == plain.identity() and mapping.cache_key() == plain.cache_key()
    assert drive.identity() != plain.identity() and drive.cache_key() != plain.cache_key()
    assert mapping.town is drive.town  # one layout, shared
    np.testing.assert_array_equal(mapping.poses, plain.poses)
    np.testing.assert_array_equal(mapping.timestamps, plain.timestamps)
    for i in (0, 77):
        np.testing.assert_array_equal(mapping.scan(i), plain.scan(i))
    # every option changes the localized drive's identity, none the map's
    for option, value in dict(
        changes=0.2, traffic=True, sensor="os1-128", mount_height=1.5, skew=True, route=2
    ).items():
        other = plain.with_world(**{option: value})
        assert other.map_source.cache_key() == plain.cache_key()
        assert other.cache_key() != plain.cache_key(), option


def test_limited_plays_inside_the_full_map():
    full = TownSequence(seed=3, extent_m=150.0, n_scans=120, sensor="vlp16")
    short = Limited(full, 40)
    assert len(short) == 40
    assert len(short.map_source) == 120 and short.map_source.cache_key() == full.map_source.cache_key()
    plain = TownSequence(seed=3, extent_m=150.0, n_scans=120)
    short_plain = Limited(plain, 40)
    assert short_plain.map_source is plain and len(short_plain.map_source) == 120
    assert short_plain.cache_key() != plain.cache_key()  # the drive is shorter, the map is not
    assert short.world_options()["sensor"] == "vlp16"  # the town's extras pass through


def test_disk_cached_scans_keep_the_map_source(tmp_path):
    plain = TownSequence(seed=3, extent_m=150.0, n_scans=40)
    cached = DiskCachedScans(Limited(plain, 10), tmp_path)
    assert cached.map_source is plain


def test_factory_passes_the_world_options():
    cfg = Config()
    cfg.town.extent_m, cfg.town.n_scans = 150.0, 40
    cfg.town.changes, cfg.town.sensor, cfg.town.route = 0.3, "vlp32c", 2
    seq = open_sequence(SourceSpec(town_seed=3, scans=12), cfg)
    assert isinstance(seq, Limited) and len(seq) == 12
    options = seq.world_options()
    assert options["changes"] == 0.3 and options["sensor"] == "vlp32c" and options["route"] == 2
    assert options["traffic"] is False and options["skew"] is False and options["mount_height"] == SENSOR_HEIGHT
    assert seq.map_source.world_options()["sensor"] == "hdl64e" and len(seq.map_source) == 40


def test_bad_world_options_are_reported():
    for options, message in (
        (dict(changes=1.5), "changes"),
        (dict(sensor="hdl32"), "sensor"),
        (dict(mount_height=9.0), "mount_height"),
        (dict(route=3), "route"),
        (dict(traffic=True, traffic_seed=-1), "traffic_seed"),
    ):
        with pytest.raises(DataError, match=message):
            TownSequence(seed=3, extent_m=150.0, n_scans=10, **options)
    with pytest.raises(DataError, match="unknown"):
        TownSequence(seed=3, extent_m=150.0, n_scans=10).with_world(rain=True)


def test_world_options_are_deterministic():
    options = dict(changes=0.4, traffic=True, sensor="vlp32c", skew=True, route=2, mount_height=1.9)
    a = TownSequence(seed=3, extent_m=150.0, n_scans=40, **options)
    b = TownSequence(seed=3, extent_m=150.0, n_scans=40, **options)
    assert a.identity() == b.identity()
    np.testing.assert_array_equal(a.poses, b.poses)
    for i in (0, 23):
        np.testing.assert_array_equal(a.scan(i), b.scan(i))
    copy = pickle.loads(pickle.dumps(a))
    np.testing.assert_array_equal(copy.scan(23), a.scan(23))


# ------------------------------------------------------------------------------ changes
def test_changes_change_a_share_of_the_movable_objects(town, changed):
    record = changed.changes_made
    n_movable = sum(1 for it in town.town.solids.items if it.kind in MOVABLE_KINDS)
    n_trees = sum(1 for it in town.town.solids.items if it.kind == "tree")
    assert record.n_movable == n_movable > 100 and record.n_trees == n_trees > 100
    n_changed = len(record.moved) + len(record.removed) + len(record.added)
    assert n_changed == round(0.3 * n_movable)
    for kind in (record.moved, record.removed, record.added):  # about a third each
        assert 0.2 * n_changed <= len(kind) <= 0.45 * n_changed
    assert len(record.cut) + len(record.grown) == round(0.3 * n_trees)
    assert abs(len(record.cut) - len(record.grown)) <= 1
    assert {it.kind for it in record.added} <= {"parked_car", "bin", "sign"}
    assert len({it.kind for it in record.added}) >= 2

    # The scans see it: straight down from 20 m above each removed car (through the foliage)
    # there is a car roof in the mapped world and none in the changed one; the other way round
    # for each added car.
    from lidarloc.core.o3d import open3d
    from lidarloc.core.sim.lidar_sim import raycasting_scene

    def roof_height(parts, items):
        scene = raycasting_scene([p for p in parts if p.name != "crown"], commit=False)  # (crowns overhang cars)
        xy = np.array([[it.x, it.y] for it in items])
        ground = town.ground(xy[:, 0], xy[:, 1])
        rays = np.zeros((len(xy), 6), np.float32)
        rays[:, :2], rays[:, 2], rays[:, 5] = xy, ground + 20.0, -1.0
        t = scene.cast_rays(open3d().core.Tensor(rays))["t_hit"].numpy()
        return 20.0 - t  # height of the first hit above the ground

    removed_cars = [it for it in record.removed if it.kind == "parked_car"]
    added_cars = [it for it in record.added if it.kind == "parked_car"]
    assert removed_cars and added_cars

    def car_roof(h):
        return (h > 0.8) & (h < 2.6)

    assert np.all(car_roof(roof_height(town.lidar.parts, removed_cars)))
    assert not np.any(car_roof(roof_height(changed.lidar.parts, removed_cars)))
    assert np.all(car_roof(roof_height(changed.lidar.parts, added_cars)))
    assert not np.any(car_roof(roof_height(town.lidar.parts, added_cars)))
    # The mapping drive's world is untouched.
    assert changed.map_source.lidar.parts is town.lidar.parts


def test_no_changes_is_the_mapped_world(town):
    same = town.with_world(changes=0.0, sensor="vlp16")
    assert same.changes_made is None
    assert [p.triangles for p in same.lidar.parts] == [p.triangles for p in town.lidar.parts]
    plain_world = town.with_world(changes=0.0)
    assert plain_world.map_source is plain_world
    np.testing.assert_array_equal(plain_world.scan(57), town.scan(57))


def test_changed_scans_differ_from_the_mapped_ones_only_near_changes(town, changed):
    """Scanned noise-free from the same poses, the mapped and the changed world differ only in
    rays that pass a changed object (on it, or behind it: uncovered or hidden)."""
    record = changed.changes_made
    sites = np.array(
        [
            (it.x, it.y, 6.0 if it.kind == "tree" else 3.5)  # (a grown crown is up to 5.6 m wide)
            for it in record.moved + record.moved_to + record.removed + record.added + record.cut + record.grown
        ]
    )
    exact = LidarModel(range_sigma=0.0, dropout=0.0, weak_dropout=0.0, intensity_noise=0.0)
    mapped, now = town.lidar.with_model(exact), changed.lidar.with_model(exact)
    differing = 0
    for i in (100, 500, 900):
        T = town.poses_town[i]
        a = mapped.scan(T, np.random.default_rng(i))
        b = now.scan(T, np.random.default_rng(i))
        A, B = {tuple(p) for p in a[:, :3].tolist()}, {tuple(p) for p in b[:, :3].tolist()}
        diff = np.array([p for p in A ^ B]).reshape(-1, 3)
        differing += len(diff)
        if not len(diff):
            continue
        pts = _to_town(T, diff)
        # the ray from the sensor to each differing point passes within a site's radius
        o, q = T[:2, 3], pts[:, :2]
        seg = q - o
        f = np.clip(((sites[None, :, :2] - o) * seg[:, None]).sum(-1) / (seg * seg).sum(-1)[:, None], 0.0, 1.0)
        d = np.linalg.norm(o + f[..., None] * seg[:, None] - sites[None, :, :2], axis=-1)  # (n, sites)
        assert (d <= sites[None, :, 2]).any(axis=1).all(), f"scan {i}"
    assert differing > 100


# ------------------------------------------------------------------------------ traffic
def test_traffic_is_in_the_scans_and_nowhere_else(town, busy):
    assert busy.map_source is town and town.traffic is None
    seen = 0
    for i in (0, 200, 400, 640, 900, 1100):
        a, b = town.scan(i), busy.scan(i)
        boxes = busy.traffic_boxes(i)
        A = {tuple(p) for p in a[:, :3].tolist()}
        B = {tuple(p) for p in b[:, :3].tolist()}
        new = np.array([p for p in B - A]).reshape(-1, 3)
        gone = np.array([p for p in A - B]).reshape(-1, 3)
        if not len(boxes):
            assert not len(new) and not len(gone)
            continue
        T = busy.poses_town[i]
        # every point only the busy scan has is on a car, cyclist or pedestrian …
        if len(new):
            assert _in_boxes(boxes, _to_town(T, new), margin=0.12).all(), f"scan {i}"
            seen += len(new)
        # … and every point it lost is behind one
        if len(gone):
            sample = gone[:: max(1, len(gone) // 300)]
            assert _behind_boxes(boxes, T[:3, 3], _to_town(T, sample), margin=0.12).all(), f"scan {i}"
        np.testing.assert_array_equal(busy.scan(i), b)  # deterministic
    assert seen > 1000
    # the map source's scans are the plain ones (no traffic in the map)
    np.testing.assert_array_equal(busy.map_source.scan(400), town.scan(400))


def test_another_days_traffic_is_other_cars_on_the_same_streets(town, busy):
    """``town.traffic_seed``: another number draws other traffic (the drives of a corpus meet
    other cars), the same number the same; 0 is the town's own, named as it always was (the
    caches of its scans stay); a traffic seed without traffic is the drive without."""
    other = town.with_world(traffic=True, traffic_seed=2)
    again = town.with_world(traffic=True, traffic_seed=2)
    mine, theirs = busy.traffic.agents_at(20.0)["xy"], other.traffic.agents_at(20.0)["xy"]
    assert len(mine) and len(theirs)
    assert len(mine) != len(theirs) or not np.allclose(mine, theirs)
    np.testing.assert_array_equal(theirs, again.traffic.agents_at(20.0)["xy"])
    assert other.identity() != busy.identity() and "traffic_seed" not in busy.identity()
    np.testing.assert_array_equal(other.poses, busy.poses)  # the same drive, other traffic
    quiet = town.with_world(traffic_seed=2)
    assert quiet.is_mapping_drive and quiet.world_options()["traffic_seed"] == 0


def test_traffic_moves_on_plausible_paths(busy):
    traffic = busy.traffic
    t_cars, t_walk = [], []
    for t in np.arange(0.0, 110.0, 10.0):
        a = traffic.agents_at(float(t))
        on_road = busy.raster.lookup(busy.road, a["xy"][:, 0], a["xy"][:, 1]).astype(bool)
        t_cars.append(on_road[a["kind"] == CAR])
        t_walk.append(on_road[a["kind"] == PEDESTRIAN])
    cars, walkers = np.concatenate(t_cars), np.concatenate(t_walk)
    assert len(cars) > 50 and cars.all()  # cars drive on the road
    assert len(walkers) > 50 and np.mean(~walkers) > 0.8  # pedestrians walk on the sidewalks (and cross)
    # they move: a car is somewhere else a second later
    a0, a1 = traffic.agents_at(30.0), traffic.agents_at(31.0)
    common, i0, i1 = np.intersect1d(a0["index"], a1["index"], return_indices=True)
    cars = (a0["kind"][i0] == CAR) & (common >= 0)
    step = np.linalg.norm(a1["xy"][i1] - a0["xy"][i0], axis=1)[cars]
    assert np.all((step > 7.0) & (step < 14.0))  # 8–13 m/s


def test_a_car_drives_ahead_now_and_then(busy):
    traffic = busy.traffic
    assert traffic.leader_windows
    ahead = 0
    for i in range(0, len(busy), 5):
        t = float(busy.timestamps[i])
        a = traffic.agents_at(t)
        lead = a["kind"] == LEADER
        if not lead.any():
            continue
        ahead += 1
        T = busy.poses_town[i]
        rel = np.linalg.inv(T)[:3, :3] @ np.append(a["xy"][lead][0] - T[:2, 3], 0.0)
        # LEADER_GAP along the path: a little less straight across when the path turns
        assert np.hypot(rel[0], rel[1]) >= 0.85 * LEADER_GAP
        # in front of the car (it may be round a corner): ahead of it rather than behind
        assert rel[0] > 0.0
    assert ahead >= 10


def test_traffic_never_engulfs_the_sensor(busy):
    for i in range(0, len(busy), 50):
        pts = busy.scan(i)
        assert np.linalg.norm(pts[:, :3], axis=1).min() > 1.0


# ------------------------------------------------------------------------------ sensors
@pytest.mark.parametrize("name", ["vlp16", "vlp32c", "os1-128"])
def test_sensor_rings_are_the_datasheets(town, name):
    model = SENSORS[name]
    seq = town.with_world(sensor=name)
    pts = seq.scan(333)
    r_xy = np.hypot(pts[:, 0], pts[:, 1]).astype(np.float64)
    elevation = np.degrees(np.arctan2(pts[:, 2].astype(np.float64), r_xy))
    rings = np.sort(np.asarray(model.elevations_deg))
    nearest = rings[np.argmin(np.abs(elevation[:, None] - rings[None]), axis=1)]
    # range noise moves a point along its ray: its elevation is the ring's (float32 rounding)
    assert np.abs(elevation - nearest).max() < 0.01
    counts = np.array([(nearest == e).sum() for e in rings])
    assert len(rings) == model.n_beams and (counts > 0).mean() > 0.9  # (a ring may see only sky)
    assert np.linalg.norm(pts[:, :3], axis=1).max() <= model.max_range
    assert seq.map_source is town


def test_vlp16_rings_every_two_degrees():
    assert SENSORS["vlp16"].elevations_deg == tuple(float(e) for e in range(-15, 16, 2))
    assert len(SENSORS["vlp32c"].elevations_deg) == 32 and min(SENSORS["vlp32c"].elevations_deg) == -25.0
    assert max(SENSORS["vlp32c"].elevations_deg) == 15.0
    os1 = np.asarray(SENSORS["os1-128"].elevations_deg)
    assert len(os1) == 128 and os1.min() == -22.5 and os1.max() == 22.5
    assert repr(SENSORS["hdl64e"]).startswith("LidarModel(n_azimuth=2000") and "elevations" not in repr(
        SENSORS["hdl64e"]
    )


@pytest.mark.parametrize("name", ["vlp16", "vlp32c", "os1-128"])
def test_every_sensor_scan_lies_on_the_mapped_surfaces_at_its_ground_truth_pose(town, name):
    """Another sensor's scan, placed by the drive's ground-truth pose, lands on the surfaces the
    mapping HDL-64E scanned from the same poses: no offset between the simulated sensor and the
    pose the error is measured against (in height above all, which the ground pins down)."""
    seq = town.with_world(sensor=name)
    for i in (120, 333):
        np.testing.assert_array_equal(seq.poses[i], town.poses[i])
        mapped = np.concatenate([_to_town(town.poses_town[k], town.scan(k)) for k in (i - 1, i, i + 1)])
        pts = seq.scan(i)
        r_xy = np.hypot(pts[:, 0], pts[:, 1])
        elevation = np.degrees(np.arctan2(pts[:, 2], r_xy))
        # where the HDL-64E looks too (it sees nothing above +2°), and near enough to be dense
        common = (elevation <= 1.5) & (r_xy > 3.0) & (r_xy < 30.0)
        world = _to_town(seq.poses_town[i], pts[common])
        d, j = cKDTree(mapped).query(world, distance_upper_bound=1.0)
        assert np.median(d) < 0.05 and np.mean(d > 0.5) < 0.02, (name, i, np.median(d), np.mean(d > 0.5))
        # walls, cars and poles (above the road) pin the horizontal position: 0.04–0.07 m at the
        # 90th percentile, ~0.3 m were the sensor 0.3 m off its pose
        upright = pts[common, 2] > -1.0
        assert upright.sum() > 1000 and np.percentile(d[upright], 90) < 0.1, (name, i, np.percentile(d[upright], 90))
        # the road and the sidewalks (returns from below the sensor) pin the height: same within 2 cm
        low = (pts[common, 2] < -1.0) & (d < 0.3)
        dz = world[low, 2] - mapped[j[low], 2]
        assert low.sum() > 500 and abs(np.median(dz)) < 0.02, (name, i, low.sum(), np.median(dz))


def test_mount_height(town):
    high = town.with_world(mount_height=2.3)
    lift = high.poses_town[:, :3, 3] - town.poses_town[:, :3, 3]
    np.testing.assert_allclose(lift, (2.3 - SENSOR_HEIGHT) * town.poses_town[:, :3, 2], atol=1e-9)
    np.testing.assert_allclose(high.poses[0, :3, 3], [0.0, 0.0, 2.3 - SENSOR_HEIGHT], atol=1e-6)
    pts = high.scan(333)
    r = np.linalg.norm(pts[:, :3], axis=1)
    elevation = np.degrees(np.arcsin(pts[:, 2] / r))
    assert abs(np.median(pts[elevation < -22.0, 2]) + 2.3) < 0.1  # the road is 2.3 m below


# ------------------------------------------------------------------------------ route 2
def test_second_route_drives_the_mapped_streets(town):
    second = town.with_world(route=2)
    assert second.map_source is town and len(second) == len(town)
    xy2, xy1 = second.poses_town[:, :2, 3], town.poses_town[:, :2, 3]
    assert np.linalg.norm(xy2[0] - xy1[0]) > 30.0  # another start
    assert not np.allclose(second.poses, town.poses)
    assert town.raster.lookup(town.road, xy2[:, 0], xy2[:, 1]).all()  # on the road
    d, _ = cKDTree(xy1).query(xy2)
    assert np.mean(d < 8.0) > 0.95  # on route 1's streets
    # it is a drive of its own: other speeds and stops, the same world frame as the map
    assert np.abs(second.speeds - town.speeds).max() > 1.0
    np.testing.assert_allclose(second.poses, town.town_to_world[None] @ second.poses_town, atol=1e-9)


def test_second_route_along_a_kitti_trajectory(shared_data):
    root = shared_data / "kitti_odometry_poses"
    poses_file, calib_file = root / "poses" / "07.txt", root / "calib" / "07.txt"
    if not poses_file.is_file() or not calib_file.is_file():
        pytest.skip(f"KITTI odometry poses 07 not found under {root}")
    first = TownSequence(seed=1, trajectory=poses_file, calib=calib_file)
    second = first.with_world(route=2)
    assert second.map_source is first and len(second) == len(first)
    xy2, xy1 = second.poses_town[:, :2, 3], first.poses_town[:, :2, 3]
    assert first.raster.lookup(first.road, xy2[:, 0], xy2[:, 1]).all()
    # the road driven the other way, in the other lane
    d = np.linalg.norm(xy2 - xy1[::-1], axis=1)
    assert np.median(d) == pytest.approx(3.5, abs=0.05)
    yaw1 = np.arctan2(first.poses_town[::-1, 1, 0], first.poses_town[::-1, 0, 0])
    yaw2 = np.arctan2(second.poses_town[:, 1, 0], second.poses_town[:, 0, 0])
    assert np.median(np.cos(yaw2 - yaw1)) < -0.99
