"""Server-level tests of the live viewer (app/viewer/) on the real Localizer (a small synthetic
street, helpers.StreetSequence, keeps it fast): every control changes the localizer as it says,
invalid values are refused with a message and the server keeps running. GUI handles are driven
programmatically: assigning ``.value`` runs the same callbacks a browser edit runs."""

from __future__ import annotations

import math
import time
import urllib.request

import numpy as np
import pytest
from helpers import make_localizer, wait_for
from lidarloc.core.config import DEG, Config
from lidarloc.core.errors import LidarlocError


# ---------------------------------------------------------------------------------- fixtures
# ---------------------------------------------------------------------------------- tests
def test_page_is_served_and_map_sent_once(viewer):
    html = urllib.request.urlopen(viewer.url, timeout=5).read().decode()
    assert "<html" in html.lower()
    v = viewer.viewer
    cloud = v.scene.node("map")
    assert cloud is not None and cloud.precision == "float32"
    assert cloud.points.dtype == np.float32


def test_step_advances_exactly_one_scan_and_pause_holds(viewer):
    v, loc = viewer.viewer, viewer.localizer
    c = v.controls
    assert loc.k == 0
    c.step.value = True  # a click: runs the button's callbacks
    wait_for(lambda: v.player.idle and loc.k == 1, what="one step")
    assert loc.k == 1
    c.step.value = True
    c.step.value = True
    wait_for(lambda: v.player.idle and loc.k == 3, what="two more steps")
    assert v.player.idle and loc.k == 3  # idle: nothing queued, nothing running; the counter stays
    c.play.value = True  # play …
    wait_for(lambda: loc.k >= 6, what="playing")
    c.play.value = True  # … and pause
    wait_for(lambda: v.player.idle, what="pause")
    k = loc.k
    assert v.player.idle and not v.player.playing and loc.k == k


def test_display_shows_latest_snapshot(viewer):
    v, loc = viewer.viewer, viewer.localizer
    v.controls.step.value = True
    wait_for(lambda: v.player.idle and loc.k == 1)
    v.update_display(force_plots=True)
    assert v.drawn is loc.snapshot()
    assert "Scan 0 of 24" in v.controls.status.content
    assert len(v.scene.node("particles").points) == 300


def test_numeric_params_reach_the_localizer(viewer):
    v, loc = viewer.viewer, viewer.localizer
    c = v.controls
    c.params["d_max"].value = 4.0  # below the built table: no rebuild
    c.params["sigma"].value = 0.8
    c.params["region_x"].value = 12.0
    c.params["region_y"].value = 18.0
    c.params["angle_step"].value = 5.0  # degrees in the GUI
    c.params["n_particles"].value = 500
    c.params["scan_voxel"].value = 0.7
    assert c.apply.label == "Apply 7 changes" and not c.apply.disabled
    assert loc.cfg.pf.sigma == 0.5  # nothing sent before Apply
    c.apply.value = True
    assert loc.cfg.pf.d_max == 4.0
    assert loc.cfg.pf.sigma == 0.8
    assert loc.cfg.s2m.region_x == 12.0 and loc.cfg.s2m.region_y == 18.0
    assert loc.cfg.s2m.angle_step == pytest.approx(5.0 * DEG)
    assert loc.cfg.pf.n_particles == 500 and isinstance(loc.cfg.pf.n_particles, int)
    assert loc.cfg.pf.scan_voxel == 0.7
    assert loc.pf.sigma == 0.8 and loc.pf.d_max == 4.0  # the filter itself, not just the config
    assert c.apply.disabled and "applied" in v.message
    assert loc.rebuild_progress is None
    # effective from the next scan
    c.step.value = True
    wait_for(lambda: v.player.idle and loc.k == 1, what="one step")
    assert len(loc.snapshot().particles) == 500


def test_q_is_shown_and_set_in_paper_units(viewer):
    v, loc = viewer.viewer, viewer.localizer
    q = v.controls.q
    assert q[3].value == pytest.approx(5.0)  # yaw: 5°
    assert q[9].value == pytest.approx(0.02)  # roll rate: 0.02°/s
    assert q[0].value == pytest.approx(0.5)  # x: 0.5 m
    q[3].value = 8.0
    q[6].value = 0.3
    v.controls.apply.value = True
    assert loc.cfg.pf.q_std[3] == pytest.approx(8.0 * DEG)
    assert loc.cfg.pf.q_std[6] == pytest.approx(0.3)
    assert loc.cfg.pf.q_std[0] == pytest.approx(0.5)
    assert loc.pf.q_std[3] == pytest.approx(8.0 * DEG) and loc.pf.q_std[6] == pytest.approx(0.3)


def test_s2m_switch_and_clock(viewer):
    v, loc = viewer.viewer, viewer.localizer
    v.controls.s2m_enabled.value = False
    assert loc.cfg.s2m.enabled is False
    v.controls.s2m_enabled.value = True
    assert loc.cfg.s2m.enabled is True
    v.controls.clock.value = "realtime"
    assert loc.cfg.localize.clock == "realtime" and v.player.clock == "realtime"
    assert v.controls.speed.disabled


@pytest.mark.parametrize(
    "key,value",
    [
        ("sigma", 0.0),
        ("sigma", -1.0),
        ("d_max", -2.0),
        ("n_particles", 0),
        ("region_x", 0.0),
        ("match_resolution", 50.0),
        ("angle_step", 0.0),
    ],
)
def test_invalid_values_are_refused_with_a_message(viewer, key, value):
    v, loc = viewer.viewer, viewer.localizer
    before = loc.cfg.to_dict()
    v.controls.params["sigma"].value = 0.9 if key != "sigma" else value
    v.controls.params[key].value = value
    v.controls.apply.value = True
    assert v.message.startswith("refused:"), v.message
    assert v.controls.message.visible
    # all or nothing: the valid σ change in the same batch was not applied either
    assert loc.cfg.to_dict()["pf"] == before["pf"] and loc.cfg.to_dict()["s2m"] == before["s2m"]
    # the server still answers and the controls still work
    urllib.request.urlopen(viewer.url, timeout=5).read()
    v.controls.params[key].value = v.params.applied[key]
    v.controls.params["sigma"].value = 0.6
    v.controls.apply.value = True
    assert loc.cfg.pf.sigma == 0.6


def test_invalid_q_refused(viewer):
    v, loc = viewer.viewer, viewer.localizer
    v.controls.q[4].value = -1.0
    v.controls.apply.value = True
    assert "refused" in v.message and "pitch" in v.message
    assert loc.cfg.pf.q_std[4] == pytest.approx(2.0 * DEG)


def test_reset_global_point_and_rectangle(viewer):
    v, loc = viewer.viewer, viewer.localizer
    c = v.controls
    c.step.value = True
    wait_for(lambda: v.player.idle and loc.k == 1)
    c.reset.value = True
    assert loc.events[-1].kind == "reset" and "globally" in loc.events[-1].detail
    # a shift-click: a ray from above onto the road at (30, 2)
    ground = v.scene.ground
    target = np.array([30.0, 2.0, ground.at(30.0, 2.0)])
    origin = target + np.array([-20.0, -5.0, 60.0])

    class Click:
        client = None
        ray_origin = tuple(origin)
        ray_direction = tuple((target - origin) / np.linalg.norm(target - origin))

    v.on_shift_click(Click())
    assert loc.events[-1].kind == "reset" and "around a pose" in loc.events[-1].detail
    xy = np.median(loc.pf.states[:, :2], axis=0)
    assert xy == pytest.approx([30.0, 2.0], abs=3.0)
    assert "particles reset around (30.0, 2.0)" in v.message

    # a rectangle dragged in a top-down view: its corners land where the camera model says
    class Camera:  # straight down from 100 m over (50, 0); image "up" = +y
        position = np.array([50.0, 0.0, 100.0])
        wxyz = np.array([0.0, 1.0, 0.0, 0.0])  # 180° about x: z forward = down, y down = -y
        fov = 2 * math.atan(0.5)  # tan(fov/2) = 0.5: 100 m up sees ±50 m vertically
        aspect = 1.0

    class Client:
        camera = Camera()
        client_id = -1  # no open tab has it: the viewer sends this one no notification

    class Rect:
        client = Client()
        screen_min = (0.5, 0.25)
        screen_max = (0.75, 0.5)

    v.on_shift_rect(Rect())
    assert loc.events[-1].kind == "reset"
    # half-height of the view at the ground is 0.5·(100 − z0); u 0.5…0.75 → x 50…50 + half/2
    half = 0.5 * (100 - ground.z_default)
    P = loc.pf.states
    assert P[:, 0].min() >= 50.0 - 1 and P[:, 0].max() <= 50 + 0.5 * half + 1
    assert P[:, 1].min() >= -1 and P[:, 1].max() <= 0.5 * half + 1
    # the reset shows from the next scan on
    c.step.value = True
    wait_for(lambda: v.player.idle and loc.k == 2)
    assert np.median(loc.snapshot().particles[:, 0]) > 45


def test_kidnap_and_restart(viewer):
    v, loc = viewer.viewer, viewer.localizer
    v.controls.step.value = True
    wait_for(lambda: v.player.idle and loc.k == 1)
    v.controls.kidnap_skip.value = 5
    v.controls.kidnap.value = True
    assert loc.k == 6 and "kidnapped" in v.message
    v.controls.kidnap_skip.value = 0
    v.controls.kidnap.value = True
    assert v.message.startswith("refused") and loc.k == 6
    v.controls.step.value = True
    wait_for(lambda: v.player.idle and loc.k == 7)
    v.update_display(force_plots=True)
    # the ground-truth line breaks at the jump: scans 0 and 6 are not joined
    assert v.history.n == 2
    v.controls.seed.value = 7
    v.controls.restart.value = True
    assert loc.k == 0 and loc.cfg.seed == 7
    assert v.history.n == 0 and v.latest.scan_index == -1


def test_layers_and_bev_level(viewer):
    v = viewer.viewer
    c = v.controls
    assert c.layers["bev_level"].visible  # the localizer has a pyramid: the toggle is offered
    c.layers["map"].value = False
    assert v.scene.node("map").visible is False
    c.layers["map_bev"].value = True
    assert v.scene.node("map_bev").visible is True
    c.layers["bev_level"].value = True
    assert v.scene.node("bev_level") is not None and v.scene.node("bev_level").visible
    c.bev_level.value = 0
    assert v.scene.bev_shown[1] == 0


def test_factory_shows_progress_then_attaches(street, cache_root):
    import threading

    from lidarloc.app.viewer.serve import serve

    go = threading.Event()
    built = []

    def factory(progress=None):
        progress("map", 0.5)
        go.wait(10)
        from lidarloc.core.localizer import Localizer

        cfg = Config()
        cfg.pf.n_particles = 200
        built.append(Localizer(street, cfg, cache_root, progress=progress))
        return built[-1]

    handle = serve(factory, port=0, autoplay=True)
    try:
        wait_for(
            lambda: handle.viewer.controls.progress_text.content.startswith("Building the prior map… 50%"),
            what="progress",
        )
        assert handle.viewer.controls.progress.visible
        handle.viewer.controls.reset.value = True
        assert "still starting" in handle.viewer.message
        go.set()
        assert handle.wait_ready(30)
        wait_for(lambda: handle.localizer.k >= 3, what="autoplay")
        wait_for(lambda: not handle.viewer.controls.progress.visible, what="progress bar hidden")
    finally:
        t0 = time.perf_counter()
        handle.stop()
        # stop() is bounded by its own join timeouts (~1.2 s, see ViewerHandle.stop); this bound
        # only catches a stop that hangs, with room for a loaded 2-core machine
        assert time.perf_counter() - t0 < 10.0
    # the viewer built it, so the viewer closes it
    wait_for(lambda: built[0].closed, what="localizer closed")


def test_factory_failure_is_shown(street):
    from lidarloc.app.viewer.serve import serve

    def factory():
        raise LidarlocError("/nowhere: no such sequence")

    handle = serve(factory, port=0)
    try:
        wait_for(lambda: "could not start" in handle.viewer.message, what="startup failure message")
        urllib.request.urlopen(handle.url, timeout=5).read()
    finally:
        handle.stop()


def test_two_viewers_two_ports(street, cache_root):
    from lidarloc.app.viewer.serve import serve

    locs = [make_localizer(street, cache_root) for _ in range(2)]
    a = serve(locs[0], port=0, autoplay=False)
    b = serve(locs[1], port=0, autoplay=False)
    try:
        assert a.port != b.port
    finally:
        a.stop()
        b.stop()
        for loc in locs:
            loc.close()


def test_speed_and_clock_controls_reach_the_player(viewer):
    v, loc = viewer.viewer, viewer.localizer
    c = v.controls
    c.speed.value = "5"
    assert v.player.speed == 5.0
    c.speed.value = "max"
    assert v.player.speed is None
    c.clock.value = "realtime"
    assert v.player.clock == "realtime" and loc.cfg.localize.clock == "realtime"
    c.clock.value = "replay"
    assert v.player.clock == "replay" and not c.speed.disabled


def test_rebuild_progress_shows_in_the_page(viewer):
    v, loc = viewer.viewer, viewer.localizer
    c = v.controls
    c.layers["bev_level"].value = True
    old = loc.pyramid
    c.params["match_resolution"].value = 2.0  # d_m: the BEV pyramid is rebuilt in the background
    c.apply.value = True
    assert loc.rebuild_progress is not None
    v.update_display()
    assert v.controls.progress.visible and "Rebuilding" in v.controls.progress_text.content
    # the new pyramid is swapped in at the next scan; the bar goes, the BEV layer follows
    wait_for(lambda: not loc.rebuilding, what="rebuild")
    c.step.value = True
    wait_for(lambda: v.player.idle and loc.k == 1)
    v.update_display()
    assert loc.rebuild_progress is None and not v.controls.progress.visible
    assert loc.pyramid is not old and loc.pyramid.resolution == 2.0
    assert v.scene.bev_shown[0] is loc.pyramid


def test_status_and_plots_follow_the_run(viewer):
    v, loc = viewer.viewer, viewer.localizer
    for _ in range(4):
        v.controls.step.value = True
    wait_for(lambda: v.player.idle and loc.k == 4)
    v.update_display(force_plots=True)
    text = v.controls.status.content
    assert "Scan 3 of 24" in text and "paused" in text
    assert "N_eff" in text and "S2M" in text and "error to truth" in text
    assert "s2m started" in text  # recent events
    plots = v.controls.plots.handles
    x, std, spread, err, cursor = plots["std"].data
    assert list(x) == [0, 1, 2, 3] and (std > 0).all() and (spread > 0).all() and (err > 0).all()
    x, pf_ms, rpe_ms, s2m_ms, accepted, rejected, cursor = plots["latency"].data
    assert not np.isfinite(cursor).any()  # live: no timeline cursor
    assert len(pf_ms) == 4 and (pf_ms > 0).all() and s2m_ms[-1] > 0
    # the scene shows this scan: its points in green at the estimate, the S2M match with its label
    snap = loc.snapshot()
    assert np.array_equal(v.scene.node("scan").points, snap.scan_world)
    assert snap.s2m is not None
    assert f"started at scan {snap.s2m.started_at}, landed at {snap.s2m.landed_at}" in v.scene.node("s2m_label").text


def test_status_shows_the_scans_confidence_and_warns_while_it_is_low(viewer):
    from dataclasses import replace

    from lidarloc.app.viewer.readouts import status_markdown

    v, loc = viewer.viewer, viewer.localizer
    for _ in range(3):
        v.controls.step.value = True
    wait_for(lambda: v.player.idle and loc.k == 3)
    v.update_display(force_plots=True)
    snap, text = loc.snapshot(), v.controls.status.content
    assert snap.inlier_share is not None and snap.n_particles == 300
    assert f"| inlier share | {100 * snap.inlier_share:.0f}% · mean residual {snap.mean_residual_m:.2f} m |" in text
    assert f"| N_eff share | {100 * snap.n_eff_share:.1f}% ({snap.n_eff:.0f} of 300)" in text
    assert "| PF converged (std below threshold) | " + ("yes" if snap.converged else "no") in text
    # the warning line: while localized with fewer inliers than localize.min_inlier_share
    floor = loc.cfg.localize.min_inlier_share
    low = replace(snap, localized=True, inlier_share=floor - 0.2)

    def status(s):
        return status_markdown(s, "paused", "replay", "10", [], min_inlier_share=floor)

    assert f"low confidence: {100 * (floor - 0.2):.0f}% of the scan fits the map" in status(low)
    assert "low confidence" not in status(replace(low, inlier_share=floor + 0.1))
    assert "low confidence" not in status(replace(low, localized=False))
    # and the viewer passes the localizer's own floor
    assert "low confidence" in v.status_markdown(low)


def test_a_failing_display_says_one_line_and_the_filter_plays_on(viewer, capfd):
    v, loc = viewer.viewer, viewer.localizer

    def broken(*args, **kwargs):
        raise RuntimeError("no such layer")

    v.scene.draw = broken
    v.controls.step.value = True
    wait_for(lambda: v.display_faults.count >= 1, what="the display's failure")
    v.controls.step.value = True
    wait_for(lambda: v.player.idle and loc.k == 2, what="the filter stepping on")
    wait_for(lambda: v.display_faults.count >= 2, what="the second frame failing")
    line = "viewer display failed: RuntimeError: no such layer; the viewer keeps serving and the filter keeps playing"
    assert v.message == line
    err = capfd.readouterr().err
    assert err.count(line) == 1 and "Traceback" not in err  # said once, however many frames fail


def test_play_again_loops_the_drive(viewer):
    v, loc = viewer.viewer, viewer.localizer
    ends = []
    v.on_finished = lambda: (ends.append(loc.k), v.play_again() if len(ends) < 2 else None)
    v.controls.speed.value = "max"
    v.controls.play.value = True
    wait_for(lambda: len(ends) == 2, timeout=120, what="two ends of the drive")
    assert ends == [loc.n_scans, loc.n_scans] and not v.step_failed
