"""Build a Sequence from the source options every command shares.

The sources are the registry's (:mod:`lidarloc.core.sequences.registry`, one module each in
``sources/``): the built-in town (the default), KITTI odometry or raw, a bag, a folder of scan
files, a Velodyne pcap … ``--map FILE`` replaces the map built from the drive with a point-cloud
map file, for any source (see :mod:`lidarloc.core.sequences.framed` for frames). A recording (a
bag, a folder, a pcap) takes ``--gt`` (with ``--gt-times`` for KITTI-format truth) and
``--extrinsic``; without ``--map`` it builds its map from its scans and truth, so it needs ``--gt``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, fields
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..config import Config
from ..errors import DataError
from .base import Limited, Sequence
from .registry import Source, all_options, as_path, check, chosen

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


def _with_source_options(cls):
    """``cls`` with a field for every registered source option (:mod:`.registry`), so that a new
    source's options are fields without being written here."""
    annotations = cls.__dict__.get("__annotations__", {})
    for option in all_options():
        kind = option.type.__name__ if option.type is not Path else "Path"
        annotations[option.name] = kind if option.default is not None else f"{kind} | None"
        setattr(cls, option.name, option.default)
    cls.__annotations__ = annotations
    return cls


@dataclass
@_with_source_options
class SourceSpec:
    """Where scans come from: one of the registered sources (``lidarloc sources``: the built-in
    town by default, KITTI odometry or raw, a bag, a scan folder, a Velodyne pcap …) with its
    options, and the options every source takes (a map file, ``--scans``, an initial guess) or a
    recording takes (ground truth, an extrinsic). Its fields are the registry's options, by name."""

    if TYPE_CHECKING:  # the fields come from the registry; a type checker sees keyword options

        def __init__(self, **options: Any) -> None: ...

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
    def source(self) -> Source:
        """The registered source this spec names."""
        return chosen(self)

    @property
    def kind(self) -> str:
        """Which source, by its registered name: town, kitti_odometry, kitti_raw, bag, scans_dir …"""
        return chosen(self).name

    def describe(self) -> str:
        on_map = f" in map {self.map}" if self.map is not None else ""
        return chosen(self).describe(self) + on_map


#: The source options that name a file or folder.
PATH_OPTIONS = frozenset(o.name for o in all_options() if o.is_path)


def check_spec(spec: SourceSpec) -> None:
    """The combinations of source options that make no sense, as one-line errors."""
    check(spec)


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

        map_file = MapFileSource(as_path(spec.map))
    source = chosen(spec)
    if not source.available():
        raise source.missing()
    seq: Sequence = source.open(spec, cfg, progress)
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
