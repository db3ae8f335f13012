"""Loading a configuration: the defaults, then a named preset and town world, then a YAML/TOML
file, then ``section.key=value`` overrides (what ``--set`` on the CLI does), validated."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any

from ..errors import LidarlocError
from .schema import Config


def _coerce(current: Any, raw: Any, key: str) -> Any:
    """Convert a raw (string or parsed) value to the type of the current value."""
    try:
        if isinstance(current, bool):
            if isinstance(raw, str):
                if raw.lower() in ("1", "true", "yes", "on"):
                    return True
                if raw.lower() in ("0", "false", "no", "off"):
                    return False
                raise ValueError(raw)
            return bool(raw)
        if isinstance(current, int):
            return int(raw)
        if isinstance(current, float):
            return float(raw)
        if isinstance(current, tuple):
            # "a,b,c", and the same in brackets as a YAML list would be typed: "[a, b, c]"
            items = raw.strip().strip("[]()").split(",") if isinstance(raw, str) else list(raw)
            return tuple(float(v) for v in items)
        return str(raw)
    except (TypeError, ValueError):
        raise LidarlocError(f"invalid configuration: {key}={raw!r} is not a valid {type(current).__name__}") from None


#: Other names a key may be written with (``--set s2m.global=exact``): ``global`` is a Python
#: keyword, so the field is ``global_search``.
ALIASES = {"s2m.global": "global_search"}


def update_from_dict(cfg: Config, data: dict, prefix: str = "") -> Config:
    for key, raw in data.items():
        key = ALIASES.get(f"{prefix}{key}", key)
        name = f"{prefix}{key}"
        if not hasattr(cfg, key):
            raise LidarlocError(f"invalid configuration: unknown key '{name}'")
        current = getattr(cfg, key)
        if dataclasses.is_dataclass(current):
            if not isinstance(raw, dict):
                raise LidarlocError(f"invalid configuration: '{name}' must be a table")
            update_from_dict(current, raw, prefix=name + ".")
        else:
            setattr(cfg, key, _coerce(current, raw, name))
    return cfg


def apply_overrides(cfg: Config, overrides: list[str] | None) -> Config:
    """Apply ``section.key=value`` strings (e.g. ``pf.sigma=0.7``)."""
    for item in overrides or []:
        if "=" not in item:
            raise LidarlocError(f"invalid override '{item}': expected section.key=value")
        path, raw = item.split("=", 1)
        parts = path.strip().split(".")
        nested: dict = {}
        node = nested
        for p in parts[:-1]:
            node = node.setdefault(p, {})
        node[parts[-1]] = raw.strip()
        update_from_dict(cfg, nested)
    return cfg


# Named configurations (``--preset NAME``), applied over the defaults before a config file and
# ``--set``. "paper" pins every choice of the paper's experiment, so that it stays the paper's
# method whatever the defaults become: its likelihood untempered and without an unexplained-point
# term, all points used, a fixed particle count, S2M searching ±(L_x, L_y) around the best
# particle from the first scan, a match accepted only if BnB beat the start and the particle's
# weight does not drop, scans used as they come. "default" is the defaults themselves.
PRESETS: dict[str, dict[str, Any]] = {
    "default": {},
    "paper": {
        "pf.temperature": 1.0,
        "pf.unexplained_share": 0.0,
        "pf.max_points": 0,
        "pf.max_elevation": math.pi / 2,
        "pf.dynamic_rejection": False,
        "pf.kld": False,
        "s2m.global_until_localized": False,
        "s2m.global_search": "exact",
        "s2m.reject_if_weight_drops": True,
        "s2m.refine_unbeaten_start": False,
        "localize.deskew": False,
        "localize.require_s2m_confirmation": False,
        "s2m.global_check_interval": 0,
        "localize.lost_after_scans": 0,
    },
}


# Worlds of the built-in town's drive (``lidarloc bench localize --world NAME``), applied after the
# preset and before a config file and ``--set``. "lived-in" is what a map meets in use: 30 % of the
# movable objects changed since mapping, traffic, scans swept while moving; "kind" is the town as
# it was mapped (the defaults). Other sources ignore the town's options.
WORLDS: dict[str, dict[str, Any]] = {
    "lived-in": {"town.changes": 0.3, "town.traffic": True, "town.skew": True},
    "kind": {},
}


def _apply_named(cfg: Config, name: str | None, table: dict[str, dict[str, Any]], what: str) -> Config:
    if name is None:
        return cfg
    if name not in table:
        raise LidarlocError(f"invalid configuration: unknown {what} '{name}' (choose {'|'.join(table)})")
    return apply_overrides(cfg, [f"{key}={value}" for key, value in table[name].items()])


def apply_world(cfg: Config, name: str | None) -> Config:
    return _apply_named(cfg, name, WORLDS, "world")


def apply_preset(cfg: Config, name: str | None) -> Config:
    return _apply_named(cfg, name, PRESETS, "preset")


def load_config(
    path: str | Path | None = None,
    overrides: list[str] | None = None,
    preset: str | None = None,
    world: str | None = None,
) -> Config:
    """Defaults, then a preset (if named), then a town world (if named), then a YAML/TOML file
    (if given), then ``section.key=value`` overrides; validated."""
    cfg = apply_world(apply_preset(Config(), preset), world)
    if path is not None:
        path = Path(path)
        if not path.is_file():
            raise LidarlocError(f"{path}: config file not found")
        try:
            text = path.read_text()
            if path.suffix.lower() == ".toml":
                try:
                    import tomllib  # pyright: ignore[reportMissingImports]  (Python ≥ 3.11)
                except ModuleNotFoundError:  # Python 3.10
                    import tomli as tomllib  # type: ignore[no-redef]
                data = tomllib.loads(text)
            else:
                import yaml

                data = yaml.safe_load(text) or {}
        except LidarlocError:
            raise
        except Exception as exc:  # parser errors differ per format; all are "unreadable config"
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            raise LidarlocError(f"{path}: unreadable config ({first})") from None
        if not isinstance(data, dict):
            raise LidarlocError(f"{path}: unreadable config (top level must be a mapping)")
        update_from_dict(cfg, data)
    apply_overrides(cfg, overrides)
    return cfg.validate()
