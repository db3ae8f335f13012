"""The S2M match in flight: where and when it started, what it runs with, and its future. The
scheduler (:mod:`.schedule`) starts and lands it; :mod:`.realtime_landing` decides through which
scan it lands on the real-time clock."""

from __future__ import annotations

from concurrent.futures import Future
from dataclasses import dataclass
from typing import Any

import numpy as np


@dataclass
class S2MJob:
    """The match in flight."""

    started_at: int
    particle: int
    generation: int
    start_pose: np.ndarray
    future: Future
    deferrals: int = 0  # real time: scans at which the finished match could not land yet
    mode: str = "local"  # "global": the search region covers the whole map (not localized);
    # "check": the whole-map second opinion once localized
    cfg: Any = None  # the S2M settings it runs with (S2MConfig)
    level: bool = False  # whether the start's z, pitch and roll are ignored (see s2m.match_local)
    estimate_pose: np.ndarray | None = None  # the filter's estimate at k₀, 4×4: what the match is
    # judged against (core/rules/integrity.py)
    agreed_early: bool = False  # real time: its agreement was reported before it could land
