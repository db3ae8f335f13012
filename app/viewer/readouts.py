"""The panel's read-outs: the progress bar (while the localizer is built, and while a table is
rebuilt in the background), the status table with the scan's confidence and the recent events,
and the plots (:mod:`~lidarloc.app.viewer.plots`)."""

from __future__ import annotations

import time

import numpy as np

from ...core.snapshot import Snapshot

from .history import History
from .legend import legend_markdown
from .panel import Controls
from .style import COLLAPSED_N_EFF_SHARE, PLOT_INTERVAL, REALTIME_LATE_S, error_markdown, shorten

BUILD_STAGES = {"starting": "Starting the localizer", "map": "Building the prior map",
                "lookup": "Building the distance lookup table", "pyramid": "Building the BEV pyramid",
                "ready": "Ready"}


def status_markdown(snap: Snapshot, state: str, clock: str, speed: str, events: list,
                    min_inlier_share: float | None = None, *, s2m_enabled: bool = True,
                    rate: float | None = None, lag_s: float | None = None, next_scan: int | None = None) -> str:
    """The status table: scan counter, play state, localized or not, the filter's figures, the
    scan's confidence and the recent events (newest first). ``speed`` is the replay speed set
    (scans/s; None: not shown); a ``state`` "recorded…" (a scan the timeline shows) names no
    clock; ``rate`` the scans/s achieved lately and ``lag_s`` how far behind the sensor clock
    the filter is (real-time clock), both while playing (None: not shown). ``next_scan``: the
    scan the localizer processes next, named when it is not the one after ``snap`` (the vehicle
    was kidnapped). ``min_inlier_share`` (``localize.min_inlier_share``): while localized with
    fewer of the scan's points fitting the map than this, a warning line says so (the
    ``confidence_low`` condition). ``s2m_enabled``: with S2M off its row says so instead of the
    last match's figures."""
    speed = "" if clock == "realtime" or speed is None else f", set to {speed} scans/s"
    k = "–" if snap.scan_index < 0 else str(snap.scan_index)
    clocked = "" if state.startswith("recorded") else f" ({clock}{speed})"
    lines = [f"**Scan {k} of {snap.n_scans}** · {state}{clocked}"]
    if rate is not None:
        achieved = f"achieved {rate:.1f} scans/s"
        if lag_s is not None:
            achieved += f" · {1000 * lag_s:.0f} ms behind the sensor clock"
        lines.append(achieved)
        if lag_s is not None and lag_s > REALTIME_LATE_S:
            lines.append(error_markdown(f"⚠ falling behind the sensor: {lag_s:.2f} s late"))
    finished = state == "finished" or snap.done
    if next_scan is not None and not finished and next_scan != snap.scan_index + 1:
        lines.append(f"next scan: {next_scan} (the vehicle was moved; the filter was not told)")
    if snap.localized:
        since = "" if snap.localized_since is None else f" since scan {snap.localized_since}"
        lines.append(f"<span style='color:#5be35b'>**localized**{since}</span>")
    else:
        lines.append("<span style='color:#ffb347'>**not localized**</span>")
    share = snap.inlier_share
    if snap.localized and share is not None and min_inlier_share is not None and share < min_inlier_share:
        lines.append(error_markdown(f"⚠ low confidence: {100 * share:.0f}% of the scan fits the map "
                                    f"(below {100 * min_inlier_share:.0f}%)"))
    std = np.asarray(snap.std_xyz, float)
    P = np.asarray(snap.particles)
    spread = P[:, :2].std(axis=0) if len(P) > 1 else np.zeros(2)
    err = "–" if snap.error_m is None else f"{snap.error_m:.2f} m"
    n = snap.n_particles if snap.n_particles else len(snap.weights)
    n_eff = f"{100 * snap.n_eff_share:.1f}% ({snap.n_eff:.0f} of {n})"
    if snap.scan_index >= 0 and snap.n_eff_share < COLLAPSED_N_EFF_SHARE:
        n_eff += " · collapsed: see Legend"
    fit = "–" if share is None else f"{100 * share:.0f}%" + (
        "" if snap.mean_residual_m is None else f" · mean residual {snap.mean_residual_m:.2f} m")
    if not s2m_enabled:
        s2m = "off"
    elif snap.s2m_pending:
        s2m = "starting: the road-removed map and BEV pyramid are being built in the background"
    else:
        s2m_ms = "–" if snap.s2m is None else f"{snap.s2m.ms:.0f} ms"
        running = " · running" if snap.s2m_running and not finished else ""
        s2m = f"{s2m_ms} · {100 * snap.s2m_acceptance:.0f}% accepted{running}"
    rpe = "–" if snap.rpe_ms is None else f"{snap.rpe_ms:.1f} ms/scan"
    lines += [
        "",
        "| | |",
        "|---|---|",
        f"| position std x/y/z (weighted) | {std[0]:.2f} / {std[1]:.2f} / {std[2]:.2f} m |",
        f"| particle cloud spread x/y | {spread[0]:.2f} / {spread[1]:.2f} m |",
        f"| converged | {'yes' if snap.converged else 'no'} |",
        f"| error to truth | {err} |",
        f"| N_eff share | {n_eff} |",
        f"| inlier share | {fit} |",
        f"| PF | {snap.pf_ms:.1f} ms/scan |",
        f"| RPE | {rpe} |",
        f"| S2M | {s2m} |",
    ]
    if events:
        lines += ["", "**Recent events**"]
        lines += [f"- {e.scan}: {e.kind.replace('_', ' ')}" + (f" — {shorten(e.detail, 60)}" if e.detail else "")
                  for e in reversed(events)]
    return "\n".join(lines)


class Readouts:
    """Fills the read-outs of a :class:`~lidarloc.app.viewer.panel.Controls`; called from the
    display thread, except the start-up reports (from the thread that builds the localizer)."""

    def __init__(self, controls: Controls, history: History):
        self.c = controls
        self.history = history
        self._stage: str | None = "starting"     # Localizer construction stage, None once built
        self._frac: float | None = None
        self._failed = False
        self._status_text = ""
        self._plot_version = None
        self._last_plot = 0.0
        self.cursor: int | None = None          # the scan the timeline shows, marked on the plots
        self.reference: tuple | None = None     # (label, series) of a second run drawn dashed

    # ------------------------------------------------------------------ start-up
    def building(self, stage, frac=None) -> None:
        self._stage = str(stage)
        self._frac = None if frac is None else float(frac)

    def built(self) -> None:
        self._stage = None

    def failed(self, message: str) -> None:
        self._failed = True
        self._stage = None
        self.c.progress_text.content = error_markdown(f"could not start: {message}")
        self.c.progress.visible = False

    def set_scan_axis(self, n_scans: int) -> None:
        self.c.plots.set_scan_axis(n_scans)

    def no_ground_truth(self) -> None:
        self.c.plots.no_ground_truth()
        self.c.legend.content = legend_markdown(has_truth=False)

    # ------------------------------------------------------------------ per display update
    def update_progress(self, rebuild: float | None) -> None:
        """The start-up stage while building, else ``rebuild`` (the localizer's background table
        rebuild, 0…1, or None: the bar goes)."""
        if self._failed:
            return
        bar, text = self.c.progress, self.c.progress_text
        if self._stage is not None:
            frac = self._frac
            label = BUILD_STAGES.get(self._stage, self._stage)
            bar.visible = True
            bar.animated = frac is None
            bar.value = 100.0 * (frac if frac is not None else 1.0)
            pct = f" {100 * frac:.0f}%" if frac is not None else ""
            text.content = f"{label}…{pct}"
            text.visible = True
        elif rebuild is not None:
            bar.visible = True
            bar.animated = False
            bar.value = float(np.clip(100.0 * rebuild, 0, 100))
            text.content = f"Rebuilding a table in the background… {100 * rebuild:.0f}% (the old one is used meanwhile)"
            text.visible = True
        else:
            bar.visible = False
            text.visible = False

    def update_status(self, text: str) -> None:
        if text != self._status_text:
            self._status_text = text
            self.c.status.content = text

    def update_plots(self, force: bool = False) -> None:
        """Resend the plots' series, at most every PLOT_INTERVAL unless ``force``d."""
        now = time.perf_counter()
        if not force and now - self._last_plot < PLOT_INTERVAL:
            return
        cursor, ref = self.cursor, self.reference
        version = (self.history.version, cursor, id(ref))
        if version == self._plot_version:
            return
        h = self.history.arrays()
        self._plot_version, self._last_plot = version, now
        self.c.plots.update(h, cursor=cursor, reference=ref)
