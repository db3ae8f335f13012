"""The registry of sources: where scans can come from, each declared once, in one module of
:mod:`lidarloc.core.sequences.sources`.

A source declares its name, its options (:class:`Option`: name, type, help, default, whether a
path) and how to open it. Everything else follows from the registry: the fields of
:class:`~lidarloc.core.sequences.factory.SourceSpec`, which source a spec names, the checks of
options that do not go together, the command line's source options and their help, and
``lidarloc sources``. Adding a source is adding one module to ``sources/`` that defines
``SOURCE``; CONTRIBUTING.md has the recipe.

Besides the sources' own options there are the options every source takes
(:data:`COMMON_OPTIONS`: ``--scans``, ``--map``, ``--init``) and those of a *recording*, a source
whose scans come without a map (:data:`RECORDING_OPTIONS`: ``--gt``, ``--gt-times``,
``--extrinsic``): a recording without ``--map`` builds its map from its scans and ``--gt``.
"""

from __future__ import annotations

import functools
import importlib
import importlib.util
import pkgutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..errors import DataError


@dataclass(frozen=True)
class Option:
    """One source option: ``name`` is the SourceSpec field and, with dashes, the flag (``scans_dir``
    is ``--scans-dir``); ``type`` str, int or Path (a path: a file or folder, resolved when a run
    records it); ``what``: what the option names, for the error when it comes without its source
    ("names a PointCloud2 topic"); ``cli``: False for an option the commands that take it declare
    themselves (``--init``); ``required``: its source needs it (``--sequence`` of KITTI odometry)."""

    name: str
    type: type
    help: str
    default: Any = None
    metavar: str | None = None
    min: int | None = None
    what: str = "is an option"
    cli: bool = True
    required: bool = False

    @property
    def flag(self) -> str:
        return "--" + self.name.replace("_", "-")

    @property
    def is_path(self) -> bool:
        return self.type is Path


@dataclass(frozen=True)
class Source:
    """One source. ``options``: its own, the first one choosing it (its file or folder: ``--bag``)
    unless the source is the ``default`` (chosen when no other is: the built-in town).
    ``open(spec, cfg, progress)`` returns its Sequence; ``describe(spec)`` one line for a user.
    ``recording``: it takes :data:`RECORDING_OPTIONS` and, without ``--map``, needs ``--gt``.
    ``indexes``: opening reads the whole recording once (worth a progress bar). ``requires``: the
    module it imports that is not installed with lidarloc, and ``install`` how to install it."""

    name: str
    title: str
    options: tuple[Option, ...]
    open: Callable[..., Any]
    describe: Callable[[Any], str]
    default: bool = False
    recording: bool = False
    indexes: bool = False
    requires: str | None = None
    install: str = ""

    @property
    def key(self) -> Option | None:
        """The option that chooses this source (None: the default source)."""
        return None if self.default else self.options[0]

    def available(self) -> bool:
        """Whether what it imports is installed (found without importing it)."""
        return self.requires is None or importlib.util.find_spec(self.requires) is not None

    def missing(self) -> DataError:
        """The one-line error for a source whose module is not installed."""
        flag = self.key.flag if self.key is not None else self.name
        return DataError(f"{flag} needs the {self.requires} module: {self.install}")


_GT_HELP = "Ground truth of a recording: TUM (t x y z qx qy qz qw) or KITTI (12 numbers a line) poses file."
_MAP_HELP = (
    "Prior map file (.pcd, .ply, .las, .laz, .npy, .npz) instead of the map built from the drive; "
    "results are written in its frame."
)

#: the options every source takes
COMMON_OPTIONS = (
    Option("scans", int, "Use only the first N scans.", min=1),
    Option("map", Path, _MAP_HELP),
    Option("init", str, "Start the particles around this pose (x,y,yaw[,σ_xy,σ_yaw]).", cli=False),
)
#: the options of a recording (a source whose scans come without a map)
RECORDING_OPTIONS = (
    Option("gt", Path, _GT_HELP),
    Option("gt_times", Path, "Times (s, one a line) of a KITTI-format --gt file."),
    Option(
        "extrinsic",
        Path,
        "4×4 base ← LiDAR transform file for --gt (default: a bag's /tf_static, else identity).",
    ),
)


@functools.cache
def sources() -> tuple[Source, ...]:
    """Every registered source: the default first, then by name. A module of ``sources/`` is a
    source when it defines ``SOURCE``."""
    from . import sources as package

    found = []
    for info in pkgutil.iter_modules(package.__path__):
        module = importlib.import_module(f"{package.__name__}.{info.name}")
        source = getattr(module, "SOURCE", None)
        if isinstance(source, Source):
            found.append(source)
    found.sort(key=lambda s: (not s.default, s.name))
    _check_registry(found)
    return tuple(found)


def _check_registry(found: list[Source]) -> None:
    """Two sources declaring one option, or not one default, is a mistake in the code."""
    names = [o.name for o in COMMON_OPTIONS + RECORDING_OPTIONS]
    for source in found:
        names += [o.name for o in source.options]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise RuntimeError(f"source options declared twice: {', '.join(twice)}")
    if sum(s.default for s in found) != 1:
        raise RuntimeError("exactly one registered source must be the default")


def source_named(name: str) -> Source:
    for source in sources():
        if source.name == name:
            return source
    raise DataError(f"unknown source {name!r}; the sources: {', '.join(s.name for s in sources())}")


def all_options() -> tuple[Option, ...]:
    """Every option, in the order of the help: each source's, then a recording's, then the common ones."""
    return tuple(o for s in sources() for o in s.options) + RECORDING_OPTIONS + COMMON_OPTIONS


def option_named(name: str) -> Option:
    return next(o for o in all_options() if o.name == name)


def given(spec, option: Option) -> bool:
    """Whether ``spec`` sets ``option`` to something other than its default."""
    return getattr(spec, option.name) != option.default


def chosen_keys(spec) -> list[Source]:
    """The non-default sources whose choosing option ``spec`` gives."""
    return [s for s in sources() if s.key is not None and getattr(spec, s.key.name) is not None]


def chosen(spec) -> Source:
    """The source ``spec`` names: the one whose choosing option it gives, else the default."""
    keys = chosen_keys(spec)
    return keys[0] if keys else next(s for s in sources() if s.default)


def as_path(value) -> Path | None:
    """An option's path as a user gave it (``~`` expanded), or None."""
    return None if value is None else Path(value).expanduser()


def truth_options(spec) -> dict[str, Path | None]:
    """A recording's ``gt``, ``gt_times`` and ``extrinsic`` as paths, the keywords its reader takes."""
    return {o.name: as_path(getattr(spec, o.name)) for o in RECORDING_OPTIONS}


def check(spec) -> None:
    """The combinations of source options that make no sense, as one-line errors."""
    keys = chosen_keys(spec)
    if len(keys) > 1:
        raise DataError(f"choose one source: {' or '.join(s.key.flag for s in keys if s.key)}, not both")
    source = chosen(spec)
    needed = [o for o in source.options if o.required and not getattr(spec, o.name)]
    if needed and source.key is not None:
        wanted = " and ".join(f"{o.flag} {o.metavar}" for o in needed)
        raise DataError(f"{source.key.flag} needs {wanted}")
    for other in sources():
        if other is source or other.key is None:
            continue
        for option in other.options[1:]:
            if given(spec, option):
                key = other.key
                raise DataError(
                    f"{option.flag} {option.what} of {key.flag}; give {key.flag} {key.metavar or ''}".strip()
                )
    recordings = [s.key.flag for s in sources() if s.recording and s.key is not None]
    for option in RECORDING_OPTIONS:
        if given(spec, option) and not source.recording:
            raise DataError(f"{option.flag} applies to a recording: give {' or '.join(recordings)}")
    if spec.gt_times is not None and spec.gt is None:
        raise DataError("--gt-times gives the times of a KITTI-format --gt file; give --gt too")
    if source.recording and spec.gt is None and spec.map is None:
        raise DataError("a prior map needs --map FILE or ground truth (--gt) to fuse the scans")
