"""The "why" views' computations (core/filter/surface.py, core/filter/residuals.py) and their viewer side
(app/viewer/why*.py) without a browser: the likelihood surface is the filter's likelihood cell by
cell and peaks at the truth for a localized scan (town and real drive), the residuals agree with a
k-d tree's nearest-map distance, a particle's inspection, the worker thread's "newest only" rule,
and a restart that leaves nothing of the old run."""

from __future__ import annotations

import math
import threading

import numpy as np
import pytest
from helpers import make_localizer, short_town, toy_scan, wait_for
from lidarloc.core.errors import LidarlocError
from lidarloc.core.filter.likelihood import PER_POINT, log_likelihood
from lidarloc.core.filter.residuals import move_scan, scan_residuals
from lidarloc.core.filter.surface import LikelihoodModel
from lidarloc.core.geometry import pose_matrix, pose_to_xyz_ypr, transform_points

TRUTH_RADIUS_M = 1.0  # the bound: the surface's maximum within 1 m of the truth


def until_localized(loc, extra: int = 2):
    """Step until the localization rule holds, then ``extra`` scans more; the last snapshot."""
    snap = loc.snapshot()
    while not snap.localized and not loc.done:
        snap = loc.step()
    assert snap.localized, "the filter never localized"
    for _ in range(extra):
        if not loc.done:
            snap = loc.step()
    return snap


def sensor_points(snap) -> np.ndarray:
    return transform_points(np.linalg.inv(snap.mean_pose), snap.scan_world)


@pytest.fixture(scope="module")
def localized_town(cache_root):
    loc = make_localizer(short_town(40), cache_root, n_particles=1000, s2m_nice=0)  # S2M at the PF's priority
    try:
        yield loc, until_localized(loc)
    finally:
        loc.close()


# ---------------------------------------------------------------------------------- the surface
@pytest.mark.parametrize("temperature, unexplained", [(1.0, 0.0), (PER_POINT, 0.0), (10.0, 0.1)])
def test_surface_is_the_filters_likelihood_cell_by_cell(toy_world, temperature, unexplained):
    world, lut = toy_world
    state = np.array([14.3, 17.6, 1.2, 0.4, 0.01, -0.02])
    pts = toy_scan(world, state, np.random.default_rng(0), 0)
    model = LikelihoodModel(lut, 4.0, 0.5, temperature, unexplained)
    s = model.surface(pts, state, half_width=3.0, cell=0.5)
    assert s.ll.shape == (13, 13)
    X, Y = np.meshgrid(s.xs, s.ys, indexing="ij")
    states = np.column_stack([X.ravel(), Y.ravel(), np.tile(state[2:6], (X.size, 1))])
    ref = log_likelihood(states, pts, lut, 4.0, 0.5, temperature=temperature, unexplained_share=unexplained)
    np.testing.assert_allclose(s.ll.ravel(), ref, rtol=1e-9)
    assert s.ll.std() > 0  # not a flat field that agrees trivially
    assert np.linalg.norm(s.argmax_xy - state[:2]) <= 0.5  # the toy world pins the pose down


def test_best_over_yaw_is_the_best_single_yaw_surface(toy_world):
    world, lut = toy_world
    state = np.array([20.0, 12.0, 1.2, -0.3, 0.0, 0.0])
    pts = toy_scan(world, state, np.random.default_rng(1), 1)
    model = LikelihoodModel(lut, 5.0, 0.5)
    step = math.radians(2.0)
    window = model.surface(pts, state, 2.0, 0.5, yaw_window=math.radians(4.0), yaw_step=step)
    singles = []
    for d in (-2, -1, 0, 1, 2):
        c = state.copy()
        c[3] += d * step
        singles.append(model.surface(pts, c, 2.0, 0.5).ll)
    np.testing.assert_allclose(window.ll, np.max(singles, axis=0), rtol=1e-12)
    best = np.argmax(singles, axis=0)
    np.testing.assert_allclose(window.yaw, state[3] + (best - 2) * step, atol=1e-12)


@pytest.mark.parametrize(
    "kwargs, needle",
    [
        ({"center": [0, 0, 0, np.nan, 0, 0]}, "finite"),
        ({"center": [0, 0, 0]}, "6 finite"),
        ({"half_width": 2000.0}, "too large"),
        ({"cell": 0.0}, "cell must be > 0"),
        ({"yaw_window": -1.0}, "yaw window"),
    ],
)
def test_surface_refuses_bad_input_in_one_line(toy_world, kwargs, needle):
    _, lut = toy_world
    args = {"center": [10, 10, 1, 0, 0, 0], **kwargs}
    with pytest.raises(LidarlocError, match=needle):
        LikelihoodModel(lut, 5.0, 0.5).surface(np.zeros((10, 3)), **args)


@pytest.mark.slow
def test_surface_peaks_at_the_truth_on_a_localized_town_scan(localized_town):
    loc, snap = localized_town
    s = LikelihoodModel.of(loc).surface(sensor_points(snap), pose_to_xyz_ypr(snap.mean_pose))
    assert s.ll.shape == (81, 81)
    err = np.linalg.norm(s.argmax_xy - snap.gt_pose[:2, 3])
    assert err <= TRUTH_RADIUS_M, (err, snap.scan_index)
    # the maximum stands out: the grid's edge (20 m away) is far less likely (e⁵ ≈ 150× at least;
    # the default likelihood is tempered, so its log-likelihoods span nats, not hundreds)
    assert s.ll.max() - np.median(np.r_[s.ll[0], s.ll[-1], s.ll[:, 0], s.ll[:, -1]]) > 5.0


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_surface_peaks_at_the_truth_on_a_localized_real_drive_scan(kitti_raw_seq, cache_root):
    from lidarloc.core.config import Config
    from lidarloc.core.localizer import Localizer

    cfg = Config()
    cfg.s2m.replay_process_nice = 0  # the replay waits for every match: a niced S2M crawls beside busy processes
    with Localizer(kitti_raw_seq, cfg, cache_root) as loc:
        snap = until_localized(loc)
        s = LikelihoodModel.of(loc).surface(sensor_points(snap), pose_to_xyz_ypr(snap.mean_pose))
    err = np.linalg.norm(s.argmax_xy - snap.gt_pose[:2, 3])
    assert err <= TRUTH_RADIUS_M, (err, snap.scan_index)


@pytest.mark.slow
def test_bench_surface_reports_time_and_accuracy(cache_root):
    from lidarloc.app.bench.surface import TARGET_MS, run
    from lidarloc.core.config import Config
    from lidarloc.core.sequences.factory import SourceSpec

    cfg = Config()
    cfg.town.n_scans = 150  # helpers.short_town's mapping drive: its map is cached already
    result = run(SourceSpec(scans=20), cfg, scans=2, repeats=2, cache_root=cache_root)
    assert result["grid"] == "81x81" and result["scans"] == 2 and result["points_median"] > 1000
    assert 0 < result["ms_median"] <= result["ms_max"] and result["ms_median_over_yaw"] > result["ms_median"]
    assert result["met"] == (result["ms_median"] <= TARGET_MS)
    assert result["argmax_error_m_median"] <= 2.0  # centres up to 5 m and 3° off the truth


# ---------------------------------------------------------------------------------- residuals
def _tolerance(lut) -> float:
    """How far a table read may be from the true nearest distance (core/maps/lookup.py)."""
    return lut.resolution * math.sqrt(3.0) / 2.0 + lut.step / 2.0 + 1e-4


@pytest.mark.slow
@pytest.mark.parametrize("at", ["estimate", "truth"])
def test_residuals_agree_with_a_kdtree_nearest_neighbour(localized_town, at):
    from lidarloc.app.viewer.why_style import RESIDUAL_LUT, residual_colors, residual_fraction
    from scipy.spatial import cKDTree

    loc, snap = localized_town
    model = LikelihoodModel.of(loc)
    pts = snap.scan_world if at == "estimate" else move_scan(snap.scan_world, snap.mean_pose, snap.gt_pose)
    res = scan_residuals(pts, model.lookup, model.d_max)
    raw = cKDTree(loc.prior_map.points[:, :3]).query(pts.astype(np.float64))[0]
    exact = np.minimum(raw, model.d_max)
    tol = _tolerance(model.lookup)
    assert len(pts) > 1000
    assert np.max(np.abs(res.distance - exact)) <= tol
    # the colours sit where the exact distance puts them on the ramp, to within the same tolerance
    span = model.d_max - model.sigma
    ramp = residual_fraction(res.distance, model.sigma, model.d_max)
    ramp_exact = residual_fraction(exact, model.sigma, model.d_max)
    assert np.max(np.abs(ramp - ramp_exact)) <= tol / span + 1e-9
    colors = residual_colors(res.distance, model.sigma, model.d_max)
    assert (exact <= model.sigma - tol).sum() > 100
    assert (colors[exact <= model.sigma - tol] == RESIDUAL_LUT[0]).all()  # green
    beyond = res.distance >= np.float32(model.d_max)
    assert beyond.sum() > 0 and (colors[beyond] == RESIDUAL_LUT[-1]).all()  # red
    # the share beyond d_max is the k-d tree's, up to points within the tolerance of d_max
    sure_in, sure_out = raw < model.d_max - tol, raw >= model.d_max + tol
    assert sure_out.sum() > 0
    assert np.mean(sure_out) <= res.share_beyond <= 1.0 - np.mean(sure_in)
    if at == "estimate":  # the localizer's own inlier share is the complement
        assert res.share_beyond == pytest.approx(1.0 - snap.inlier_share, abs=2.0 / len(pts))


def test_move_scan_places_the_scan_at_another_pose():
    rng = np.random.default_rng(3)
    sensor = rng.normal(0, 10, (200, 3))
    A = pose_matrix(5, -3, 1.7, 0.4, 0.02, -0.01)
    B = pose_matrix(-12, 40, 2.0, -2.0, 0.0, 0.03)
    moved = move_scan(transform_points(A, sensor), A, B)
    np.testing.assert_allclose(moved, transform_points(B, sensor), atol=1e-4)
    with pytest.raises(LidarlocError):
        move_scan(np.zeros((3, 2)), A, B)


# ---------------------------------------------------------------------------------- a particle
def test_pick_particle_takes_the_one_nearest_the_ray():
    from lidarloc.app.viewer.why_particle import pick_particle

    P = np.zeros((4, 11))
    P[:, :3] = [[0, 0, 1.7], [10, 0, 1.7], [10, 3, 1.7], [50, 50, 1.7]]
    origin = np.array([10.0, 0.5, 40.0])
    assert pick_particle(P, origin, np.array([0, -0.5, -38.3])) == 1  # just beside particle 1
    with pytest.raises(LidarlocError, match="no particle near"):
        pick_particle(P, origin, np.array([0.0, 0.0, 1.0]))  # looking up at the sky


@pytest.mark.slow
def test_particle_report_ranks_by_the_filters_likelihood(localized_town):
    from dataclasses import replace

    from lidarloc.app.viewer.why_particle import particle_markdown, particle_report

    loc, snap = localized_town
    model = LikelihoodModel.of(loc)
    # after a resampling the snapshot's particles are copies of a few heavy ones: the report says so
    best = particle_report(snap, int(snap.best_index), model)
    P = np.asarray(snap.particles)
    assert best.copies == int(np.sum(np.all(P == P[snap.best_index], axis=1)))
    # spread them to rank distinct particles
    P = P.copy()
    P[:, :2] += np.random.default_rng(0).normal(0.0, 1.5, (len(P), 2))
    spread = replace(snap, particles=P)
    ll = model.log_likelihood(P, sensor_points(snap))
    top, worst = int(np.argmax(ll)), int(np.argmin(ll))
    r = particle_report(spread, top, model)
    assert r.rank == 1 and r.log_likelihood == pytest.approx(ll.max()) and r.copies == 1
    low = particle_report(spread, worst, model)
    assert low.rank == len(P) and low.log_likelihood == pytest.approx(ll.min())
    text = particle_markdown(low)
    assert f"| yaw | {math.degrees(P[worst, 3]):.3f} deg |" in text
    assert f"| x | {P[worst, 0]:.3f} m |" in text
    assert f"rank **{len(P)}**" in text
    # a georeferenced map file: positions shown in its own frame, the rest as it is
    utm = particle_markdown(particle_report(spread, worst, model, origin=(500_000.0, 4_000_000.0, 0.0)))
    assert f"| x | {P[worst, 0] + 500_000.0:.3f} m |" in utm and f"| y | {P[worst, 1] + 4_000_000.0:.3f} m |" in utm
    assert f"| yaw | {math.degrees(P[worst, 3]):.3f} deg |" in utm
    with pytest.raises(LidarlocError):
        particle_report(snap, len(P), model)


# ---------------------------------------------------------------------------------- the worker
def test_worker_keeps_only_the_newest_job_of_a_kind():
    from lidarloc.app.viewer.why_worker import LatestOnly

    worker = LatestOnly("test-why")
    release = threading.Event()
    started = threading.Event()
    done: list = []
    try:

        def slow():
            started.set()
            release.wait(10)
            return "first"

        worker.submit("surface", slow, done.append, done.append)
        wait_for(started.is_set, 10, "the first job to start")
        worker.submit("surface", lambda: "second", done.append, done.append)  # superseded while pending …
        worker.submit("surface", lambda: "third", done.append, done.append)  # … by this one
        worker.submit("particle", lambda: 1 / 0, done.append, lambda m: done.append(f"failed: {m}"))
        release.set()
        wait_for(lambda: worker.idle, 10, "the worker to finish")
        assert done == ["third", "failed: internal error: ZeroDivisionError: division by zero"]

        # cancel drops the running job's result
        release.clear()
        started.clear()
        done.clear()
        worker.submit("surface", slow, done.append, done.append)
        wait_for(started.is_set, 10, "the job to start")
        worker.cancel()
        release.set()
        wait_for(lambda: worker.idle, 10, "the worker to finish")
        assert done == []
    finally:
        release.set()
        worker.stop()


# ---------------------------------------------------------------------------------- the viewer
@pytest.mark.slow
def test_why_views_draw_and_a_restart_clears_them(street, cache_root):
    from lidarloc.app.viewer.serve import serve

    # the viewer tests' street and its map in the session's cache; S2M at the PF's priority, as
    # in the browser tests (two scans are drawn: a niced S2M starves beside busy processes)
    loc = make_localizer(street, cache_root, s2m_nice=0)
    handle = serve(loc, port=0, autoplay=False)
    try:
        v, w = handle.viewer, handle.viewer.why
        for k in (0, 1):
            v.step_once()
            wait_for(lambda: v.drawn is not None and v.drawn.scan_index == k, 60, f"scan {k} drawn")
        with pytest.raises(LidarlocError):
            w.inspect_at((0, 0, 1000), (0, 0, 1))  # nothing up there
        w.residuals.enabled.value = True
        assert "beyond d_max" in w.residuals.readout.content
        assert w.residuals.last is not None and len(w.residuals.last.distance) == len(v.drawn.scan_world)
        w.request_surface()
        wait_for(lambda: w.surface.last is not None, 60, "the surface")
        assert "maximum at" in w.surface.readout.content and w.surface.bar.visible
        w.surface.over_yaw.value = True  # recomputes the surface, best over the yaw window
        wait_for(lambda: "best of ±10° in 2° steps" in w.surface.readout.content, 60, "the best-over-yaw surface")
        assert "best yaw there:" in w.surface.readout.content and w.surface.last.yaw_window > 0
        w.inspect_best()
        assert w.residuals.at.value == "inspected particle"
        wait_for(lambda: w.particle.report is not None, 60, "the particle's report")
        assert w.particle.report.index == v.drawn.best_index
        assert "rank" in w.particle.details.content
        w.s2m_enabled.value = True
        assert w.s2m_text.visible and "S2M" in w.s2m_text.content
        nodes = [w.residuals.cloud, w.surface.image, w.surface.marks, w.particle.marker]
        assert all(n is not None for n in nodes)

        v.restart()
        assert w.surface.last is None and w.particle.report is None and w.residuals.last is None
        assert w.surface.readout.content == "" and w.particle.details.content == ""
        assert w.residuals.cloud is None and w.surface.image is None and w.particle.marker is None
        assert w.s2m.node_names == []
    finally:
        handle.stop()
        loc.close()
