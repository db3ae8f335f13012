"""The recording format: every step's full state, appended to disk as it happens, and read back.

A run's results folder gets ``recording/``; ``open(folder)`` reads it back (in a notebook too)::

    from .. import recording
    rec = recording.open("out/run0")
    rec.n                       # complete steps recorded
    rec.mean_pose[i]            # 4×4 estimate after step i (the i-th processed scan)
    rec.particles(i)            # (N, 11) float32 particles after step i, rec.weights(i) their weights
    rec.events                  # [(step, Event), …]
    rec.snapshot(i, seq)        # the step as the viewer shows it

Format (version 1), chosen so that a recording is cheap to append, memory-mappable and readable
up to its last complete step after a crash:

- ``index.json``: ``format`` ("lidarloc-recording"), ``version``, ``meta`` (the source options,
  the configuration, the seed, the sequence, the clock, …) and ``fields``: per field its dtype,
  per-step shape and the first step it was written at.
- One raw little-endian file per per-step field (``mean_pose.bin``: rows of 4×4 float64, …).
  Particles vary in number (KLD, tracking), so ``particles.bin`` (float32 rows of 11 states) and
  ``log_weights.bin`` (float32) hold every step's rows one after the other, and the per-step field
  ``particle_rows`` says where (first row, count). Float32 is what a display needs; the filter's
  exact float64 state for resuming is in the resume payload's checkpoints.
- ``events.jsonl``: one event per line with the step after which it was recorded (-1: before the
  first scan).
- ``s2m/STEP.json`` and ``s2m/STEP.f16``: each S2M match that landed (an
  :class:`~lidarloc.core.snapshot.S2MView`; its road-removed scan in the matched pose's frame as
  float16: a display's precision, ≤ 6 cm at 100 m).
- ``resume/STEP-NAME.npz``: what resuming needs (:meth:`Localizer.resume_payload`: checkpoints of
  the filter's exact state, raw S2M outcomes); its per-step arrays are ordinary fields.
- ``steps.bin``: the commit log, one int64 per step, written after everything else of the step.
  A step exists only once its row is there, so a recording cut short (Ctrl-C, a killed process)
  opens up to its last complete step.

- ``segments/FIRST/``: a run kept under a size budget (the viewer's ``--max-record-gb``) goes on
  in segments, each a recording of this format starting at the run's step ``FIRST``, and drops
  its oldest segments whole: it keeps a rolling window of its newest steps (:mod:`.segments`
  describes the layout; :class:`~.reader.Recording` reads the kept steps as one recording whose
  ``first_step`` says where they start).

The scan itself is not stored: it is a reference to the source the recording names, and
:meth:`Recording.snapshot` recomputes the prepared scan (the same voxel and random seed as the
filter used). With ``localize.deskew`` the filter saw the scan de-skewed with the odometry of
that moment; the recomputed one is not de-skewed (a display difference of a few centimetres).

Size: 48 bytes per particle per step (11 float32 states and a float32 log-weight), ~0.5 kB of
per-step fields, plus the resume payload: ~55 MB per 1000 steps at 1000 particles
(``lidarloc bench record``).
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np

from ...cache import atomic_write_file
from ...errors import LidarlocError
from ...localizer.state import ResumePayload  # noqa: F401  (the payload a step's record carries)
from ...snapshot import S2MView

FORMAT = "lidarloc-recording"
VERSION = 1
FOLDER = "recording"
INDEX = "index.json"
STEPS = "steps.bin"
N_STATE = 11
COMPRESS_ABOVE_BYTES = 64 * 1024
# Steps the writing thread may fall behind before a step waits for it (~50 kB each at 1000
# particles, a checkpoint ~0.2 MB): a slow disk slows the run instead of filling the memory.
QUEUE_STEPS = 64


class RecordingError(LidarlocError):
    """A recording folder is missing, foreign, corrupt or unwritable."""


# The display fields every step has: name → (dtype, per-step shape).
FIELDS: dict[str, tuple[str, tuple]] = {
    "scan_index": ("<i8", ()),
    "timestamp": ("<f8", ()),
    "mean_pose": ("<f8", (4, 4)),
    "cov_xyz": ("<f8", (3, 3)),
    "std_xyz": ("<f8", (3,)),
    "ellipse_xy": ("<f8", (3,)),
    "n_eff": ("<f8", ()),
    "n_particles": ("<i8", ()),
    "best_index": ("<i8", ()),
    "localized": ("|u1", ()),
    "localized_since": ("<i8", ()),
    "converged": ("|u1", ()),
    "error_m": ("<f8", ()),
    "gt_pose": ("<f8", (4, 4)),
    "pf_ms": ("<f8", ()),
    "rpe_ms": ("<f8", ()),
    "s2m_ms": ("<f8", ()),
    "reinit": ("|u1", ()),
    "inlier_share": ("<f8", ()),
    "mean_residual_m": ("<f8", ()),
    "inside_2sigma": ("|i1", ()),
    "scan_voxel": ("<f8", ()),
    "s2m_running": ("|u1", ()),
    "s2m_pending": ("|u1", ()),
    "s2m_acceptance": ("<f8", ()),
    "done": ("|u1", ()),
    "particle_rows": ("<i8", (2,)),
    "awaiting_confirmation": ("|u1", ()),
    "confirmed_at": ("<i8", ()),
    "s2m_status": ("|i1", ()),
}
#: ``s2m_status`` as recorded (the index into this tuple)
S2M_STATUSES = ("ready", "building", "held", "off")
PARTICLES = ("particles", "<f4", (N_STATE,))
LOG_WEIGHTS = ("log_weights", "<f4", ())

S2M_ARRAYS = ("pose", "start_pose", "candidates", "match_pose", "gicp_pose", "alternatives")


def nan_or_value(value) -> float:
    return float("nan") if value is None else float(value)


def jsonable(value: Any) -> Any:
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, dict):
        return {k: jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value


def write_json_atomic(path: Path, data: dict) -> None:
    """A reader never sees half an index; a write that fails (a full disk) leaves the old one and
    no temporary file."""
    text = json.dumps(jsonable(data), indent=1)
    atomic_write_file(path, lambda tmp: tmp.write_text(text))


def save_s2m(folder: Path, step: int, view: S2MView) -> None:
    """``STEP.json`` (every field but the scan; JSON keeps float64 exactly) and ``STEP.f16`` (the
    scan: its bulk, in the matched pose's frame as float16, ≤ 6 cm at 100 m, a display's needs,
    about a quarter of the size of float32 world coordinates). Plain files, no zip: a match lands
    every other scan, and compressing it cost more than the rest of the step's record."""
    data: dict[str, Any] = {}
    for f in dataclasses.fields(view):
        value = getattr(view, f.name)
        if f.name == "scan_world":
            pose = np.asarray(view.pose, np.float64)
            local = (np.asarray(value, np.float64).reshape(-1, 3) - pose[:3, 3]) @ pose[:3, :3]
            (folder / f"{step:06d}.f16").write_bytes(local.astype("<f2").tobytes())
        elif isinstance(value, np.ndarray):
            data[f.name] = np.asarray(value, np.float64).tolist()
        elif isinstance(value, tuple):
            data[f.name] = [float(v) for v in value]
        else:
            data[f.name] = jsonable(value)
    (folder / f"{step:06d}.json").write_text(json.dumps(data))


def load_s2m(folder: Path, step: int) -> S2MView:
    d = json.loads((folder / f"{step:06d}.json").read_text())
    kw: dict[str, Any] = {}
    for f in dataclasses.fields(S2MView):
        if f.name == "scan_world":
            raw = folder / f"{step:06d}.f16"
            local = (
                np.frombuffer(raw.read_bytes(), "<f2").reshape(-1, 3).astype(np.float64)
                if raw.is_file()
                else np.zeros((0, 3))
            )
            pose = np.asarray(d["pose"], np.float64)
            kw[f.name] = (local @ pose[:3, :3].T + pose[:3, 3]).astype(np.float32)
            continue
        if f.name not in d:
            continue
        v = d[f.name]
        if f.name in S2M_ARRAYS:
            kw[f.name] = None if v is None else np.asarray(v, np.float64)
        elif f.name == "nodes_per_level":
            kw[f.name] = tuple(int(x) for x in v)
        elif f.name in ("region", "gicp_correction"):
            kw[f.name] = tuple(float(x) for x in v)
        else:
            kw[f.name] = v
    for name in ("candidates", "alternatives"):
        if kw.get(name) is not None:
            kw[name] = kw[name].reshape(-1, 4)
    return S2MView(**kw)


def named_field(fields: dict, name: str) -> tuple[str, dict]:
    return name, fields[name]
