"""The corpus file: a YAML list of drives, each any source the other commands open (the source
options' names, as in :class:`~lidarloc.core.sequences.factory.SourceSpec`), with its own world,
preset, configuration entries and seed; a ``defaults`` block every drive starts from.

Everything that can be checked without running is checked when the file is read, as one line
naming the drive and the field: unknown fields, wrong types, source options that do not go
together, configuration entries that do not exist. Paths are relative to the corpus file's
folder. A path that does not exist is not an error of the file: that drive is reported as
failed when the corpus runs and the other drives go on (a log moved away should not hide the
results of the others).
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ...core.config import Config, load_config
from ...core.errors import LidarlocError
from ...core.sequences.factory import PATH_OPTIONS, SourceSpec, check_spec

SOURCE_FIELDS = tuple(f.name for f in dataclasses.fields(SourceSpec))
# the sources first: a drive whose log is gone says so before naming its map
_SOURCES = ("kitti_odometry", "kitti_raw", "bag", "scans_dir")
PATH_FIELDS = _SOURCES + tuple(f for f in SOURCE_FIELDS if f in PATH_OPTIONS and f not in _SOURCES)
# YAML reads 05 as the number 5 and 0013 as 11 (octal): these must be written in quotes
TEXT_FIELDS = ("sequence", "date", "drive", "topic", "init")
INT_FIELDS = ("town_seed", "scans", "seed")
RUN_FIELDS = ("name", "world", "preset", "config", "set", "seed")
DRIVE_FIELDS = SOURCE_FIELDS + RUN_FIELDS
# a drive's name is its folder's name under drives/
NAME_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]*")
#: beside a drive's run: what it was run with (source, configuration, seed, code), so that a kept
#: run is not mixed with another definition, and compare finds one log under several seeds
IDENTITY_FILE = "drive.json"


@dataclass(frozen=True)
class Drive:
    """One drive of a corpus: where its scans come from and how it is run."""

    name: str
    spec: SourceSpec
    seed: int = 0
    world: str | None = None
    preset: str | None = None
    config: Path | None = None
    overrides: tuple[str, ...] = ()

    def config_for(self, extra: Sequence[str] = ()) -> Config:
        """The drive's configuration with ``extra`` entries (the command's ``--set``) set last.
        The odometry is recorded once per drive, as ``lidarloc sweep`` does: the same numbers as
        computing it during the run, and a drive run again only loads it."""
        return load_config(
            self.config,
            ["localize.recorded_odometry=true", *self.overrides, *extra],
            preset=self.preset,
            world=self.world,
        )

    def missing_path(self) -> str | None:
        """Why the drive cannot run because a file or folder it names is not there (None: all are)."""
        for name in (*PATH_FIELDS, "config"):
            value = self.config if name == "config" else getattr(self.spec, name)
            if value is not None and not Path(value).exists():
                return f"{name}: {value} does not exist"
        return None


@dataclass(frozen=True)
class Corpus:
    path: Path
    drives: list[Drive]


def load_corpus(path: Path, extra: Sequence[str] = ()) -> Corpus:
    """The corpus in ``path``, every drive checked, its configuration with ``extra`` (``--set``)."""
    path = Path(path)
    if not path.is_file():
        raise LidarlocError(f"{path}: corpus file not found")
    import yaml

    try:
        data = yaml.safe_load(path.read_text())
    except Exception as exc:  # the parser's messages span lines: its first is enough
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise LidarlocError(f"{path}: unreadable corpus file ({first})") from None
    return parse_corpus(data, path, extra)


def parse_corpus(data: Any, path: Path, extra: Sequence[str] = ()) -> Corpus:
    """A corpus from the file's parsed YAML ``data`` (``path`` names it in errors and anchors its
    relative paths)."""
    if not isinstance(data, dict):
        raise LidarlocError(f"{path}: the corpus file must be a mapping with 'drives:' (see docs/corpus.md)")
    unknown = sorted(set(data) - {"defaults", "drives"})
    if unknown:
        raise LidarlocError(f"{path}: unknown top-level field '{unknown[0]}' (fields: defaults, drives)")
    defaults = data.get("defaults") or {}
    if not isinstance(defaults, dict):
        raise LidarlocError(f"{path}: defaults: must be a mapping of drive fields")
    if "name" in defaults:
        raise LidarlocError(f"{path}: defaults: name: each drive names itself")
    _check_fields(defaults, path, "defaults")
    drives_data = data.get("drives")
    if not isinstance(drives_data, list) or not drives_data:
        raise LidarlocError(f"{path}: drives: must be a list of at least one drive")
    drives, seen = [], set()
    for i, raw in enumerate(drives_data):
        where = f"drive {i + 1}"
        if not isinstance(raw, dict):
            raise LidarlocError(f"{path}: {where}: must be a mapping of fields")
        name = raw.get("name")
        if name is None:
            raise LidarlocError(f"{path}: {where}: missing field 'name'")
        if not isinstance(name, str) or not NAME_PATTERN.fullmatch(name):
            raise LidarlocError(f"{path}: {where}: name: {name!r} must be letters, digits, '.', '_' or '-'")
        where = f"drive '{name}'"
        if name in seen:
            raise LidarlocError(f"{path}: {where}: duplicate name (each drive's folder is drives/NAME)")
        seen.add(name)
        _check_fields(raw, path, where)
        drives.append(_drive(defaults, raw, path, where, extra))
    return Corpus(path, drives)


def _check_fields(fields: dict, path: Path, where: str) -> None:
    for key, value in fields.items():
        if key not in DRIVE_FIELDS:
            raise LidarlocError(f"{path}: {where}: unknown field '{key}' (see docs/corpus.md)")
        if value is None:
            continue
        if key in TEXT_FIELDS and not isinstance(value, str):
            raise LidarlocError(f'{path}: {where}: {key}: write it in quotes, e.g. {key}: "{value}"')
        if key in INT_FIELDS and (isinstance(value, bool) or not isinstance(value, int) or value < 0):
            raise LidarlocError(f"{path}: {where}: {key}: must be a whole number ≥ 0, not {value!r}")
        if key in (*PATH_FIELDS, "config", "world", "preset", "name") and not isinstance(value, str):
            raise LidarlocError(f"{path}: {where}: {key}: must be text, not {value!r}")
        if key == "set" and not (
            isinstance(value, str) or (isinstance(value, list) and all(isinstance(v, str) for v in value))
        ):
            raise LidarlocError(f"{path}: {where}: set: must be a list of section.key=value entries")
    if fields.get("scans") == 0:
        raise LidarlocError(f"{path}: {where}: scans: must be ≥ 1")


def _entries(value) -> list[str]:
    return [] if value is None else [value] if isinstance(value, str) else list(value)


def _drive(defaults: dict, raw: dict, path: Path, where: str, extra: Sequence[str]) -> Drive:
    """The drive ``raw`` over ``defaults``: its fields replace theirs, its ``set`` entries follow theirs."""
    merged = {**defaults, **raw}
    source: dict[str, Any] = {}
    for key in SOURCE_FIELDS:
        value = merged.get(key)
        if value is not None and key in PATH_FIELDS:
            value = (path.parent / Path(value).expanduser()).absolute()
        if value is not None:
            source[key] = value
    spec = SourceSpec(**source)
    try:
        check_spec(spec)
    except LidarlocError as exc:
        raise LidarlocError(f"{path}: {where}: {exc}") from None
    config = merged.get("config")
    drive = Drive(
        name=raw["name"],
        spec=spec,
        seed=int(merged.get("seed") or 0),
        world=merged.get("world"),
        preset=merged.get("preset"),
        config=None if config is None else (path.parent / Path(config).expanduser()).absolute(),
        overrides=(*_entries(defaults.get("set")), *_entries(raw.get("set"))),
    )
    if drive.config is None or drive.config.is_file():  # a missing config file fails that drive alone
        try:
            drive.config_for(extra)
        except LidarlocError as exc:
            raise LidarlocError(f"{path}: {where}: {exc}") from None
    return drive
