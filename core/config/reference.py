"""The configuration reference (``docs/configuration.md``), generated from the schema itself so it
cannot go stale: every section and entry with its default and the comment that explains it in
:mod:`.schema`, the presets and worlds, and the live parameters.

``python -m lidarloc.core.config.reference > docs/configuration.md`` writes it; a test checks that
the committed page equals what this prints.
"""

from __future__ import annotations

import ast
import dataclasses
import inspect
import math

from . import schema
from .live import LIVE_PARAMS
from .loading import PRESETS, WORLDS
from .schema import DEG, Config

SECTIONS = ("map", "pf", "s2m", "localize", "town")


def _comments(cls) -> dict[str, str]:
    """Each field's explanation: the comment lines right above it and the comment after it on its
    line (with the comment-only lines that continue it)."""
    source = inspect.getsource(cls)
    lines = source.splitlines()
    tree = ast.parse(source)
    out: dict[str, str] = {}
    for node in tree.body[0].body:
        if not isinstance(node, ast.AnnAssign) or not isinstance(node.target, ast.Name):
            continue
        i = node.lineno - 1
        above = []
        j = i - 1
        while j >= 0 and lines[j].strip().startswith("#"):
            above.insert(0, lines[j].strip()[1:].strip())
            j -= 1
        after = []
        if "#" in lines[node.end_lineno - 1]:
            after.append(lines[node.end_lineno - 1].split("#", 1)[1].strip())
            j = node.end_lineno
            indent = lines[node.end_lineno - 1].index("#")
            while j < len(lines) and lines[j].strip().startswith("#") and lines[j].index("#") >= indent:
                after.append(lines[j].strip()[1:].strip())
                j += 1
        out[node.target.id] = " ".join(above + after)
    return out


def _value(v, angle: bool = False) -> str:
    if isinstance(v, float):
        if v == math.pi:
            return "π"
        if v == math.pi / 2:
            return "π/2"
        return f"{v:.6g}" + (f" ({v / DEG:.4g}°)" if angle and v else "")
    if isinstance(v, tuple):
        return ", ".join(_value(x) for x in v)
    if isinstance(v, bool):
        return "true" if v else "false"
    return str(v)


def _cell(text: str) -> str:
    return text.replace("|", "\\|")


def markdown() -> str:
    cfg = Config()
    lines = [
        "# Configuration reference",
        "",
        "Every entry of lidarloc's configuration, its default and what it means. Set entries with",
        "`--set section.key=value`, a YAML/TOML file (`--config`), or a named `--preset` / `--world`",
        "(applied first). Units are metres, seconds and radians (angles are listed with their degrees).",
        "This page is generated from `core/config/schema.py` (`python -m lidarloc.core.config.reference`).",
        "",
    ]
    for name in SECTIONS:
        section = getattr(cfg, name)
        cls = type(section)
        doc = inspect.getdoc(cls) or ""
        lines += [f"## `{name}`", "", doc.replace("\n", " "), "", "| key | default | meaning |", "|---|---|---|"]
        notes = _comments(cls)
        for f in dataclasses.fields(section):
            note = notes.get(f.name, "")
            angle = note.startswith("rad") or note.endswith(" rad") or ", rad" in note
            lines.append(f"| `{name}.{f.name}` | {_cell(_value(getattr(section, f.name), angle))} | {_cell(note)} |")
        lines.append("")
    lines += ["## Presets (`--preset`)", ""]
    for preset, entries in PRESETS.items():
        body = ", ".join(f"`{k}={_value(v)}`" for k, v in entries.items()) or "the defaults above"
        lines.append(f"- `{preset}`: {body}")
    lines += ["", "## Worlds of the built-in town (`--world`)", ""]
    for world, entries in WORLDS.items():
        body = ", ".join(f"`{k}={_value(v)}`" for k, v in entries.items()) or "the town as it was mapped"
        lines.append(f"- `{world}`: {body}")
    lines += [
        "",
        "## Live parameters",
        "",
        "What the viewer's Parameters folder (and `Localizer.set_params`) may change during a run.",
        "",
        "| name | entry | rule | what changes with it |",
        "|---|---|---|---|",
    ]
    effects = {
        "": "read where it is used",
        "lookup": "a larger d_max rebuilds the lookup table in the background",
        "filter": "the particle filter takes it from the next scan",
        "particles": "the particle count; the match in flight is dropped",
        "s2m_switch": "off drops the match in flight",
        "pyramid": "the BEV pyramid is rebuilt in the background",
        "clock": "real time gets an S2M process at normal priority",
    }
    for key, p in LIVE_PARAMS.items():
        lines.append(f"| `{key}` | `{p.section}.{p.attr}` | {_cell(p.rule)} | {effects.get(p.effect, p.effect)} |")
    return "\n".join(lines) + "\n"


assert schema  # the module whose source this page reads

if __name__ == "__main__":
    print(markdown(), end="")
