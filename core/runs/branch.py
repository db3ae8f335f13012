"""Branching a recorded run: a localizer in exactly the state the recorded run was in right after
one of its steps, to continue from there, with other parameters if wished.

:func:`open_branch` builds a localizer on the run's source with the configuration of the nearest
checkpoint at or before the step (:mod:`lidarloc.core.runs.resume`), puts it into that checkpoint's
state, and replays the steps between the checkpoint and the step. The replay is deterministic:

- the filter's random generator continues from the checkpoint's state, and each scan's prepared
  points come from the generator seeded with (seed, scan, 1) as in every run;
- the odometry is the recorded run's, pose for pose (no KISS-ICP runs while the recorded poses
  last);
- a scan-to-map match whose start scan, start pose (bit for bit), S2M settings and ``level`` equal
  those of a match the recorded run landed takes the recorded outcome instead of running the
  matcher: the matcher is a deterministic function of exactly these (the scan is fixed by its
  index and the source), so nothing changes but the time it takes.

So in the replay clock a branch without a change reproduces the recorded run from the step on bit
for bit (``tests/test_branch.py``). In the real-time clock the recorded run's landings and the
odometry its rules read depended on timing; the replay repeats both as recorded (the scan each
recorded match landed at, the odometry scan the rules read at each scan), so it comes back to the
recorded state, but bit-identity is only promised for the replay clock: what else timing chose
there (the de-skewing's odometry, a match cancelled before it landed) is not recorded. After the
step a real-time branch keeps its own time.

After the step the branch goes on as any run: the recorded odometry while the recorded run has it
for the scans the branch reaches, then a live KISS-ICP warmed up on the scans before
(:data:`~lidarloc.core.odometry.feed.WARMUP_SCANS`); each match reuses a recorded outcome where the rule
above allows, else runs for real.

A run the viewer kept as a rolling window of its newest steps (``--max-record-gb``, see
:mod:`lidarloc.core.runs.recording.segments`) branches from any step it kept: each of its
segments starts with a checkpoint, so the nearest one at or before the step is always there. The
branch's history (events, per-scan records, trajectory: what its plots and summary read) then
starts at the window's first step; a step that was dropped is refused with one line saying which
steps the window holds.

Overrides: ``section.key=value`` strings as ``--set`` takes them, or a dict of live parameters
(:data:`~lidarloc.core.config.LIVE_PARAMS` keys, SI units). Live ones go through
``Localizer.set_params`` (effective from the next scan, as in the viewer); the others are written
into the branch's configuration (read at each scan). What the prior map, the lookup table, the
source or the child processes were built from cannot change in a branch and is refused.
"""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..config import LIVE_PARAMS, Config, apply_overrides
from ..errors import LidarlocError
from .recording import Recording, RecordingError

#: Settings a branch cannot change: what its map, lookup table, source and processes were built from.
FIXED_SECTIONS = ("map", "town")
FIXED_KEYS = ("pf.lookup_resolution", "localize.rpe_process", "localize.s2m_process", "localize.recorded_odometry")


def open_recording(run) -> Recording:
    """``run``: a Recording, a run folder or its ``recording/`` folder."""
    from . import recording

    return run if isinstance(run, Recording) else recording.open(run)


def checkpoint_for(rec: Recording, step: int) -> int:
    """The recorded step of the nearest checkpoint at or before ``step``."""
    ckpts = [s for s in rec.resume_steps("checkpoint") if s <= step]
    if not ckpts:
        raise RecordingError(
            f"{rec.path}: no resume data at or before step {step} (recorded by a lidarloc without branching)"
        )
    return ckpts[-1]


def check_step(rec: Recording, step) -> int:
    """The row of ``rec`` that holds its step ``step`` (counted from the recording's start: the
    row itself unless a rolling window dropped the first steps)."""
    if isinstance(step, bool) or not isinstance(step, (int, np.integer)):
        raise LidarlocError(f"branch step must be a whole number, got {step!r}")
    step = int(step)
    if rec.n == 0:
        raise RecordingError(f"{rec.path}: the recording has no complete step to branch from")
    first, last = rec.dropped, rec.dropped + rec.n - 1
    if 0 <= step < first:
        raise LidarlocError(
            f"step {step} was dropped by the recording budget: this run keeps a rolling window of "
            f"steps {first}…{last}; branch from one of those"
        )
    if not first <= step <= last:
        raise LidarlocError(f"step {step} is outside the recording ({first}…{last})")
    return step - first


def open_branch(
    rec,
    step: int,
    overrides=None,
    seq=None,
    cache_root: Path | None = None,
    progress: Callable[[str, float], None] | None = None,
):
    """A :class:`~lidarloc.core.localizer.Localizer` in the state of the recorded run ``rec`` (a
    Recording or a run folder) right after its step ``step`` (0-based, counted from the
    recording's first step: its row, unless a rolling window dropped the first steps, see
    :mod:`~lidarloc.core.runs.recording.segments`), with ``overrides`` applied (module docstring). ``seq``: the run's sequence if already open (else
    rebuilt from the source the recording names; a moved source is a one-line error naming the path
    it expected). ``progress(stage, fraction)`` as for the Localizer, plus stage "replay"."""
    from ..localizer import Localizer
    from . import resume

    rec = open_recording(rec)
    asked = int(step) if isinstance(step, (int, np.integer)) and not isinstance(step, bool) else step
    step = check_step(rec, step)  # the row from here on
    c = checkpoint_for(rec, step)
    data = rec.resume_file(c, "checkpoint")
    where = rec.path / "resume" / f"{c:06d}-checkpoint.npz"
    if data is None:
        raise RecordingError(f"{where}: missing")
    try:
        cfg = resume.checkpoint_config(data).validate()
    except LidarlocError as exc:
        raise RecordingError(f"{where}: corrupt checkpoint ({exc})") from None
    live, fixed = _split_overrides(cfg, overrides)  # bad overrides fail before the long part
    if seq is None:
        seq = rec.open_sequence()
    n_source = rec.meta.get("n_source_scans")
    if n_source is not None and int(n_source) != len(seq):
        raise RecordingError(
            f"the run's source now has {len(seq)} scans, the recording {n_source}: it changed "
            f"since ({rec.meta.get('source_description', 'source')})"
        )
    loc = Localizer(seq, cfg, cache_root, progress=progress, known_odometry=recorded_odometry(rec), lazy_s2m=True)
    try:
        loc.s2m.recorded = RecordedMatches(rec, timing_until=step)
        loc.odometry.used_plan = recorded_used(rec, step)
        try:
            state = loc.restore(data)
        except (KeyError, ValueError, TypeError, IndexError) as exc:
            raise RecordingError(f"{where}: corrupt checkpoint ({type(exc).__name__}: {exc})") from None
        # the scan of the checkpoint's step only shows if no replayed step follows it
        _restore_history(loc, rec, c, state, seq if c == step else None)
        ready_at = _s2m_ready_at(loc, rec, c, state)
        scan_index = rec.scan_index
        for i in range(c + 1, step + 1):
            if progress is not None:
                progress("replay", (i - c) / max(step - c, 1))
            if loc.k != int(scan_index[i]):
                raise RecordingError(
                    f"{rec.path}: step {i} processed scan {int(scan_index[i])}, the replay is at "
                    f"scan {loc.k} (a control without a checkpoint: corrupt recording)"
                )
            if ready_at is not None and loc.k >= ready_at[0]:
                _join_s2m(loc, ready_at[1])
                ready_at = None
            loc.step()
        # the recorded run's events end here: the branch's own recording holds what follows
        loc.recorded_events_base = len(loc.events)
        if ready_at is not None:  # the branch's own time: its tables are there
            _join_s2m(loc, ready_at[1])
        _apply(loc, live, fixed)
        if loc.cfg.s2m.enabled:
            loc.s2m.start_matcher()  # sets up in the background while the branch is looked at
        loc.branch_of = {"run": str(rec.run_dir), "step": asked}
    except BaseException:
        loc.close()
        raise
    return loc


def _s2m_ready_at(loc, rec: Recording, c: int, state: dict):
    """A recorded run whose S2M was still waiting for its tables at the checkpoint (a viewer's first
    start on an empty cache, ``defer_s2m``) played without S2M until a scan its timing chose: the
    replay holds S2M back until the same scan. Returns (that scan, the waiting scheduler's real
    one), or None; the localizer's S2M is the stand-in meanwhile."""
    if not state["s2m"].get("pending"):
        return None
    from ..matching.pending import S2MNotReady

    ready = [ev.scan for s, ev in rec.events if s > c and ev.kind == "s2m_ready"]
    real, loc.s2m = loc.s2m, S2MNotReady()
    return (ready[0] if ready else float("inf")), real


def _join_s2m(loc, real) -> None:
    from ..localizer import S2M_READY_DETAIL

    loc.s2m = real
    loc._event(loc.k, "s2m_ready", S2M_READY_DETAIL)


# ---------------------------------------------------------------------------------------- overrides
def _split_overrides(cfg: Config, overrides) -> tuple[dict, dict]:
    """(live parameter changes for set_params, other {(section, attr): value} changes), validated
    on a copy of ``cfg``."""
    if not overrides:
        return {}, {}
    if isinstance(overrides, dict):
        from ..config import check_live_changes

        check_live_changes(cfg, overrides)
        return dict(overrides), {}
    items = list(overrides)
    for item in items:
        key = str(item).split("=", 1)[0].strip()
        if key.split(".")[0] in FIXED_SECTIONS or key in FIXED_KEYS:
            what = "the map would differ" if key.startswith("map.") else "it was fixed when the run was set up"
            raise LidarlocError(f"{key} cannot change in a branch ({what}); rerun with it instead")
    trial = apply_overrides(copy.deepcopy(cfg), items).validate()
    live_of = {(p.section, p.attr): key for key, p in LIVE_PARAMS.items()}
    live, fixed = {}, {}
    for section in ("pf", "s2m", "localize"):
        for f in dataclasses.fields(getattr(cfg, section)):
            old, new = getattr(getattr(cfg, section), f.name), getattr(getattr(trial, section), f.name)
            if old != new:
                if (section, f.name) in live_of:
                    live[live_of[(section, f.name)]] = new
                else:
                    fixed[(section, f.name)] = new
    if trial.seed != cfg.seed:
        fixed[(None, "seed")] = trial.seed
    if live:
        from ..config import check_live_changes

        check_live_changes(cfg, live)
    return live, fixed


def _apply(loc, live: dict, fixed: dict) -> None:
    for (section, name), value in fixed.items():
        setattr(loc.cfg if section is None else getattr(loc.cfg, section), name, value)
        if (section, name) == ("pf", "dynamic_rejection"):
            from ..filter.dynamic import DynamicPointFilter

            pf = loc.pf
            pf.dynamic = (
                DynamicPointFilter(pf.lookup, loc.cfg.pf.dynamic_distance, loc.cfg.pf.dynamic_scans) if value else None
            )
        elif section == "pf" and name in ("dynamic_distance", "dynamic_scans") and loc.pf.dynamic is not None:
            setattr(loc.pf.dynamic, name.split("_", 1)[1], value)
    if fixed:
        loc.controls += 1  # the branch's recording checkpoints the changed configuration
    if live:
        loc.set_params(**live)


# ---------------------------------------------------------------------------------------- recorded data
def recorded_odometry(rec: Recording) -> dict[int, tuple[int, np.ndarray]] | None:
    """scan → (its odometry run's first scan, T_odom←scan) of every scan the recording holds an
    odometry pose for (None: recorded without them)."""
    names = set(rec.field_names)
    if not {"odom_pose", "odom_origin", "odom_prev_pose"} <= names:
        return None
    scans, origins = rec.scan_index, rec.field("odom_origin")
    poses, prev = rec.field("odom_pose"), rec.field("odom_prev_pose")
    known: dict[int, tuple[int, np.ndarray]] = {}
    for i in range(rec.n):
        k, origin = int(scans[i]), int(origins[i])
        if k - 1 >= origin and np.all(np.isfinite(prev[i])):
            known.setdefault(k - 1, (origin, prev[i]))
        if np.all(np.isfinite(poses[i])):
            known[k] = (origin, poses[i])
    return known


def recorded_used(rec: Recording, until: int) -> dict[int, int] | None:
    """scan → the odometry scan the recorded run's rules read at it, for its steps up to ``until``
    (real time; None: not recorded)."""
    if "odom_used" not in rec.field_names:
        return None
    used = rec.field("odom_used")[: until + 1]
    return {int(k): int(u) for k, u in zip(rec.scan_index[: until + 1], used) if u >= 0}


class RecordedMatches:
    """The S2M scheduler's ``recorded``: the outcome the recorded run's matcher gave for exactly the
    match asked for (see :func:`lidarloc.core.runs.resume.recorded_outcome`), else None."""

    def __init__(self, rec: Recording, timing_until: int | None = None):
        self.rec = rec
        self.timing_until = rec.n - 1 if timing_until is None else int(timing_until)
        started = rec.field("s2m_landed_started") if "s2m_landed_started" in rec.field_names else np.zeros(0)
        self.rows = {int(s): i for i, s in enumerate(started) if s >= 0}
        self.reused = 0
        self._agreed: dict[int, int] | None = None  # match start → the scan it agreed early at

    def landing_scan(self, started_at: int) -> int | None:
        """The scan at which the replay lands the match started at ``started_at`` (real time): the
        recorded run's, if it landed in a step up to ``timing_until``; if it landed later, the
        scan after ``timing_until``'s (the recorded run had not landed it by then, and from there
        the branch keeps its own time; landing it as soon as its recorded outcome is at hand
        made the replay depend on timing). None: no recorded landing."""
        row = self.rows.get(int(started_at))
        if row is None:
            return None
        if row <= self.timing_until:
            return int(self.rec.scan_index[row])
        return int(self.rec.scan_index[self.timing_until]) + 1

    def landing_through(self, started_at: int) -> int | None:
        """The scan whose odometry carried the match started at ``started_at`` when the recorded
        run landed it before its own scan's odometry was done (real time), if the replay lands it
        where the recorded run did; None: its landing scan's own."""
        row = self.rows.get(int(started_at))
        if row is None or row > self.timing_until:
            return None
        view = self.rec.s2m(row)
        return None if view is None else view.carried_through

    def agreed_early_scan(self, started_at: int) -> int | None:
        """The scan at which the recorded run heard the match started at ``started_at`` agree with
        the estimate before it could land (an ``s2m_agrees`` event, real time), if that was in a
        step up to ``timing_until``; None: it did not."""
        if self._agreed is None:
            from ..matching.schedule import early_agreement_start

            self._agreed = {}
            for step, ev in self.rec.events:
                if ev.kind == "s2m_agrees" and 0 <= step <= self.timing_until:
                    k0 = early_agreement_start(ev.detail)
                    if k0 is not None:
                        self._agreed.setdefault(k0, int(ev.scan))
        return self._agreed.get(int(started_at))

    def __call__(self, started_at: int, start_pose, cfg, level: bool):
        from .resume import recorded_outcome

        row = self.rows.get(int(started_at))
        if row is None:
            return None
        d = self.rec.resume_file(row, "s2m_outcome")
        if d is None:
            return None
        view = self.rec.s2m(row)
        scan_world = view.scan_world if view is not None and view.landed_at == int(self.rec.scan_index[row]) else None
        outcome = recorded_outcome(d, scan_world, start_pose, cfg, level)
        if outcome is not None:
            self.reused += 1
        return outcome


def _restore_history(loc, rec: Recording, c: int, state: dict, seq) -> None:
    """The events, per-scan records, trajectory and snapshot of the recorded steps up to ``c``."""
    from dataclasses import replace

    # a rolling window holds the run's newest steps only: its history starts at the window
    events, records, trajectory = _parent_history(rec) if rec.dropped == 0 else ([], [], [])
    loc.events = events + [ev for _, ev in rec.events[: max(int(state["n_events"]) - rec.events_dropped, 0)]]
    loc.records = records + _records(rec, c)
    loc.est_trajectory = trajectory + [rec.mean_pose[i].copy() for i in range(c + 1)]
    snap = rec.snapshot(c, seq)
    loc.s2m.last = snap.s2m
    loc._snapshot = replace(
        snap,
        particles=loc.pf.states.copy(),
        weights=loc.pf.weights.copy(),
        log_weights=loc.pf.log_weights.copy(),
        events=tuple(loc.events[-50:]),
        s2m_running=loc.s2m.job is not None,
        n_scans=loc.n_scans,
        done=loc.done,
    )


def _parent_history(rec: Recording, depth: int = 0) -> tuple[list, list, list]:
    """A branch's recording holds its own steps only: the events, per-scan records and trajectory
    of the run it branched from, up to the step it branched at (recursively; empty where that run
    is gone or ``rec`` is no branch)."""
    from . import recording

    parent = rec.meta.get("branch_of")
    if not parent or depth > 50:
        return [], [], []
    try:
        prec = recording.open(parent["run"])
        step = min(int(parent["step"]) - prec.dropped, prec.n - 1)  # its row
    except (LidarlocError, KeyError, TypeError, ValueError, OSError):
        return [], [], []
    if step < 0:  # the branch point was dropped from the original's rolling window since
        return [], [], []
    events, records, trajectory = _parent_history(prec, depth + 1) if prec.dropped == 0 else ([], [], [])
    events += [ev for s, ev in prec.events if s <= step]
    records += _records(prec, step)
    trajectory += [prec.mean_pose[i].copy() for i in range(step + 1)]
    return events, records, trajectory


def _opt(v) -> float | None:
    return None if not np.isfinite(v) else float(v)


def _records(rec: Recording, upto: int) -> list:
    """The per-scan records (:class:`~lidarloc.core.snapshot.ScanRecord`) of steps 0…``upto``."""
    from ..snapshot import ScanRecord, Snapshot

    names = (
        "scan_index",
        "timestamp",
        "best_index",
        "mean_pose",
        "cov_xyz",
        "std_xyz",
        "ellipse_xy",
        "n_eff",
        "localized",
        "localized_since",
        "gt_pose",
        "error_m",
        "pf_ms",
        "n_particles",
        "converged",
        "inlier_share",
        "mean_residual_m",
        "inside_2sigma",
        "s2m_ms",
        "reinit",
    )
    f = {name: rec.field(name) for name in names}
    out = []
    for i in range(upto + 1):
        gt, inside, since = f["gt_pose"][i], int(f["inside_2sigma"][i]), int(f["localized_since"][i])
        snap = Snapshot(
            scan_index=int(f["scan_index"][i]),
            n_scans=0,
            timestamp=float(f["timestamp"][i]),
            particles=np.zeros((0, 11)),
            weights=np.zeros(0),
            best_index=int(f["best_index"][i]),
            mean_pose=f["mean_pose"][i],
            cov_xyz=f["cov_xyz"][i],
            std_xyz=f["std_xyz"][i],
            ellipse_xy=tuple(f["ellipse_xy"][i]),
            n_eff=float(f["n_eff"][i]),
            localized=bool(f["localized"][i]),
            localized_since=None if since < 0 else since,
            scan_world=np.zeros((0, 3), np.float32),
            gt_pose=gt if np.all(np.isfinite(gt)) else None,
            error_m=_opt(f["error_m"][i]),
            pf_ms=float(f["pf_ms"][i]),
            s2m=None,
            s2m_running=False,
            s2m_acceptance=0.0,
            n_particles=int(f["n_particles"][i]),
            converged=bool(f["converged"][i]),
            inlier_share=_opt(f["inlier_share"][i]),
            mean_residual_m=_opt(f["mean_residual_m"][i]),
            inside_2sigma=None if inside < 0 else bool(inside),
        )
        out.append(ScanRecord.from_snapshot(snap, _opt(f["s2m_ms"][i]), bool(f["reinit"][i])))
    return out


def continue_recording(writer, loc) -> None:
    """Make a branch's :class:`~lidarloc.core.runs.recording.RecordingWriter` start after the state
    ``loc`` was branched in: the events up to ``loc.recorded_events_base``, the last scan and the
    last S2M view it already has are the recorded run's, not the branch's."""
    writer.continue_from(loc)
