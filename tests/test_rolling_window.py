"""A viewer's run that reaches the recording budget keeps recording a rolling window of its newest
steps: the filter never stops, the run's files stay within the budget, the user is told once,
the timeline's lower end follows the window, the newest step reads back as it was live, the
folder opens as the window after the run (``view --run``, ``runs list``), and a kept step still
branches while a dropped one says why not."""

from __future__ import annotations

import json
import time
from types import SimpleNamespace

import numpy as np
import pytest
from helpers import MAPPING_SCANS
from lidarloc.core.config import Config
from lidarloc.core.errors import LidarlocError
from lidarloc.core.runs import recording
from lidarloc.core.sequences.factory import SourceSpec, open_sequence

SCANS = 60
STEPS = 40
# bytes: the short town's run without S2M takes ~16 kB a step (300 particles), so it reaches the
# budget after ~25 steps and keeps a window of a dozen steps or more
BUDGET = 800e3


def run_bytes(run_dir) -> int:
    return sum(f.stat().st_size for f in run_dir.rglob("*") if f.is_file())


@pytest.fixture(scope="module")
def rolled(cache_root, tmp_path_factory):
    """The short town played in a paused viewer under a 400 kB budget, one step at a time on
    this thread (as the player hands a step over: recorded, shown, the timeline synced), with
    what the viewer showed along the way; the viewer is stopped (the run is over) at the end."""
    from lidarloc.app.viewer.recorder import SEGMENT_SHARE, Budget
    from lidarloc.app.viewer.serve import serve
    from lidarloc.core.localizer import Localizer

    cfg = Config()
    cfg.town.n_scans = MAPPING_SCANS
    cfg.pf.n_particles = 300
    cfg.s2m.enabled = False  # the filter alone: a tenth of a second a step (S2M in segments: test_recording)
    spec = SourceSpec(scans=SCANS)
    seq = open_sequence(spec, cfg)
    loc = Localizer(seq, cfg, cache_root)
    root = tmp_path_factory.mktemp("rolling")
    t0 = time.perf_counter()
    handle = serve(
        loc,
        port=0,
        autoplay=False,
        record_to=root / "viewer",
        spec=spec,
        cache_root=cache_root,
        budget=Budget(root, None, BUDGET),
    )
    out = SimpleNamespace(seq=seq, spec=spec, root=root, segment=BUDGET * SEGMENT_SHARE, trace=[], snaps=[])
    try:
        v = handle.viewer
        rec, tl = v.travel.recorder, v.travel.timeline
        out.notices, shown = [], rec._on_notice
        rec._on_notice = lambda message: (out.notices.append(message), shown(message))
        for _ in range(STEPS):
            snap = loc.step()
            v._on_step(snap)  # the player's hand-over: recorded, then shown
            out.snaps.append(snap)
            recording_on = rec.writer is not None
            rec.flush()  # the step's bytes on disk, a dropped segment's files removed
            v.update_display()  # the timeline follows the recording
            out.trace.append(
                {
                    "recording": recording_on,
                    "n": rec.n,
                    "first": rec.first_kept,
                    "bytes": run_bytes(rec.run_dir),
                    "slider": (tl.slider.min, tl.slider.max),
                    "timeline": (tl.first, tl.n),
                }
            )
        out.run_dir, out.steps, out.message = rec.run_dir, loc.steps, v.message
        first = rec.first_kept
        # while live: the newest step read back, and the timeline scrubbed below the window
        out.newest = rec.run.snapshot(rec.n - 1)
        out.went = tl.go(0)
        v.update_display()
        out.drawn = v.drawn.scan_index
        out.where = tl.where.content
        with pytest.raises(LidarlocError) as back:
            tl.back()
        out.back = str(back.value)
        with pytest.raises(recording.RecordingError) as dropped:
            rec.run.snapshot(first - 1)
        out.dropped = str(dropped.value)
        tl.live()
    finally:
        handle.stop()
        loc.close()
    out.seconds = time.perf_counter() - t0
    return out


def test_the_filter_plays_on_and_the_recording_keeps_its_newest_steps_within_the_budget(rolled):
    trace = rolled.trace
    assert rolled.steps == STEPS and all(t["recording"] for t in trace)  # never stopped
    assert [t["n"] for t in trace] == list(range(1, STEPS + 1))  # every step recorded
    worst = max(t["bytes"] for t in trace)
    assert worst <= BUDGET + rolled.segment, f"{worst} bytes on disk, the budget {BUDGET:.0f} + a segment"
    firsts = [t["first"] for t in trace]
    assert firsts == sorted(firsts) and firsts[0] == 0 and len(set(firsts)) >= 3  # the window moved on
    # the window holds at least half the budget's worth of the newest steps
    assert trace[-1]["bytes"] >= BUDGET / 2
    rolling = [m for m in rolled.notices if "rolling window" in m]
    assert len(rolling) == 1 and len(rolled.notices) == 1, rolled.notices
    start = firsts[next(i for i, f in enumerate(firsts) if f > 0)]
    assert "reached the budget (800 kB)" in rolling[0] and f"from step {start}" in rolling[0]
    assert "rolling window" in rolled.message  # the page's message line
    assert rolled.seconds < 60


def test_the_timeline_covers_the_window_and_says_the_rest_was_dropped(rolled):
    for t in rolled.trace:
        n, first = t["n"], t["first"]
        assert t["timeline"] == (first, n) and t["slider"] == (first, max(n - 1, first + 1))
    first = rolled.trace[-1]["first"]
    # scrubbing to step 0 lands on the window's first step, drawn from the recording
    assert rolled.went == first and rolled.drawn == first
    assert f"step {first} of {first}…{STEPS - 1}" in rolled.where and "dropped by the recording budget" in rolled.where
    assert "dropped by the recording budget" in rolled.back
    assert f"step {first - 1} was dropped by the recording budget" in rolled.dropped


def test_the_newest_step_reads_back_as_it_was_live(rolled):
    live, back = rolled.snaps[-1], rolled.newest
    assert back.scan_index == live.scan_index == STEPS - 1
    np.testing.assert_array_equal(back.mean_pose, live.mean_pose)
    np.testing.assert_array_equal(back.particles, live.particles.astype(np.float32))
    np.testing.assert_allclose(back.weights, live.weights, atol=1e-6)
    np.testing.assert_array_equal(back.scan_world, live.scan_world)  # recomputed from the source
    assert back.n_eff == live.n_eff and back.localized == live.localized
    assert list(back.events) == list(live.events)[len(live.events) - len(back.events) :]


def test_the_folder_opens_as_the_window_after_the_run(rolled, cache_root):
    from lidarloc.app.cli.groups import app
    from lidarloc.app.viewer.runs import open_runs
    from typer.testing import CliRunner

    first = rolled.trace[-1]["first"]
    rec = recording.open(rolled.run_dir)
    assert (rec.first_step, rec.dropped, rec.n) == (first, first, STEPS - first)
    np.testing.assert_array_equal(rec.scan_index, np.arange(first, STEPS))
    for i in range(rec.n):
        np.testing.assert_array_equal(rec.mean_pose[i], rolled.snaps[first + i].mean_pose)
    assert rec.meta["closed"] and rec.summary is not None
    # view --run: the timeline opens at the window's first step and goes no lower
    handle = open_runs([rolled.run_dir], port=0, cache_root=cache_root)
    try:
        tl = handle.viewer.travel.timeline
        assert tl.step == first and tl.first == first and tl.slider.min == first and tl.n == STEPS
        with pytest.raises(LidarlocError, match="dropped by the recording budget"):
            tl.back()
        assert tl.go(3) == first and tl.forward() == first + 1
    finally:
        handle.stop()
    cli = CliRunner()
    listed = cli.invoke(app, ["runs", "list", "--dir", str(rolled.root)])
    assert listed.exit_code == 0, listed.output
    assert f"{STEPS - first} steps" in listed.output and f"(rolling window: steps {first}–{STEPS - 1})" in listed.output
    data = json.loads(cli.invoke(app, ["runs", "list", "--dir", str(rolled.root), "--json"]).output)
    assert [r["window"] for r in data["runs"]] == [[first, STEPS - 1]]


def test_a_kept_step_branches_and_a_dropped_one_says_why(rolled, cache_root):
    """Each segment starts with a checkpoint: a step two after the window's first is restored
    from it and replayed, and the branch's next step is the recorded one, bit for bit."""
    from lidarloc.core.runs.branch import open_branch

    first = rolled.trace[-1]["first"]
    kept = recording.segments.continuation_folders(rolled.run_dir / "recording")
    # a segment opens as soon as the one before is full: if the run ended right there, the last
    # one holds no step (readers skip it), and so no checkpoint either
    holding = [folder for folder in kept if (folder / recording.segments.STEPS).stat().st_size > 0]
    assert holding == kept[: len(holding)] and len(kept) - len(holding) <= 1
    assert len(holding) >= 3 and holding[0].name == f"{first:09d}"
    assert all((folder / "resume" / "000000-checkpoint.npz").is_file() for folder in holding)
    with pytest.raises(LidarlocError, match=f"step {first - 1} was dropped by the recording budget"):
        open_branch(rolled.run_dir, first - 1, seq=rolled.seq, cache_root=cache_root)
    at = first + 2
    loc = open_branch(rolled.run_dir, at, seq=rolled.seq, cache_root=cache_root)
    try:
        assert loc.branch_of["step"] == at
        np.testing.assert_array_equal(loc.snapshot().mean_pose, rolled.snaps[at].mean_pose)
        snap = loc.step()
        assert snap.scan_index == at + 1
        np.testing.assert_array_equal(snap.mean_pose, rolled.snaps[at + 1].mean_pose)
        np.testing.assert_array_equal(snap.particles, rolled.snaps[at + 1].particles)
    finally:
        loc.close()


def test_a_part_dropped_while_it_is_opened_counts_as_gone_not_as_a_failure(recorded_town_run, tmp_path, monkeypatch):
    """The recorder drops a rolling window's oldest part while the display opens the recording: a
    field file that was there when looked for and gone when read (here: ``done.bin``) leaves its
    part with no step, and the recording opens (before, the display failed with
    FileNotFoundError and said so in the page's message line)."""
    import shutil
    from pathlib import Path

    run_dir, _ = recorded_town_run
    copy = tmp_path / "run"
    shutil.copytree(run_dir / "recording", copy / "recording")
    assert recording.open(copy).n == 14
    real_stat, real_is_file = Path.stat, Path.is_file

    def stat(self, *args, **kwargs):
        if self.name == "done.bin":
            raise FileNotFoundError(2, "No such file or directory", str(self))
        return real_stat(self, *args, **kwargs)

    monkeypatch.setattr(Path, "stat", stat)
    monkeypatch.setattr(Path, "is_file", lambda self: True if self.name == "done.bin" else real_is_file(self))
    assert recording.open(copy).n == 0
