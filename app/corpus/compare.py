"""``lidarloc corpus compare BASE NEW``: what got worse from one corpus run to the other, beyond
the seed-to-seed noise (:mod:`.noise`), where along each drive, and the viewer command that
shows it.

Per drive of both runs: each whole-drive figure (:data:`~.figures.FIGURES`), and each stretch of
NEW's health (poor fit, wrong, unlocalized) that BASE lacks or that grew: its scans beyond the
scans of BASE's stretches of the same kind that it overlaps, weighed against the threshold of the
count it adds to. A whole-drive count whose kind has a stretch reported is not reported again:
the stretch says the same with where. Improvements are the same, BASE and NEW swapped.

The first diverging scan of a drive is the first scan where the two runs' estimates differ
(x or y by more than :data:`XY_TOL_M`, yaw by more than :data:`YAW_TOL_RAD`, from scans.csv) or
that only one of them processed: from there on every difference is the change's doing.

Ranking, worst first: false fires and wrong localization before anything else, then by severity,
the change's excess over its threshold in threshold units (a threshold of 0 counts in the
figure's own unit: one scan, 0.01 m).
"""

from __future__ import annotations

import math
import shlex
from pathlib import Path

import numpy as np

from .figures import BY_NAME, FIGURES, STRETCH_FIGURE, CorpusOutput, DriveRun
from .noise import K, Noise, measure_noise, noise_table

#: the estimates of two runs are the same within these (scans.csv keeps 6 significant digits:
#: a centimetre at a kilometre from the map's origin)
XY_TOL_M = 0.05
YAW_TOL_RAD = math.radians(0.5)


def first_diverging_scan(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> int | None:
    """The first scan where tables ``a`` and ``b`` (scans.csv columns) disagree on x, y or yaw,
    or that only one of them holds, up to the last scan both reach; None: they agree throughout."""
    sa, sb = a.get("scan", np.zeros(0)), b.get("scan", np.zeros(0))
    if not len(sa) or not len(sb):
        return None
    upto = min(sa.max(), sb.max())
    scans = np.union1d(sa[sa <= upto], sb[sb <= upto])
    ia, ib = np.searchsorted(sa, scans), np.searchsorted(sb, scans)
    in_a = (ia < len(sa)) & (sa[np.minimum(ia, len(sa) - 1)] == scans)
    in_b = (ib < len(sb)) & (sb[np.minimum(ib, len(sb) - 1)] == scans)
    differs = in_a != in_b
    both = in_a & in_b
    ja, jb = ia[both], ib[both]

    def apart(column: str, tol: float, wrap: bool = False) -> np.ndarray:
        x, y = a[column][ja], b[column][jb]
        d = np.abs(x - y)
        if wrap:
            d = np.abs((x - y + np.pi) % (2 * np.pi) - np.pi)
        # NaN on one side only is a difference; on both, none
        return np.where(np.isnan(x) | np.isnan(y), np.isnan(x) != np.isnan(y), d > tol)

    differs[both] = apart("x", XY_TOL_M) | apart("y", XY_TOL_M) | apart("yaw", YAW_TOL_RAD, wrap=True)
    hits = np.flatnonzero(differs)
    return int(scans[hits[0]]) if hits.size else None


def _length(stretch: dict) -> int:
    return stretch["last_scan"] - stretch["first_scan"] + 1


def grown_stretches(before: list[dict], after: list[dict]) -> list[tuple[dict, int]]:
    """``after``'s stretches of the compared kinds, each with the scans of ``before``'s stretches
    of the same kind that overlap it (0: a new stretch)."""
    out = []
    for s in after:
        if s["kind"] not in STRETCH_FIGURE:
            continue
        overlap = [
            b
            for b in before
            if b["kind"] == s["kind"] and b["first_scan"] <= s["last_scan"] and s["first_scan"] <= b["last_scan"]
        ]
        out.append((s, sum(_length(b) for b in overlap)))
    return out


def view_command(base: Path, new: Path, name: str, scan: int) -> str:
    """The command that opens both runs of drive ``name`` side by side at ``scan``."""
    a, b = shlex.quote(str(Path(base) / "drives" / name)), shlex.quote(str(Path(new) / "drives" / name))
    return f"lidarloc view --run {a} --run {b} --at {scan}"


def _shown(name: str, value: float | None, drive: DriveRun) -> str:
    if value is None:
        return "—"
    if name == "first_fix_scan" and drive.health.get("first_fix") is None:
        return "never"
    return f"{value:.{BY_NAME[name].digits}f}"


class _DriveComparison:
    """One drive's regressions and improvements (both lists of entries as the report lists them)."""

    def __init__(self, name: str, base: CorpusOutput, new: CorpusOutput, noise: Noise):
        self.name, self.base_out, self.new_out, self.noise = name, base, new, noise
        self.b, self.n = base.drives[name], new.drives[name]
        self.diverging = first_diverging_scan(self.b.table, self.n.table)
        scans = self.n.table.get("scan", np.zeros(1))
        self.first_scan = int(scans[0]) if len(scans) else 0
        self.regressions = self._stretches(self.b, self.n, worse=True)
        self.improvements = self._stretches(self.n, self.b, worse=False)
        self._whole_drive()

    def _entry(self, figure: str, stretch: dict | None, base, new, threshold: float, change: float) -> dict:
        f = BY_NAME[figure]
        at = stretch["first_scan"] if stretch is not None else self.diverging
        if at is None:
            at = self.first_scan
        return {
            "drive": self.name,
            "stretch": None if stretch is None else {k: stretch[k] for k in ("first_scan", "last_scan")},
            "kind": None if stretch is None else stretch["kind"],
            "figure": figure,
            "label": f.label,
            "base": base,
            "new": new,
            "threshold": threshold,
            "severity": (change - threshold) / max(threshold, f.scale),
            "first_diverging_scan": self.diverging,
            "at": int(at),
            "view": view_command(self.base_out.folder, self.new_out.folder, self.name, int(at)),
        }

    def _stretches(self, before: DriveRun, after: DriveRun, worse: bool) -> list[dict]:
        found = []
        for s, was in grown_stretches(before.health.get("stretches", []), after.health.get("stretches", [])):
            figure = STRETCH_FIGURE[s["kind"]]
            change, threshold = _length(s) - was, self.noise.threshold(self.name, figure)
            if change > threshold:
                base, new = (was, _length(s)) if worse else (_length(s), was)
                entry = self._entry(figure, s, base, new, threshold, change)
                what = "new" if was == 0 else f"{was} scans there before"
                if worse:
                    entry["text"] = f"{s['text']} ({what}, {_length(s)} scans in NEW)"
                else:
                    gone = "gone" if was == 0 else f"{was} scans there now"
                    entry["text"] = f"{s['text']} in BASE ({gone})"
                found.append(entry)
        return found

    def _whole_drive(self) -> None:
        fb, fn = self.b.figures(), self.n.figures()
        told = {
            (e["figure"], worse) for worse, es in ((True, self.regressions), (False, self.improvements)) for e in es
        }
        for f in FIGURES:
            base, new = fb[f.name], fn[f.name]
            if base is None or new is None:  # no truth, never localized: nothing to weigh
                continue
            change, threshold = f.worse * (new - base), self.noise.threshold(self.name, f.name)
            if abs(change) <= threshold or (f.name, change > 0) in told:
                continue
            entry = self._entry(f.name, None, base, new, threshold, abs(change))
            entry["text"] = (
                f"{f.label}: {_shown(f.name, base, self.b)} → {_shown(f.name, new, self.n)} "
                f"(beyond noise: a change of more than {threshold:.{f.digits}f})"
            )
            (self.regressions if change > 0 else self.improvements).append(entry)


def _rank(entries: list[dict]) -> list[dict]:
    return sorted(entries, key=lambda e: (not BY_NAME[e["figure"]].first, -e["severity"], e["drive"], e["at"]))


def compare_outputs(base: CorpusOutput, new: CorpusOutput) -> dict:
    """The comparison of two corpus outputs: regressions and improvements ranked worst (best)
    first, the drives compared, unchanged, or in one output only, each compared drive's first
    diverging scan, and the noise rule's figures."""
    noise = measure_noise(base, new)
    common = [name for name in new.drives if name in base.drives]
    regressions, improvements, unchanged, diverging = [], [], [], {}
    for name in common:
        drive = _DriveComparison(name, base, new, noise)
        regressions += drive.regressions
        improvements += drive.improvements
        diverging[name] = drive.diverging
        if not drive.regressions and not drive.improvements:
            unchanged.append(name)
    return {
        "base": str(base.folder),
        "new": str(new.folder),
        "regressions": _rank(regressions),
        "drives_compared": len(common),
        "improvements": _rank(improvements),
        "only_in_base": [name for name in base.drives if name not in new.drives],
        "only_in_new": [name for name in new.drives if name not in base.drives],
        "unchanged": unchanged,
        "first_diverging_scan": diverging,
        "noise": {"k": K, "seed_groups": len(noise.groups), "figures": noise_table(noise)},
    }


#: what ``--json`` prints of :func:`compare_outputs`
JSON_KEYS = ("regressions", "drives_compared", "improvements", "only_in_base", "only_in_new")
