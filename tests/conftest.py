import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def shared_data_dir() -> Path | None:
    """The real KITTI data: $LIDARLOC_DATA, else ../shared/data beside the project."""
    env = os.environ.get("LIDARLOC_DATA")
    path = Path(env) if env else REPO.parent / "shared" / "data"
    return path if path.is_dir() else None


@pytest.fixture(scope="session")
def shared_data() -> Path:
    path = shared_data_dir()
    if path is None:
        pytest.skip("real KITTI data not found (../shared/data or $LIDARLOC_DATA); licence keeps it out of the repo")
    return path


@pytest.fixture(scope="session")
def kitti_raw_dir(shared_data) -> Path:
    path = shared_data / "kitti_raw"
    if not (path / "2011_09_26" / "2011_09_26_drive_0013_sync").is_dir():
        pytest.skip(f"KITTI raw drive 0013 not found under {path}")
    return path


@pytest.fixture(scope="session")
def kitti_raw_seq(kitti_raw_dir):
    from lidarloc.core.sequences.kitti_raw import KittiRaw

    return KittiRaw(kitti_raw_dir, "2011_09_26", "0013")
