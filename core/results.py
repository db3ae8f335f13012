"""Writing a run's results: trajectories in KITTI and TUM formats (so ``evo`` reads them), the
per-scan CSV, the event list and the summary JSON.

Poses are LiDAR poses in the map frame (world = first LiDAR pose of the sequence). The ground
truth is written beside the estimate in the same frame and format (``groundtruth_*.txt``) so
``evo_ape kitti groundtruth_kitti.txt trajectory_kitti.txt`` compares like with like.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation


def write_kitti(path: Path, poses: np.ndarray) -> None:
    with open(path, "w") as f:
        for T in poses:
            f.write(" ".join(f"{v:.6e}" for v in np.asarray(T)[:3, :4].reshape(-1)) + "\n")


def write_tum(path: Path, times: np.ndarray, poses: np.ndarray) -> None:
    with open(path, "w") as f:
        for t, T in zip(times, poses):
            q = Rotation.from_matrix(np.asarray(T)[:3, :3]).as_quat()  # x, y, z, w (TUM order)
            x, y, z = np.asarray(T)[:3, 3]
            f.write(f"{t:.6f} {x:.6f} {y:.6f} {z:.6f} {q[0]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f}\n")


def write_records_csv(path: Path, records: list) -> None:
    if not records:
        path.write_text("")
        return
    names = [f.name for f in dataclasses.fields(records[0])]
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(names)
        for r in records:
            row = []
            for n in names:
                v = getattr(r, n)
                if v is None:
                    row.append("")
                elif isinstance(v, bool):
                    row.append(int(v))
                elif isinstance(v, float):
                    row.append(f"{v:.6g}")
                else:
                    row.append(v)
            w.writerow(row)


def write_events(path: Path, events: list) -> None:
    path.write_text(json.dumps([dataclasses.asdict(e) for e in events], indent=1))


def json_safe(value):
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, (np.floating, float)):
        v = float(value)
        return v if math.isfinite(v) else None
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.bool_):
        return bool(value)
    return value


def write_json(path: Path, data: dict) -> None:
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(json_safe(data), indent=2))
    tmp.replace(path)
