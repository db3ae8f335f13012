"""A folder of scan files: ``--scans-dir`` (.pcd, .ply, .bin or .npy; times from its times.txt)."""

from __future__ import annotations

from pathlib import Path

from ..registry import Option, Source, as_path, truth_options


def _open(spec, cfg, progress=None):
    from ..scan_folder import ScanFolderSequence

    return ScanFolderSequence(as_path(spec.scans_dir), **truth_options(spec))


SOURCE = Source(
    name="scans_dir",
    title="a folder of scans (.pcd, .ply, .bin or .npy, in name order; times from its times.txt)",
    options=(
        Option(
            "scans_dir",
            Path,
            "Folder of scans (.pcd, .ply, .bin or .npy, in name order; times from its times.txt).",
            metavar="DIR",
        ),
    ),
    open=_open,
    describe=lambda spec: f"scan folder {spec.scans_dir}",
    recording=True,
)
