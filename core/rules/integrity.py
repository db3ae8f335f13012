"""Whether the filter's word can be trusted: S2M's confirmation of the estimate, the whole-map
second opinion once localized, and loss detection beyond the paper's std rule.

The paper's localization rule reads only the particle filter's spread: a filter that converged on
a look-alike street meets it as well as one that converged on the truth. With S2M late (its
tables still being built, a busy machine, a child process restarting) the rule fired on the
particle filter alone, and once "localized" the S2M matches searched only ±(L_x, L_y) around the
wrong place. These checks close that gap:

- **Confirmation** (``localize.require_s2m_confirmation``): the rule fires only once an S2M match
  has *agreed* with the estimate during the rule's window: its pose, carried forward to the
  landing scan, lies within ``localize.confirm_distance`` and ``localize.confirm_yaw`` of the
  particle filter's estimate taken just before the match is written into its particle (after,
  the match would agree with itself). A whole-map match that finds nothing in the whole map
  scoring higher than the particle it started from agrees too: the best particle is the best
  place the matcher can see. Without S2M (not ready, held back, switched off) the filter may
  converge, but it says "PF only, unconfirmed" and never "localized". Chosen over firing as
  "unconfirmed": a debugging tool's green must mean that two independent blocks agree, and every
  figure (metrics A–E, the false-fire rate) keeps counting only such localizations.
- **Second opinion** (``s2m.global_check_interval``): once localized, every that many scans, and
  at once when the confidence falls (the scan fits the map poorly at the estimate, see below, or
  ``DISAGREEMENTS_FOR_CHECK`` local matches in a row did not agree with it), the next match
  searches the whole map. It is never written into a particle unless it agrees with the
  estimate. A pose far from the estimate moves the filter there (``relocalized`` event with both
  scores) only if both blocks prefer it clearly: its BEV score is at least
  ``s2m.relocalize_score_ratio`` times the estimate's own, and in 3D the scan fits the map there
  clearly better than at the estimate (mean lookup-table residual below
  ``RELOCALIZE_RESIDUAL_RATIO`` times the estimate's, inlier share no lower). A far pose that
  fails either is a look-alike and changes nothing. (Measured: a VLP-16's sparse bird's-eye view
  let a far pose beat a correct estimate's BEV score by 1.25× once in a 400-scan lived-in drive;
  its 3D fit was worse.)
- **Poor fit**: the scan's mean residual at the estimate rises above ``FIT_RATIO`` times (and
  ``FIT_MARGIN_M`` above) its median over the last ``FIT_BASELINE_SCANS`` scans that fitted well
  while localized, its inlier share falls below ``FIT_SHARE_RATIO`` times its median over the
  same scans, or below ``localize.min_inlier_share``. Relative, not absolute: a correct
  estimate's mean residual is 0.12 m on the real drive and ~0.9 m for a VLP-16 or OS1-128 in the
  lived-in town (their beams above the map's sensor find nothing near), while an estimate 80 m
  off on the town scored 1.1 m against its 0.15 m. The inlier share separates best (measured
  over ``lidarloc bench integrity``'s 28 runs, every scan localized: a correct estimate's share
  never fell below 0.90 of its median, an estimate moved 60 m had 0.63–0.71 of it, in every
  sensor's town and on the real drive; the residual ratio overlapped, 1.8–2.0 for both on
  HDL-64E).
- **Withdrawal**: while localized, a whole-map check asked for by a poor fit that lands without
  agreeing with the estimate — a look-alike or no opinion — withdraws "localized"
  (``unconfirmed`` event): green means that the two blocks agree, and here they do not. The
  particles stay where they are; S2M searches the whole map again as before localization, and
  the rule must fire again with S2M's word. (A check that finds a clearly better pose
  relocalizes instead; one that agrees clears the doubt.) Local matches that disagree ask for
  the check but do not withdraw: in the robustness matrix a VLP-16's local matches disagreed
  with a correct estimate three times in a row and its whole-map check found a look-alike (3 of
  the 12 VLP-16 cells would have withdrawn a correct estimate).
- **Undecided doubt**: while localized, a poor fit that has lasted ``WITHDRAW_AFTER_POOR_FIT_SCANS``
  scans in a row with no whole-map match agreeing with the estimate meanwhile withdraws
  "localized" too, without waiting for the check: the check may not land in time (S2M busy with
  a long whole-map search, its landing waiting for a lagging odometry, its child restarting), and
  meanwhile the estimate is unconfirmed. Measured on the recordings of four real-time soaks of
  the town (114 runs, 137 k scans): every one of the 136 scans that were green while more than
  5 m off lay in a poor fit that had begun 1.5–2.7 m off (the filter drifting while S2M could
  not land, KISS-ICP behind the clock), none within its first 5 scans (after 8: 9 scans, after
  10: 21); 7 poor fits of an estimate never more than 2 m off lasted 5 scans or more (withdrawn:
  amber until S2M confirms again). A whole-map match that agreed in spite of a poor fit (the
  world changed there) keeps "localized" for ``CLEARED_DOUBT_HOLDS_SCANS`` scans.
- **Stale word** (``localize.confirm_within``): the rule fires only on an agreement at most that
  many scans old, and once localized, no agreement for that many scans withdraws "localized":
  S2M's word has gone stale, whatever the fit says (a filter that drifts along a street can keep
  fitting the map, and the poor-fit baseline, learned while localized, follows a slow drift).
  Localized, a match lands about every 10 scans: in an 85-minute real-time soak of the town (43
  runs, 5050 agreements while localized) the gaps between agreements had a median of 10 scans
  and a 99th percentile of 20; the two longer than 50 both hid a drift (3.6 and 9.3 m).
- **Loss** (``localize.lost_after_scans``): while localized, that many scans in a row that fit
  poorly, with no whole-map match agreeing with the estimate meanwhile, are a loss (re-initialise
  over the whole map), as the paper's std > 50 m.

Truth never feeds any of this; it only grades it (``false_fire`` events, :func:`truth_alarm`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..config import Config
from ..geometry import pose_to_xyz_ypr, wrap_angle

#: Local matches in a row that did not agree with the estimate, after which the second opinion
#: is asked for at once.
DISAGREEMENTS_FOR_CHECK = 3
#: Poor fit (module docstring): residual ratio and margin (m) over the baseline, and the baseline's
#: window (scans); the baseline needs FIT_MIN_SAMPLES scans before it judges.
FIT_RATIO = 2.0
FIT_MARGIN_M = 0.3
FIT_BASELINE_SCANS = 50
FIT_MIN_SAMPLES = 10
#: Poor fit (module docstring): an inlier share below this share of its recent median.
FIT_SHARE_RATIO = 0.8
#: Undecided doubt (module docstring): a poor fit this many scans in a row, with no whole-map
#: match agreeing meanwhile, withdraws "localized" (half a second at 10 Hz) …
WITHDRAW_AFTER_POOR_FIT_SCANS = 5
#: … unless a whole-map match agreed in spite of a poor fit within this many scans.
CLEARED_DOUBT_HOLDS_SCANS = 50
#: A far whole-map match moves the filter only if the scan's mean residual there is below this
#: share of the estimate's (module docstring).
RELOCALIZE_RESIDUAL_RATIO = 0.6
#: After a check asked for by low confidence, the next one waits at least this many scans (a
#: scan that fits poorly for many scans must not keep S2M on whole-map searches back to back).
CHECK_COOLDOWN_SCANS = 10
#: A first "localized" rests on S2M's word about the estimate of at most this many scans ago
#: (1 s at 10 Hz). In real time a match that agreed before the odometry let it land judged the
#: estimate it started from; a filter whose odometry lags can slide along a straight street
#: meanwhile with a small spread: on the 16 km² city from a city-wide start, 12.5 m in the 30
#: scans between such a match's start and its word, its std under 2 m, and the rule fired there.
#: Such a word still keeps an estimate already confirmed from going stale.
FIRST_FIX_WORD_AGE_SCANS = 10


@dataclass(frozen=True)
class Verdict:
    """What a landed S2M match says about the particle filter's estimate."""

    kind: str  # "agrees", "disagrees" (a far pose, written as the paper does before
    # localization), "relocalize" (a far pose clearly better: the filter
    # moves there), "look_alike" (a far pose not clearly better: ignored),
    # "no_opinion" (rejected: no pose to compare)
    mode: str  # the match's mode: "global", "local" or "check"
    distance_m: float  # x-y distance of the match pose to the estimate (nan: no opinion)
    yaw_rad: float  # |yaw difference| (nan: no opinion)
    pose: np.ndarray | None  # the match pose at the landing scan (4×4, world ← LiDAR)
    score: float  # the match's BEV score
    estimate_score: float  # the BEV score of the pose it started from (the best particle)
    # the scan whose estimate it judged, where that is not the scan it is taken at: a real-time
    # match that agreed before the odometry let it land judged the estimate it started from
    judged_at: int | None = None

    def describe(self) -> str:
        if self.pose is None:
            return "no pose"
        x, y = self.pose[0, 3], self.pose[1, 3]
        return (
            f"({x:.1f}, {y:.1f}), {self.distance_m:.1f} m and {math.degrees(self.yaw_rad):.0f}° from the "
            f"estimate; score {self.score:.0f} against the estimate's {self.estimate_score:.0f}"
        )


#: How a landing event names each verdict.
VERDICT_TEXT = {
    "agrees": "agrees with the estimate",
    "disagrees": "far from the estimate",
    "relocalize": "clearly better far from the estimate",
    "look_alike": "a look-alike far from the estimate",
    "no_opinion": "no opinion on the estimate",
}


def judge(
    mode: str,
    accepted: bool,
    unbeaten: bool,
    pose_k0: np.ndarray | None,
    estimate_pose: np.ndarray,
    score: float,
    start_score: float,
    cfg: Config,
) -> Verdict:
    """The verdict of one landed match (see the module docstring), judged at the scan k₀ it
    matched. ``pose_k0``: the accepted match, or for a search that nothing beat the start pose;
    ``estimate_pose``: the filter's estimate at k₀. The verdict's ``pose`` is ``pose_k0`` until
    the caller carries it forward to the landing scan."""
    pose_k = pose_k0
    if pose_k is None or not (accepted or unbeaten):
        return Verdict("no_opinion", mode, math.nan, math.nan, None, score, start_score)
    mx, my, _, myaw, _, _ = pose_to_xyz_ypr(pose_k)
    ex, ey, _, eyaw, _, _ = pose_to_xyz_ypr(estimate_pose)
    dist = float(math.hypot(mx - ex, my - ey))
    dyaw = float(abs(wrap_angle(myaw - eyaw)))
    lc = cfg.localize
    if dist <= lc.confirm_distance and dyaw <= lc.confirm_yaw:
        kind = "agrees"
    elif mode != "check":
        kind = "disagrees"
    elif accepted and np.isfinite(start_score) and score >= cfg.s2m.relocalize_score_ratio * max(start_score, 1e-9):
        kind = "relocalize"
    else:
        kind = "look_alike"
    return Verdict(kind, mode, dist, dyaw, np.asarray(pose_k, np.float64), float(score), float(start_score))


class Integrity:
    """The localizer's record of S2M's word on its estimate: when a match last agreed, when the
    next whole-map check is due, and how long the scan has fitted poorly."""

    def __init__(self, cfg: Config):
        self.cfg = cfg
        self.reset()

    def reset(self) -> None:
        """A new start (restart, re-initialisation, kidnap): nothing confirmed yet."""
        self.confirmed_at: int | None = None
        self.confirmed_about: int | None = None  # the scan whose estimate that agreement judged
        self.rejections_in_row = 0
        self.poor_fit_scans = 0
        self.check_reason: str | None = None  # why the next match should search the whole map
        self.check_doubt = False  # whether that check decides on a doubt (a poor fit)
        self.last_check_at: int | None = None
        self.localized_at: int | None = None
        self.fit_baseline: list[float] = []  # mean residuals of scans that fitted well while localized
        self.share_baseline: list[float] = []  # their inlier shares
        self.doubt: str | None = None  # the poor fit the whole-map check in flight decides on
        self.poor_fit_why: str | None = None  # why the latest scan fitted poorly
        self.doubt_cleared_at: int | None = None  # a whole-map match agreed in spite of a poor fit

    _STATE = (
        "confirmed_at",
        "confirmed_about",
        "rejections_in_row",
        "poor_fit_scans",
        "check_reason",
        "check_doubt",
        "last_check_at",
        "localized_at",
        "fit_baseline",
        "share_baseline",
        "doubt",
        "poor_fit_why",
        "doubt_cleared_at",
    )

    def state(self) -> dict:
        """What a checkpoint keeps (JSON-ready)."""
        return {name: getattr(self, name) for name in self._STATE}

    def load(self, state: dict) -> None:
        """Back to a :meth:`state` (missing entries keep their fresh values)."""
        for name in self._STATE:
            if name in state:
                setattr(self, name, state[name])
        if "confirmed_about" not in state:  # a checkpoint from before it was kept: the landing's own scan
            self.confirmed_about = self.confirmed_at

    # ------------------------------------------------------------------ confirmation
    def confirmed_since(self, k0: int | None, k: int | None = None) -> bool:
        """Whether a match agreed with the estimate at or after scan ``k0`` (and, at scan ``k``,
        within the last ``localize.confirm_within`` scans)."""
        if self.confirmed_at is None or k0 is None or self.confirmed_at < k0:
            return False
        return k is None or not self._stale(k)

    def confirms_first_fix(self, k0: int | None, k: int) -> bool:
        """Whether S2M's word lets the rule say "localized" for the first time at scan k, for a
        streak of small spread since scan ``k0``: a match agreed at or after ``k0`` and judged an
        estimate at most :data:`FIRST_FIX_WORD_AGE_SCANS` scans old."""
        if not self.confirmed_since(k0, k) or self.confirmed_about is None:
            return False
        return k - self.confirmed_about <= FIRST_FIX_WORD_AGE_SCANS

    def _stale(self, k: int) -> bool:
        """Whether the last agreement is more than ``localize.confirm_within`` scans old at scan k
        (never with 0; there must have been one)."""
        within = self.cfg.localize.confirm_within
        return within > 0 and self.confirmed_at is not None and k - self.confirmed_at > within

    def stale_word(self, k: int) -> str | None:
        """Why "localized" is withdrawn at scan k because no S2M match has agreed with the
        estimate for ``localize.confirm_within`` scans (module docstring), or None."""
        if not self.required or not self._stale(k):
            return None
        return f"no S2M match has agreed with the estimate for {k - self.confirmed_at} scans (since scan {self.confirmed_at})"

    @property
    def required(self) -> bool:
        return bool(self.cfg.localize.require_s2m_confirmation)

    def note_verdict(self, k: int, verdict: Verdict) -> str | None:
        """Take a landed match's verdict; returns why "localized" is withdrawn (module docstring:
        a whole-map check asked for by a poor fit did not agree), or None."""
        if verdict.kind == "agrees":
            self.confirmed_at = k
            self.confirmed_about = k if verdict.judged_at is None else verdict.judged_at
            if verdict.mode in ("global", "check"):
                if self.poor_fit_scans > 0 or self.doubt is not None:
                    self.doubt_cleared_at = k
                self.poor_fit_scans = 0  # the whole map agrees: a poor fit is the world's change
        if verdict.mode == "local":
            self.rejections_in_row = 0 if verdict.kind == "agrees" else self.rejections_in_row + 1
            if self.rejections_in_row >= DISAGREEMENTS_FOR_CHECK:
                self.want_check(k, f"{self.rejections_in_row} local matches in a row did not agree with the estimate")
        if verdict.mode == "check":
            self.rejections_in_row = 0
            doubt, self.doubt = self.doubt, None
            if doubt is not None and verdict.kind in ("look_alike", "no_opinion"):
                found = "found only a look-alike" if verdict.kind == "look_alike" else "gave no opinion"
                return f"S2M no longer confirms the estimate ({doubt}; the whole-map check {found})"
        return None

    # ------------------------------------------------------------------ the second opinion
    def on_localized(self, k: int) -> None:
        self.localized_at = k
        self.last_check_at = k

    def want_check(self, k: int, why: str, doubt: bool = False) -> None:
        """Ask for a whole-map check at the next match start (unless one ran just now). ``doubt``:
        the check decides whether the estimate keeps its "localized" (a poor fit, see the module
        docstring)."""
        periodic = self.check_reason == f"every {self.cfg.s2m.global_check_interval} scans"
        if (self.check_reason is None or periodic or (doubt and not self.check_doubt)) and (
            self.last_check_at is None or k - self.last_check_at >= CHECK_COOLDOWN_SCANS
        ):
            self.check_reason, self.check_doubt = why, doubt

    def check_due(self, k: int, localized: bool) -> str | None:
        """Why the match starting at scan k should be a whole-map check (None: it should not)."""
        interval = self.cfg.s2m.global_check_interval
        if not localized or interval <= 0:
            return None
        if self.check_reason is None and self.last_check_at is not None and k - self.last_check_at >= interval:
            self.check_reason = f"every {interval} scans"
        return self.check_reason

    def check_started(self, k: int) -> None:
        reason, self.check_reason = self.check_reason, None
        self.last_check_at = k
        # a check asked for by a poor fit decides on the doubt (not the periodic one, nor one
        # asked for by local disagreements: a VLP-16's local matches disagree with a correct
        # estimate three times in a row now and then, and its whole-map checks find look-alikes)
        self.doubt = reason if self.check_doubt else None
        self.check_doubt = False

    # ------------------------------------------------------------------ loss
    def poor_fit(self, inlier_share: float, residual: float | None) -> str | None:
        """Why the scan fits the map poorly at the estimate (module docstring), or None."""
        lc = self.cfg.localize
        if inlier_share < lc.min_inlier_share:
            return f"inlier share {inlier_share:.2f} < {lc.min_inlier_share:g}"
        if len(self.share_baseline) >= FIT_MIN_SAMPLES:
            share_base = float(np.median(self.share_baseline))
            if inlier_share < FIT_SHARE_RATIO * share_base:
                return f"inlier share {inlier_share:.2f} against {share_base:.2f} lately"
        if residual is None or len(self.fit_baseline) < FIT_MIN_SAMPLES:
            return None
        base = float(np.median(self.fit_baseline))
        if residual > max(FIT_RATIO * base, base + FIT_MARGIN_M):
            return f"mean residual {residual:.2f} m against {base:.2f} m lately"
        return None

    def note_fit(self, k: int, localized: bool, inlier_share: float, residual: float | None) -> str | None:
        """Take scan k's fit at the estimate; the loss's detail when a poor fit has lasted too long."""
        lc = self.cfg.localize
        if not localized:
            self.poor_fit_scans = 0
            self.fit_baseline = []
            self.share_baseline = []
            self.doubt = None
            return None
        why = self.poor_fit(inlier_share, residual)
        if why is None:
            self.poor_fit_scans = 0
            if residual is not None:
                self.fit_baseline = (self.fit_baseline + [float(residual)])[-FIT_BASELINE_SCANS:]
                self.share_baseline = (self.share_baseline + [float(inlier_share)])[-FIT_BASELINE_SCANS:]
            return None
        self.poor_fit_scans += 1
        self.poor_fit_why = why
        if self.cfg.s2m.global_check_interval > 0:
            self.want_check(k, why, doubt=True)
        if lc.lost_after_scans > 0 and self.poor_fit_scans >= lc.lost_after_scans:
            self.poor_fit_scans = 0
            return (
                f"the scan fitted the map poorly ({why}) for {lc.lost_after_scans} scans and no "
                "whole-map match agreed with the estimate"
            )
        return None

    def undecided_doubt(self, k: int) -> str | None:
        """Why "localized" is withdrawn at scan k because a poor fit has lasted
        ``WITHDRAW_AFTER_POOR_FIT_SCANS`` scans with no whole-map match agreeing (module
        docstring), or None. Call after :meth:`note_fit`; says it once per poor fit. Only where
        green needs S2M's word (``localize.require_s2m_confirmation``; the paper's rule has no
        such withdrawal)."""
        if not self.required or self.poor_fit_scans != WITHDRAW_AFTER_POOR_FIT_SCANS:
            return None
        if self.doubt_cleared_at is not None and k - self.doubt_cleared_at < CLEARED_DOUBT_HOLDS_SCANS:
            return None
        return (
            f"the scan has fitted the map poorly for {self.poor_fit_scans} scans ({self.poor_fit_why}) "
            "and no whole-map match has agreed with the estimate"
        )


def fits_clearly_better(candidate: tuple[float, float], estimate: tuple[float, float]) -> bool:
    """Whether the scan fits the map clearly better at a candidate pose than at the estimate:
    each is (inlier share, mean residual m) from :func:`~lidarloc.core.filter.likelihood.residual_stats`."""
    (c_share, c_res), (e_share, e_res) = candidate, estimate
    if not math.isfinite(c_res):
        return False
    if not math.isfinite(e_res):
        return True
    return c_res < RELOCALIZE_RESIDUAL_RATIO * e_res and c_share >= e_share
