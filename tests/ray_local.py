"""One local Ray instance for every Ray test of a pytest process (2 CPUs, a small object store,
no dashboard), started by the first test that needs it; its workers find tests/ on their path."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

TESTS = str(Path(__file__).parent)


@pytest.fixture(scope="session")
def ray_local():
    ray = pytest.importorskip("ray", reason="Ray is part of the test environment: pip install -e '.[test]'")
    from lidarloc.app.sweep.cluster import OBJECT_STORE_BYTES

    if not ray.is_initialized():
        path = os.pathsep.join(p for p in (TESTS, os.environ.get("PYTHONPATH")) if p)
        os.environ.setdefault("RAY_AIR_NEW_OUTPUT", "0")
        ray.init(
            num_cpus=2,
            include_dashboard=False,
            object_store_memory=OBJECT_STORE_BYTES,
            log_to_driver=False,
            runtime_env={"env_vars": {"PYTHONPATH": path}},
        )
    return ray
