"""``lidarloc sources``: the registered sources and their options, read from the registry."""

from __future__ import annotations

import typer

from ...core.sequences.registry import COMMON_OPTIONS, RECORDING_OPTIONS, Option, Source, sources
from ..console import emit_json
from ..options import JsonOpt
from .groups import app


def _option_row(option: Option) -> dict:
    return {
        "flag": option.flag,
        "type": "path" if option.is_path else option.type.__name__,
        "default": option.default,
        "help": option.help,
    }


def _source_row(source: Source) -> dict:
    return {
        "name": source.name,
        "title": source.title,
        "default": source.default,
        "recording": source.recording,
        "options": [_option_row(o) for o in source.options],
        "available": source.available(),
        "install": None if source.available() else source.install,
    }


def _option_line(option: Option) -> str:
    default = f" (default {option.default})" if option.default is not None else ""
    return f"    {option.flag:<16} {option.help}{default}"


@app.command("sources")
def list_sources(as_json: JsonOpt = False):
    """The sources scans can come from, with their options: every command that takes a sequence
    accepts them, and a corpus drive names them by their field names (--scans-dir: scans_dir)."""
    if as_json:
        emit_json(
            {
                "sources": [_source_row(s) for s in sources()],
                "recording_options": [_option_row(o) for o in RECORDING_OPTIONS],
                "common_options": [_option_row(o) for o in COMMON_OPTIONS if o.cli],
            }
        )
        return
    for source in sources():
        tags = [t for t, on in (("default", source.default), ("recording", source.recording)) if on]
        typer.echo(f"{source.name}{' (' + ', '.join(tags) + ')' if tags else ''}: {source.title}")
        for option in source.options:
            typer.echo(_option_line(option))
        if not source.available():
            typer.echo(f"    not installed: {source.install}")
    typer.echo("a recording (a source without a map of its own) also takes:")
    for option in RECORDING_OPTIONS:
        typer.echo(_option_line(option))
    typer.echo("every source takes:")
    for option in COMMON_OPTIONS:
        if option.cli:
            typer.echo(_option_line(option))
