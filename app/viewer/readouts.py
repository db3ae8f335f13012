"""The panel's read-outs: the progress bar (while the localizer is built, and while a table is
rebuilt in the background), the status table with the scan's confidence and the recent events,
and the plots (:mod:`~lidarloc.app.viewer.plots`)."""

from __future__ import annotations

import time

import numpy as np

from ...core.rules.truth import truth_alarm as core_truth_alarm
from ...core.snapshot import Snapshot
from .history import History
from .legend import legend_markdown
from .panel import Controls
from .style import COLLAPSED_N_EFF_SHARE, PLOT_INTERVAL, REALTIME_LATE_S, error_markdown, shorten

BUILD_STAGES = {
    "starting": "Starting the localizer",
    "map": "Building the prior map",
    "point tiles": "Cutting the map into tiles",
    "lookup": "Building the distance lookup table",
    "pyramid": "Building the BEV pyramid",
    "ready": "Ready",
}


AMBER_CSS = "#ffb347"
GREEN_CSS = "#5be35b"


def _coloured(text: str, colour: str) -> str:
    return f"<span style='color:{colour}'>**{text}**</span>"


def s2m_readiness(snap: Snapshot, live: tuple[str, str] | None = None, s2m_enabled: bool = True) -> tuple[str, str]:
    """(status, detail) of S2M: ``live`` (the localizer's ``s2m_status()``, which moves on while
    the player is paused) where given, else the snapshot's; a snapshot from a localizer that only
    says ``s2m_pending`` counts as building."""
    status, detail = live if live is not None else (snap.s2m_status, snap.s2m_status_detail)
    if not s2m_enabled:
        return "off", ""
    if status == "ready" and snap.s2m_pending:
        return "building", "road-removed map and BEV pyramid"
    return status, detail


def s2m_not_ready_text(status: str, detail: str) -> str:
    """The status line while the filter runs without S2M (empty when S2M is ready)."""
    if status == "ready":
        return ""
    if status == "off":
        return "PF only — S2M off"
    if status == "building":
        return f"PF only — S2M not ready (building{': ' + detail if detail else ' its tables'})"
    return f"PF only — S2M not ready ({detail or status})"


def truth_alarm(snap: Snapshot) -> str | None:
    """The snapshot's truth alarm: localized while the truth is farther than
    :data:`~lidarloc.core.rules.truth.FALSE_FIRE_M` (a snapshot made without it, e.g. by a stand-in
    localizer, gets the same test on its figures). None without truth."""
    if snap.gt_pose is None and snap.error_m is None:
        return None
    return snap.truth_alarm or core_truth_alarm(bool(snap.localized), snap.error_m)


def _next_scan_line(snap: Snapshot, next_scan: int | None, clock: str, events: list, finished: bool) -> str:
    """Why the next scan is not the one after the shown one: a kidnap, or scans the real-time
    clock dropped to keep up."""
    if next_scan is None or finished or next_scan == snap.scan_index + 1:
        return ""
    if any(e.kind == "kidnap" and e.scan == snap.scan_index for e in events):
        return f"next scan: {next_scan} (the vehicle was moved; the filter was not told)"
    if clock == "realtime":
        n = next_scan - snap.scan_index - 1
        return f"next scan: {next_scan} ({n} scan{'s' if n != 1 else ''} dropped to keep up with the sensor)"
    return f"next scan: {next_scan}"


def _verdict_lines(snap: Snapshot, s2m: tuple[str, str]) -> list[str]:
    """Localized (green) only when the localizer says so and the truth does not contradict it."""
    alarm = truth_alarm(snap)
    not_ready = s2m_not_ready_text(*s2m)
    lines = []
    if alarm:
        lines.append(error_markdown(f"⚠ false fire: {alarm}"))
    elif snap.localized:
        since = "" if snap.localized_since is None else f" since scan {snap.localized_since}"
        confirmed = "" if snap.confirmed_at is None else f" · S2M confirmed at scan {snap.confirmed_at}"
        lines.append(_coloured(f"localized{since}", GREEN_CSS) + confirmed)
    elif snap.awaiting_confirmation:
        lines.append(_coloured("PF converged — waiting for S2M to confirm", AMBER_CSS))
    else:
        lines.append(_coloured("not localized", AMBER_CSS))
    if not_ready:
        lines.append(_coloured(not_ready, AMBER_CSS))
    return lines


def _converged_cell(snap: Snapshot, s2m_ready: bool) -> str:
    """The PF's own convergence, worded so that it never reads as the localizer's verdict."""
    if not snap.converged:
        return "no"
    if snap.localized:
        return "yes"
    return (
        "yes — PF only, not confirmed by S2M"
        if snap.awaiting_confirmation or not s2m_ready
        else "yes — the localization rule is not met yet"
    )


def _s2m_cell(snap: Snapshot, s2m: tuple[str, str], finished: bool) -> str:
    status, detail = s2m
    if status == "off":
        return "off"
    if status == "building":
        return f"building in the background: {detail or 'road-removed map and BEV pyramid'}"
    if status == "held":
        return detail or "held back"
    s2m_ms = "–" if snap.s2m is None else f"{snap.s2m.ms:.0f} ms"
    running = " · running" if snap.s2m_running and not finished else ""
    return f"{s2m_ms} · {100 * snap.s2m_acceptance:.0f}% accepted{running}"


def status_markdown(
    snap: Snapshot,
    state: str,
    clock: str,
    speed: str,
    events: list,
    min_inlier_share: float | None = None,
    *,
    s2m_enabled: bool = True,
    rate: float | None = None,
    lag_s: float | None = None,
    next_scan: int | None = None,
    playing: bool = False,
    s2m_status: tuple[str, str] | None = None,
) -> str:
    """The status table: scan counter, play state, the localizer's verdict, the filter's figures,
    the scan's confidence and the recent events (newest first). ``speed`` is the replay speed set
    (scans/s; None: not shown); a ``state`` "recorded…" (a scan the timeline shows) names no
    clock; ``rate`` the scans/s achieved lately and ``lag_s`` how far behind the sensor clock
    the filter is (real-time clock), both while playing (None: not shown; ``playing`` with no
    rate yet says it is being measured). ``next_scan``: the scan the localizer processes next,
    named when it is not the one after ``snap`` (a kidnap, or scans the real-time clock
    dropped). ``min_inlier_share`` (``localize.min_inlier_share``): while localized with fewer
    of the scan's points fitting the map than this, a warning line says so (the
    ``confidence_low`` condition). ``s2m_enabled``: with S2M off its row says so instead of the
    last match's figures; ``s2m_status``: the localizer's live (status, detail) of S2M (default:
    the snapshot's).

    The verdict is green only when the localizer says localized and the truth (where known)
    does not contradict it; a filter that converged without S2M's word, or runs without S2M,
    reads amber."""
    speed = "" if clock == "realtime" or speed is None else f", set to {speed} scans/s"
    k = "–" if snap.scan_index < 0 else str(snap.scan_index)
    clocked = "" if state.startswith("recorded") else f" ({clock}{speed})"
    lines = [f"**Scan {k} of {snap.n_scans}** · {state}{clocked}"]
    if rate is not None:
        achieved = f"achieved {rate:.2f} scans/s" if rate < 1 else f"achieved {rate:.1f} scans/s"
        if lag_s is not None:
            achieved += f" · {1000 * lag_s:.0f} ms behind the sensor clock"
        lines.append(achieved)
        if lag_s is not None and lag_s > REALTIME_LATE_S:
            lines.append(error_markdown(f"⚠ falling behind the sensor: {lag_s:.2f} s late"))
    elif playing:
        lines.append("achieved – scans/s (measuring)")
    finished = state == "finished" or snap.done
    moved = _next_scan_line(snap, next_scan, clock, events, finished)
    if moved:
        lines.append(moved)
    s2m = s2m_readiness(snap, s2m_status, s2m_enabled)
    lines += _verdict_lines(snap, s2m)
    share = snap.inlier_share
    if snap.localized and share is not None and min_inlier_share is not None and share < min_inlier_share:
        lines.append(
            error_markdown(
                f"⚠ low confidence: {100 * share:.0f}% of the scan fits the map (below {100 * min_inlier_share:.0f}%)"
            )
        )
    std = np.asarray(snap.std_xyz, float)
    P = np.asarray(snap.particles)
    spread = P[:, :2].std(axis=0) if len(P) > 1 else np.zeros(2)
    err = "–" if snap.error_m is None else f"{snap.error_m:.2f} m"
    n = snap.n_particles if snap.n_particles else len(snap.weights)
    n_eff = f"{100 * snap.n_eff_share:.1f}% ({snap.n_eff:.0f} of {n})"
    if snap.scan_index >= 0 and snap.n_eff_share < COLLAPSED_N_EFF_SHARE:
        n_eff += " · collapsed: see Legend"
    fit = (
        "–"
        if share is None
        else f"{100 * share:.0f}%"
        + ("" if snap.mean_residual_m is None else f" · mean residual {snap.mean_residual_m:.2f} m")
    )
    rpe = "–" if snap.rpe_ms is None else f"{snap.rpe_ms:.1f} ms/scan"
    lines += [
        "",
        "| | |",
        "|---|---|",
        f"| position std x/y/z (weighted) | {std[0]:.2f} / {std[1]:.2f} / {std[2]:.2f} m |",
        f"| particle cloud spread x/y | {spread[0]:.2f} / {spread[1]:.2f} m |",
        f"| PF converged (std below threshold) | {_converged_cell(snap, s2m[0] == 'ready')} |",
        f"| error to truth | {err} |",
        f"| N_eff share | {n_eff} |",
        f"| inlier share | {fit} |",
        f"| PF | {snap.pf_ms:.1f} ms/scan |",
        f"| RPE | {rpe} |",
        f"| S2M | {_s2m_cell(snap, s2m, finished)} |",
    ]
    if events:
        lines += ["", "**Recent events**"]
        lines += [
            f"- {e.scan}: {e.kind.replace('_', ' ')}" + (f" — {shorten(e.detail, 60)}" if e.detail else "")
            for e in reversed(events)
        ]
    return "\n".join(lines)


class Readouts:
    """Fills the read-outs of a :class:`~lidarloc.app.viewer.panel.Controls`; called from the
    display thread, except the start-up reports (from the thread that builds the localizer)."""

    def __init__(self, controls: Controls, history: History):
        self.c = controls
        self.history = history
        self._stage: str | None = "starting"  # Localizer construction stage, None once built
        self._frac: float | None = None
        self._failed = False
        self._status_text = ""
        self._plot_version = None
        self._last_plot = 0.0
        self.cursor: int | None = None  # the scan the timeline shows, marked on the plots
        self.reference: tuple | None = None  # (label, series) of a second run drawn dashed

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

    def not_current(self, error: str, *, shown: int | None, n_scans: int | None, at: int | None) -> None:
        """The display failed: the status says it is not current, with no verdict (a stale green
        would claim a localization the page cannot vouch for), until an update succeeds."""
        scan = "–" if shown is None or shown < 0 else str(shown)
        head = f"**Scan {scan} of {n_scans}** · not current" if n_scans is not None else "**not current**"
        lines = [head, error_markdown("⚠ the display is not current: its last update failed; retrying")]
        if at is not None:
            lines.append(f"the filter is at scan {at}")
        lines.append(f"<small>{shorten(error, 120)}</small>")
        text = "\n\n".join(lines)
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
