"""What the localizer reports after each scan: the snapshot the viewer and the writers read, the
events, the scan's fit to the map at the estimate, the frame checks and the truth's grade.

Confidence: after each scan the localizer measures how well the scan fits the map at the
estimate (the share of prepared scan points within d_max of the map and their mean distance,
:func:`~lidarloc.core.filter.likelihood.residual_stats`, one pose: well under a millisecond) and, with
the particles' spread and N_eff, reports it in the snapshot and the per-scan record (see
:mod:`lidarloc.core.snapshot`). A ``confidence_low`` event marks the scan at which, while
localized, the inlier share drops below ``localize.min_inlier_share``; it fires once and is
re-armed when the share recovers or localization ends.
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from ..geometry import transform_points
from ..rules.checks import truth_outside_map
from ..rules.truth import inside_2sigma, truth_alarm
from ..snapshot import Event, Snapshot


class OutputsMixin:
    """Snapshots, events and the per-scan checks (see the module docstring). A part of :class:`~lidarloc.core.localizer.Localizer`."""

    def snapshot(self) -> Snapshot:
        return self._snapshot

    def waiting(self) -> tuple[str, float] | None:
        """While a step waits for a block: what it waits for and for how many seconds so far
        (e.g. ("the S2M match started at scan 412", 4.2)); None otherwise. Lock-free: a viewer
        asks while the step holds the lock."""
        w = self._waiting
        return None if w is None else (w[0], time.monotonic() - w[1])

    def _refresh_snapshot(self) -> None:
        """A control changed the state between scans (kidnap, S2M off): the snapshot says so at
        once — a paused viewer shows it without waiting for the next scan."""
        status, status_detail = self.s2m_status()
        self._snapshot = replace(
            self._snapshot,
            events=tuple(self.events[-50:]),
            localized=self.rules.localized,
            localized_since=self.rules.localized_since,
            s2m_running=self.s2m.job is not None,
            s2m_pending=self.s2m_pending,
            s2m_status=status,
            s2m_status_detail=status_detail,
            awaiting_confirmation=False,
            truth_alarm=truth_alarm(self.rules.localized, self._snapshot.error_m),
        )

    def _event(self, k: int, kind: str, detail: str = "") -> None:
        self.events.append(Event(int(k), kind, detail))

    def _check_truth_frame(self) -> None:
        why = truth_outside_map(self.seq, self._bounds, self.prior_map.origin, self.cfg.pf.d_max)
        if why is not None:
            self._event(-1, "frame_mismatch", why)

    def _check_scan_frame(self, k: int, est, prepared: np.ndarray) -> None:
        """The scan-side frame check (:class:`~lidarloc.core.rules.checks.ScanFrameCheck`): the inlier
        share at the highest-weight particle."""
        if not self._frame_check.wanted(self.steps):
            return
        from ..filter.likelihood import residual_stats

        share, _ = residual_stats(self.pf.states[est.best_index][:6], prepared, self.lookup, self.effective_d_max)
        why = self._frame_check.update(self.steps, self.n_scans, share, self.effective_d_max)
        if why is not None:
            self._event(k, "frame_mismatch", why)

    def _scan_fit(self, k: int, est, prepared: np.ndarray) -> tuple[float, float | None]:
        """How well the scan fits the map at the estimate: (inlier share, mean residual m), see
        :func:`~lidarloc.core.filter.likelihood.residual_stats`; a ``confidence_low`` event when it
        drops (:class:`~lidarloc.core.rules.checks.ConfidenceWatch`)."""
        from ..filter.likelihood import residual_stats

        share, residual = residual_stats(est.state[:6], prepared, self.lookup, self.effective_d_max)
        share, residual = float(share), (float(residual) if np.isfinite(residual) else None)  # None: no inlier
        why = self._confidence.update(self.rules.localized, share, residual, self.cfg.localize.min_inlier_share)
        if why is not None:
            self._event(k, "confidence_low", why)
        return share, residual

    def _make_snapshot(
        self,
        k: int,
        prepared,
        pf_ms: float,
        est,
        n_weighed: int | None = None,
        fit: tuple[float, float | None] | None = None,
    ) -> Snapshot:
        """The snapshot after scan k (-1: none yet). ``n_weighed``: the particles the estimate
        ``est`` was computed from; ``fit``: :meth:`_scan_fit`'s (inlier share, mean residual)."""
        if est is None:
            est = self.pf.estimate()
            n_weighed = self.pf.n
        mean_T = est.pose
        gt = self.seq.pose(k) if k >= 0 and self.seq.has_poses else None
        err = None if gt is None else float(np.linalg.norm(mean_T[:3, 3] - gt[:3, 3]))
        inside = None if gt is None else inside_2sigma(mean_T[:2, 3] - gt[:2, 3], est.cov_xyz[:2, :2])
        share, residual = (None, None) if fit is None else fit
        status, status_detail = self.s2m_status(max(k, 0))
        scan_world = (
            np.zeros((0, 3), np.float32) if prepared is None else transform_points(mean_T, prepared).astype(np.float32)
        )
        return Snapshot(
            scan_index=k,
            n_scans=self.n_scans,
            timestamp=self.seq.timestamp(k) if k >= 0 else 0.0,
            particles=self.pf.states.copy(),
            weights=self.pf.weights.copy(),
            log_weights=self.pf.log_weights.copy(),
            best_index=int(est.best_index),
            mean_pose=mean_T,
            cov_xyz=est.cov_xyz,
            std_xyz=est.std_xyz,
            ellipse_xy=tuple(est.ellipse_xy),
            n_eff=float(est.n_eff),
            localized=self.rules.localized,
            localized_since=self.rules.localized_since,
            scan_world=scan_world,
            gt_pose=gt,
            error_m=err,
            pf_ms=pf_ms,
            rpe_ms=self.odometry.last_ms,
            s2m=self.s2m.last,
            s2m_running=self.s2m.job is not None,
            s2m_acceptance=self.s2m.acceptance,
            s2m_pending=self.s2m_pending,
            n_particles=int(n_weighed if n_weighed is not None else len(self.pf.states)),
            converged=bool(np.all(est.std_xyz < self.cfg.localize.std_threshold)),
            inlier_share=share,
            mean_residual_m=residual,
            inside_2sigma=inside,
            events=tuple(self.events[-50:]),
            done=self.k >= self.n_scans,
            s2m_status=status,
            s2m_status_detail=status_detail,
            awaiting_confirmation=bool(self.rules.awaiting_confirmation and not self.rules.localized),
            confirmed_at=self.integrity.confirmed_at,
            truth_alarm=truth_alarm(self.rules.localized, err),
        )

    def _truth_check(self, k: int, est) -> None:
        """A ``false_fire`` event when the rule says localized while the truth is farther than
        the metrics' 5 m (at the onset, or later while still localized): truth grades the filter,
        it never steers it."""
        if not self.seq.has_poses:
            return
        err = float(np.linalg.norm(est.pose[:3, 3] - self.seq.pose(k)[:3, 3]))
        alarm = truth_alarm(self.rules.localized, err)
        if alarm is not None and not self._alarm_on:
            onset = self.rules.localized_since == k
            self._event(
                k, "false_fire", alarm + ("" if onset else f" (localized since scan {self.rules.localized_since})")
            )
        self._alarm_on = alarm is not None
