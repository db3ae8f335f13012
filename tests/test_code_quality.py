"""The code's habits, checked: ruff's lint and format, and pyright resolving every import (the
repository's root is the lidarloc package; inside it, imports are relative)."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _tool(name: str) -> str:
    exe = Path(sys.executable).parent / name
    if exe.is_file():
        return str(exe)
    found = shutil.which(name)
    if found is None:
        pytest.skip(f"{name} is not installed (it is in the test extras: pip install -e '.[test]')")
    return found


def test_ruff_lint_is_clean():
    r = subprocess.run([_tool("ruff"), "check", "--no-cache", "."], cwd=ROOT, capture_output=True, text=True)
    assert r.returncode == 0, r.stdout[-4000:]


def test_ruff_format_is_clean():
    r = subprocess.run(
        [_tool("ruff"), "format", "--check", "--no-cache", "."], cwd=ROOT, capture_output=True, text=True
    )
    assert r.returncode == 0, r.stdout[-4000:]


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_pyright_resolves_every_import_and_is_clean():
    link = Path(sys.prefix) / "src" / "lidarloc"  # what ./run makes: `lidarloc` for tests and examples
    if Path(sys.prefix).resolve() != (ROOT / ".venv").resolve():
        pytest.skip("pyright reads the project's .venv (run the tests with ./run test)")
    if not link.exists():
        link.parent.mkdir(parents=True, exist_ok=True)
        link.symlink_to("../..", target_is_directory=True)
    r = subprocess.run([_tool("pyright")], cwd=ROOT, capture_output=True, text=True, timeout=840)
    if r.returncode not in (0, 1):  # pyright could not start (its Node.js runtime could not be fetched)
        pytest.skip(f"pyright did not run: {(r.stderr or r.stdout).strip().splitlines()[-1:]}")
    assert r.returncode == 0 and "0 errors" in r.stdout, r.stdout[-6000:]
