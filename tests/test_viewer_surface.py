"""The likelihood surface in the viewer: computed on one thread (the same values as on two), drawn
above the map's road with its marks above the vehicles, and a result superseded by the next
scan's request still shown rather than dropped."""

from __future__ import annotations

import threading

import numpy as np
from helpers import wait_for


def test_one_thread_gives_the_same_surface(toy_world):
    from lidarloc.core.filter.surface import LikelihoodModel

    pts, table = toy_world
    model = LikelihoodModel(table, 5.0, 0.5)
    rng = np.random.default_rng(3)
    scan = pts[rng.choice(len(pts), 3000, replace=False)] - np.array([20.0, 20.0, 1.7], np.float32)
    center = (20.0, 20.0, 1.7, 0.0, 0.0, 0.0)
    two = model.surface(scan, center, 5.0, 0.5, 0.1, 0.05)
    one = model.surface(scan, center, 5.0, 0.5, 0.1, 0.05, parallel=False)
    np.testing.assert_array_equal(one.ll, two.ll)
    np.testing.assert_array_equal(one.yaw, two.yaw)


def test_surface_is_drawn_above_the_road_and_its_marks_above_the_vehicles(viewer):
    v, loc = viewer.viewer, viewer.localizer
    for _ in range(3):
        v.controls.step.value = True
    wait_for(lambda: v.player.idle and loc.k == 3, what="3 steps")
    v.update_display()
    v.why.request_surface()
    wait_for(lambda: v.why.surface.last is not None, what="the surface")
    surface, snap = v.why.surface.last, v.why.surface.last_snapshot
    image_z = float(v.why.surface.image.position[2])
    # the map's road under the grid: its points' squares reach half a point size above them
    cloud = v.scene.node("map")
    p = np.asarray(cloud.points)
    x0, y0, x1, y1 = surface.extent
    under = p[(p[:, 0] > x0) & (p[:, 0] < x1) & (p[:, 1] > y0) & (p[:, 1] < y1)]
    road = float(np.median(under[under[:, 2] < np.percentile(under[:, 2], 30), 2]))
    assert image_z > road + cloud.point_size / 2, (image_z, road)
    # the marks (estimate, truth, maximum) above the vehicles' outlines, large enough to see round them
    marks = np.asarray(v.why.surface.marks.points).reshape(-1, 3)
    vehicle_z = max(float(np.asarray(v.scene.node(n).points)[..., 2].max()) for n in ("est_vehicle", "gt_vehicle"))
    assert marks[:, 2].min() > vehicle_z
    est = np.asarray(snap.mean_pose)[:2, 3]
    assert np.abs(marks[:, :2] - est).max() >= 1.5


def test_a_superseded_result_is_still_delivered_unless_cancelled():
    from lidarloc.app.viewer.why_worker import LatestOnly

    worker = LatestOnly("test")
    try:
        for superseded_ok, expect in ((True, ["first", "second"]), (False, ["second"])):
            started, release, done = threading.Event(), threading.Event(), []

            def slow():
                started.set()
                release.wait(10)
                return "first"

            worker.submit("surface", slow, done.append, done.append, superseded_ok=superseded_ok)
            assert started.wait(10)
            worker.submit("surface", lambda: "second", done.append, done.append, superseded_ok=superseded_ok)
            release.set()
            wait_for(lambda: len(done) == len(expect) and worker.idle, what="the results")
            assert done == expect
        # cancel (a restart, a move on the timeline) drops even a superseded_ok result
        started, release, done = threading.Event(), threading.Event(), []
        worker.submit(
            "surface", lambda: (started.set(), release.wait(10), "old")[2], done.append, done.append, superseded_ok=True
        )
        assert started.wait(10)
        worker.cancel("surface")
        release.set()
        wait_for(lambda: worker.idle, what="the cancelled job")
        assert done == []
    finally:
        worker.stop()
