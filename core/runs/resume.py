"""What a recording keeps of a localizer so that it can be resumed at any recorded step, and
putting a localizer back into that state.

After each step a :class:`~lidarloc.core.runs.recording.RecordingWriter` asks
:meth:`Localizer.resume_payload <lidarloc.core.localizer.Localizer.resume_payload>` for:

- per-step fields (one row per step): the odometry poses of the step's scan and of the scan before
  it as the filter used them (T_odom←scan, float64, NaN where not registered yet), with their path
  lengths and rotation sums, the odometry run's first scan (``odom_origin``: a kidnap restarts
  it), the rules' last odometry scan (``odom_used``), and the scan an S2M match that landed in this
  step started at (``s2m_landed_started``, −1: none). About 0.3 kB per step.
- a ``checkpoint`` file every :data:`CHECKPOINT_EVERY` steps and after the first step that follows
  any control (restart, reset, kidnap, a live parameter change, tracking entry, re-initialisation):
  the filter's exact state (particles, log-weights and log-likelihoods in float64, the random
  generator's state, the protected particle, the dynamic-point history, the KLD bin count), the
  rules, the confidence and frame checks, the scan counters, the odometry buffer, the S2M
  scheduler (the match in flight, its settings and start pose; the counts) and the live
  configuration. Between a checkpoint and any later step up to the next checkpoint no control
  happened, so replaying the steps between them needs nothing but the source, the per-step
  odometry and the recorded S2M outcomes.
- an ``s2m_outcome`` file at every step where a match landed: everything the landing reads of the
  matcher's outcome, with the match's start scan, start pose, settings and ``level``. The
  road-removed scan at the match is not repeated: the step's S2M view in the recording has it.

:meth:`Localizer.restore <lidarloc.core.localizer.Localizer.restore>` puts a freshly built localizer
(same source, same configuration as the checkpoint) into a checkpoint's state;
:mod:`lidarloc.core.runs.branch` then replays the steps after it. This module reads what a
checkpoint file holds; :mod:`lidarloc.core.matching.outcome_io` reads the S2M outcomes.

Sizes per 1000 steps (``lidarloc bench branch``, the built-in town's first 1000 scans, 1000
particles): checkpoints 1.5 MB, per-step fields 0.3 MB (budget for both: 10 MB), S2M outcomes
2.4 MB (a few kB each, stored uncompressed: compressing them cost more time than it saved space). A checkpoint is small because a resampled cloud holds runs of identical particles, which
the compression folds; 1000 distinct particles would take ~0.1 MB per checkpoint, still within
the budget.
"""

from __future__ import annotations

from ..localizer.state import CHECKPOINT_EVERY, ResumePayload, checkpoint_config, checkpoint_state
from ..matching.outcome_io import recorded_outcome

__all__ = ["CHECKPOINT_EVERY", "ResumePayload", "checkpoint_config", "checkpoint_state", "recorded_outcome"]
