"""A ``lidarloc bench integrity`` run's figures from its per-scan records and events: false fires,
scans green and wrong, recovery and the rule's floor (what each means: :mod:`.integrity`)."""

from __future__ import annotations

import json
import math
from pathlib import Path

from ...core.config import LocalizeConfig
from ...core.rules.truth import FALSE_FIRE_M
from ...core.runs.results import integrity_summary

#: the run summary's counts of relocalizations and withdrawals a case reports as they are
MOVE_KEYS = ("relocalizations", "spurious_relocalizations", "withdrawals", "spurious_withdrawals")


def case_figures(records: list, events: list, at: int, localize: LocalizeConfig | None = None) -> dict:
    """A run's integrity figures from its per-scan records and events, the disturbance at scan
    ``at`` (see the module docstring); None where the run has no truth. ``localize``: the rule's
    settings, for the rule's floor (the defaults when None)."""
    localize = localize or LocalizeConfig()
    # relocalizations and withdrawals, and which were of a correct estimate: as the run's summary counts them
    counted = integrity_summary(events, records)
    moves = {key: counted[key] for key in MOVE_KEYS}
    err = {r.scan: r.error_m for r in records}
    if not any(v is not None for v in err.values()):
        return {
            "estimate_recovery": None,
            "rule_floor": None,
            "false_fires": None,
            "wrong_green": None,
            "noticed": None,
            "recovery": None,
            "lost_after": None,
            **moves,
        }
    onsets = [e.scan for e in events if e.kind == "localized"]
    false_fires = sum(1 for k in onsets if err.get(k) is not None and err[k] > FALSE_FIRE_M)
    after = [r for r in records if r.scan >= at]
    wrong_green = sum(1 for r in after if r.localized and r.error_m is not None and r.error_m > FALSE_FIRE_M)
    right = next((r.scan for r in after if r.localized and r.error_m is not None and r.error_m <= FALSE_FIRE_M), None)
    honest = next(
        (r.scan for r in after if not (r.localized and r.error_m is not None and r.error_m > FALSE_FIRE_M)), None
    )
    lost = next((e.scan for e in events if e.kind == "loss" and e.scan >= at), None)
    # a run resumed after a kidnap numbers its scans from where the vehicle landed
    first = after[0].scan if after else at
    return {
        **floor_figures(records, first, localize, {e.scan for e in events if e.kind in STREAK_RESETS}),
        "false_fires": false_fires,
        "wrong_green": wrong_green,
        "noticed": None if honest is None else (honest - first if after else None),
        "recovery": None if right is None else right - first,
        "lost_after": None if lost is None else lost - first,
        **moves,
    }


#: events after which the rule's streak starts again (see core/rules/paper.py, core/localizer)
STREAK_RESETS = ("false_positive", "loss", "relocalized", "unconfirmed", "reset", "kidnap")


def floor_figures(records: list, first: int, localize: LocalizeConfig, resets: set | frozenset = frozenset()) -> dict:
    """How soon the filter could have said "localized" at all after the disturbance at scan
    ``first`` (``records``: the run's per-scan records, with truth; ``resets``: the scans of events
    that restart the rule's streak, :data:`STREAK_RESETS`).

    ``estimate_recovery``: scans from the disturbance until the estimate is within 5 m of the
    truth and stays so for the rule's window (``min_consecutive`` scans), whether or not the rule
    fired. ``rule_floor``: the fewest scans after the disturbance at which the paper's rule could
    fire with that estimate: a streak of at least ``min_consecutive`` scans with the filter's std
    below ``std_threshold`` (it may have begun before the estimate was right, but not before the
    last reset) over which the vehicle drove ``min_moved`` or turned ``min_turned`` (by the
    truth), ending no sooner than the estimate was right. A vehicle standing at a junction
    raises the floor: no recovery can be counted sooner."""
    none = {"estimate_recovery": None, "rule_floor": None}
    n_window = max(1, int(localize.min_consecutive))
    ok = [r.error_m is not None and r.error_m <= FALSE_FIRE_M for r in records]
    at = next((i for i, r in enumerate(records) if r.scan >= first), len(records))
    right = next((i for i in range(at, len(records) - n_window + 1) if all(ok[i : i + n_window])), None)
    if right is None:
        return none

    def small(r) -> bool:
        return max(r.std_x, r.std_y) < localize.std_threshold

    start = right
    while start > 0 and records[start].scan not in resets and small(records[start - 1]):
        start -= 1  # the streak that was running when the estimate came right
    if any(r.gt_x is None or r.gt_yaw is None for r in records[start:]):
        return none
    path, yaw0 = 0.0, float(records[start].gt_yaw)
    floor = None
    for i in range(start + 1, len(records)):
        a, b = records[i - 1], records[i]
        path += math.hypot(b.gt_x - a.gt_x, b.gt_y - a.gt_y)
        turned = abs((b.gt_yaw - yaw0 + math.pi) % (2 * math.pi) - math.pi)
        if i >= right and i - start + 1 >= n_window and (path >= localize.min_moved or turned >= localize.min_turned):
            floor = max(0, records[i].scan - first)
            break
    return {"estimate_recovery": max(0, records[right].scan - first), "rule_floor": floor}


def figures_from_run_dir(run_dir: Path, figures: dict, localize: LocalizeConfig | None = None) -> dict:
    """``figures`` (a kept ``integrity.json``) with the rule's floor counted again from the run's
    own ``scans.csv`` and ``events.json`` (a kept run may predate how the floor is counted)."""
    import csv
    from types import SimpleNamespace

    def num(row: dict, key: str) -> float | None:
        return None if row.get(key) in (None, "") else float(row[key])

    with open(run_dir / "scans.csv", newline="") as fh:
        rows = [
            SimpleNamespace(
                scan=int(row["scan"]),
                **{key: num(row, key) for key in ("error_m", "std_x", "std_y", "gt_x", "gt_y", "gt_yaw")},
            )
            for row in csv.DictReader(fh)
        ]
    events = json.loads((run_dir / "events.json").read_text())
    events = events if isinstance(events, list) else events.get("events", [])
    resets = {int(e["scan"]) for e in events if e.get("kind") in STREAK_RESETS}
    at = int(figures["disturbance_scan"])
    first = next((r.scan for r in rows if r.scan >= at), at)
    return {**figures, **floor_figures(rows, first, localize or LocalizeConfig(), resets)}


# ------------------------------------------------------------------------------ look-alike start
