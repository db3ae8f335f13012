"""The viewer on a map too big to send whole (a city): the tiles at full density follow the
estimate with hysteresis, the points sent stay within the budget, and the panel's overview draws
the particles, the estimate and the truth where they are."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from helpers import wait_for
from lidarloc.app.viewer.map_tiles import TileGrid, TileSettings, candidates, fit
from lidarloc.app.viewer.minimap import BACKGROUND, Footprint, Overview, render
from lidarloc.app.viewer.style import DISPLAY_BUDGET, EST_COLOR, GT_COLOR, PARTICLE_HIGH, TILE_COLOR


# ------------------------------------------------------------------------------ which tiles
def test_tiles_near_the_pose_are_chosen_and_stay_until_clearly_left():
    g = TileGrid.covering((0.0, 0.0), (399.0, 99.0), 100.0)  # 4 × 1 tiles of 100 m
    assert (g.nx, g.ny) == (4, 1) and g.tiles_of(np.array([[150.0, 50.0], [-5.0, 500.0]])).tolist() == [1, 0]
    near = dict(radius=20.0, hysteresis=30.0)
    assert candidates(g, 50.0, 50.0, (), **near) == [0]  # tile 1 is 50 m away
    at_90 = candidates(g, 90.0, 50.0, (), **near)
    assert at_90 == [0, 1]  # nearest first: tile 1 is 10 m away
    # back to x = 70: tile 1 is 30 m away, beyond the radius, but shown: it stays …
    assert candidates(g, 70.0, 50.0, at_90, **near) == [0, 1]
    assert candidates(g, 70.0, 50.0, (), **near) == [0]  # … where a tile not shown is not added
    # … until it is farther than radius + hysteresis
    assert candidates(g, 45.0, 50.0, at_90, **near) == [0]
    # on the far side, tile 0 is the one kept by hysteresis
    assert candidates(g, 130.0, 50.0, [0, 1], **near) == [1, 0]
    assert candidates(g, 151.0, 50.0, [0, 1], **near) == [1]


def test_fit_takes_the_nearest_tiles_while_they_fit():
    assert fit([3, 1, 2], {1: 5, 2: 5, 3: 5}, 12) == ([3, 1], None)
    assert fit([3, 1, 2], {1: 5, 2: 5, 3: 5}, 15) == ([3, 1, 2], None)
    # a tile that does not fit ends the choice: a farther small one is not taken in its place
    assert fit([3, 1, 2], {3: 5, 1: 50, 2: 1}, 12) == ([3], None)
    assert fit([3, 1, 2], {3: 5}, 12) == ([3], 1)  # tile 1 must be read first


# ------------------------------------------------------------------------------ the budget
def _city_map(seed: int = 0) -> np.ndarray:
    """4 × 4 km: 0.6 M points scattered over the whole city, a downtown of 600 × 600 m (tiles
    9–11 of 200 m in x and y) holding a point in every 0.5 m voxel of three layers, and a
    suburb tile (0, 0) with a point in every 0.5 m voxel of the ground."""
    rng = np.random.default_rng(seed)
    spread = np.c_[rng.uniform(0, 4000, (600_000, 2)), rng.uniform(0, 10, 600_000)]
    a = np.arange(1800.25, 2400.0, 0.5)
    x, y, z = np.meshgrid(a, a, [0.25, 2.25, 4.25], indexing="ij")
    downtown = np.c_[x.ravel(), y.ravel(), z.ravel()]
    b = np.arange(0.25, 200.0, 0.5)
    x, y = np.meshgrid(b, b, indexing="ij")
    suburb = np.c_[x.ravel(), y.ravel(), np.zeros(x.size)]
    return np.concatenate([spread, downtown, suburb]).astype(np.float32)


def _full_density(points: np.ndarray, rect, voxel: float = 0.5) -> int:
    x0, y0, x1, y1 = rect
    inside = points[(points[:, 0] >= x0) & (points[:, 0] < x1) & (points[:, 1] >= y0) & (points[:, 1] < y1)]
    return len(np.unique(np.floor(inside / voxel).astype(np.int64), axis=0))


@pytest.fixture(scope="module")
def server():
    import viser

    s = viser.ViserServer(port=0, verbose=False)
    yield s
    s.stop()


def test_a_city_sized_map_stays_within_the_budget(server):
    from lidarloc.app.viewer.scene import SceneView

    pts = _city_map()
    bev = pts[pts[:, 2] == 4.25]  # the roofs downtown
    scene = SceneView(server.scene)
    scene.set_map(SimpleNamespace(points=pts, points_bev=bev, voxel_size=0.2))
    assert scene.tiled  # at full density it would be ~5.8 M points: sent in tiles
    coarse = scene._coarse_nodes
    assert sum(len(n.points) for n in coarse.values()) <= 500_000
    vehicle = np.eye(4)
    vehicle[:3, 3] = (2100.0, 2100.0, 1.0)  # in downtown tile (10, 10)
    scene.follow_map(vehicle, now=0.0)
    scene.wait_map_tiles(60)
    scene.follow_map(vehicle, now=10.0)
    near = scene.near_tiles
    sent = (
        sum(len(n.points) for n in coarse.values())
        + sum(len(scene.near_tile_node(r).points) for r in near)
        + len(scene.node("map_bev").points)
    )
    assert sent == scene.map_points_sent <= DISPLAY_BUDGET
    # the vehicle's tile and the nearest beside it at full density, as many as the budget takes:
    # a downtown tile holds 480 000 points at 0.5 m, and 20 tiles lie within the radius
    assert (2000.0, 2000.0, 2200.0, 2200.0) in near and len(near) in (2, 3)
    for rect in near:
        node = scene.near_tile_node(rect)
        assert node.precision == "float32" and len(node.points) == _full_density(pts, rect)
        assert node.points.dtype == np.float32
        i, j = int(rect[0] // 200), int(rect[1] // 200)
        assert not coarse[i * 20 + j].visible  # its coarse points give way
    # far tiles are coarse only
    far = coarse[0]
    assert far.visible and far.point_size > 2 * 0.5 * 0.8
    assert len(far.points) < _full_density(pts, (0.0, 0.0, 200.0, 200.0)) / 4
    # the vehicle leaves downtown: its tiles go, the coarse points come back
    vehicle[:3, 3] = (500.0, 500.0, 1.0)
    scene.follow_map(vehicle, now=20.0)
    scene.wait_map_tiles(60)
    scene.follow_map(vehicle, now=30.0)
    assert (400.0, 400.0, 600.0, 600.0) in scene.near_tiles
    assert all(r[0] < 1000 for r in scene.near_tiles)
    assert coarse[10 * 20 + 10].visible
    assert scene.map_points_sent <= DISPLAY_BUDGET


def test_the_whole_city_stays_within_the_browsers_view_distance(server):
    from lidarloc.app.viewer.camera import TabCameras

    scene = SimpleNamespace(map_center=np.array([2000.0, 2000.0, 0.0]), map_extent=4000.0)
    cameras = TabCameras(server, scene, lambda: None, lambda action, needs_localizer=True: None, 0.0)
    cameras.overview()
    distance = np.linalg.norm(np.asarray(server.initial_camera.position) - scene.map_center)
    assert server.initial_camera.far > distance + 0.71 * 4000  # the farthest corner
    scene.map_extent = 400.0  # the town: the browser's own view distance
    cameras.overview()
    assert server.initial_camera.far == 1000.0 and server.initial_camera.near == 0.01


# ------------------------------------------------------------------------------ the overview
def test_overview_draws_the_particles_estimate_truth_and_tiles_where_they_are():
    rng = np.random.default_rng(1)
    # map points in the west half of a 100 × 100 m map only
    pts = np.c_[rng.uniform(0, 50, (20_000, 2)), np.zeros(20_000)]
    fp = Footprint.of_points(pts, (0.0, 0.0, 0.0), (100.0, 100.0, 0.0), size=200)

    def px(x, y):
        r, c, inside = fp.pixels(np.array([[x, y]]))
        assert inside[0]
        return int(r[0]), int(c[0])

    img = render(
        fp,
        particles_xy=np.array([[80.0, 20.0], [85.0, 20.0]]),
        estimate_xy=(25.0, 75.0),
        truth_xy=(70.0, 70.0),
        tiles=[(50.0, 50.0, 100.0, 100.0)],
    )
    assert img.shape == (200, 200, 3) and img.dtype == np.uint8
    grey = img[px(20.0, 20.0)]
    assert grey[0] == grey[1] == grey[2] and tuple(grey) != BACKGROUND  # map: grey
    assert tuple(img[px(90.0, 40.0)]) == BACKGROUND  # no map there
    for x in (80.0, 85.0):
        assert tuple(img[px(x, 20.0)]) == tuple(PARTICLE_HIGH.astype(int))
    assert tuple(img[px(82.5, 20.0)]) == BACKGROUND  # between the two dots
    assert tuple(img[px(25.0, 75.0)]) == EST_COLOR
    r, c = px(70.0, 70.0)
    assert tuple(img[r, c + 5]) == GT_COLOR and tuple(img[r, c]) == BACKGROUND  # a hollow square
    r, c = px(50.0, 60.0)
    assert tuple(img[r, c]) == TILE_COLOR  # the tile's west edge
    # north up: y grows towards row 0
    assert px(25.0, 75.0)[0] < px(20.0, 20.0)[0]


def test_overview_redraws_at_most_once_a_second_and_only_on_change():
    handle = SimpleNamespace(image=None, visible=False)
    ov = Overview(handle, interval=1.0)
    assert not ov.update(None, (), 0.0)  # no map yet
    fp = Footprint.of_points(np.zeros((1, 3)), (0.0, 0.0), (50.0, 50.0), size=64)
    ov.set_map(fp)
    T = np.eye(4)
    a = SimpleNamespace(particles=np.zeros((5, 11)), mean_pose=T, gt_pose=None)
    b = SimpleNamespace(particles=np.full((5, 11), 30.0), mean_pose=T, gt_pose=T)
    assert ov.update(a, (), 0.0) and handle.visible and handle.image.shape == (64, 64, 3)
    assert not ov.update(b, (), 0.5)  # another snapshot, but drawn less than a second ago
    assert ov.update(b, (), 1.0)
    assert not ov.update(b, (), 5.0)  # nothing changed
    tile = ((0.0, 0.0, 10.0, 10.0),)
    assert ov.update(b, tile, 5.2)  # the tiles at full density changed
    assert not ov.update(a, tile, 5.7)
    assert ov.update(a, tile, 6.2) and ov.renders == 4


# ------------------------------------------------------------------------------ in the viewer
def test_a_town_sized_map_is_one_node_and_the_overview_shows_it(viewer):
    v = viewer.viewer
    assert not v.scene.tiled and v.scene.near_tiles == ()
    cloud = v.scene.node("map")
    assert cloud.precision == "float32" and len(cloud.points) == v.scene.map_points_sent - len(
        v.scene.node("map_bev").points
    )
    v.update_display()
    assert v.controls.overview.visible and v.controls.overview.image.shape[:2] == (256, 256)


def test_moving_the_vehicle_swaps_the_tiles_at_full_density(viewer):
    v, loc = viewer.viewer, viewer.localizer
    c = v.controls
    # the street as if it were a city: 5 m tiles, full density within 1 m of the estimate
    settings = TileSettings(
        tile_m=5.0,
        budget=40_000,
        coarse_max=3_000,
        road_removed_max=3_000,
        radius_m=1.0,
        hysteresis_m=1.0,
        interval_s=0.0,
    )
    v.scene.set_map(loc.prior_map, max_points=5_000, tiles=settings)
    assert v.scene.tiled

    def settle():
        # each display update swaps in the tiles read for an earlier pose and asks for the
        # current one's: twice round, the tiles shown are the current pose's (a read asked for
        # during the steps may still be in flight at the first round)
        for _ in range(2):
            v.update_display()
            v.scene.wait_map_tiles(30)
        v.update_display()
        x, y = np.asarray(v.drawn.mean_pose)[:2, 3]
        return float(x), float(y), v.scene.near_tiles

    c.step.value = True
    wait_for(lambda: v.player.idle and loc.k == 1, what="one step")
    v.reset(pose=np.asarray(loc.seq.pose(loc.k), float))  # the particles round the vehicle
    x1, y1, first = settle()
    assert first and any(r[0] <= x1 < r[2] and r[1] <= y1 < r[3] for r in first)  # the estimate's tile
    old = {r: v.scene.near_tile_node(r) for r in first}
    for _ in range(9):
        c.step.value = True
    wait_for(lambda: v.player.idle and loc.k == 10, what="9 more steps")
    x2, y2, second = settle()
    assert x2 - x1 > 5.0  # the vehicle drove on
    assert any(r[0] <= x2 < r[2] and r[1] <= y2 < r[3] for r in second)
    left = [r for r in first if r not in second]
    assert left and all(r[2] <= x2 - 2.0 for r in left)  # behind by more than radius + hysteresis
    assert all(old[r]._impl.removed for r in left)  # their nodes are gone from the scene
    assert all(v.scene.near_tile_node(r) is not None for r in second)
    assert v.scene.map_points_sent <= settings.budget


def test_a_map_on_disk_is_tiled_for_display_as_one_in_memory(tmp_path):
    """A city map kept on disk (memory-mapped) is read through mappings of the display's own:
    the same coarse layer and the same tiles as from the map in memory."""
    from lidarloc.app.viewer.map_tiles import TiledMap

    pts = _city_map(1)
    np.save(tmp_path / "map_points.npy", pts)
    on_disk = np.load(tmp_path / "map_points.npy", mmap_mode="r")
    a = TiledMap(pts, 0.2, 0.5, TileSettings())
    b = TiledMap(on_disk, 0.2, 0.5, TileSettings())
    assert np.array_equal(a.coarse, b.coarse) and np.array_equal(a.counts, b.counts)
    downtown = int(a.grid.tiles_of(np.array([[2000.0, 2000.0]]))[0])
    assert np.array_equal(a.load(downtown), b.load(downtown)) and len(a.load(downtown)) > 10_000
    assert b.points is on_disk  # the map's own array is kept, not a copy
