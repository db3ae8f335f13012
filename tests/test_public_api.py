"""The public API: the names ``lidarloc`` exports, that they load on first use (the command line
starts quickly), that they work from a wheel as pip installs it, and that a localizer given a
world opened beforehand runs as one that opens its own."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]

PUBLIC = [
    "Config",
    "Event",
    "LidarlocError",
    "Localizer",
    "Recording",
    "S2MView",
    "ScanRecord",
    "Snapshot",
    "SourceSpec",
    "World",
    "load_config",
    "open_branch",
    "open_recording",
    "open_sequence",
    "open_world",
    "summarize_run",
    "write_run",
]


def test_the_public_names_are_pinned_and_each_resolves():
    import lidarloc

    assert sorted(n for n in lidarloc.__all__ if n != "__version__") == PUBLIC
    assert sorted(lidarloc._PUBLIC) == PUBLIC  # what loads on first use is what is exported
    for name in PUBLIC:
        value = getattr(lidarloc, name)
        assert value.__module__.startswith("lidarloc.core."), (name, value.__module__)
    assert set(PUBLIC) <= set(dir(lidarloc))
    with pytest.raises(AttributeError, match="no attribute 'localizer'"):
        lidarloc.localizer  # noqa: B018 - a misspelt name is an AttributeError, not a deep import


def test_importing_the_package_loads_nothing_heavy():
    code = "import sys, lidarloc; print(sorted(m for m in ('numpy', 'numba', 'open3d', 'viser') if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_the_public_api_imports_from_a_built_wheel(tmp_path):
    # build from a copy of the sources, so that the checkout gets no build/ folder
    src = tmp_path / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md", "__init__.py"):
        shutil.copy(ROOT / name, src / name)
    for name in ("core", "app"):
        shutil.copytree(ROOT / name, src / name, ignore=shutil.ignore_patterns("__pycache__"))
    wheels = tmp_path / "wheels"
    build = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w", str(wheels), str(src)],
        capture_output=True,
        text=True,
    )
    assert build.returncode == 0, build.stderr[-2000:]
    (wheel,) = wheels.glob("lidarloc-*.whl")
    site = tmp_path / "site"
    shutil.unpack_archive(wheel, site, format="zip")
    code = (
        f"import sys; sys.path.insert(0, {str(site)!r}); import lidarloc; "
        f"assert lidarloc.__file__.startswith({str(site)!r}), lidarloc.__file__; "
        "from lidarloc import Localizer, Config, open_sequence, open_world, SourceSpec; "
        "print(Config().pf.sigma > 0, Localizer.__module__)"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path)
    assert run.returncode == 0, run.stderr[-2000:]
    assert run.stdout.split() == ["True", "lidarloc.core.localizer.scan_loop"]


def test_a_localizer_on_a_world_opened_beforehand_runs_as_one_that_opens_its_own(town_cache):
    from helpers import MAPPING_SCANS
    from lidarloc import Localizer, SourceSpec, load_config, open_sequence, open_world

    # the particle filter alone (no S2M, odometry in this process): the world is what differs
    cfg = load_config(
        overrides=[
            f"town.n_scans={MAPPING_SCANS}",
            "pf.n_particles=300",
            "s2m.enabled=false",
            "localize.rpe_process=false",
        ]
    )
    seq = open_sequence(SourceSpec(scans=6), cfg)

    def errors(**kwargs):
        with Localizer(seq, cfg, cache_root=town_cache, **kwargs) as loc:
            loc.run()
            return loc.world, np.array([np.nan if r.error_m is None else r.error_m for r in loc.records])

    world = open_world(seq.map_source, cfg, town_cache)
    own_world, own = errors()
    used, given = errors(world=world)
    assert used is world and own_world is not world  # the one given is used, not opened again
    assert len(own) == 6 and np.array_equal(own, given, equal_nan=True)


def test_the_examples_and_the_python_page_use_only_the_public_api():
    import re

    texts = {p: p.read_text() for p in [*(ROOT / "examples").glob("*.py"), ROOT / "docs" / "python-api.md"]}
    for path, text in texts.items():
        deep = re.findall(r"(?:from|import) lidarloc\.\w+", text)
        assert not deep, (path.name, deep)
        names = {n.strip() for m in re.findall(r"from lidarloc import ([\w, ]+)", text) for n in m.split(",")}
        assert names and names <= set(PUBLIC), (path.name, names - set(PUBLIC))
