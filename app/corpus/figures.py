"""A ``lidarloc corpus run`` output folder read back, and each drive's figures as
``lidarloc corpus compare`` weighs them.

The figures come from what the run wrote: corpus.json's health of each drive (:mod:`.health`) and
the drive's scans.csv; drive.json (its source, configuration and seed) says which drives are one
log under several seeds. Each figure has a direction (which way is worse), a floor (the smallest
change that counts however quiet the seeds are) and a scale (a severity's unit when the floor is
0: one scan, 0.01 m). Late scans are left out: wall-clock figures, they vary with the machine's
load, not with the change compared.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ...core.errors import LidarlocError
from .health import read_run
from .spec import IDENTITY_FILE


@dataclass(frozen=True)
class Figure:
    name: str
    label: str
    worse: int  # +1: a higher value is worse; -1: a lower one
    floor: float  # a change must exceed this to count, whatever the seeds' spread
    scale: float  # the severity's unit where the threshold is 0
    digits: int = 0  # decimals shown
    first: bool = False  # ranked before every other kind of regression


FIGURES = (
    # a false fire or a wrong localized scan is what a user must never see: any new one counts
    Figure("false_fires", "false fires", +1, 0.0, 1.0, first=True),
    Figure("wrong_scans", "localized but wrong (scans)", +1, 0.0, 1.0, first=True),
    # a few centimetres is what a different subsample of the scan moves the estimate by
    Figure("rmse_localized_m", "RMSE while localized (m)", +1, 0.05, 0.01, digits=3),
    # a never-localized drive counts as localized after its last scan (its scan count)
    Figure("first_fix_scan", "first fix (scan)", +1, 5.0, 1.0),
    Figure("withdrawals", "withdrawals", +1, 0.0, 1.0),
    Figure("poor_fit_scans", "poor-fit scans", +1, 5.0, 1.0),
    Figure("unlocalized_scans", "unlocalized scans after the first fix", +1, 5.0, 1.0),
    Figure("inlier_share_median", "median inlier share (localized scans)", -1, 0.02, 0.01, digits=3),
)
BY_NAME = {f.name: f for f in FIGURES}
#: a stretch kind and the whole-drive count it adds to: a stretch's growth is weighed against
#: that count's threshold
STRETCH_FIGURE = {"poor_fit": "poor_fit_scans", "wrong": "wrong_scans", "unlocalized": "unlocalized_scans"}


@dataclass
class DriveRun:
    """One drive of a corpus output: its folder, summary, health and identity (None: no drive.json)."""

    name: str
    folder: Path
    summary: dict
    health: dict
    identity: dict | None
    _table: dict | None = field(default=None, repr=False)

    @property
    def table(self) -> dict[str, np.ndarray]:
        """Its scans.csv as columns (read once)."""
        if self._table is None:
            if not (self.folder / "scans.csv").is_file():
                raise LidarlocError(f"{self.folder}: no scans.csv (drive '{self.name}' of corpus.json is incomplete)")
            self._table = read_run(self.folder)[0]
        return self._table

    @property
    def seed_group(self) -> str | None:
        """What the drive is apart from its seed (source, configuration, preset), as text: drives
        with the same text are one log under several seeds."""
        if self.identity is None:
            return None
        rest = {k: v for k, v in self.identity.items() if k not in ("seed", "code")}
        return json.dumps(rest, sort_keys=True, default=str)

    @property
    def seed(self):
        return None if self.identity is None else self.identity.get("seed")

    def figures(self) -> dict[str, float | None]:
        """Each of :data:`FIGURES` (None where the drive cannot say: no truth, never localized)."""
        h = self.health
        table = self.table
        n = len(table.get("scan", ()))
        fix = h.get("first_fix")
        share = table.get("inlier_share", np.full(n, np.nan))
        localized = table.get("localized", np.zeros(n)) == 1
        shares = share[localized & np.isfinite(share)]
        unlocalized = [s for s in h.get("stretches", []) if s["kind"] == "unlocalized"]
        return {
            "false_fires": h.get("false_fires"),
            "wrong_scans": h.get("wrong_scans"),
            "rmse_localized_m": h.get("rmse_localized_m"),
            "first_fix_scan": float(n if fix is None else fix["scan"]),
            "withdrawals": float(len(h.get("withdrawals", []))),
            "poor_fit_scans": h.get("poor_fit_scans"),
            "unlocalized_scans": float(sum(s["last_scan"] - s["first_scan"] + 1 for s in unlocalized)),
            "inlier_share_median": float(np.median(shares)) if shares.size else None,
        }


@dataclass
class CorpusOutput:
    """A ``lidarloc corpus run --out`` folder: its drives that finished, by name."""

    folder: Path
    drives: dict[str, DriveRun]

    def seed_siblings(self, name: str) -> list[str]:
        """The drives that are drive ``name``'s log under other seeds, itself included (its
        name alone when it has none)."""
        group = self.drives[name].seed_group
        if group is None:
            return [name]
        return [n for n, d in self.drives.items() if d.seed_group == group]


def read_output(folder: Path, role: str) -> CorpusOutput:
    """The corpus output in ``folder`` (``role``, BASE or NEW, names it in errors): one-line
    :class:`LidarlocError` for a missing folder, one without corpus.json or an unreadable one."""
    folder = Path(folder)
    if not folder.is_dir():
        raise LidarlocError(f"{folder}: no such folder ({role}: the --out folder of a lidarloc corpus run)")
    path = folder / "corpus.json"
    if not path.is_file():
        raise LidarlocError(f"{folder}: no corpus.json ({role} must be the --out folder of a lidarloc corpus run)")
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise LidarlocError(f"{path}: unreadable ({first})") from None
    drives_data = data.get("drives") if isinstance(data, dict) else None
    if not isinstance(drives_data, dict):
        raise LidarlocError(f"{path}: not a corpus.json of lidarloc corpus run (no 'drives')")
    drives = {}
    for name, entry in drives_data.items():
        if not isinstance(entry, dict) or not isinstance(entry.get("health"), dict):
            raise LidarlocError(f"{path}: drive '{name}' has no health")
        drive_dir = folder / "drives" / name
        marker = drive_dir / IDENTITY_FILE
        identity = None
        if marker.is_file():
            try:
                identity = json.loads(marker.read_text())
            except (OSError, ValueError):
                identity = None  # without it the drive simply has no seed siblings
        drives[name] = DriveRun(name, drive_dir, entry.get("summary") or {}, entry["health"], identity)
    return CorpusOutput(folder, drives)
