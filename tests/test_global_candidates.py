"""Global localization by candidates (core/maps/places.py, core/matching/candidates.py and the
scan-to-map matcher's whole-map matches, core/matching/candidate_match.py): the place index's
look-up finds the true place, the exact search and GICP verify it, two identical blocks make an
"ambiguous" answer instead of a confident one, the exact whole-map search stays as the fallback
and as a setting, and the index is cached and rebuilt when damaged."""

import dataclasses
import math

import numpy as np
import pytest
from lidarloc.core.config import Config, S2MConfig
from lidarloc.core.config.loading import apply_overrides
from lidarloc.core.errors import LidarlocError
from lidarloc.core.geometry import inv_pose, pose_matrix, pose_to_xyz_ypr, transform_points
from lidarloc.core.maps.bev import BEVPyramid
from lidarloc.core.maps.mapping import PriorMap
from lidarloc.core.maps.places import PlaceIndex, PlaceSettings, index_of_pyramid, places_for_pyramid, uses_places
from lidarloc.core.matching.candidates import Place, look_up, rerank
from lidarloc.core.matching.m3rsm import scan_cells, score_pose
from lidarloc.core.matching.s2m import ScanToMapMatcher

SENSOR_HEIGHT = 1.7
TWIN_SHIFT = 160.0  # m between the two copies of the block


def _walls(rng, n: int, lo: float, hi: float) -> np.ndarray:
    walls = []
    for _ in range(n):
        a = rng.uniform(lo, hi, 2)
        b = a + rng.uniform(-20, 20, 2)
        k = max(int(np.linalg.norm(b - a) / 0.2), 2)
        xy = a + (b - a) * np.linspace(0, 1, k)[:, None]
        for z in np.arange(0.2, rng.uniform(3, 8), 0.2):
            walls.append(np.c_[xy, np.full(k, z)])
    w = np.concatenate(walls)
    return w[(w[:, :2] >= lo - 5).all(1) & (w[:, :2] <= hi + 5).all(1)]


def _prior(walls: np.ndarray, x_extent: float) -> PriorMap:
    g = np.arange(0, x_extent, 0.4)
    gx, gy = np.meshgrid(g, np.arange(0, 140, 0.4), indexing="ij")
    ground = np.c_[gx.ravel(), gy.ravel(), np.zeros(gx.size)]
    return PriorMap(
        points=np.concatenate([ground, walls]).astype(np.float32),
        points_bev=walls.astype(np.float32),
        voxel_size=0.2,
        source="synthetic",
    )


@pytest.fixture(scope="module")
def single_matcher(twins):
    """The matcher of the single block with the default settings (its GICP target and place index
    built once for the tests that only read it)."""
    return _matcher(twins[1])


@pytest.fixture(scope="module")
def twins():
    """Two identical blocks of 40 random walls, 160 m apart on one flat ground (nothing in sight
    of one block from the other), and a third world with only the first block."""
    block = _walls(np.random.default_rng(7), 40, 10.0, 130.0)
    twin = np.concatenate([block, block + np.array([TWIN_SHIFT, 0.0, 0.0])])
    return _prior(twin, 300.0), _prior(block, 300.0)


def _scan(prior: PriorMap, T: np.ndarray, radius: float = 40.0) -> np.ndarray:
    """The map's points within ``radius`` of the pose in its sensor frame, the ground thinned to a
    quarter (a scan's ground is sparse away from the sensor, and road removal drops it anyway)."""
    pts = prior.points
    keep = (pts[:, 2] > 0.1) | (np.arange(len(pts)) % 4 == 0)
    near = pts[keep & (np.hypot(pts[:, 0] - T[0, 3], pts[:, 1] - T[1, 3]) < radius)]
    return transform_points(inv_pose(T), near).astype(np.float32)


def _matcher(prior: PriorMap, **s2m) -> ScanToMapMatcher:
    # these worlds are small enough for "auto" to search them whole: the candidates, asked for
    cfg = dataclasses.replace(S2MConfig(), **{"global_search": "candidates", **s2m})
    return ScanToMapMatcher(prior, BEVPyramid.build(prior.points_bev, cfg.match_resolution), cfg)


def _free_pose(prior: PriorMap, rng, lo: float, hi: float) -> np.ndarray:
    """A pose at least 2 m from every wall (where a vehicle could be), any yaw."""
    walls = prior.points_bev
    while True:
        x, y = rng.uniform(lo, hi, 2)
        if np.hypot(walls[:, 0] - x, walls[:, 1] - y).min() > 2.0:
            return pose_matrix(x, y, SENSOR_HEIGHT, rng.uniform(-math.pi, math.pi), 0.0, 0.0)


def test_two_identical_blocks_are_ambiguous_not_a_confident_answer(twins, single_matcher):
    """From a pose in one of two identical blocks, the whole-map match names both places and says
    "ambiguous": refused, so the filter is not moved. With one block only, the same scan is
    answered confidently at the truth."""
    twin, single = twins
    truth = pose_matrix(70.3, 64.6, SENSOR_HEIGHT, 0.9, 0.0, 0.0)
    scan = _scan(single, truth)
    out = _matcher(twin).match_global(scan)
    assert out.search == "candidates" and out.ambiguous and not out.accepted, out.reason
    assert out.reason.startswith("ambiguous: 2 places")
    places = [(out.match_pose[0, 3], out.match_pose[1, 3])] + [(a[0], a[1]) for a in out.alternatives]
    assert any(abs(x - 70.3) < 2 for x, y in places) and any(abs(x - 70.3 - TWIN_SHIFT) < 2 for x, y in places)
    alone = single_matcher.match_global(scan)
    assert alone.accepted and alone.search == "candidates" and not alone.ambiguous, alone.reason
    x, y, _, yaw, _, _ = pose_to_xyz_ypr(alone.pose)
    assert math.hypot(x - 70.3, y - 64.6) < 0.3 and abs(yaw - 0.9) < math.radians(1.0)
    # ambiguity_ratio = 1 asks for strictly equal scores to call it ambiguous: the twins are
    never = _matcher(twin, ambiguity_ratio=1.0).match_global(scan)
    assert never.ambiguous


def test_between_identical_blocks_the_estimates_own_place_is_kept(twins):
    """The second opinion from an estimate in one of two identical blocks: both places verify,
    the estimate's own is the answer (its evidence decides, as the exact search's unbeaten start
    would), the twin named beside it; from a start near neither, the answer stays "ambiguous"."""
    twin, single = twins
    truth = pose_matrix(70.3, 64.6, SENSOR_HEIGHT, 0.9, 0.0, 0.0)
    scan = _scan(single, truth)
    m = _matcher(twin, region_x=400.0, region_y=400.0)
    check = m.match_local(scan, pose_matrix(70.9, 64.1, SENSOR_HEIGHT, 0.93, 0.0, 0.0), level=True)
    assert check.accepted and not check.ambiguous and check.search == "candidates", check.reason
    x, y, *_ = pose_to_xyz_ypr(check.pose)
    assert math.hypot(x - 70.3, y - 64.6) < 0.5
    assert any(abs(a[0] - 70.3 - TWIN_SHIFT) < 2 for a in check.alternatives)
    lost = m.match_local(scan, pose_matrix(150.0, 20.0, SENSOR_HEIGHT, 0.0, 0.0, 0.0), level=True)
    assert lost.ambiguous and not lost.accepted


def test_the_candidates_find_the_true_place_from_any_yaw(twins, single_matcher):
    """Recall on the single block: 6 free poses at random yaws, every one answered by the
    candidates within 0.5 m and 1°, and the true place the look-up's first."""
    _, single = twins
    m = single_matcher
    rng = np.random.default_rng(3)
    for _ in range(6):
        truth = _free_pose(single, rng, 30.0, 110.0)
        prep = m.prepare(_scan(single, truth, radius=65.0))  # beyond the rays' 60 m, as a sensor's range
        x, y, _, yaw, _, _ = pose_to_xyz_ypr(truth)
        lu = look_up(m.place_index(), prep.points, 8)  # level already: the whole scan, as the matcher does
        assert math.hypot(lu.places[0].x - x, lu.places[0].y - y) < 3.0
        out = m.match_global(None, prepared=prep)
        assert out.accepted and out.search == "candidates", out.reason
        ox, oy, _, oyaw, _, _ = pose_to_xyz_ypr(out.pose)
        assert math.hypot(ox - x, oy - y) < 0.5
        assert abs((oyaw - yaw + math.pi) % (2 * math.pi) - math.pi) < math.radians(1.0)


def test_the_rerank_moves_a_place_metres_off_and_named_the_wrong_way_to_the_truth(twins, single_matcher):
    """A place standing for the truth 2.5 m off and named the wrong way round (a straight street
    looks much the same both ways) is moved to the truth by the BEV re-ranking and ranked first
    among places elsewhere; with only its own yaw and cell scored it would not be."""
    _, single = twins
    m = single_matcher
    truth = pose_matrix(70.3, 64.6, SENSOR_HEIGHT, 0.9, 0.0, 0.0)
    prep = m.prepare(_scan(single, truth, radius=65.0))
    x, y, _, yaw, _, _ = pose_to_xyz_ypr(truth)
    rng = np.random.default_rng(5)
    elsewhere = [Place(float(px), float(py), float(a), 1.0) for px, py, a in
                 zip(rng.uniform(20, 120, 40), rng.uniform(20, 120, 40), rng.uniform(-math.pi, math.pi, 40))]  # fmt: skip
    off = Place(x + 2.5, y - 1.5, yaw + math.pi, 1.0)
    grid = m._finest()
    ranked = rerank([*elsewhere, off], grid, prep.road_removed[:, :2], 8, m.cfg.angle_step)
    first = ranked[0]
    assert math.hypot(first.x - x, first.y - y) < 1.5
    assert abs((first.yaw - yaw + math.pi) % (2 * math.pi) - math.pi) < math.radians(5.0)
    # the place's own pose scores below the truth's: the move is what found it
    B = scan_cells(prep.road_removed[:, :2], grid[2])
    own = score_pose(m.pyramid, prep.road_removed[:, :2], off.x, off.y, off.yaw)
    assert own < score_pose(m.pyramid, prep.road_removed[:, :2], first.x, first.y, first.yaw) and len(B) > 50


def test_the_exact_search_stays_as_setting_and_fallback(twins, single_matcher):
    """``s2m.global=exact`` runs the whole-map branch and bound; an index with no place (every
    place asked for more hits than it has rays) falls back to it; both find the truth."""
    _, single = twins
    truth = pose_matrix(70.3, 64.6, SENSOR_HEIGHT, 0.9, 0.0, 0.0)
    scan = _scan(single, truth)
    cfg = apply_overrides(Config(), ["s2m.global=exact"])
    assert cfg.s2m.global_search == "exact" and Config().s2m.global_search == "auto"
    m = single_matcher
    saved = m.cfg, m.places
    try:
        m.cfg = dataclasses.replace(m.cfg, global_search="exact")
        exact = m.match_global(scan)
        m.cfg = saved[0]
        m.places = index_of_pyramid(m.pyramid, single.points, PlaceSettings(min_hits=PlaceSettings().sectors + 1))
        assert len(m.places) == 0
        fallback = m.match_global(scan)
    finally:
        m.cfg, m.places = saved
    assert exact.accepted and exact.search == "exact"
    assert fallback.accepted and fallback.search == "exact"
    assert np.allclose(fallback.pose, exact.pose)
    with pytest.raises(LidarlocError, match="global_search"):
        apply_overrides(Config(), ["s2m.global=nearest"]).validate()


def test_a_whole_map_check_from_the_truth_agrees_through_the_candidates(twins, single_matcher):
    """The second opinion while localized (a whole-map region from the estimate): no place beats
    a start at the truth, so the start itself is refined and accepted, as after the exact search."""
    _, single = twins
    truth = pose_matrix(70.3, 64.6, SENSOR_HEIGHT, 0.9, 0.0, 0.0)
    m = single_matcher
    saved, m.cfg = m.cfg, dataclasses.replace(m.cfg, region_x=400.0, region_y=400.0)
    start = pose_matrix(70.5, 64.4, SENSOR_HEIGHT, 0.91, 0.0, 0.0)
    try:
        out = m.match_local(_scan(single, truth), start, level=True)
    finally:
        m.cfg = saved
    assert out.search == "candidates" and out.accepted, out.reason
    x, y, *_ = pose_to_xyz_ypr(out.pose)
    assert math.hypot(x - 70.3, y - 64.6) < 0.3
    assert len(out.match.candidates) >= 1  # the inspection shows what was scored


def test_auto_looks_places_up_only_on_a_large_map():
    """``auto``: the exact search on a small map (cheap and certain), the candidates from 0.25 km²."""
    auto, never = S2MConfig(), S2MConfig(global_search="exact")
    assert not uses_places(auto, (400, 260)) and uses_places(auto, (1000, 1000))
    assert uses_places(S2MConfig(global_search="candidates"), (10, 10)) and not uses_places(never, (4000, 4000))


def test_the_place_index_is_cached_and_a_damaged_file_rebuilt(twins, tmp_path, caplog):
    _, single = twins
    pyr = BEVPyramid.build(single.points_bev, 1.0)
    first = places_for_pyramid(pyr, single.points, tmp_path, S2MConfig())
    [path] = list(tmp_path.glob("places-*.npz"))
    again = PlaceIndex.load(path)
    assert len(again) == len(first) > 100
    assert np.array_equal(again.profiles, first.profiles) and np.array_equal(again.xy, first.xy)
    path.write_bytes(path.read_bytes()[:100])
    with pytest.raises(LidarlocError, match="unreadable place index"):
        PlaceIndex.load(path)
    rebuilt = places_for_pyramid(pyr, single.points, tmp_path, S2MConfig())
    assert np.array_equal(rebuilt.profiles, first.profiles)
    assert "building it again" in caplog.text


def test_the_viewer_shows_an_ambiguous_answers_places_with_their_scores():
    """The overview rings every place an ambiguous whole-map answer found (none for a local
    match), and the S2M details list them with their scores."""
    from lidarloc.app.viewer.minimap import Footprint, render, verified_places
    from lidarloc.app.viewer.s2m_detail import s2m_detail_markdown
    from lidarloc.app.viewer.style import PLACE_ANSWER_COLOR, PLACE_OTHER_COLOR
    from lidarloc.core.snapshot import S2MView

    match = pose_matrix(40.0, 50.0, SENSOR_HEIGHT, 0.3, 0.0, 0.0)
    view = S2MView(
        started_at=10, landed_at=12, accepted=False, score=4434.0, start_score=math.nan, pose=match,
        scan_world=np.zeros((0, 3), np.float32), region=(36.0, 46.0, 204.0, 54.0), ms=612.0,
        reason="ambiguous: 2 places verify with scores within 3% of each other", mode="global",
        start_pose=match, match_pose=match, search="candidates", ambiguous=True,
        alternatives=np.array([[200.0, 50.0, 0.3, 4301.0]]),
    )  # fmt: skip
    places = verified_places(view)
    assert [(x, y) for x, y, _ in places] == [(40.0, 50.0), (200.0, 50.0)]
    assert all(c == PLACE_OTHER_COLOR for *_, c in places)  # ambiguous: no place is the answer
    fp = Footprint.of_points(np.array([[0.0, 0.0], [240.0, 100.0]]), (0, 0), (240, 100))
    img = render(fp, places=places)
    for x, y, _ in places:
        rows, cols, inside = fp.pixels(np.array([[x, y]]))
        ring = img[max(rows[0] - 7, 0) : rows[0] + 8, max(cols[0] - 7, 0) : cols[0] + 8]
        assert inside[0] and (ring == np.asarray(PLACE_OTHER_COLOR, np.uint8)).all(axis=2).any()
    text = s2m_detail_markdown(view)
    assert "places (ambiguous)" in text and "4434" in text and "4301 at 200.0, 50.0 m" in text
    answered = dataclasses.replace(view, accepted=True, ambiguous=False, reason="")
    assert verified_places(answered)[0][2] == PLACE_ANSWER_COLOR
    assert verified_places(dataclasses.replace(view, search="")) == []
