"""Build a Sequence from the source options every command shares.

Sources: KITTI odometry, KITTI raw, the built-in town (the default), a bag (``--bag``) or a folder
of scan files (``--scans-dir``). ``--gt`` (with ``--gt-times`` for KITTI-format truth) and
``--extrinsic`` refine a bag or folder; ``--map FILE`` replaces the map built from the drive with
a point-cloud map file, for any source (see :mod:`lidarloc.core.sequences.framed` for frames).
Without ``--map``, a bag or folder builds its map from its scans and truth, so it needs ``--gt``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from ..config import Config
from ..errors import DataError
from .base import Limited, Sequence

#: default spread of ``--init`` around its pose: 2 m in x and y, 10° in yaw
INIT_SIGMA_XY = 2.0
INIT_SIGMA_YAW = math.radians(10.0)


@dataclass(frozen=True)
class InitialGuess:
    """Where the filter starts instead of over the whole map (``--init``): x, y (m) and yaw
    (rad) in the map's frame (the map file's coordinates), with Gaussian spreads."""

    x: float
    y: float
    yaw: float
    sigma_xy: float = INIT_SIGMA_XY
    sigma_yaw: float = INIT_SIGMA_YAW


def parse_init(text: str) -> InitialGuess:
    """``x,y,yaw[,σ_xy,σ_yaw]`` (metres, degrees) as an :class:`InitialGuess`, or a one-line error."""
    parts = [p.strip() for p in str(text).split(",")]
    usage = "--init takes x,y,yaw or x,y,yaw,σ_xy,σ_yaw (metres, degrees)"
    if len(parts) not in (3, 5):
        raise DataError(f"{usage}; got {text!r}")
    try:
        values = [float(p) for p in parts]
    except ValueError:
        raise DataError(f"{usage}; got {text!r}") from None
    if not all(math.isfinite(v) for v in values):
        raise DataError(f"{usage}, all finite; got {text!r}")
    x, y, yaw_deg = values[:3]
    sigma_xy, sigma_yaw_deg = values[3:] if len(values) == 5 else (INIT_SIGMA_XY, math.degrees(INIT_SIGMA_YAW))
    if sigma_xy <= 0 or sigma_yaw_deg <= 0:
        raise DataError(f"--init: σ_xy and σ_yaw must be > 0; got {text!r}")
    return InitialGuess(x, y, math.radians(yaw_deg), sigma_xy, math.radians(sigma_yaw_deg))


@dataclass
class SourceSpec:
    """Where scans come from: KITTI odometry, KITTI raw, a bag, a scan folder, or the built-in town;
    optionally with a map file, ground truth, an extrinsic and an initial guess."""

    kitti_odometry: Path | None = None
    sequence: str | None = None
    kitti_raw: Path | None = None
    date: str | None = None
    drive: str | None = None
    town_seed: int = 0
    trajectory: Path | None = None  # lay the town along a KITTI poses file …
    calib: Path | None = None  # … whose calib (Tr line) converts cam0 → LiDAR
    scans: int | None = None  # keep only the first N scans
    map: Path | None = None  # a point-cloud map file instead of the drive's map
    bag: Path | None = None  # ROS 1 .bag, ROS 2 bag folder, .db3 or .mcap
    topic: str | None = None  # its PointCloud2 topic (default: the only one)
    scans_dir: Path | None = None  # a folder of scan files
    gt: Path | None = None  # ground truth, TUM or KITTI
    gt_times: Path | None = None  # times of KITTI-format ground truth
    extrinsic: Path | None = None  # base ← LiDAR 4×4 text file
    init: str | None = None  # x,y,yaw[,σ_xy,σ_yaw] (metres, degrees): start around it

    def to_dict(self, absolute: bool = False) -> dict:
        """Every option as JSON takes it: paths as strings, resolved when ``absolute`` (what a run
        folder keeps, so that it finds its data when opened from elsewhere)."""
        out = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, Path):
                value = str(value.expanduser().resolve()) if absolute else str(value)
            out[f.name] = value
        return out

    @classmethod
    def from_dict(cls, d: dict, ignore_unknown: bool = False) -> SourceSpec:
        """The options :meth:`to_dict` wrote (paths back to ``Path``). ``ignore_unknown``: skip
        the keys this version does not know (a run recorded by another version of lidarloc)."""
        known = {f.name for f in fields(cls)}
        if not ignore_unknown and set(d) - known:
            raise DataError(f"unknown source options: {', '.join(sorted(set(d) - known))}")
        return cls(**{k: (Path(v) if k in PATH_OPTIONS and v is not None else v) for k, v in d.items() if k in known})

    @property
    def kind(self) -> str:
        """Which source: kitti_odometry, kitti_raw, bag, scans_dir or town."""
        for name in ("kitti_odometry", "kitti_raw", "bag", "scans_dir"):
            if getattr(self, name) is not None:
                return name
        return "town"

    def describe(self) -> str:
        on_map = f" in map {self.map}" if self.map is not None else ""
        if self.kitti_odometry is not None:
            return f"KITTI odometry {self.kitti_odometry} seq {self.sequence}{on_map}"
        if self.kitti_raw is not None:
            return f"KITTI raw {self.kitti_raw} {self.date} drive {self.drive}{on_map}"
        if self.bag is not None:
            return f"bag {self.bag}{' ' + self.topic if self.topic else ''}{on_map}"
        if self.scans_dir is not None:
            return f"scan folder {self.scans_dir}{on_map}"
        along = f" along {self.trajectory}" if self.trajectory else ""
        return f"built-in town (seed {self.town_seed}){along}{on_map}"


#: The source options that name a file or folder.
PATH_OPTIONS = frozenset(f.name for f in fields(SourceSpec) if "Path" in str(f.type))


def _path(value) -> Path | None:
    return None if value is None else Path(value).expanduser()


def check_spec(spec: SourceSpec) -> None:
    """The combinations of source options that make no sense, as one-line errors."""
    chosen = [
        f"--{n.replace('_', '-')}"
        for n in ("kitti_odometry", "kitti_raw", "bag", "scans_dir")
        if getattr(spec, n) is not None
    ]
    if len(chosen) > 1:
        raise DataError(f"choose one source: {' or '.join(chosen)}, not both")
    if spec.topic is not None and spec.bag is None:
        raise DataError("--topic names a PointCloud2 topic of --bag; give --bag FILE_OR_DIR")
    own_data = spec.bag is not None or spec.scans_dir is not None
    for name in ("gt", "gt_times", "extrinsic"):
        if getattr(spec, name) is not None and not own_data:
            raise DataError(f"--{name.replace('_', '-')} applies to a recording: give --bag or --scans-dir")
    if spec.gt_times is not None and spec.gt is None:
        raise DataError("--gt-times gives the times of a KITTI-format --gt file; give --gt too")
    if own_data and spec.gt is None and spec.map is None:
        raise DataError("a prior map needs --map FILE or ground truth (--gt) to fuse the scans")


def open_sequence(
    spec: SourceSpec, cfg: Config | None = None, progress: Callable[[int, int], None] | None = None
) -> Sequence:
    """The sequence ``spec`` names. ``progress(i, n)``: indexing a bag's topic (seconds for a long
    bag). Its ``notes`` (when the source has any) are lines a user should read."""
    cfg = cfg or Config()
    check_spec(spec)
    init = parse_init(spec.init) if spec.init is not None else None
    map_file = None
    if spec.map is not None:  # a missing or unreadable map fails before a long bag is indexed
        from ..maps.map_source import MapFileSource

        map_file = MapFileSource(_path(spec.map))
    if spec.kitti_odometry is not None:
        if not spec.sequence:
            raise DataError("--kitti-odometry needs --sequence SS")
        from .kitti_odometry import KittiOdometry

        seq: Sequence = KittiOdometry(_path(spec.kitti_odometry), spec.sequence)
    elif spec.kitti_raw is not None:
        if not spec.date or not spec.drive:
            raise DataError("--kitti-raw needs --date YYYY_MM_DD and --drive NNNN")
        from .kitti_raw import KittiRaw

        seq = KittiRaw(_path(spec.kitti_raw), spec.date, spec.drive)
    elif spec.bag is not None:
        from .rosbag import BagSequence

        seq = BagSequence(
            _path(spec.bag),
            topic=spec.topic,
            gt=_path(spec.gt),
            extrinsic=_path(spec.extrinsic),
            gt_times=_path(spec.gt_times),
            progress=progress,
        )
    elif spec.scans_dir is not None:
        from .scan_folder import ScanFolderSequence

        seq = ScanFolderSequence(
            _path(spec.scans_dir), gt=_path(spec.gt), extrinsic=_path(spec.extrinsic), gt_times=_path(spec.gt_times)
        )
    else:
        if (spec.trajectory is None) != (spec.calib is None):
            raise DataError("--trajectory and --calib go together (the calib's Tr converts cam0 poses to LiDAR)")
        from .town import TownSequence

        seq = TownSequence.from_config(
            cfg.town, seed=spec.town_seed, trajectory=_path(spec.trajectory), calib=_path(spec.calib)
        )
    if map_file is not None:
        from .framed import MapFramed

        seq = MapFramed(seq, map_file)
    if spec.scans is not None:
        seq = Limited(seq, spec.scans)
    if init is not None:
        # read by the localizer at every (re)start; Limited forwards attribute reads to its inner
        seq.initial_guess = init
    return seq


def sequence_notes(seq) -> list[str]:
    """The lines a source wants its user to read (a bag's dropped scans, a missing times.txt …)."""
    return list(getattr(seq, "notes", None) or [])


def initial_pose(guess: InitialGuess, origin: np.ndarray, z: float) -> np.ndarray:
    """The 4×4 pose of ``guess`` in the map's local frame (file frame − ``origin``) at height ``z``."""
    c, s = math.cos(guess.yaw), math.sin(guess.yaw)
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:3, 3] = (guess.x - float(origin[0]), guess.y - float(origin[1]), z)
    return T
