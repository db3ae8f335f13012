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
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .config import LocalizeConfig


@dataclass
class RuleOutcome:
    localized: bool
    event: str | None = None        # "localized", "false_positive", "loss" or None
    reinit: bool = False


class LocalizationRules:
    def __init__(self, cfg: LocalizeConfig):
        self.cfg = cfg
        self.reset()

    def reset(self) -> None:
        self.localized = False
        self.localized_since: int | None = None
        self.streak_start: int | None = None
        self.streak_path = 0.0          # metres driven since the streak started
        self.streak_yaw0 = 0.0

    def update(self, k: int, std_xyz: np.ndarray, step_distance: float, yaw_odom: float) -> RuleOutcome:
        """Feed scan k: the filter's per-axis std, the RPE distance since scan k−1, and the
        RPE (odometry-frame) yaw at scan k."""
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
                self.localized, self.localized_since = True, k
                return RuleOutcome(True, "localized")
            return RuleOutcome(False)
        if self.streak_start is not None:
            self.reset()
            return RuleOutcome(False, "false_positive", reinit=True)
        return RuleOutcome(False)
