"""Options every command shares: where the scans come from, and the configuration."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, NamedTuple, Optional

import typer

from lidarloc.core.config import PRESETS, Config, load_config
from lidarloc.core.sequences.factory import SourceSpec

_SRC = "Source (default: the built-in town)"
_CFG = "Configuration"


class SourceOptions(NamedTuple):
    """The source options' types, shown under one help panel."""

    kitti_odometry: Any
    sequence: Any
    kitti_raw: Any
    date: Any
    drive: Any
    town_seed: Any
    trajectory: Any
    calib: Any
    scans: Any


def source_options(panel: str) -> SourceOptions:
    """The source options under the help panel ``panel`` (a command whose default source is not
    the built-in town says which it is there)."""
    return SourceOptions(
        Annotated[Optional[Path], typer.Option("--kitti-odometry", help="KITTI odometry root (holds sequences/ and poses/).", rich_help_panel=panel)],
        Annotated[Optional[str], typer.Option("--sequence", help="KITTI odometry sequence id, e.g. 05.", rich_help_panel=panel)],
        Annotated[Optional[Path], typer.Option("--kitti-raw", help="KITTI raw root (holds YYYY_MM_DD/).", rich_help_panel=panel)],
        Annotated[Optional[str], typer.Option("--date", help="KITTI raw date, YYYY_MM_DD.", rich_help_panel=panel)],
        Annotated[Optional[str], typer.Option("--drive", help="KITTI raw drive number, NNNN.", rich_help_panel=panel)],
        Annotated[int, typer.Option("--town-seed", min=0, help="Seed of the built-in generated town.", rich_help_panel=panel)],
        Annotated[Optional[Path], typer.Option("--trajectory", help="Lay the town along this KITTI poses file (cam0 poses).", rich_help_panel=panel)],
        Annotated[Optional[Path], typer.Option("--calib", help="KITTI calib file with the Tr line for --trajectory.", rich_help_panel=panel)],
        Annotated[Optional[int], typer.Option("--scans", min=1, help="Use only the first N scans.", rich_help_panel=panel)],
    )


(KittiOdometryOpt, SequenceOpt, KittiRawOpt, DateOpt, DriveOpt, TownSeedOpt, TrajectoryOpt, CalibOpt,
 ScansOpt) = source_options(_SRC)
ConfigOpt = Annotated[Optional[Path], typer.Option("--config", help="YAML or TOML configuration file.", rich_help_panel=_CFG)]
SetOpt = Annotated[Optional[list[str]], typer.Option("--set", help="Override one entry, e.g. --set pf.sigma=0.7 or --set town.changes=0.3 (repeatable).", rich_help_panel=_CFG)]
# a plain string checked by load_config, not a click Choice: a bad name is then one line and exit
# status 2 like every other configuration error, not a usage box
PresetOpt = Annotated[Optional[str], typer.Option(
    "--preset", metavar="|".join(PRESETS), rich_help_panel=_CFG,
    help="Named configuration the defaults start from, before --config and --set: "
         "'paper' pins the paper's method (untempered likelihood, fixed particle count, its S2M acceptance).")]
JsonOpt = Annotated[bool, typer.Option("--json", help="Print the result as JSON on stdout (else a readable summary on stderr).")]
CacheOpt = Annotated[Optional[Path], typer.Option("--cache", help="Cache directory for maps and tables (default ~/.cache/lidarloc or $LIDARLOC_CACHE).", rich_help_panel=_CFG)]


# The options that choose which sequence (the others refine it): a command whose default source
# is not the town asks whether one of them was given.
SOURCE_CHOICE = ("kitti_odometry", "kitti_raw", "town_seed", "trajectory")
SOURCE_OPTIONS = SOURCE_CHOICE + ("sequence", "date", "drive", "calib", "scans")


def given(ctx: typer.Context, names: tuple[str, ...]) -> list[str]:
    """Which of the parameters ``names`` were given on the command line (not left at their default)."""
    # by name: typer may bring its own copy of click, whose ParameterSource is another enum
    return [n for n in names if getattr(ctx.get_parameter_source(n), "name", "DEFAULT") not in ("DEFAULT", "DEFAULT_MAP")]


def source_spec(kitti_odometry, sequence, kitti_raw, date, drive, town_seed, trajectory, calib, scans) -> SourceSpec:
    return SourceSpec(kitti_odometry=kitti_odometry, sequence=sequence, kitti_raw=kitti_raw, date=date,
                      drive=drive, town_seed=town_seed, trajectory=trajectory, calib=calib, scans=scans)


def config_from(config: Path | None, overrides: list[str] | None, seed: int | None = None,
                preset: str | None = None) -> Config:
    """The configuration: the defaults, then ``preset`` (``--preset``), ``config`` (``--config``),
    ``overrides`` (``--set``), and ``seed`` (``--seed``) last."""
    cfg = load_config(config, overrides, preset=preset)
    if seed is not None:
        cfg.seed = seed
    return cfg
