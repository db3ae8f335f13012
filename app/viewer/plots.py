"""The panel's plots, all on the same scan axis: position std, cloud spread and error; the error
against the truth split along-track, cross-track and vertical; the heading error; N_eff as a share
of the particles; each block's latency. Localization events are marked on the curves (points-only
series).

Every plot's x axis is pinned to the whole sequence (scan 0 … n − 1) instead of following the
data. viser's browser side keeps a user's x zoom across data updates by storing the x range
relative to the data's extent; a page that handles several updates in one go (a tab opened while
playing replays the backlog, and software WebGL keeps the page busy) stored a shrunken range
before the previous one was applied, and the curves then seemed frozen at the left edge. A fixed
range takes that path out (and keeps every plot on the same axis).

Each plot's legend names its curves only: the event dots and the timeline's cursor are the same on
every plot, so one key above the plots names them (:func:`dots_key_html`), and the plots keep their
height for the curves (:data:`PLOT_ASPECT`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import viser.uplot as uplot

from ...core.config import DEG
from .history import MARKED_EVENTS
from .style import CURSOR_COLOR, PLOT_MAX_POINTS

# events marked on the curves: (label, colour, the event kinds)
RUN_MARKS = (
    ("localized", "#5be35b", ("localized",)),
    ("lost / false positive / unconfirmed", "#ff5a5a", ("loss", "false_positive", "unconfirmed")),
    ("false fire (truth > 5 m)", "#ff2a2a", ("false_fire",)),
    ("reset / kidnap / relocalized", "#ffffff", ("reset", "kidnap", "relocalized")),
)
S2M_MARKS = (("S2M accepted", "#ff3cff", ("s2m_accepted",)), ("S2M rejected", "#969696", ("s2m_rejected",)))
assert {k for _, _, kinds in RUN_MARKS + S2M_MARKS for k in kinds} == set(MARKED_EVENTS)

PLOT_ASPECT = 1.1  # width / height of a plot's chart: nearly square in the panel's width
NOT_IN_LEGEND = "lidarloc-not-in-legend"  # the class of the series the shared key names instead
# the page hides those series' legend entries (uPlot gives each entry its series' class)
LEGEND_CSS = f"<style>.u-legend .{NOT_IN_LEGEND} {{ display: none !important; }}</style>"
CURSOR_LABEL = "scan on the timeline"


def dots_key_html() -> str:
    """The key of the dots every plot shares: the events' colours and the timeline's cursor."""
    dots = " ".join(f"<span style='color:{color}'>●</span>&nbsp;{label}" for label, color, _ in RUN_MARKS + S2M_MARKS)
    cursor = f"<span style='color:{CURSOR_COLOR}'>◉</span>&nbsp;{CURSOR_LABEL}"
    return f"<small>Dots on the curves: {dots}; {cursor}.</small>{LEGEND_CSS}"


def _line(label: str, color: str, show: bool = True) -> uplot.Series:
    return uplot.Series(label=label, stroke=color, width=2, show=show)


def _marks(marks) -> tuple:
    """Points-only series: no line, a dot per event (NaN elsewhere: nothing drawn)."""
    return tuple(
        uplot.Series(
            label=label,
            stroke=color,
            width=0,
            auto=False,
            points={"show": True, "size": 8, "fill": color, "stroke": color},
            **{"class": NOT_IN_LEGEND},
        )
        for label, color, _ in marks
    )


@dataclass
class PlotSpec:
    key: str
    title: str
    lines: tuple  # (history series, label, colour, scale factor)
    marks: tuple  # RUN_MARKS, S2M_MARKS or ()
    log: bool = False
    needs_truth: bool = False


SPECS = (
    PlotSpec(
        "std",
        "Position std, cloud spread and error (m)",
        (
            ("std", "std, weighted", "#ff5a5a", 1.0),
            ("spread", "cloud spread", "#ffb347", 1.0),
            ("error", "error to truth", "#e6e6e6", 1.0),
        ),
        (),
        log=True,
    ),
    PlotSpec(
        "error",
        "Error to truth: along, cross-track, vertical (m)",
        (
            ("along", "along-track", "#5ab4ff", 1.0),
            ("cross", "cross-track", "#ffb347", 1.0),
            ("vertical", "vertical", "#b48cff", 1.0),
        ),
        RUN_MARKS,
        needs_truth=True,
    ),
    PlotSpec(
        "heading", "Heading error (°)", (("heading", "heading", "#5ab4ff", 1.0 / DEG),), RUN_MARKS, needs_truth=True
    ),
    PlotSpec("n_eff", "N_eff share of the particles (%)", (("n_eff_share", "N_eff / N", "#5be35b", 100.0),), RUN_MARKS),
    PlotSpec(
        "latency",
        "Latency per scan (ms)",
        (
            ("pf_ms", "PF", "#ff9620", 1.0),
            ("rpe_ms", "RPE (KISS-ICP)", "#5ab4ff", 1.0),
            ("s2m_ms", "S2M", "#ff3cff", 1.0),
        ),
        S2M_MARKS,
    ),
)


def _scales(n_scans: int, log: bool) -> dict:
    y = uplot.Scale(auto=True, distr=3) if log else uplot.Scale(auto=True)
    return {"x": uplot.Scale(time=False, range=(0.0, float(max(n_scans - 1, 1)))), "y": y}


def decimate(n: int, max_points: int = PLOT_MAX_POINTS) -> slice:
    """Every how many recorded scans one is plotted (long runs)."""
    return slice(None, None, max(1, int(np.ceil(n / max_points))))


def mark_series(x: np.ndarray, y: np.ndarray, marks: list, kinds: tuple) -> np.ndarray:
    """A points-only series on ``x``: NaN except at the plotted scan nearest each event of ``kinds``
    (at or after it), where it takes the curve's value ``y`` (0 where the curve has none)."""
    out = np.full(len(x), np.nan)
    if len(x) == 0:
        return out
    scans = np.array([s for s, kind in marks if kind in kinds], float)
    if len(scans) == 0:
        return out
    i = np.clip(np.searchsorted(x, scans), 0, len(x) - 1)
    v = y[i]
    out[i] = np.where(np.isfinite(v), v, 0.0)
    return out


class Plots:
    """The plot handles (``handles[key]``, keys of :data:`SPECS`) and their updates; built inside
    the panel's Plots folder.

    Each plot also has a cursor (a points-only series: one dot on the first curve at the scan the
    timeline shows) and, with a second run on screen, that run's curves dashed (labels end in its
    name)."""

    def __init__(self, gui):
        self.handles: dict = {}
        self.n_scans = 1
        self.has_truth = True
        self._ref_label: str | None = None
        self.key = gui.add_html(dots_key_html())
        x = np.zeros(1)
        for spec in SPECS:
            series = self._series(spec)
            self.handles[spec.key] = gui.add_uplot(
                (x,) * len(series),
                series,
                title=spec.title,
                scales=_scales(1, spec.log),
                aspect=PLOT_ASPECT,
                legend=uplot.Legend(live=False),
            )

    def _series(self, spec: PlotSpec) -> tuple:
        lines = []
        for _, lbl, c, _ in spec.lines:
            if spec.key == "std" and lbl == "error to truth" and not self.has_truth:
                lines.append(uplot.Series(label="error: no ground truth", show=False))
            else:
                lines.append(_line(lbl, c))
        ref = ()
        if self._ref_label is not None:
            ref = tuple(
                uplot.Series(label=f"{lbl} ({self._ref_label})", stroke=c, width=1.5, dash=(6.0, 4.0))
                for _, lbl, c, _ in self._ref_lines(spec)
            )
        cursor = uplot.Series(
            label=CURSOR_LABEL,
            stroke=CURSOR_COLOR,
            width=0,
            auto=False,
            points={"show": True, "size": 11, "fill": CURSOR_COLOR, "stroke": "#000000"},
            **{"class": NOT_IN_LEGEND},
        )
        scan = uplot.Series(label="scan", **{"class": NOT_IN_LEGEND})
        return (scan,) + tuple(lines) + _marks(spec.marks) + ref + (cursor,)

    def _ref_lines(self, spec: PlotSpec) -> tuple:
        if spec.needs_truth and not self.has_truth:
            return ()
        return tuple(line for line in spec.lines if self.has_truth or line[0] != "error")

    def set_scan_axis(self, n_scans: int) -> None:
        """Pin every plot's x axis to the sequence's scans 0 … n − 1."""
        self.n_scans = int(n_scans)
        for spec in SPECS:
            self.handles[spec.key].scales = _scales(self.n_scans, spec.log)

    def no_ground_truth(self) -> None:
        """The source has no truth: the plots against it go, the error curve is hidden."""
        self.has_truth = False
        for spec in SPECS:
            h = self.handles[spec.key]
            if spec.needs_truth:
                h.visible = False
            elif spec.key == "std":
                h.series = self._series(spec)

    def _set_reference(self, label: str | None) -> None:
        if label == self._ref_label:
            return
        self._ref_label = label
        for spec in SPECS:
            self.handles[spec.key].series = self._series(spec)

    def update(self, h: dict, cursor: int | None = None, reference: tuple | None = None) -> None:
        """Resend every visible plot's series from :meth:`History.arrays`; ``cursor``: the scan the
        timeline shows; ``reference``: (label, series) of a second run."""
        self._set_reference(None if reference is None else reference[0])
        ref = None if reference is None else reference[1]
        scans = h["scan"]
        if ref is not None and len(ref["scan"]):
            x_all = np.union1d(scans, ref["scan"])
        else:
            x_all = scans
        sl = decimate(len(x_all))
        x = np.asarray(x_all[sl], np.float64)
        if len(x) == 0:
            return
        for spec in SPECS:
            if spec.needs_truth and not self.has_truth:
                continue
            ys = [self._on(x, scans, h[key], factor, spec.log, h["std"]) for key, _, _, factor in spec.lines]
            first = ys[-1] if spec.key == "latency" else ys[0]  # S2M marks sit on the S2M curve
            ys += [mark_series(x, first, h["marks"], kinds) for _, _, kinds in spec.marks]
            if self._ref_label is not None:
                for key, _, _, factor in self._ref_lines(spec):
                    ys.append(
                        self._on(x, ref["scan"], ref[key], factor, spec.log, ref["std"])
                        if ref is not None
                        else np.full(len(x), np.nan)
                    )
            dot = np.full(len(x), np.nan)
            if cursor is not None:
                i = int(np.clip(np.searchsorted(x, cursor), 0, len(x) - 1))
                dot[i] = first[i] if np.isfinite(first[i]) else (1e-3 if spec.log else 0.0)
            ys.append(dot)
            self.handles[spec.key].data = (x, *ys)

    @staticmethod
    def _on(
        x: np.ndarray, scans: np.ndarray, values: np.ndarray, factor: float, log: bool, std: np.ndarray
    ) -> np.ndarray:
        """``values`` (one per scan of ``scans``) at the plotted scans ``x`` (NaN where the run has none)."""
        y = np.full(len(x), np.nan)
        if len(scans):
            i = np.clip(np.searchsorted(scans, x), 0, len(scans) - 1)
            hit = scans[i] == x
            v = np.asarray(values, float)[i] * factor
            if log:
                # a log scale needs positive finite values: a missing one takes the weighted std's
                v = np.where(np.isfinite(v), np.maximum(v, 1e-3), np.maximum(np.asarray(std, float)[i], 1e-3))
            y[hit] = v[hit]
        return y
