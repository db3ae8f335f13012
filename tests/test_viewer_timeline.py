"""The viewer's timeline on a recorded run: the viewer records what it plays, the slider shows a
recorded step exactly as it was (particles, estimate, status, plots' cursor), dragging pauses
playback, the event buttons land on event steps, "Branch from here" continues in a folder of its
own beside the original, and ``view --run`` opens a finished run (a moved source is one line)."""

from __future__ import annotations

import json
import shutil
import threading

import numpy as np
import pytest
from helpers import MAPPING_SCANS, wait_for
from lidarloc.core.config import Config
from lidarloc.core.errors import LidarlocError
from lidarloc.core.runs import recording
from lidarloc.core.sequences.factory import SourceSpec, open_sequence

SCANS = 30


def show(v) -> None:
    """Redraw until the scene shows the timeline's step with its scan (recomputed on a thread)."""
    wait_for(
        lambda: v.update_display(force_plots=True) is not None and v.travel.scan_shown,
        timeout=30,
        what="the recorded step's scan",
    )


def town_setup(scans: int = SCANS, n_particles: int = 300):
    """The short town (helpers.short_town) with its configuration, so that a recording of it can
    be reopened from its source: (spec, cfg, seq)."""
    cfg = Config()
    cfg.town.n_scans = MAPPING_SCANS
    cfg.pf.n_particles = n_particles
    spec = SourceSpec(scans=scans)
    return spec, cfg, open_sequence(spec, cfg)


@pytest.fixture(scope="module")
def recorded(cache_root, tmp_path_factory):
    """A paused viewer on the short town that recorded its first steps: (handle, record root)."""
    from lidarloc.app.viewer.serve import serve
    from lidarloc.core.localizer import Localizer

    spec, cfg, seq = town_setup()
    loc = Localizer(seq, cfg, cache_root)
    root = tmp_path_factory.mktemp("viewer-runs")
    handle = serve(loc, port=0, autoplay=False, record_to=root, spec=spec, cache_root=cache_root)
    v = handle.viewer
    for _ in range(12):
        v.step_once()
        wait_for(lambda: v.player.idle, what="a step")
    wait_for(lambda: v.travel.recorder.n == 12, what="12 recorded steps")
    v.update_display(force_plots=True)
    yield handle, root
    handle.stop()
    loc.close()


def test_the_viewer_records_what_it_plays(recorded):
    handle, root = recorded
    v, loc = handle.viewer, handle.localizer
    run_dir = v.travel.recorder.run_dir
    assert run_dir.parent == root
    rec = recording.open(run_dir)
    assert rec.n == loc.steps == 12
    assert rec.meta["source"]["scans"] == SCANS
    np.testing.assert_array_equal(rec.scan_index, np.arange(12))
    # the last recorded step is the localizer's state now
    snap = loc.snapshot()
    np.testing.assert_allclose(rec.mean_pose[-1], snap.mean_pose)
    np.testing.assert_allclose(rec.particles(11), snap.particles.astype(np.float32))
    assert v.travel.timeline.n == 12 and v.travel.timeline.slider.value == 11


def test_scrubbing_shows_the_recorded_step(recorded):
    handle, _ = recorded
    v = handle.viewer
    tl = v.travel.timeline
    rec = recording.open(v.travel.recorder.run_dir)
    try:
        tl.slider.value = 4  # as a drag in the browser: the callbacks run
        assert tl.step == 4
        v.update_display(force_plots=True)  # at once: the step's particles and estimate …
        np.testing.assert_allclose(v.scene.node("particle_dots").points, rec.particles(4)[:, :3], atol=1e-5)
        show(v)  # … then its scan
        drawn = v.drawn
        assert drawn.scan_index == 4
        np.testing.assert_allclose(v.scene.node("particle_dots").points, rec.particles(4)[:, :3], atol=1e-5)
        np.testing.assert_allclose(v.scene.node("pose").position, rec.mean_pose[4][:3, 3], atol=1e-5)
        assert len(v.scene.node("scan").points) > 1000  # the scan, recomputed from the source
        assert "**Scan 4 of" in v.controls.status.content and "recorded" in v.controls.status.content
        assert "**Scan 4**" in tl.where.content
        # the plots' cursor: one dot, at scan 4
        x, *series = v.controls.plots.handles["std"].data
        cursor = series[-1]
        assert np.count_nonzero(np.isfinite(cursor)) == 1 and x[np.isfinite(cursor)][0] == 4
        # a step back and forward
        assert tl.back() == 3
        show(v)
        assert v.drawn.scan_index == 3
        assert tl.forward() == 4
    finally:
        tl.live()
    v.update_display()
    assert v.drawn is handle.localizer.snapshot()
    assert tl.step is None and tl.slider.value == 11


def test_dragging_pauses_live_playback_and_live_plays_on(recorded):
    handle, _ = recorded
    v, loc = handle.viewer, handle.localizer
    tl = v.travel.timeline
    v.play()
    wait_for(lambda: loc.k >= 14, what="playing")
    try:
        tl.slider.value = 2
        assert not v.player.playing
        wait_for(lambda: v.player.idle, what="the scan in progress")
        v.update_display()
        assert v.drawn.scan_index == 2
        # back to live: the newest scan, and playing again as before the drag
        tl.buttons.value = "Live"
        assert tl.step is None and v.player.playing
        k = loc.k
        wait_for(lambda: loc.k > k, what="playback going on")
    finally:
        v.pause()
        tl.live()
    wait_for(lambda: v.player.idle, what="the scan in progress")
    assert not v.player.playing  # Live after a pause by hand stays paused
    wait_for(lambda: v.travel.recorder.n == loc.steps, what="the last step recorded")
    v.update_display()
    assert tl.slider.value == loc.steps - 1


def test_a_tabs_drag_written_over_by_the_live_follow_still_goes_where_it_was_dragged(recorded):
    """The display thread follows the newest step while live; a drag applied just before that
    write lands, and moved after it, goes to the dragged step, not the newest."""
    from lidarloc.app.bench.socket_tabs import SocketTab

    handle, _ = recorded
    v = handle.viewer
    tl = v.travel.timeline
    tab = SocketTab(handle.port)
    try:
        wait_for(lambda: len(handle.server.get_clients()) >= 1, what="the tab counted")
        newest = tl.n - 1
        assert tl.step is None and tl.slider.value == newest > 2
        with v._gui_gate:  # the move waits here, as behind a display update in progress
            tab.set(tl.slider, 2)
            wait_for(lambda: tl._dragged == 2, what="the drag applied")
            with tl._writing():  # the live follow, from a value read before the drag
                tl.slider.value = newest
        wait_for(lambda: tl.step is not None, what="the move")
        assert tl.step == 2 and tl.slider.value == 2
    finally:
        tab.close()
        tl.live()
    assert tl.step is None and tl.slider.value == newest


def test_event_buttons_land_on_event_steps(recorded):
    from lidarloc.app.viewer.timeline import DEFAULT_FILTER, EVENT_FILTERS

    handle, _ = recorded
    v = handle.viewer
    tl = v.travel.timeline
    rec = recording.open(v.travel.recorder.run_dir)

    def walk() -> list:
        tl.go(0)
        landed = []
        while True:
            try:
                landed.append(tl.next_event())
            except LidarlocError:
                return landed

    try:
        # "all": every event kind the filter offers, S2M verdicts included
        tl.kinds.value = "all"
        steps = sorted({max(s, 0) for s, e in rec.events if e.kind in EVENT_FILTERS["all"]})
        assert len(steps) >= 2, f"the run should have had events by now: {rec.events}"
        landed = walk()
        assert landed == [s for s in steps if s > 0 and s < tl.n]
        back = tl.prev_event()
        assert back == landed[-2]
        tl.buttons.value = "◀"  # the button group, as clicked
        assert tl.step == back - 1
        # the default passes over the S2M verdicts (every few scans) to what changed the run
        tl.kinds.value = DEFAULT_FILTER
        run_steps = sorted({max(s, 0) for s, e in rec.events if e.kind in EVENT_FILTERS[DEFAULT_FILTER]})
        assert walk() == [s for s in run_steps if 0 < s < tl.n]
        s2m = sorted({max(s, 0) for s, e in rec.events if e.kind.startswith("s2m_") and e.kind != "s2m_started"})
        assert s2m and not set(s2m) <= set(run_steps)
        # one kind: only its steps, and the list under the filter names them
        tl.kinds.value = "S2M"
        assert walk() == [s for s in s2m if 0 < s < tl.n]
        assert "s2m accepted" in tl.event_list.content or "s2m rejected" in tl.event_list.content
    finally:
        tl.kinds.value = DEFAULT_FILTER
        tl.live()


def test_scrubbing_clears_or_redraws_another_scans_surface(recorded):
    handle, _ = recorded
    v = handle.viewer
    tl, why = v.travel.timeline, v.why
    try:
        tl.go(4)
        show(v)
        why.request_surface()
        wait_for(lambda: why.surface.last is not None, what="the surface of step 4")
        assert why.surface.last_snapshot.scan_index == tl.run.scan_of(4)
        tl.go(6)
        show(v)
        assert why.surface.last is None and why.surface.image is None  # not scan 4's under scan 6
        # with "Surface on every scan" the shown scan gets its own
        why.surface.every_scan.value = True
        tl.go(7)
        show(v)
        wait_for(
            lambda: why.surface.last is not None and why.surface.last_snapshot.scan_index == tl.run.scan_of(7),
            what="the surface of step 7",
        )
    finally:
        why.surface.every_scan.value = False
        why.clear()
        tl.live()
        v.pause()


def test_view_run_opens_a_finished_run_and_a_moved_source_is_one_line(recorded, cache_root, tmp_path):
    from lidarloc.app.viewer.runs import load_run, open_runs

    handle, _ = recorded
    run_dir = handle.viewer.travel.recorder.run_dir
    h2 = open_runs([run_dir], port=0, cache_root=cache_root, record_to=tmp_path / "branches")
    try:
        v = h2.viewer
        tl = v.travel.timeline
        assert tl.n >= 12 and tl.step == 0
        tl.go(7)
        show(v)
        rec = recording.open(run_dir)
        assert v.drawn.scan_index == 7
        np.testing.assert_allclose(v.scene.node("particle_dots").points, rec.particles(7)[:, :3], atol=1e-5)
        assert len(v.scene.node("scan").points) > 1000
        assert "**Scan 7 of" in v.controls.status.content
        # the Why views work on the recorded scan: its residuals at the estimate
        v.why.residuals.enabled.value = True
        v.why.redraw_residuals()
        assert v.why.residuals.last is not None and len(v.why.residuals.last.points) > 0
        # Play plays the recording's timeline; a drag pauses it
        v.controls.speed.value = "max"
        v.controls.play.value = True
        wait_for(lambda: tl.step >= 10, what="the recorded run to play")
        tl.slider.value = 2
        assert not v.travel.replaying and tl.step == 2
        # controls that need a live filter say why they cannot
        v.controls.reset.value = True
        assert "recorded run" in v.message
        # a branch turns the recorded run into a live one, recorded beside it, with the panel's numbers
        tl.go(5)
        v.controls.params["sigma"].value = 0.8
        assert v.controls.apply.label == "Apply 1 change"
        tl.branch.value = True
        wait_for(lambda: v.localizer is not None and not v.travel.branching, timeout=120, what="the branch")
        assert v.localizer.k == rec.scan_index[5] + 1 and v.localizer.cfg.pf.sigma == 0.8
        v.step_once()
        wait_for(lambda: v.player.idle and v.travel.recorder.n == 7, what="a recorded branch step")
        branch = recording.open(v.travel.recorder.run_dir)
        assert v.travel.recorder.run_dir.parent == tmp_path / "branches"
        assert branch.n == 1 and branch.meta["branch_of"] == {"run": str(rec.run_dir), "step": 5}
    finally:
        h2.stop()
    # a run whose source moved: one line naming the path it expected
    moved = tmp_path / "moved-run"
    shutil.copytree(run_dir, moved)
    index = moved / "recording" / "index.json"
    data = json.loads(index.read_text())
    data["meta"]["source"]["scans_dir"] = str(tmp_path / "gone" / "scans")
    data["meta"]["source"]["town_seed"] = None
    index.write_text(json.dumps(data))
    with pytest.raises(LidarlocError) as exc:
        load_run(moved, cache_root)
    msg = str(exc.value)
    assert "\n" not in msg and str(tmp_path / "gone" / "scans") in msg
    with pytest.raises(LidarlocError) as exc:
        load_run(tmp_path / "no-such-run", cache_root)
    assert "\n" not in str(exc.value)


def test_a_move_while_the_replay_takes_a_step_is_the_step_that_stays(recorded, cache_root, tmp_path):
    """A drag (or Back, an event button) that comes while a recorded run's playback is taking a
    step stops the playback, and the user's step is the one shown: the replay's step lands before
    it, never after it. The replay is held inside a step until the user's move has returned or 2 s
    have passed: a move that does not wait for the step lets the replay read the user's step and
    go one further."""
    from lidarloc.app.viewer.runs import open_runs

    handle, _ = recorded
    h2 = open_runs([handle.viewer.travel.recorder.run_dir], port=0, cache_root=cache_root, record_to=tmp_path)
    try:
        v = h2.viewer
        travel, tl = v.travel, v.travel.timeline
        in_step, moved = threading.Event(), threading.Event()
        current = tl.current

        def current_in_a_replay_step():
            if threading.current_thread() is travel._replay and not in_step.is_set():
                in_step.set()
                moved.wait(2.0)  # the user's move lands now, unless it waits for this step
            return current()

        tl.current = current_in_a_replay_step
        v.controls.speed.value = "max"
        v.controls.play.value = True
        assert in_step.wait(30), "the recorded run did not start playing"
        mover = threading.Thread(target=lambda: (tl.go(2), moved.set()))
        mover.start()
        mover.join(30)
        assert moved.is_set()
        wait_for(lambda: not travel.replaying, what="the playback to stop")
        assert tl.step == 2
        travel._replay.join(5)
        assert not travel._replay.is_alive() and tl.step == 2
    finally:
        h2.stop()


def test_view_two_runs_side_by_side_in_lockstep(recorded, cache_root):
    from lidarloc.app.viewer.runs import open_runs

    handle, root = recorded
    v = handle.viewer
    first = v.travel.recorder.run_dir
    v.controls.seed.value = 1
    v.controls.restart.value = True  # a new run, recorded in a folder of its own
    second = v.travel.recorder.run_dir
    assert second != first and second.parent == root
    for _ in range(10):
        v.step_once()
        wait_for(lambda: v.player.idle, what="a step")
    wait_for(lambda: v.travel.recorder.n == 10, what="10 recorded steps")
    v.travel.recorder.close()  # as the viewer does on stop: the summary is written
    assert recording.open(first).summary is not None
    h2 = open_runs([first, second], port=0, cache_root=cache_root)
    try:
        w = h2.viewer
        a, b = recording.open(first), recording.open(second)
        tl = w.travel.timeline
        assert tl.n == a.n
        tl.go(6)
        w.update_display(force_plots=True)
        # both particle clouds at the same step, one colour each
        np.testing.assert_allclose(w.scene.node("particle_dots").points, a.particles(6)[:, :3], atol=1e-5)
        ref = w.travel.reference_node("particles")
        np.testing.assert_allclose(ref.points, b.particles(6)[:, :3], atol=1e-5)
        assert tuple(ref.colors.reshape(-1, 3)[0]) != tuple(w.scene.node("particle_dots").colors.reshape(-1, 3)[0])
        # both trajectories, the second in its own colour, end at the step on screen
        ref_pts = np.concatenate([h.points.reshape(-1, 3) for h in w.travel.ref_line.handles])
        assert np.allclose(ref_pts[-1], b.mean_pose[6][:3, 3], atol=1e-4)
        own = np.concatenate([h.points.reshape(-1, 3) for h in w.scene.est_line.handles])
        assert np.allclose(own[-1], a.mean_pose[6][:3, 3], atol=1e-4)
        # a step past the second run's end shows its last step
        tl.go(a.n - 1)
        w.update_display()
        np.testing.assert_allclose(ref.points, b.particles(b.n - 1)[:, :3], atol=1e-5)
        # overlaid plots: the second run's curves, dashed, on the same scan axis
        h = w.controls.plots.handles["n_eff"]
        labels = [s["label"] for s in h.series]
        i_ref = next(i for i, lbl in enumerate(labels) if second.name in lbl)
        ys = h.data[1:]
        y_ref = ys[i_ref - 1]
        share = b.n_eff / b.n_particles * 100.0
        np.testing.assert_allclose(y_ref[: b.n], share, rtol=1e-9)
        # the table: both runs' figures side by side
        table = w.travel.compare_text.content
        assert first.name in table and second.name in table and "RMSE while localized" in table
        assert "steps from 0" in table
        assert table.count("|") > 20
    finally:
        h2.stop()


def test_the_second_run_is_drawn_between_display_updates(recorded):
    """A branch sets the second run from its own thread: it draws only between display updates.
    Two threads writing one trajectory line at once left it holding a node viser had replaced
    (same name), and a later scrub failed on it."""
    handle, _ = recorded
    v = handle.viewer
    done = threading.Event()
    with v.drawing():  # a display update in progress
        threading.Thread(target=lambda: (v.travel.set_reference(None), done.set()), daemon=True).start()
        assert not done.wait(0.3), "the second run was drawn during a display update"
    assert done.wait(30), "setting the second run never finished"


def test_branch_from_here_continues_in_its_own_folder_beside_the_original(recorded):
    """Last in the file: the branch takes the viewer over."""
    handle, root = recorded
    v = handle.viewer
    tl = v.travel.timeline
    original_dir = v.travel.recorder.run_dir
    original_n = recording.open(original_dir).n
    tl.go(8)
    scan = tl.run.scan_of(8)
    original = handle.localizer
    v.controls.params["sigma"].value = 0.9  # a changed parameter for the branch
    tl.branch.value = True  # the button, as clicked
    wait_for(
        lambda: v.localizer is not original and v.travel.reference is not None and not v.travel.branching,
        timeout=120,
        what="the branch to start",
    )
    loc = v.localizer
    assert loc.k == scan + 1 and loc.cfg.pf.sigma == 0.9 and v.controls.apply.disabled
    branch_dir = v.travel.recorder.run_dir
    assert branch_dir.parent == root and branch_dir != original_dir and "branch" in branch_dir.name
    # the branch plays on from there, recorded in its folder; the original stays as it was
    for _ in range(3):
        v.step_once()
        wait_for(lambda: v.player.idle, what="a branch step")
    wait_for(lambda: v.travel.recorder.n == 12, what="the branch's steps recorded")
    rec = recording.open(branch_dir)
    assert rec.n == 3 and rec.meta["branch_of"]["step"] == 8 and rec.meta["first_step"] == 9
    np.testing.assert_array_equal(rec.scan_index, [scan + 1, scan + 2, scan + 3])
    assert recording.open(original_dir).n == original_n
    # the original's trajectory in its own colour beside the branch's; its curves dashed in the plots
    v.update_display(force_plots=True)
    assert v.travel.ref_line.handles, "no trajectory of the original drawn"
    ref_pts = np.concatenate([h.points.reshape(-1, 3) for h in v.travel.ref_line.handles])
    orig = recording.open(original_dir)
    assert np.allclose(ref_pts[-1], orig.mean_pose[orig.n - 1][:3, 3], atol=1e-4)
    labels = [s["label"] for s in v.controls.plots.handles["std"].series]
    assert any("original" in lbl for lbl in labels)
    # the timeline covers the original's steps before the branch and the branch's after
    assert tl.n == 12 and tl.run.scan_of(3) == 3 and tl.run.scan_of(10) == scan + 2
    tl.go(2)
    v.update_display()
    np.testing.assert_allclose(v.scene.node("particle_dots").points, orig.particles(2)[:, :3], atol=1e-5)
    assert "B: scans until first localized" in v.travel.compare_text.content
    # the Compare table follows the branch as it plays: its figures are of the steps after the
    # branch point only (before it, both runs are the same run)
    tl.live()

    def compared(n_branch: int) -> bool:
        v.update_display()
        return f"branch after scan {scan} 9…{n_branch - 1}" in v.travel.compare_text.content

    wait_for(lambda: compared(12), what="the Compare table over the branch's 3 steps")
    v.step_once()
    wait_for(lambda: v.player.idle and v.travel.recorder.n == 13, what="one more branch step")
    wait_for(lambda: compared(13), what="the Compare table following the branch")
    table = v.travel.compare_text.content
    rec = recording.open(branch_dir)
    err, loc = rec.error_m[:4], rec.localized[:4].astype(bool)
    row = next(line for line in table.splitlines() if line.startswith("| steps compared |"))
    assert row.split("|")[2].strip() == "4"  # the branch's own steps only
    if loc.any():
        rmse = float(np.sqrt(np.mean(err[loc] ** 2)))
        row = next(line for line in table.splitlines() if line.startswith("| RMSE while localized"))
        assert row.split("|")[2].strip() == (f"{rmse:.2f}" if rmse < 100 else f"{rmse:.0f}")


@pytest.mark.parametrize("command", ["demo", "view"])
def test_no_record_reaches_the_viewer(command, monkeypatch):
    from helpers import viewer_options

    assert viewer_options(command, [], monkeypatch)["record"] is True
    assert viewer_options(command, ["--no-record"], monkeypatch)["record"] is False


def test_a_viewer_that_does_not_record_says_so_on_branch(viewer):
    """Served without a recording (``--no-record``): Branch from here is refused in one line that
    says why, not "nothing recorded yet"."""
    v = viewer.viewer
    assert v.travel.recorder is None
    v.step_once()
    wait_for(lambda: v.localizer.k >= 1, what="a scan played")
    with pytest.raises(LidarlocError, match="does not record"):
        v.travel.branch_from_here()
