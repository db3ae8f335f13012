"""``--preset NAME`` on the command line: every command that takes a configuration offers it, it
comes before --config and --set, ``lidarloc run`` records it in its summary, and a bad name is one
line with exit status 2."""

import json

import pytest
import typer
from helpers import cli_here, run_cli
from lidarloc.core.config import PRESETS

# A small town (100 m, a 40-scan mapping drive) keeps the map build to seconds.
SMALL_TOWN = ("--set", "town.extent_m=100", "--set", "town.n_scans=40")
# The commands with a configuration; bench robustness runs the presets as one of its axes instead.
WITH_PRESET = {
    ("demo",),
    ("view",),
    ("run",),
    ("synth",),
    ("inspect",),
    ("map", "build"),
    ("map", "export"),
    *[
        ("bench", b)
        for b in (
            "town",
            "map",
            "pf",
            "s2m",
            "rpe",
            "viewer",
            "startup",
            "stop",
            "localize",
            "surface",
            "bag",
            "record",
            "branch",
            "scrub",
            "filter",
            "peers",
            "integrity",
            "soak",
            "clients",
            "city",
            "shards",
        )
    ],
    ("sweep",),
    ("tune",),
}


def cli(*args, cache):
    return run_cli(*args, cache=cache)


def _commands(group, prefix=()):
    for name, command in group.commands.items():
        if hasattr(command, "commands"):
            yield from _commands(command, prefix + (name,))
        else:
            yield prefix + (name,), command


def test_every_command_with_a_configuration_takes_preset():
    from lidarloc.app.cli import app

    commands = dict(_commands(typer.main.get_command(app)))
    with_config = {path for path, c in commands.items() if any("--config" in p.opts for p in c.params)}
    with_preset = {path for path, c in commands.items() if any("--preset" in p.opts for p in c.params)}
    assert with_preset == WITH_PRESET
    assert with_config - with_preset == {("bench", "robustness")}


def test_preset_comes_before_the_config_file_and_set(tmp_path):
    from lidarloc.app.options import config_from

    assert PRESETS["paper"]["s2m.reject_if_weight_drops"] is True  # the entry this test follows
    assert config_from(None, None).s2m.reject_if_weight_drops is False
    assert config_from(None, None, preset="default").s2m.reject_if_weight_drops is False
    assert config_from(None, None, preset="paper").s2m.reject_if_weight_drops is True
    f = tmp_path / "c.yaml"
    f.write_text("s2m: {reject_if_weight_drops: false}\n")
    assert config_from(f, None, preset="paper").s2m.reject_if_weight_drops is False
    assert config_from(None, ["s2m.reject_if_weight_drops=false"], preset="paper").s2m.reject_if_weight_drops is False
    assert config_from(None, None, seed=7, preset="paper").seed == 7


def test_the_world_comes_after_the_preset_and_before_the_config_file_and_set(tmp_path):
    from lidarloc.app.options import config_from
    from lidarloc.core.config import WORLDS

    lived_in = config_from(None, None, preset="paper", world="lived-in")
    assert (lived_in.town.changes, lived_in.town.traffic, lived_in.town.skew) == (0.3, True, True)
    assert lived_in.pf.temperature == 1.0  # the preset is still applied
    kind = config_from(None, None, world="kind")
    assert (kind.town.changes, kind.town.traffic, kind.town.skew) == (0.0, False, False) and WORLDS["kind"] == {}
    f = tmp_path / "c.yaml"
    f.write_text("town: {traffic: false}\n")
    assert config_from(f, None, world="lived-in").town.traffic is False
    assert config_from(None, ["town.changes=0.6"], world="lived-in").town.changes == 0.6


def test_bench_localize_defaults_to_the_lived_in_world_and_a_bad_world_is_one_line(tmp_path):
    from lidarloc.app.cli import app

    bench = typer.main.get_command(app).commands["bench"]
    with_world = {name for name, c in bench.commands.items() if any("--world" in p.opts for p in c.params)}
    # the benchmarks of localization and matching quality, and of the filter's word and its peers
    assert with_world == {"localize", "s2m", "integrity", "peers"}
    for name in with_world:
        assert next(p for p in bench.commands[name].params if "--world" in p.opts).default == "lived-in"
    out = tmp_path / "out"
    r = cli("bench", "localize", "--world", "nice", "--scans", "2", "--out", str(out), cache=tmp_path / "cache")
    assert r.returncode == 2, r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "unknown world 'nice'" in lines[0] and "lived-in|kind" in lines[0]
    assert not out.exists()


def test_run_records_the_preset_in_its_summary(tmp_path, cache_root):
    out = tmp_path / "run"
    r = cli("run", "--preset", "paper", "--scans", "5", *SMALL_TOWN, "--out", str(out), "--json", cache=cache_root)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["preset"] == "paper"
    assert json.loads((out / "summary.json").read_text())["preset"] == "paper"


@pytest.mark.parametrize("command", [("run", "--out", "OUT"), ("map", "build"), ("bench", "localize", "--out", "OUT")])
def test_a_bad_preset_is_one_line(tmp_path, command):
    out = tmp_path / "out"
    args = [str(out) if a == "OUT" else a for a in command]
    # by the entry point in this process: the refusal's output, without a child's start-up (these
    # commands run as users start them in the other tests)
    r = cli_here(*args, "--preset", "fastest", "--scans", "2", cache=tmp_path / "cache")
    assert r.returncode == 2, r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    assert "unknown preset 'fastest'" in lines[0] and "paper" in lines[0]
    assert not out.exists()


@pytest.mark.slow
def test_bench_s2m_matches_a_lived_in_drive_unless_told_kind(tmp_path, cache_root):
    worlds = {}
    for world in ("lived-in", "kind"):
        r = cli(
            "bench",
            "s2m",
            "--world",
            world,
            "--matches",
            "3",
            "--no-gicp-comparison",
            "--scans",
            "12",
            *SMALL_TOWN,
            "--json",
            cache=cache_root,
        )
        assert r.returncode == 0, r.stderr
        worlds[world] = json.loads(r.stdout)["world"]
    assert (worlds["lived-in"]["changes"], worlds["lived-in"]["traffic"], worlds["lived-in"]["skew"]) == (
        0.3,
        True,
        True,
    )
    assert (worlds["kind"]["changes"], worlds["kind"]["traffic"], worlds["kind"]["skew"]) == (0.0, False, False)
