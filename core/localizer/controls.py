"""What a user does to a running localizer between scans: reset the particles, kidnap the vehicle,
move the estimate unannounced, and change a live parameter — validated once by
:func:`~lidarloc.core.config.check_live_changes`, applied through the reaction
:data:`~lidarloc.core.config.LIVE_PARAMS` names for it (:data:`REACTIONS`).

Kidnap (viewer feature): the data index jumps ahead without telling the filter. The RPE's
KISS-ICP cannot register across a jump, so it is restarted at the new scan (a real system would
detect the failed registration the same way); the filter itself learns nothing.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..config import LIVE_PARAMS, check_live_changes
from ..errors import LidarlocError


class ControlsMixin:
    """The user's controls (see the module docstring). A part of :class:`~lidarloc.core.localizer.Localizer`."""

    def reset(self, pose: np.ndarray | None = None, region: tuple | None = None) -> None:
        """Re-initialise the particles: globally, around a 4×4 pose, or inside (x0, y0, x1, y1)."""
        with self._lock:
            if region is not None:
                x0, y0, x1, y1 = region
                region = (min(x0, x1), min(y0, y1), max(x0, x1), max(y0, y1))
                if region[2] - region[0] <= 0 or region[3] - region[1] <= 0:
                    raise LidarlocError("reset region must have a positive width and height")
            self._reinitialize(region=region, pose=pose, why="particles reset")
            self.rules.reset()
            self.integrity.reset()
            self.controls += 1
            where = (
                "globally"
                if pose is None and region is None
                else ("around a pose" if pose is not None else f"in {tuple(round(v, 1) for v in region)}")
            )
            self._event(self.k - 1, "reset", f"particles re-initialised {where}")
            # A paused viewer shows the new particles at once; the last scan stays as it was.
            prev = self._snapshot
            fresh = self._make_snapshot(prev.scan_index, None, prev.pf_ms, None)
            self._snapshot = replace(fresh, scan_world=prev.scan_world)

    def kidnap(self, skip: int = 100) -> int:
        """Jump the vehicle ``skip`` scans ahead without telling the filter; returns the new index."""
        with self._lock:
            if skip < 1:
                raise LidarlocError("kidnap skip must be ≥ 1 scan")
            if self.k + 1 >= self.n_scans:
                raise LidarlocError("cannot kidnap: the sequence has no scans left")
            target = min(self.k + skip, self.n_scans - 1)
            self.controls += 1
            self.s2m.cancel(self.k - 1, "kidnap")
            self._event(self.k - 1, "kidnap", f"vehicle moved from scan {self.k} to {target}")
            self.k = target
            self.odometry.restart(origin=target)
            self._prev_t = None
            self.rules.reset()  # the odometry restarts: a window must not span the jump
            self.integrity.reset()
            self._refresh_snapshot()
            return target

    def move_estimate(self, dx: float, dy: float) -> None:
        """Move every particle by (dx, dy) metres without telling the filter: a wrong estimate
        that nobody announced (what a wrongly accepted match or a long stretch without features
        leaves behind), to test that the filter notices (``lidarloc bench integrity``). The S2M
        match in flight is dropped (its pose would put the filter right at once); the rules and
        the second opinion are not told."""
        with self._lock:
            self.controls += 1
            self.s2m.cancel(self.k - 1, "particles moved")
            self.pf.states[:, 0] += float(dx)
            self.pf.states[:, 1] += float(dy)
            self._event(
                self.k - 1, "kidnap", f"particles moved {float(np.hypot(dx, dy)):.0f} m; the filter was not told"
            )
            self._refresh_snapshot()

    def set_params(self, **params) -> None:
        """Live parameter changes (:data:`~lidarloc.core.config.LIVE_PARAMS`, SI units), validated
        all together, once (:func:`~lidarloc.core.config.check_live_changes`), stored in the
        configuration and followed by the reaction each one's ``effect`` names; effective from
        the next scan."""
        with self._lock:
            if params.get("clock") == "realtime" and self.odometry.recorded:
                raise LidarlocError("the real-time clock needs live odometry (localize.recorded_odometry is on)")
            check_live_changes(self.cfg, params)
            self.controls += 1
            for key, value in params.items():
                p = LIVE_PARAMS[key]
                section = getattr(self.cfg, p.section)
                before = getattr(section, p.attr)
                setattr(section, p.attr, p.coerce(value))
                if p.effect:
                    REACTIONS[p.effect](self, before)

    # The reactions LIVE_PARAMS names (``effect``, the keys of REACTIONS below); each gets the
    # value before the change.
    def _after_lookup(self, before: float) -> None:
        if not self.lookup.covers(self.cfg.pf.d_max):
            self._rebuild_lookup(self.cfg.pf.d_max)
        self.pf.set_d_max(self.effective_d_max)

    def _after_filter(self, before) -> None:
        self.pf.set_sigma(self.cfg.pf.sigma)
        self.pf.set_q_std(self.cfg.pf.q_std)

    def _after_particles(self, before: int) -> None:
        self.s2m.cancel(self.k - 1, "particle count changed")  # particle indices change
        self.pf.set_n_particles(self.cfg.pf.n_particles)

    def _after_s2m_switch(self, before: bool) -> None:
        if not self.cfg.s2m.enabled:
            self.s2m.cancel(self.k - 1, "S2M switched off")
            self._refresh_snapshot()

    def _after_pyramid(self, before: float) -> None:
        if abs(self.cfg.s2m.match_resolution - before) > 1e-9:
            self._rebuild_pyramid()

    def _after_clock(self, before: str) -> None:
        self.s2m.follow_clock(self.k - 1)

    def live_params(self) -> dict:
        """The current value of every live parameter (keys of ``LIVE_PARAMS``, SI units)."""
        with self._lock:
            return {key: getattr(getattr(self.cfg, p.section), p.attr) for key, p in LIVE_PARAMS.items()}


#: What the localizer does when a live parameter changes, by the ``effect`` its LIVE_PARAMS entry
#: names (a table, so that a misspelt effect fails at import, not on the first change).
REACTIONS = {
    "lookup": ControlsMixin._after_lookup,
    "filter": ControlsMixin._after_filter,
    "particles": ControlsMixin._after_particles,
    "s2m_switch": ControlsMixin._after_s2m_switch,
    "pyramid": ControlsMixin._after_pyramid,
    "clock": ControlsMixin._after_clock,
}
_unknown = {p.effect for p in LIVE_PARAMS.values() if p.effect} - REACTIONS.keys()
if _unknown:  # a programming error in LIVE_PARAMS: every effect it names needs a reaction here
    raise ImportError(f"LIVE_PARAMS names effects with no reaction: {sorted(_unknown)}")
