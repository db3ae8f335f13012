"""The package as installed: every package folder is listed in pyproject.toml, and the
configuration reference in docs/ is what the schema says today."""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_every_package_folder_is_installed():
    if sys.version_info >= (3, 11):
        import tomllib
    else:  # pragma: no cover
        import tomli as tomllib  # pyright: ignore[reportMissingImports]  (Python 3.10)
    listed = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    found = {"lidarloc"} | {
        "lidarloc." + ".".join(p.parent.relative_to(ROOT).parts)
        for top in ("core", "app")
        for p in (ROOT / top).rglob("__init__.py")
    }
    assert listed == found


def test_the_configuration_reference_is_current():
    from lidarloc.core.config.reference import markdown

    page = (ROOT / "docs" / "configuration.md").read_text()
    assert page == markdown(), "regenerate it: python -m lidarloc.core.config.reference > docs/configuration.md"
