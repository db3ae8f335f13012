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
def test_pyright_resolves_every_import_and_is_clean(pyright_run):
    """pyright over the repository (started when the tests were collected: tests/conftest.py)."""
    if isinstance(pyright_run, str):
        pytest.skip(pyright_run)
    code, stdout, stderr = pyright_run.result(timeout=840)
    if code not in (0, 1):  # pyright could not start (its Node.js runtime could not be fetched)
        pytest.skip(f"pyright did not run: {(stderr or stdout).strip().splitlines()[-1:]}")
    assert code == 0 and "0 errors" in stdout, stdout[-6000:]
