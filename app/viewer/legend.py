"""The panel's legend: what every colour of the scene means, built from the colours the scene
uses (:mod:`~lidarloc.app.viewer.style`), and a word on reading the particle weights."""

from __future__ import annotations

from .s2m_detail import LEGEND_MARKDOWN as S2M_DETAIL_LEGEND
from .style import (
    BEST_COLOR,
    BEV_COLOR,
    ELLIPSE_COLOR,
    EST_COLOR,
    GT_COLOR,
    HEIGHT_LUT,
    PARTICLE_HIGH,
    PARTICLE_LOW,
    PLACE_ANSWER_COLOR,
    PLACE_OTHER_COLOR,
    RESET_COLOR,
    S2M_ACCEPTED_COLOR,
    S2M_REJECTED_COLOR,
    SCAN_COLOR,
    TILE_COLOR,
    css,
)
from .why_style import RESIDUAL_BAD, RESIDUAL_GOOD, RESIDUAL_MID, SELECTED_COLOR, SURFACE_BEST_COLOR, SURFACE_LUT


def _swatch(rgb, shape: str = "■") -> str:
    return f"<span style='color:{css(rgb)}'>{shape}</span>"


def _ramp(colors) -> str:
    stops = ", ".join(css(c) for c in colors)
    return (
        f"<span style='display:inline-block;width:4em;height:0.8em;vertical-align:middle;"
        f"background:linear-gradient(to right, {stops})'></span>"
    )


#: one entry per colour of the scene: (name used by tests, markdown line)
ENTRIES = (
    ("map", f"{_ramp(HEIGHT_LUT[::64].tolist() + [HEIGHT_LUT[-1].tolist()])} map, by height (low → high)"),
    ("scan", f"{_swatch(SCAN_COLOR, '●')} current scan, at the estimate"),
    ("estimate", f"{_swatch(EST_COLOR, '▬')} estimate: vehicle, trajectory (red-green-blue axes: x-y-z)"),
    ("truth", f"{_swatch(GT_COLOR, '▬')} ground truth: vehicle, trajectory"),
    (
        "particles",
        f"{_ramp([PARTICLE_LOW.tolist(), PARTICLE_HIGH.tolist()])} particles by log-weight rank "
        "(low → high); a longer arrow carries more weight",
    ),
    ("best", f"{_swatch(BEST_COLOR, '➜')} best particle (highest weight)"),
    ("ellipse", f"{_swatch(ELLIPSE_COLOR, '◌')} 2σ ellipse of the weighted position"),
    (
        "s2m",
        f"{_swatch(S2M_ACCEPTED_COLOR)} S2M match accepted · {_swatch(S2M_REJECTED_COLOR)} rejected "
        "(matched scan, search area)",
    ),
    ("bev", f"{_swatch(BEV_COLOR)} BEV pyramid level (Layers)"),
    ("reset", f"{_swatch(RESET_COLOR, '□')} where particles were just reset (until the next scan)"),
    (
        "overview",
        f"Overview: the map from above in grey, {_swatch(PARTICLE_HIGH.tolist(), '●')} particles, "
        f"{_swatch(EST_COLOR)} estimate, {_swatch(GT_COLOR, '□')} truth, {_swatch(PLACE_ANSWER_COLOR, '□')} the "
        f"place a whole-map match answered and {_swatch(PLACE_OTHER_COLOR, '□')} the others it verified (all of "
        f'them when it said "ambiguous"; scores in the S2M details), {_swatch(TILE_COLOR, "□")} the map\'s '
        "tiles drawn at full density (a map too big to draw whole)",
    ),
    # the Why folder's views
    (
        "residuals",
        f"{_ramp([RESIDUAL_GOOD.tolist(), RESIDUAL_MID.tolist(), RESIDUAL_BAD.tolist()])} scan residuals "
        "(Why): distance to the map, ≤ σ → ≥ d_max",
    ),
    (
        "surface",
        f"{_ramp(SURFACE_LUT[::64].tolist() + [SURFACE_LUT[-1].tolist()])} likelihood surface (Why), "
        f"low → high; {_swatch(SURFACE_BEST_COLOR, '◯')} its maximum",
    ),
    ("inspected", f"{_swatch(SELECTED_COLOR, '➜')} the inspected particle (Why)"),
    ("s2m_detail", S2M_DETAIL_LEGEND + " (Why › S2M details)"),
)

N_EFF_HELP = (
    "**N_eff share** is how many particles effectively carry the weight. Near 0 % the weights "
    "have collapsed onto one particle: the weighted std and the 2σ ellipse then shrink to "
    "nothing although the cloud is still spread (its spread is shown beside the std), so "
    "neither means certainty. Judge the estimate by the inlier share, the error plots and "
    "the S2M matches instead."
)


def legend_markdown(has_truth: bool = True) -> str:
    lines = [text for name, text in ENTRIES if has_truth or name != "truth"]
    return "  \n".join(lines) + "\n\n" + N_EFF_HELP
