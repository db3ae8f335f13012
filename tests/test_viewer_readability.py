"""Reading the scene and the panel: particles coloured by log-weight rank and sized by weight, the
true vehicle beside the estimate, the legend naming every colour, the weighted std beside the
cloud's own spread, the error split along and across the truth's heading, and the plots' event
marks on the scan axis."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from helpers import StreetSequence, make_localizer, wait_for
from lidarloc.core.geometry import pose_matrix


def test_log_weight_rank_orders_particles_that_hold_no_weight():
    from lidarloc.app.viewer.shapes import log_weight_rank

    # one particle holds all the weight; the others differ by hundreds of nats (exp underflows)
    lw = np.array([-2000.0, 0.0, -900.0, -900.0, -1500.0])
    r = log_weight_rank(lw)
    assert r[1] == 1.0 and r[0] == 0.0
    assert r[2] == r[3] and r[4] < r[2] < r[1]  # ties share a rank, the order is kept
    w = np.exp(lw - lw.max())
    assert (w[[0, 2, 3, 4]] == 0).all()  # by weight they would all look the same
    assert np.array_equal(log_weight_rank(np.zeros(4)), np.full(4, 0.5))


def test_error_components_follow_the_truths_heading():
    from lidarloc.app.viewer.history import error_components

    truth = pose_matrix(10.0, 5.0, 1.0, math.pi / 2, 0.0, 0.0)  # heading +y
    est = pose_matrix(9.0, 7.0, 1.5, math.pi / 2 + 0.1, 0.0, 0.0)  # 2 m ahead, 1 m to its right
    along, cross, vertical, heading = error_components(est, truth)
    assert along == pytest.approx(2.0) and cross == pytest.approx(1.0) and vertical == pytest.approx(0.5)
    assert heading == pytest.approx(0.1)
    # wrapped: 359° vs 1° is −2°
    a = pose_matrix(0, 0, 0, math.radians(359), 0, 0)
    b = pose_matrix(0, 0, 0, math.radians(1), 0, 0)
    assert math.degrees(error_components(a, b)[3]) == pytest.approx(-2.0)


def test_event_marks_sit_on_the_plotted_scans():
    from lidarloc.app.viewer.plots import mark_series

    x = np.array([0.0, 2.0, 4.0, 6.0])  # a decimated axis
    y = np.array([1.0, 2.0, np.nan, 4.0])
    m = mark_series(x, y, [(3, "localized"), (6, "loss"), (1, "s2m_accepted")], ("localized",))
    assert np.isnan(m[[0, 1, 3]]).all() and m[2] == 0.0  # at scan 4 (the curve has no value there)
    m = mark_series(x, y, [(6, "loss")], ("loss", "false_positive"))
    assert m[3] == 4.0


def test_legend_names_every_colour_the_scene_uses():
    from lidarloc.app.viewer import style
    from lidarloc.app.viewer.legend import legend_markdown

    text = legend_markdown()
    for rgb in (
        style.SCAN_COLOR,
        style.EST_COLOR,
        style.GT_COLOR,
        style.BEST_COLOR,
        style.ELLIPSE_COLOR,
        style.S2M_ACCEPTED_COLOR,
        style.S2M_REJECTED_COLOR,
        style.BEV_COLOR,
        style.RESET_COLOR,
        style.PARTICLE_LOW,
        style.PARTICLE_HIGH,
        style.HEIGHT_LUT[0],
        style.HEIGHT_LUT[-1],
    ):
        assert style.css(rgb) in text, rgb
    assert "N_eff share" in text and "collapsed" in text
    assert "ground truth" not in legend_markdown(has_truth=False)


@pytest.fixture(scope="module")
def viewer(cache_root):
    from lidarloc.app.viewer.serve import serve

    loc = make_localizer(StreetSequence(), cache_root)
    handle = serve(loc, port=0, autoplay=False)
    yield handle
    handle.stop()
    loc.close()


def test_particles_truth_and_status_read_as_the_legend_says(viewer):
    from lidarloc.app.viewer.shapes import log_weight_rank, snapshot_log_weights
    from lidarloc.app.viewer.style import PARTICLE_ARROW_MAX, PARTICLE_ARROW_MIN, PARTICLE_HIGH, PARTICLE_LOW

    v, loc = viewer.viewer, viewer.localizer
    for _ in range(3):
        v.controls.step.value = True
    wait_for(lambda: v.player.idle and loc.k == 3)
    v.update_display(force_plots=True)
    snap = v.drawn
    # particles: colour by log-weight rank, arrow length by weight
    colors = v.scene.node("particle_dots").colors
    rank = log_weight_rank(snapshot_log_weights(snap))
    expect = (PARTICLE_LOW + (PARTICLE_HIGH - PARTICLE_LOW) * rank[:, None].astype(np.float32)).astype(np.uint8)
    assert np.array_equal(colors, expect)
    segs = v.scene.node("particles").points
    length = np.linalg.norm(segs[:, 1] - segs[:, 0], axis=1)
    heaviest = int(np.argmax(snap.weights))
    assert length[heaviest] == pytest.approx(PARTICLE_ARROW_MAX, rel=1e-4)
    assert length.min() >= PARTICLE_ARROW_MIN - 1e-4
    # the true vehicle, in its own colour, at the truth; the estimate's in orange at the estimate
    truth = v.scene.node("gt_vehicle").points
    assert v.scene.node("gt_vehicle").visible
    assert np.allclose(truth.reshape(-1, 3).mean(axis=0)[:2], snap.gt_pose[:2, 3], atol=1.5)
    est = v.scene.node("est_vehicle").points
    assert np.allclose(est.reshape(-1, 3).mean(axis=0)[:2], snap.mean_pose[:2, 3], atol=1.5)
    # status: the weighted std and the cloud's own spread, N_eff as a share
    text = v.controls.status.content
    spread = snap.particles[:, :2].std(axis=0)
    assert f"| particle cloud spread x/y | {spread[0]:.2f} / {spread[1]:.2f} m |" in text
    assert f"| N_eff share | {100 * snap.n_eff_share:.1f}%" in text
    collapsed = replace(snap, n_eff=1.0)
    assert "collapsed: see Legend" in v.status_markdown(collapsed)
    assert "collapsed" not in v.status_markdown(replace(snap, n_eff=0.5 * len(snap.weights)))
    # plots on one scan axis: every one spans the whole sequence
    for h in v.controls.plots.handles.values():
        assert tuple(h.scales["x"]["range"]) == (0.0, float(loc.n_scans - 1))
    x, along, cross, vertical, *marks = v.controls.plots.handles["error"].data
    assert list(x) == [0, 1, 2] and np.isfinite(along).all() and np.isfinite(cross).all()
