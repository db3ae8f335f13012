"""The live parameters as the Parameters folder shows them. Labels, display units, steps and
hints come from :data:`~lidarloc.core.config.LIVE_PARAMS`; here: which control shows which
parameter, the conversion between display units and the localizer's SI values, and which of the
shown values differ from what the localizer was last given."""

from __future__ import annotations

import math

from ...core.config import ANGULAR_STATE, DEG, LIVE_PARAMS, STATE_NAMES
from ...core.errors import LidarlocError

# Three live parameters have controls of their own: the 11 process-noise entries (a folder of
# numbers), the S2M switch (a checkbox, applied at once) and the clock (a choice, in Playback).
# Every other one is a number field, applied with the others by the Apply button.
Q_STD = LIVE_PARAMS["q_std"]
S2M_ENABLED = LIVE_PARAMS["s2m_enabled"]
CLOCK = LIVE_PARAMS["clock"]
NUMBER_FIELDS = tuple(p for p in LIVE_PARAMS.values() if p not in (Q_STD, S2M_ENABLED, CLOCK))


def q_units() -> tuple[str, ...]:
    """Display units of the 11 process-noise standard deviations (the paper's units)."""
    units = []
    for name, angular in zip(STATE_NAMES, ANGULAR_STATE):
        rate = name.endswith("_rate") or name == "v"
        if name == "a":
            units.append("m/s²")
        elif angular:
            units.append("deg/s" if rate else "deg")
        else:
            units.append("m/s" if rate else "m")
    return tuple(units)


def q_labels() -> tuple[str, ...]:
    return tuple(f"{name} ({unit})" for name, unit in zip(STATE_NAMES, q_units()))


def q_to_gui(q_std) -> list[float]:
    return [float(q) / DEG if ang else float(q) for q, ang in zip(q_std, ANGULAR_STATE)]


def q_from_gui(values) -> tuple[float, ...]:
    return tuple(float(v) * DEG if ang else float(v) for v, ang in zip(values, ANGULAR_STATE))


def _same(a, b) -> bool:
    return math.isclose(float(a), float(b), rel_tol=1e-9, abs_tol=1e-12)


#: Upper limits of the page's fields (display units) where the localizer's own rule has none (its
#: rules cap d_max, σ and the S2M region themselves): far beyond any sensible setting, low enough
#: that a value sent by a modified page cannot spread the particles over a continent in one step.
PAGE_MAX = {Q_STD.key: 1e4}


class ParamForm:
    """The numbers of the Parameters folder (display units) against what the localizer was last
    given: which of them changed, and what they are in SI units."""

    def __init__(self, fields: dict, q: list):
        self.fields = fields  # set_params key → number handle, NUMBER_FIELDS order
        self.q = q  # 11 number handles
        self.applied: dict = {}  # key → display value(s) the localizer has

    def show(self, live: dict) -> None:
        """Put the localizer's current values (``Localizer.live_params()``, SI) in the fields;
        they count as applied."""
        applied = {}
        for p in NUMBER_FIELDS:
            v = live[p.key]
            shown = int(v) if p.integer else float(v) / p.scale
            self.fields[p.key].value = shown
            applied[p.key] = shown
        q = q_to_gui(live[Q_STD.key])
        for h, v in zip(self.q, q):
            h.value = v
        applied[Q_STD.key] = q
        self.applied = applied

    def changed(self) -> dict:
        """Shown values that differ from what the localizer was last given (display units)."""
        out = {}
        for key, h in self.fields.items():
            old = self.applied.get(key)
            if old is None or not _same(h.value, old):
                out[key] = h.value
        q, old = [h.value for h in self.q], self.applied.get(Q_STD.key)
        if old is None or any(not _same(a, b) for a, b in zip(q, old)):
            out[Q_STD.key] = q
        return out

    @staticmethod
    def to_si(changed: dict) -> dict:
        """Display values → the localizer's units. Checked here, on the server, whatever the page
        sent (a modified page can send anything): a finite number, a whole one where it must be,
        and below :data:`PAGE_MAX` where the localizer's own rule has no upper limit."""
        si: dict = {}
        for key, v in changed.items():
            values = list(v) if key == Q_STD.key else [v]
            for x in values:
                if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x):
                    label = "Q" if key == Q_STD.key else LIVE_PARAMS[key].label
                    raise LidarlocError(f"{label} must be a finite number, got {x!r}")
                if abs(x) > PAGE_MAX.get(key, math.inf):
                    label = "Q" if key == Q_STD.key else LIVE_PARAMS[key].label
                    raise LidarlocError(f"{label} must be at most {PAGE_MAX[key]:g} here, got {x:g}")
            if key == Q_STD.key:
                si[key] = q_from_gui(v)
                continue
            p = LIVE_PARAMS[key]
            if p.integer:
                if not (math.isfinite(v) and float(v).is_integer()):
                    raise LidarlocError(f"{p.label} must be a whole number, got {v}")
                si[key] = int(v)
            else:
                si[key] = float(v) * p.scale
        return si

    def accept(self, changed: dict) -> None:
        """The localizer took ``changed``: it is what the fields are compared with from now on."""
        for key, v in changed.items():
            self.applied[key] = list(v) if key == Q_STD.key else v

    @staticmethod
    def names(changed: dict) -> str:
        """The changed parameters as the message after Apply names them."""
        return ", ".join("Q" if k == Q_STD.key else LIVE_PARAMS[k].label for k in changed)
