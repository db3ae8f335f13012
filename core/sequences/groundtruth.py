"""Ground-truth pose files and matching them to scans by time.

Formats (evo's conventions):

- **TUM**: one pose per line, ``t x y z qx qy qz qw`` (seconds, metres, unit quaternion with w
  last); ``#`` lines are comments.
- **KITTI**: one pose per line, 12 numbers (the row-major 3×4 top of the 4×4 pose). The format has
  no times: they come from a separate file (one time in seconds per line, as KITTI's
  ``times.txt``), or else pose ``i`` belongs to scan ``i``.

:func:`load_truth` tells the two apart by the number of columns (8 or 12).

Matching (:func:`match`): a scan takes the truth sample nearest in time when one lies within
``tol`` (20 ms: half a 10 Hz scan period would mix up neighbouring scans, and GPS/INS logs at
≥ 50 Hz always have a sample that close); otherwise the pose interpolated between the samples
either side (linear in position, slerp in rotation). A scan before the first or after the last
sample has no truth.

What a sequence does with scans without truth (:func:`truth_for_scans`): it **drops them** and
says so in a note, rather than keeping them with no pose. Everything downstream (the prior map,
the error plots, the metrics A–E) assumes that a sequence with poses has one for every scan, and
the truth's span is contiguous, so only scans at the start or the end of the recording go.
Truth whose times do not overlap the scans' at all is an error (usually a truth file in
relative seconds beside a recording in Unix time, or the other way round).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import DataError

#: a truth sample this close in time to a scan is taken as is (seconds)
MATCH_TOL_S = 0.02


@dataclass(frozen=True)
class Truth:
    """Poses (N, 4, 4) of some body in the truth's world frame, with their times (N,) in seconds,
    or None when they are matched to scans by index (a KITTI file without a times file)."""

    poses: np.ndarray
    times: np.ndarray | None
    source: str

    def __len__(self) -> int:
        return len(self.poses)


def _number_rows(path: Path) -> list[tuple[int, np.ndarray]]:
    if not path.is_file():
        raise DataError(f"{path}: ground-truth file not found")
    rows = []
    with open(path, errors="replace") as f:
        for lineno, line in enumerate(f, 1):
            line = line.split("#", 1)[0].strip()
            if not line:
                continue
            try:
                rows.append((lineno, np.array([float(v) for v in line.replace(",", " ").split()])))
            except ValueError:
                raise DataError(f"{path}:{lineno}: not a line of numbers") from None
    if not rows:
        raise DataError(f"{path}: no poses in file")
    return rows


def _rows_of(path: Path, rows, width: int, what: str) -> np.ndarray:
    for lineno, values in rows:
        if values.size != width:
            raise DataError(f"{path}:{lineno}: expected {width} numbers ({what}), got {values.size}")
    table = np.vstack([v for _, v in rows])
    if not np.isfinite(table).all():
        raise DataError(f"{path}: NaN or infinite values")
    return table


def read_tum(path: str | os.PathLike) -> Truth:
    from scipy.spatial.transform import Rotation

    path = Path(path)
    table = _rows_of(path, _number_rows(path), 8, "TUM: t x y z qx qy qz qw")
    q = table[:, 4:8]
    norms = np.linalg.norm(q, axis=1)
    if (norms < 1e-6).any():
        raise DataError(f"{path}: a quaternion is zero (line {int(np.argmax(norms < 1e-6)) + 1} of the poses)")
    poses = np.tile(np.eye(4), (len(table), 1, 1))
    poses[:, :3, :3] = Rotation.from_quat(q / norms[:, None]).as_matrix()
    poses[:, :3, 3] = table[:, 1:4]
    return Truth(poses=poses, times=table[:, 0].copy(), source=str(path))


def read_times(path: str | os.PathLike) -> np.ndarray:
    """One time (seconds) per line, as KITTI's ``times.txt``."""
    path = Path(path)
    table = _rows_of(path, _number_rows(path), 1, "one time in seconds")
    return table[:, 0].copy()


def read_times_precise(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """A times file as (absolute, since the first) seconds. The second is computed from the decimal
    text, so Unix times (~1.7·10⁹ s, where float64 resolves only ~0.2 µs) keep every digit given."""
    from decimal import Decimal, InvalidOperation

    absolute = read_times(path)
    lines = [
        ln.split("#", 1)[0].replace(",", " ").strip() for ln in Path(path).read_text(errors="replace").splitlines()
    ]
    try:
        exact = [Decimal(ln) for ln in lines if ln]
    except InvalidOperation:  # read_times accepted it: a float-only spelling
        return absolute, absolute - absolute[0]
    return absolute, np.array([float(t - exact[0]) for t in exact], dtype=np.float64)


def read_kitti(path: str | os.PathLike, times: str | os.PathLike | np.ndarray | None = None) -> Truth:
    path = Path(path)
    table = _rows_of(path, _number_rows(path), 12, "KITTI: a row-major 3×4 pose")
    poses = np.tile(np.eye(4), (len(table), 1, 1))
    poses[:, :3, :4] = table.reshape(-1, 3, 4)
    t = None
    if times is not None:
        t = read_times(times) if isinstance(times, (str, os.PathLike)) else np.asarray(times, dtype=np.float64)
        if len(t) != len(poses):
            where = "the times" if isinstance(times, np.ndarray) else str(times)
            raise DataError(f"{path}: {len(poses)} poses but {len(t)} times in {where}")
    return Truth(poses=poses, times=t, source=str(path))


def load_truth(path: str | os.PathLike, times: str | os.PathLike | None = None) -> Truth:
    """A TUM or KITTI poses file, told apart by its number of columns (8 or 12)."""
    path = Path(path)
    rows = _number_rows(path)
    width = rows[0][1].size
    if width == 8:
        if times is not None:
            raise DataError(
                f"{path}: a TUM file carries its own times; a separate times file applies to KITTI poses only"
            )
        return read_tum(path)
    if width == 12:
        return read_kitti(path, times)
    raise DataError(
        f"{path}: {width} numbers per line; ground truth must be TUM (8: t x y z qx qy qz qw) or KITTI (12: a 3×4 pose)"
    )


def _sorted_unique(truth: Truth) -> tuple[np.ndarray, np.ndarray]:
    order = np.argsort(truth.times, kind="stable")
    t, poses = truth.times[order], truth.poses[order]
    keep = np.r_[True, np.diff(t) > 0]
    return t[keep], poses[keep]


def match(scan_times: np.ndarray, truth: Truth, tol: float = MATCH_TOL_S) -> tuple[np.ndarray, np.ndarray]:
    """Truth poses at ``scan_times`` (absolute seconds, on the truth's clock).

    Returns ``(poses (M, 4, 4), has (M,) bool)``; where ``has`` is False the pose is NaN. Raises
    DataError when no scan falls inside the truth's span."""
    from scipy.spatial.transform import Rotation

    s = np.asarray(scan_times, dtype=np.float64)
    if truth.times is None:
        if len(truth) != len(s):
            raise DataError(
                f"{truth.source}: {len(truth)} poses for {len(s)} scans and no times to match them by "
                "(give a times file, or poses one per scan)"
            )
        return truth.poses.copy(), np.ones(len(s), dtype=bool)
    t, poses = _sorted_unique(truth)
    out = np.full((len(s), 4, 4), np.nan)
    has = np.zeros(len(s), dtype=bool)
    idx = np.searchsorted(t, s)  # t[idx-1] < s ≤ t[idx]
    lo, hi = np.clip(idx - 1, 0, len(t) - 1), np.clip(idx, 0, len(t) - 1)
    nearest = np.where(np.abs(s - t[lo]) <= np.abs(t[hi] - s), lo, hi)
    close = np.abs(t[nearest] - s) <= tol
    out[close] = poses[nearest[close]]
    has[close] = True
    inside = ~close & (idx > 0) & (idx < len(t))
    if inside.any():
        a, b = idx[inside] - 1, idx[inside]
        f = (s[inside] - t[a]) / (t[b] - t[a])
        Ra, Rb = poses[a, :3, :3], poses[b, :3, :3]
        step = Rotation.from_matrix(np.swapaxes(Ra, 1, 2) @ Rb).as_rotvec()
        interp = np.tile(np.eye(4), (len(a), 1, 1))
        interp[:, :3, :3] = Ra @ Rotation.from_rotvec(step * f[:, None]).as_matrix()
        interp[:, :3, 3] = (1 - f)[:, None] * poses[a, :3, 3] + f[:, None] * poses[b, :3, 3]
        out[inside] = interp
        has[inside] = True
    if not has.any():
        raise DataError(
            f"{truth.source}: ground-truth times {t[0]:.3f}–{t[-1]:.3f} s do not overlap the scans' "
            f"times {s.min():.3f}–{s.max():.3f} s (same clock? TUM times must be the scans' header stamps)"
        )
    return out, has


@dataclass
class MatchedTruth:
    """The truth of a recording's scans, moved to the LiDAR: ``keep`` the indices of the scans
    that have truth (every other scan is dropped), ``poses`` their world ← LiDAR poses in the
    truth's own frame (not re-based), ``notes`` what a user should know."""

    keep: np.ndarray
    poses: np.ndarray
    notes: list[str] = field(default_factory=list)
    source: str = ""  # the truth's file

    @property
    def origin(self) -> np.ndarray:
        """The first kept scan's LiDAR pose in the truth's frame (a sequence's ``truth_origin``)."""
        return self.poses[0].copy()

    @property
    def rebased(self) -> np.ndarray:
        """The poses in the frame of the first one, as every Sequence gives them."""
        from ..geometry import inv_pose

        return inv_pose(self.poses[0])[None] @ self.poses

    @property
    def identity(self) -> str:
        """The truth file's identity, for cache keys."""
        from ..cache import file_identity

        return file_identity(self.source)


def truth_for_scans(
    scan_times: np.ndarray, truth: Truth, T_base_lidar: np.ndarray | None, tol: float = MATCH_TOL_S
) -> MatchedTruth:
    """Match ``truth`` to the scans and move it to the LiDAR: ``T_world_lidar = T_world_base ·
    T_base_lidar`` (identity when None)."""
    poses, has = match(scan_times, truth, tol)
    keep = np.flatnonzero(has)
    lidar = poses[keep]
    if T_base_lidar is not None:
        lidar = lidar @ np.asarray(T_base_lidar, dtype=np.float64)[None]
    notes = []
    dropped = len(has) - len(keep)
    if dropped:
        before = int(keep[0]) if len(keep) else 0
        after = dropped - before
        notes.append(
            f"{truth.source}: {dropped} of {len(has)} scans lie outside the ground truth's time span and "
            f"are left out ({before} at the start, {after} at the end)"
        )
    return MatchedTruth(keep=keep, poses=lidar, notes=notes, source=str(truth.source))


def truth_of_recording(
    gt, gt_times, scan_times: np.ndarray, T_base_lidar: np.ndarray | None, tol: float = MATCH_TOL_S
) -> MatchedTruth:
    """A recording's ``--gt`` (a file, or a :class:`Truth` already read; ``gt_times`` for KITTI
    files) matched to its scan times (seconds) and moved to the LiDAR (:func:`truth_for_scans`)."""
    truth = gt if isinstance(gt, Truth) else load_truth(gt, gt_times)
    return truth_for_scans(scan_times, truth, T_base_lidar, tol)
