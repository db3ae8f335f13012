"""A sweep's grid: ``--grid KEY=V1,V2,…`` per swept configuration entry, every combination × seeds.

The keys are the configuration's own (``docs/configuration.md``: ``pf.sigma``, ``pf.d_max``,
``pf.n_particles``, ``s2m.region_x`` …); each value is checked the way ``--set KEY=VALUE`` checks
it before any run starts, so a typo is one line, not a sweep of failed runs. A list-valued entry
(``pf.q_std``) cannot be swept: its commas would read as several values.
"""

from __future__ import annotations

import itertools
import re
from dataclasses import dataclass

import yaml

from ...core.errors import LidarlocError


@dataclass(frozen=True)
class Grid:
    """The swept entries in the order given, each with its values (as typed on the command line)."""

    axes: dict[str, tuple[str, ...]]

    def combinations(self) -> list[tuple[str, ...]]:
        """Every combination of values, the first entry varying slowest."""
        return list(itertools.product(*self.axes.values()))

    def overrides(self, combo: tuple[str, ...]) -> list[str]:
        """The combination as ``--set`` entries."""
        return [f"{k}={v}" for k, v in zip(self.axes, combo)]

    def name(self, combo: tuple[str, ...]) -> str:
        """A folder name for the combination: ``pf.sigma=0.5,pf.d_max=1``."""
        return ",".join(f"{k}={_safe(v)}" for k, v in zip(self.axes, combo))

    def to_dict(self) -> dict:
        return {k: list(v) for k, v in self.axes.items()}


def _safe(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9._+-]", "_", text)


def typed(text: str):
    """A value as the CSV and best.yaml keep it: ``0.5`` → 0.5, ``true`` → True, else the text."""
    try:
        value = yaml.safe_load(text)
    except yaml.YAMLError:
        return text
    return value if isinstance(value, (int, float, bool)) else text


def parse_grid(items: list[str] | None, option: str = "--grid") -> Grid:
    """``KEY=V1,V2,…`` items as a Grid (each key once, each value once, in the order given)."""
    axes: dict[str, tuple[str, ...]] = {}
    for item in items or []:
        key, sep, values = item.partition("=")
        key = key.strip()
        if not sep or not key:
            raise LidarlocError(f"{option} {item}: expected KEY=V1,V2,… (e.g. {option} pf.sigma=0.5,1,2)")
        if key == "seed":
            raise LidarlocError(f"{option} seed: the seeds are 0…N−1 of --runs")
        if key in axes:
            raise LidarlocError(f"{option} {key}: given twice; list its values once, comma-separated")
        vals = tuple(dict.fromkeys(v.strip() for v in values.split(",") if v.strip()))
        if not vals:
            raise LidarlocError(f"{option} {key}: give at least one value")
        axes[key] = vals
    if not axes:
        raise LidarlocError(f"give at least one {option} KEY=V1,V2,… (e.g. {option} pf.sigma=0.5,1,2)")
    return Grid(axes)


def check_grid(grid: Grid, check) -> None:
    """Each value checked as ``--set`` checks it: ``check(overrides)`` raises a one-line error."""
    for key, values in grid.axes.items():
        for v in values:
            check([f"{key}={v}"])
