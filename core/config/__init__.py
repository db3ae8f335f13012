"""One typed configuration for the whole localizer, with the paper's defaults.

- :mod:`.schema`: the sections (``map``, ``pf``, ``s2m``, ``localize``, ``town``) with their units
  and defaults, and :meth:`Config.validate`;
- :mod:`.loading`: :func:`load_config` (defaults, preset, world, file, ``--set``);
- :mod:`.live`: :data:`LIVE_PARAMS`, the parameters a running localizer accepts, and
  :func:`check_live_changes`, their one validation.

``docs/configuration.md`` lists every entry; it is generated from this package
(``python -m lidarloc.core.config.reference``) and a test keeps it current.
"""

from .live import LIVE_PARAMS, LiveParam, check_live_changes
from .loading import PRESETS, WORLDS, apply_overrides, apply_preset, apply_world, load_config, update_from_dict
from .schema import (
    ANGULAR_STATE,
    DEG,
    PAPER_Q_STD,
    STATE_NAMES,
    TOWN_MAX_EXTENT,
    TOWN_SENSORS,
    Config,
    LocalizeConfig,
    MapConfig,
    PFConfig,
    S2MConfig,
    TownConfig,
)

__all__ = [
    "ANGULAR_STATE",
    "DEG",
    "LIVE_PARAMS",
    "PAPER_Q_STD",
    "PRESETS",
    "STATE_NAMES",
    "TOWN_MAX_EXTENT",
    "TOWN_SENSORS",
    "WORLDS",
    "Config",
    "LiveParam",
    "LocalizeConfig",
    "MapConfig",
    "PFConfig",
    "S2MConfig",
    "TownConfig",
    "apply_overrides",
    "apply_preset",
    "apply_world",
    "check_live_changes",
    "load_config",
    "update_from_dict",
]
