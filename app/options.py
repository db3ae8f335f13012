"""Options every command shares: where the scans come from, and the configuration.

The source options are one unit: :func:`with_source` adds them to a command (under one help
panel) and hands the command a :class:`~lidarloc.core.sequences.factory.SourceSpec` built from them
by name, so a new source option is declared once, in :func:`source_parameters`. The configuration
options are another: :func:`with_settings` adds them and hands the command the configuration they
make, or :class:`ConfigOptions`, the options as given.
"""

from __future__ import annotations

import functools
import inspect
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, NamedTuple

import typer

from ..core.config import PRESETS, WORLDS, Config, load_config
from ..core.sequences.factory import SourceSpec

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
        Annotated[
            Path | None,
            typer.Option(
                "--kitti-odometry", help="KITTI odometry root (holds sequences/ and poses/).", rich_help_panel=panel
            ),
        ],
        Annotated[
            str | None, typer.Option("--sequence", help="KITTI odometry sequence id, e.g. 05.", rich_help_panel=panel)
        ],
        Annotated[
            Path | None, typer.Option("--kitti-raw", help="KITTI raw root (holds YYYY_MM_DD/).", rich_help_panel=panel)
        ],
        Annotated[str | None, typer.Option("--date", help="KITTI raw date, YYYY_MM_DD.", rich_help_panel=panel)],
        Annotated[str | None, typer.Option("--drive", help="KITTI raw drive number, NNNN.", rich_help_panel=panel)],
        Annotated[
            int, typer.Option("--town-seed", min=0, help="Seed of the built-in generated town.", rich_help_panel=panel)
        ],
        Annotated[
            Path | None,
            typer.Option(
                "--trajectory", help="Lay the town along this KITTI poses file (cam0 poses).", rich_help_panel=panel
            ),
        ],
        Annotated[
            Path | None,
            typer.Option("--calib", help="KITTI calib file with the Tr line for --trajectory.", rich_help_panel=panel),
        ],
        Annotated[
            int | None, typer.Option("--scans", min=1, help="Use only the first N scans.", rich_help_panel=panel)
        ],
    )


(KittiOdometryOpt, SequenceOpt, KittiRawOpt, DateOpt, DriveOpt, TownSeedOpt, TrajectoryOpt, CalibOpt, ScansOpt) = (
    source_options(_SRC)
)

_MAP_HELP = (
    "Prior map file (.pcd, .ply, .las, .laz, .npy, .npz) instead of the map built from the drive; "
    "results are written in its frame."
)
_GT_HELP = "Ground truth of --bag/--scans-dir: TUM (t x y z qx qy qz qw) or KITTI (12 numbers a line) poses file."


def own_data_options(panel: str) -> dict[str, Any]:
    """The options for a user's own data (map file, recording, truth), under ``panel``."""
    return {
        "map": Annotated[Path | None, typer.Option("--map", help=_MAP_HELP, rich_help_panel=panel)],
        "bag": Annotated[
            Path | None,
            typer.Option(
                "--bag",
                help="ROS 1 .bag, ROS 2 bag folder, .db3 or .mcap with PointCloud2 scans.",
                rich_help_panel=panel,
            ),
        ],
        "topic": Annotated[
            str | None,
            typer.Option("--topic", help="PointCloud2 topic of --bag (default: its only one).", rich_help_panel=panel),
        ],
        "scans_dir": Annotated[
            Path | None,
            typer.Option(
                "--scans-dir",
                help="Folder of scans (.pcd, .ply, .bin or .npy, in name order; times from its times.txt).",
                rich_help_panel=panel,
            ),
        ],
        "gt": Annotated[Path | None, typer.Option("--gt", help=_GT_HELP, rich_help_panel=panel)],
        "gt_times": Annotated[
            Path | None,
            typer.Option(
                "--gt-times", help="Times (s, one a line) of a KITTI-format --gt file.", rich_help_panel=panel
            ),
        ],
        "extrinsic": Annotated[
            Path | None,
            typer.Option(
                "--extrinsic",
                help="4×4 base ← LiDAR transform file for --gt (default: the bag's /tf_static, else identity).",
                rich_help_panel=panel,
            ),
        ],
    }


#: the defaults of the source options (what SourceSpec has when an option is not given)
_SOURCE_DEFAULTS = {"town_seed": 0}
#: every source option's parameter name, in the order of the help
SOURCE_PARAMS = (
    "kitti_odometry",
    "sequence",
    "kitti_raw",
    "date",
    "drive",
    "town_seed",
    "trajectory",
    "calib",
    "scans",
    "map",
    "bag",
    "topic",
    "scans_dir",
    "gt",
    "gt_times",
    "extrinsic",
)
#: ``--init``: run, view and inspect start around a pose with it
InitOpt = Annotated[
    str | None,
    typer.Option(
        "--init",
        metavar="X,Y,YAW[,σXY,σYAW]",
        help="Start the particles around this pose (map frame; metres, degrees; default σ 2 m, 10°) instead of over the whole map.",
    ),
]


def source_parameters(panel: str = _SRC, exclude: tuple[str, ...] = ()) -> list[inspect.Parameter]:
    """The source options as keyword parameters of a command, under the help panel ``panel``."""
    annotations = dict(zip(SOURCE_PARAMS[:9], source_options(panel)))
    annotations.update(own_data_options(panel))
    return [
        inspect.Parameter(
            name, inspect.Parameter.KEYWORD_ONLY, annotation=annotations[name], default=_SOURCE_DEFAULTS.get(name)
        )
        for name in SOURCE_PARAMS
        if name not in exclude
    ]


def with_source(panel: str = _SRC, exclude: tuple[str, ...] = ()):
    """Decorator: the command gets every source option (but ``exclude``) under the help panel
    ``panel``, and its ``spec`` parameter receives the SourceSpec they make. The options keep their
    names, so :func:`given` still asks about them."""

    def decorate(func):
        # eval_str: the command's module may use string annotations (``from __future__ import annotations``)
        signature = inspect.signature(func, eval_str=True)
        params = [
            p.replace(kind=inspect.Parameter.KEYWORD_ONLY) for name, p in signature.parameters.items() if name != "spec"
        ] + source_parameters(panel, exclude)

        @functools.wraps(func)
        def command(**kwargs):
            values = {name: kwargs.pop(name) for name in SOURCE_PARAMS if name in kwargs}
            return func(spec=SourceSpec(**values), **kwargs)

        return _with_parameters(command, signature, params)

    return decorate


def _with_parameters(command, signature: inspect.Signature, params: list[inspect.Parameter]):
    """``command`` (a wrapper made by :func:`functools.wraps`) showing typer the parameters ``params``."""
    # typer reads the signature (and the annotations) of the command it is given
    del command.__wrapped__
    command.__signature__ = signature.replace(parameters=params)
    command.__annotations__ = {p.name: p.annotation for p in params}
    return command


ConfigOpt = Annotated[
    Path | None, typer.Option("--config", help="YAML or TOML configuration file.", rich_help_panel=_CFG)
]
SetOpt = Annotated[
    list[str] | None,
    typer.Option(
        "--set",
        help="Override one entry, e.g. --set pf.sigma=0.7 or --set town.changes=0.3 (repeatable).",
        rich_help_panel=_CFG,
    ),
]
# a plain string checked by load_config, not a click Choice: a bad name is then one line and exit
# status 2 like every other configuration error, not a usage box
PresetOpt = Annotated[
    str | None,
    typer.Option(
        "--preset",
        metavar="|".join(PRESETS),
        rich_help_panel=_CFG,
        help="Named configuration the defaults start from, before --config and --set: "
        "'paper' pins the paper's method (untempered likelihood, fixed particle count, its S2M acceptance).",
    ),
]
# a plain string checked by load_config too (one line, exit status 2)
WorldOpt = Annotated[
    str,
    typer.Option(
        "--world",
        metavar="|".join(WORLDS),
        rich_help_panel=_CFG,
        help="The built-in town's drive: 'lived-in' (30 % of the movable objects changed since mapping, traffic, "
        "scans swept while moving: what a map meets in use) or 'kind' (the town as it was mapped). After "
        "--preset, before --config and --set; other sources ignore it.",
    ),
]
JsonOpt = Annotated[
    bool, typer.Option("--json", help="Print the result as JSON on stdout (else a readable summary on stderr).")
]
CacheOpt = Annotated[
    Path | None,
    typer.Option(
        "--cache",
        help="Cache directory for maps and tables (default ~/.cache/lidarloc or $LIDARLOC_CACHE).",
        rich_help_panel=_CFG,
    ),
]


# The options that choose which sequence (the others refine it): a command whose default source
# is not the town asks whether one of them was given.
SOURCE_CHOICE = ("kitti_odometry", "kitti_raw", "town_seed", "trajectory", "bag", "scans_dir")
SOURCE_OPTIONS = SOURCE_PARAMS
#: the options for a user's own data (commands whose work cannot take them exclude these)
OWN_DATA = ("map", "bag", "topic", "scans_dir", "gt", "gt_times", "extrinsic")


def given(ctx: typer.Context, names: tuple[str, ...]) -> list[str]:
    """Which of the parameters ``names`` were given on the command line (not left at their default)."""
    # by name: typer may bring its own copy of click, whose ParameterSource is another enum
    return [
        n for n in names if getattr(ctx.get_parameter_source(n), "name", "DEFAULT") not in ("DEFAULT", "DEFAULT_MAP")
    ]


def source_spec(**values) -> SourceSpec:
    """A SourceSpec from source options given by name (the others at their defaults)."""
    return SourceSpec(**values)


def open_source(spec: SourceSpec, cfg: Config, console=None):
    """``open_sequence`` with a progress bar while a bag's topic is indexed, and the source's
    notes printed on ``console`` (stderr), one line each."""
    from ..core.sequences.factory import open_sequence, sequence_notes
    from .console import err, progress_bar

    console = console or err
    if spec.bag is None:
        seq = open_sequence(spec, cfg)
    else:
        with progress_bar() as bar:
            task = bar.add_task(f"indexing {Path(spec.bag).name}", total=None)
            seq = open_sequence(spec, cfg, progress=lambda i, n: bar.update(task, completed=i, total=n))
    for line in sequence_notes(seq):
        console.print(f"note: {line}", markup=False, highlight=False, soft_wrap=True)
    return seq


def config_from(
    config: Path | None,
    overrides: list[str] | None,
    seed: int | None = None,
    preset: str | None = None,
    world: str | None = None,
) -> Config:
    """The configuration: the defaults, then ``preset`` (``--preset``), ``world`` (``--world``),
    ``config`` (``--config``), ``overrides`` (``--set``), and ``seed`` (``--seed``) last."""
    cfg = load_config(config, overrides, preset=preset, world=world)
    if seed is not None:
        cfg.seed = seed
    return cfg


@dataclass(frozen=True)
class ConfigOptions:
    """``--preset``, ``--config``, ``--set`` and ``--world`` as given: None (no entries for --set)
    where one was not given or the command does not take it."""

    preset: str | None = None
    config: Path | None = None
    overrides: tuple[str, ...] = ()
    world: str | None = None

    def load(self, seed: int | None = None, first: Sequence[str] = (), last: Sequence[str] = ()) -> Config:
        """The configuration they make, with the entries ``first`` set before ``--set`` (the
        command's own defaults, which --set may change) and ``last`` after it (what the command's
        own options say); ``seed`` (``--seed``) last."""
        return config_from(
            self.config, [*first, *self.overrides, *last], seed=seed, preset=self.preset, world=self.world
        )

    def args(self) -> list[str]:
        """``--preset``, ``--config`` and ``--set`` as given, for a ``lidarloc`` command in a fresh
        process (``demo``, ``view``, ``run``: none of them takes ``--world``)."""
        args = ["--preset", self.preset] if self.preset is not None else []
        args += ["--config", str(self.config)] if self.config is not None else []
        for item in self.overrides:
            args += ["--set", item]
        return args


#: the configuration options as keyword parameters of a command, in the order of the help
_SETTINGS = {
    name: inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY, annotation=annotation, default=default)
    for name, annotation, default in (
        ("world", WorldOpt, "lived-in"),
        ("preset", PresetOpt, None),
        ("config", ConfigOpt, None),
        ("set_", SetOpt, None),
    )
}


def with_settings(world: bool = False, preset: bool = True):
    """Decorator: the command gets ``--preset`` (unless not ``preset``), ``--config`` and ``--set``,
    and ``--world`` first with ``world``, in place of its ``cfg`` or ``settings`` parameter.

    ``cfg`` receives the configuration they make, built before the command's body runs: a bad
    value stops the command before it does anything. ``settings`` receives them as given
    (:class:`ConfigOptions`), for a command that checks its other options first, adds entries or a
    seed, or hands them to a child process. The options keep their names, so :func:`given` still
    asks about them."""
    options = [p for name, p in _SETTINGS.items() if (world or name != "world") and (preset or name != "preset")]

    def decorate(func):
        # eval_str: the command's module may use string annotations (``from __future__ import annotations``)
        signature = inspect.signature(func, eval_str=True)
        targets = [name for name in ("cfg", "settings") if name in signature.parameters]
        if len(targets) != 1:
            raise TypeError(f"{func.__name__}: with_settings needs a cfg or a settings parameter (one)")
        (target,) = targets
        params = []
        for name, p in signature.parameters.items():
            # in the parameter's place: the options' order in --help is where the command puts them
            params += options if name == target else [p.replace(kind=inspect.Parameter.KEYWORD_ONLY)]

        @functools.wraps(func)
        def command(**kwargs):
            settings = ConfigOptions(
                preset=kwargs.pop("preset", None),
                config=kwargs.pop("config"),
                overrides=tuple(kwargs.pop("set_") or ()),
                world=kwargs.pop("world", None),
            )
            kwargs[target] = settings.load() if target == "cfg" else settings
            return func(**kwargs)

        return _with_parameters(command, signature, params)

    return decorate
