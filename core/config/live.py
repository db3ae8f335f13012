"""The parameters a running localizer accepts (``Localizer.set_params``): :data:`LIVE_PARAMS` is
the one table of them — label, display unit, validity rule, and what the localizer must do when
one changes — and :func:`check_live_changes` the one validation of a change."""

from __future__ import annotations

import copy
import math
import numbers
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from ..errors import LidarlocError
from .schema import DEG, STATE_NAMES, Config


@dataclass(frozen=True)
class LiveParam:
    """A parameter the running localizer accepts (``Localizer.set_params``), with what a GUI
    needs to show it."""

    key: str  # keyword of Localizer.set_params
    section: str  # Config section holding the value ("pf", "s2m", "localize")
    attr: str  # attribute in that section
    label: str  # display label incl. display unit, e.g. "d_max (m)", "d_θ (deg)"
    unit: str  # display unit: "m", "deg", "", ...
    scale: float = 1.0  # display value = SI value / scale (DEG shows radians as degrees)
    step: float = 0.01
    integer: bool = False
    hint: str = ""
    rule: str = ""  # human-readable validity rule, e.g. "> 0", used in error messages
    limit: Callable[[Any], bool] = lambda v: True  # the localizer's own limit, what ``rule`` says (SI)
    # What the localizer does when the value changes, beyond storing it in the configuration (the
    # name of one of its reactions; "" = nothing: the value is read where it is used):
    # "lookup" (a larger d_max than the table's rebuilds it; the filter's cap follows), "filter"
    # (the particle filter takes the new value), "particles" (the count changes: the match in flight
    # is dropped), "s2m_switch", "pyramid" (a new d_m rebuilds the BEV pyramid), "clock".
    effect: str = ""

    def coerce(self, value: Any) -> Any:
        """The value as the configuration stores it (float, int, bool, str, tuple of floats)."""
        if self.key == "q_std":
            return tuple(float(q) for q in value)
        if self.integer:
            return int(value)
        if isinstance(value, bool) or isinstance(value, str):
            return value
        return float(value)


LIVE_PARAMS: dict[str, LiveParam] = {
    p.key: p
    for p in (
        LiveParam(
            "d_max",
            "pf",
            "d_max",
            "d_max (m)",
            "m",
            rule="in (0, 100]",
            limit=lambda v: 0 < v <= 100,
            effect="lookup",
            hint="Distance cap of the likelihood (a larger one than the built table rebuilds it in the background)",
        ),
        LiveParam(
            "sigma",
            "pf",
            "sigma",
            "σ (m)",
            "m",
            rule="in (0, 100]",
            limit=lambda v: 0 < v <= 100,
            effect="filter",
            hint="Likelihood scale",
        ),
        LiveParam(
            "n_particles",
            "pf",
            "n_particles",
            "N particles",
            "",
            step=1,
            integer=True,
            rule="a whole number in 1..200000",
            limit=lambda v: 1 <= v <= 200_000,
            effect="particles",
        ),
        LiveParam(
            "scan_voxel",
            "pf",
            "scan_voxel",
            "scan voxel (m)",
            "m",
            rule="in 0.05..10",
            limit=lambda v: 0.05 <= v <= 10,
            hint="Random point per voxel of each scan",
        ),
        LiveParam(
            "region_x",
            "s2m",
            "region_x",
            "L_x (m)",
            "m",
            step=0.5,
            rule="in (0, 5000]",
            limit=lambda v: 0 < v <= 5000,
            hint="S2M local search half-width in x",
        ),
        LiveParam(
            "region_y",
            "s2m",
            "region_y",
            "L_y (m)",
            "m",
            step=0.5,
            rule="in (0, 5000]",
            limit=lambda v: 0 < v <= 5000,
            hint="S2M local search half-width in y",
        ),
        LiveParam(
            "match_resolution",
            "s2m",
            "match_resolution",
            "d_m (m)",
            "m",
            step=0.1,
            rule="in 0.1..10",
            limit=lambda v: 0.1 <= v <= 10,
            effect="pyramid",
            hint="S2M match resolution (rebuilds the BEV pyramid)",
        ),
        LiveParam(
            "angle_step",
            "s2m",
            "angle_step",
            "d_θ (deg)",
            "deg",
            scale=DEG,
            step=0.1,
            rule="in (0, 180]",
            limit=lambda v: 0 < v <= math.pi,
            hint="S2M angular resolution",
        ),
        # per-entry units and degrees: see STATE_NAMES and ANGULAR_STATE
        LiveParam(
            "q_std",
            "pf",
            "q_std",
            "Process noise Q (std)",
            "",
            step=0.001,
            rule="11 entries, each finite and ≥ 0",
            effect="filter",
            limit=lambda v: len(v) == 11 and all(math.isfinite(q) and q >= 0 for q in v),
            hint="Standard deviations of the 11-state process noise (angles in degrees)",
        ),
        LiveParam(
            "s2m_enabled",
            "s2m",
            "enabled",
            "S2M enabled",
            "",
            rule="on or off",
            effect="s2m_switch",
            hint="Scan-to-map matching on/off (applies at once)",
        ),
        LiveParam(
            "clock",
            "localize",
            "clock",
            "Clock",
            "",
            rule="replay or realtime",
            limit=lambda v: v in ("replay", "realtime"),
            effect="clock",
            hint="replay: deterministic; realtime: S2M lands when it finishes, playback at the sequence's timestamps",
        ),
    )
}


def _is_number(value: Any) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def _has_type_of(current: Any, value: Any) -> bool:
    """Whether ``value`` can stand in for the configuration's ``current`` value."""
    if isinstance(current, bool):
        return isinstance(value, bool)
    if isinstance(current, int):
        return _is_number(value) and math.isfinite(value) and float(value).is_integer()
    if isinstance(current, float):
        return _is_number(value)
    if isinstance(current, tuple):
        try:
            return all(_is_number(q) for q in value)
        except TypeError:
            return False
    return isinstance(value, type(current))


def check_live_changes(cfg: Config, changes: dict) -> None:
    """Refuse live parameter changes (``Localizer.set_params`` keywords, SI units) that the
    localizer cannot use: raises LidarlocError with a one-line message, changes nothing.

    A change must pass the rules of any configuration (Config.validate on a copy of ``cfg`` with
    the changes in) and the localizer's own limits (each parameter's ``rule``)."""
    for key in changes:
        if key not in LIVE_PARAMS:
            raise LidarlocError(f"unknown parameter '{key}'")
    for key, value in changes.items():
        p = LIVE_PARAMS[key]
        if not _has_type_of(getattr(getattr(cfg, p.section), p.attr), value):
            raise LidarlocError(f"invalid value for {key}: {value!r} (must be {p.rule})")
        if key == "q_std":
            bad = [name for name, q in zip(STATE_NAMES, value) if not (math.isfinite(q) and q >= 0)]
            if bad:
                raise LidarlocError(f"Q std of {', '.join(bad)} must be finite and ≥ 0")
        elif _is_number(value) and not math.isfinite(value):
            raise LidarlocError(f"{key} must be a finite number")
    trial = copy.deepcopy(cfg)
    for key, value in changes.items():
        p = LIVE_PARAMS[key]
        setattr(getattr(trial, p.section), p.attr, tuple(value) if key == "q_std" else value)
    trial.validate()
    for key, value in changes.items():
        if not LIVE_PARAMS[key].limit(value):
            raise LidarlocError(f"invalid value for {key}: {value!r} (must be {LIVE_PARAMS[key].rule})")
