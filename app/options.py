"""Options every command shares: where the scans come from, and the configuration.

The source options are one unit: :func:`with_source` adds them to a command (under one help
panel) and hands the command a :class:`~lidarloc.core.sequences.factory.SourceSpec` built from them
by name. The options are the source registry's (:mod:`lidarloc.core.sequences.registry`): a new
source's options are declared once, in its module of ``core/sequences/sources/``. The configuration
options are another: :func:`with_settings` adds them and hands the command the configuration they
make, or :class:`ConfigOptions`, the options as given.
"""

from __future__ import annotations

import functools
import inspect
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

import typer

from ..core.config import PRESETS, WORLDS, Config, load_config
from ..core.sequences.factory import SourceSpec
from ..core.sequences.registry import RECORDING_OPTIONS, Option, all_options, option_named, sources

# the registered sources by their choosing options: ``lidarloc sources`` describes each
_SRC = (
    "Source (default: the built-in town; or "
    + ", ".join(s.key.flag for s in sources() if s.key is not None)
    + "; lidarloc sources lists them)"
)
_CFG = "Configuration"


def source_annotation(option: Option, panel: str = _SRC) -> Any:
    """The typer annotation of a registered source option, under the help panel ``panel``."""
    kind = option.type if option.default is not None else option.type | None
    return Annotated[
        kind,
        typer.Option(option.flag, help=option.help, metavar=option.metavar, min=option.min, rich_help_panel=panel),
    ]


#: every source option the commands take, in the order of the help (``--init``: see InitOpt)
SOURCE_PARAMS = tuple(o.name for o in all_options() if o.cli)
ScansOpt = source_annotation(option_named("scans"))
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
    return [
        inspect.Parameter(
            o.name, inspect.Parameter.KEYWORD_ONLY, annotation=source_annotation(o, panel), default=o.default
        )
        for o in all_options()
        if o.cli and o.name not in exclude
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
SOURCE_CHOICE = tuple(
    o.name for s in sources() for o in (s.options if s.default else s.options[:1]) if o.name != "calib"
)
SOURCE_OPTIONS = SOURCE_PARAMS
#: the options for a user's own data (commands whose work cannot take them exclude these)
OWN_DATA = (
    ("map",)
    + tuple(o.name for s in sources() if s.recording for o in s.options)
    + tuple(o.name for o in RECORDING_OPTIONS)
)
#: the options of every source but the built-in town (a command that works on the town alone excludes these)
NOT_TOWN = tuple(o.name for s in sources() if not s.default for o in s.options)


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
    """``open_sequence`` with a progress bar while a recording is indexed, and the source's
    notes printed on ``console`` (stderr), one line each."""
    from ..core.sequences.factory import open_sequence, sequence_notes
    from .console import err, progress_bar

    console = console or err
    key = spec.source.key
    if not spec.source.indexes or key is None:
        seq = open_sequence(spec, cfg)
    else:
        with progress_bar() as bar:
            task = bar.add_task(f"indexing {Path(getattr(spec, key.name)).name}", total=None)
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
