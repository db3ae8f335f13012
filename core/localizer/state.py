"""What a localizer hands over to be resumed at any step, and putting it back into that state.

After each step a recording asks :meth:`StateMixin.resume_payload` for the per-step odometry
fields, the S2M outcome that landed (:mod:`lidarloc.core.matching.outcome_io`) and, every
:data:`CHECKPOINT_EVERY` steps and after any control, a :meth:`StateMixin.checkpoint` of the
exact state; :meth:`StateMixin.restore` puts a fresh localizer (same source, same configuration)
back into it. The files are described in :mod:`lidarloc.core.runs.resume`.

A localizer built to resume (:mod:`lidarloc.core.runs.branch`) is given ``known_odometry``, which
makes the odometry use a recorded run's poses instead of registering those scans again, and
``lazy_s2m``, which starts the S2M matcher only when a match needs it (a resumed run replays
recorded matches first).
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np

from ..config import Config, update_from_dict
from ..errors import LidarlocError
from ..matching.outcome_io import outcome_arrays

#: Steps between two checkpoints: a branch replays at most this many − 1 steps.
CHECKPOINT_EVERY = 10


@dataclasses.dataclass
class ResumePayload:
    """What a localizer adds to a step's record for resuming from it: ``per_step`` arrays (one
    fixed shape per name, appended as fields) and ``files`` (each saved as ``resume/STEP-NAME.npz``)."""

    per_step: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)
    files: dict[str, dict[str, np.ndarray]] = dataclasses.field(default_factory=dict)


class StateMixin:
    """Checkpoints and resume payloads. A part of :class:`~lidarloc.core.localizer.Localizer`."""

    def resume_payload(self, step: int) -> ResumePayload:
        """The resume payload of the step just made, the ``step``-th row of its recording (the
        module docstring). Call it before the next control."""
        with self._lock:
            k = int(self.snapshot().scan_index)
            per_step = self.odometry.pose_record(k)
            files: dict[str, dict[str, np.ndarray]] = {}
            landing = getattr(self.s2m, "last_landing", None)
            landed_here = landing is not None and landing[0] == k
            per_step["s2m_landed_started"] = np.int64(landing[1].started_at if landed_here else -1)
            if landed_here:
                files["s2m_outcome"] = outcome_arrays(landing[1], landing[2])
            if step % CHECKPOINT_EVERY == 0 or self._controls_checkpointed != self.controls:
                files["checkpoint"] = self.checkpoint()
                self._controls_checkpointed = self.controls
            return ResumePayload(per_step=per_step, files=files)

    def checkpoint(self) -> dict[str, np.ndarray]:
        """The localizer's exact state between two scans, as arrays: the filter's (particles,
        log-weights and log-likelihoods in float64, its random generator, KLD, dynamic points),
        the rules', the checks', the scan counters, the odometry buffer, the S2M scheduling (the
        match in flight) and the live configuration. :meth:`restore` continues bit for bit."""
        with self._lock:
            s2m_state, s2m_arrays = self.s2m.checkpoint()
            s2m_state["pending"] = bool(self.s2m_pending) or bool(s2m_state["pending"])
            state = {
                "k": self.k,
                "steps": self.steps,
                "prev_t": self._prev_t,
                "n_events": len(self.events) - self.recorded_events_base,
                "rules": self.rules.state(),
                "integrity": self.integrity.state(),
                "alarm_on": bool(self._alarm_on),
                "confidence_armed": self._confidence.armed,
                "frame_best_share": float(self._frame_check.best_share),
                "s2m": s2m_state,
                "config": self.cfg.to_dict(),
            }
            out = {"state": np.array(json.dumps(state)), **s2m_arrays}
            out.update({f"pf_{k}": v for k, v in self.pf.checkpoint().items()})
            out.update({f"odometry_{k}": v for k, v in self.odometry.checkpoint().items()})
            return out

    def restore(self, data: dict[str, np.ndarray]) -> dict:
        """Put this localizer (built on the same source with the checkpoint's configuration, no
        step made yet) into the state of a :meth:`checkpoint`. Events, per-scan records and the
        snapshot are the caller's (they live in the recording). Returns the checkpoint's JSON state."""
        state = checkpoint_state(data)
        with self._lock:
            self.pf.restore({k[3:]: v for k, v in data.items() if k.startswith("pf_")})
            self.odometry.restore({k[9:]: v for k, v in data.items() if k.startswith("odometry_")})
            self.rules.load(state["rules"])
            self._confidence.armed = bool(state["confidence_armed"])
            self._frame_check.best_share = float(state["frame_best_share"])
            self.integrity.load(state.get("integrity", {}))  # absent in recordings made before the checks
            self._alarm_on = bool(state.get("alarm_on", False))
            self.k, self.steps, self._prev_t = int(state["k"]), int(state["steps"]), state["prev_t"]
            self.odometry.catch_up(self.k, self.seq.scan, self.seq.timestamp)
            self.s2m.restore(state["s2m"], data, self._odometry_scan)
            self._controls_checkpointed = self.controls
        return state


def checkpoint_state(data: dict[str, np.ndarray]) -> dict:
    """The JSON part of a checkpoint file."""
    try:
        return json.loads(str(data["state"]))
    except (KeyError, ValueError) as exc:
        raise LidarlocError(f"no readable state: {exc}") from None


def checkpoint_config(data: dict[str, np.ndarray]) -> Config:
    """The live configuration the localizer had at a checkpoint."""
    return update_from_dict(Config(), checkpoint_state(data)["config"])
