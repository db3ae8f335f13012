"""The paper's localization, false-positive and loss rules (Simulation section).

Localized: the per-axis position standard deviation stays below ``std_threshold`` (10 m) for at
least ``min_consecutive`` (10) consecutive scans AND over that window the vehicle moved at least
``min_moved`` (10 m) or turned at least ``min_turned`` (30°), both measured by relative pose
estimation (not ground truth). A streak of small std that ends before the rule is met is a false
positive (re-initialise over the whole map). After localization a std above ``loss_std`` (50 m)
is a loss (re-initialise).

Choices where the paper is vague, written down:
- "turned" is the absolute yaw change between the first and the last scan of the window (net
  turn), "moved" the path length over the window (sum of RPE steps).
- A streak that is still running and long enough but not yet moved/turned enough is neither
  localized nor false: we wait (a stopped car keeps its streak).

Beyond the paper (``localize.require_s2m_confirmation``, see :mod:`lidarloc.core.rules.integrity`): the
rule also needs an S2M match that agreed with the estimate at or after the streak's first scan.
A streak that meets the paper's conditions without it waits (``awaiting_confirmation``) like a
streak that has not moved enough: it is neither localized nor false.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..config import LocalizeConfig


@dataclass
class RuleOutcome:
    localized: bool
    event: str | None = None  # "localized", "false_positive", "loss" or None
    reinit: bool = False


class LocalizationRules:
    def __init__(self, cfg: LocalizeConfig):
        self.cfg = cfg
        self.reset()

    def reset(self) -> None:
        self.localized = False
        self.localized_since: int | None = None
        self.streak_start: int | None = None
        self.streak_path = 0.0  # metres driven since the streak started
        self.streak_yaw0 = 0.0
        self.awaiting_confirmation = False  # the paper's conditions hold; S2M has not agreed yet

    _STATE = ("localized", "localized_since", "streak_start", "streak_path", "streak_yaw0", "awaiting_confirmation")

    def state(self) -> dict:
        """What a checkpoint keeps (JSON-ready)."""
        return {name: (float(v) if isinstance(v, float) else v) for name in self._STATE for v in [getattr(self, name)]}

    def load(self, state: dict) -> None:
        """Back to a :meth:`state` (entries a checkpoint lacks keep their fresh values)."""
        for name in self._STATE:
            if name in state:
                setattr(self, name, state[name])

    def update(
        self,
        k: int,
        std_xyz: np.ndarray,
        step_distance: float,
        yaw_odom: float,
        confirmed: Callable[[int], bool] | None = None,
    ) -> RuleOutcome:
        """Feed scan k: the filter's per-axis std, the RPE distance since scan k−1, and the
        RPE (odometry-frame) yaw at scan k. ``confirmed(k0)``: whether an S2M match agreed with
        the estimate at or after scan k0 (None: the paper's rule, no confirmation needed)."""
        cfg = self.cfg
        max_std = float(np.max(std_xyz))
        if self.localized:
            if max_std > cfg.loss_std:
                self.reset()
                return RuleOutcome(False, "loss", reinit=True)
            return RuleOutcome(True)
        if max_std < cfg.std_threshold:
            if self.streak_start is None:
                self.streak_start, self.streak_path, self.streak_yaw0 = k, 0.0, yaw_odom
            else:
                self.streak_path += step_distance
            length = k - self.streak_start + 1
            turned = abs((yaw_odom - self.streak_yaw0 + np.pi) % (2 * np.pi) - np.pi)
            if length >= cfg.min_consecutive and (self.streak_path >= cfg.min_moved or turned >= cfg.min_turned):
                if confirmed is not None and not confirmed(self.streak_start):
                    self.awaiting_confirmation = True
                    return RuleOutcome(False)
                self.localized, self.localized_since = True, k
                self.awaiting_confirmation = False
                return RuleOutcome(True, "localized")
            return RuleOutcome(False)
        if self.streak_start is not None:
            self.reset()
            return RuleOutcome(False, "false_positive", reinit=True)
        return RuleOutcome(False)
