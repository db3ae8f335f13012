"""``lidarloc bench record``: what recording a run costs and how fast it opens again.

A localizer runs over the source's scans (default: the town's first 1000, 1000 particles) with a
:class:`~lidarloc.core.runs.recording.RecordingWriter` attached, the way ``lidarloc run`` records.
Measured:

- the time ``on_scan`` takes per step on the stepping thread (gathering copies of the display
  fields, the particles, the events and the resume payload, and handing them to the writer's
  thread), against the PF step's own time: target ≤ 5 % (medians); beside it the CPU time the
  writer's thread spends per step putting them on disk (mean: it writes in batches), which runs
  alongside the filter instead of in its step;
- the recording's size per 1000 steps at the run's particle count: target ≤ 60 MB at 1000
  particles without scan points (the scans are a reference to the source, not stored; the
  road-removed scan of each S2M match is, at float16, and counted apart); the resume payload
  (checkpoints, S2M outcomes) separately;
- opening it again (``recording.open`` and reading every per-step field and the last step's
  particles, what ``lidarloc view --run`` does first): target ≤ 3 s for 1000 steps, median of
  repeats.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from ...core.localizer import Localizer
from ...core.runs import recording
from .common import load_avg, machine

TARGET_SHARE = 0.05
TARGET_MB_PER_1000 = 60.0
TARGET_OPEN_S = 3.0


def _open_all(path: Path) -> float:
    t0 = time.perf_counter()
    rec = recording.open(path)
    for name in rec.field_names:
        if name not in ("particles", "log_weights"):
            rec.field(name)
    rec.particles(rec.n - 1)
    rec.weights(rec.n - 1)
    _ = rec.events
    rec.s2m(rec.n - 1)
    return time.perf_counter() - t0


def run(spec, seq, cfg, cache_root: Path | None = None, open_repeats: int = 5, progress=None) -> dict:
    """Record a run of ``seq`` with ``cfg`` and measure it (see the module docstring)."""
    with tempfile.TemporaryDirectory(prefix="lidarloc-record-") as tmp:
        loc = Localizer(seq, cfg, cache_root)
        record_ms: list[float] = []
        try:
            writer = recording.RecordingWriter(Path(tmp), spec, cfg, seq)
            while not loc.done:
                snap = loc.step()
                t0 = time.perf_counter()
                writer.on_scan(loc, snap)
                record_ms.append((time.perf_counter() - t0) * 1000.0)
                if progress is not None:
                    progress(len(record_ms), len(seq))
            writer.close()
            writer_cpu_ms = writer.writer_cpu_s * 1000.0 / max(writer.n, 1)
            pf_ms = [r.pf_ms for r in loc.records]
            particles = [r.n_particles for r in loc.records]
        finally:
            loc.close()
        rec = recording.open(tmp)
        n = rec.n
        folder = rec.path
        total = rec.size_bytes()
        scan_points = sum(f.stat().st_size for f in (folder / "s2m").glob("*.f16"))
        resume = sum(f.stat().st_size for f in (folder / "resume").glob("*") if f.is_file())
        resume += sum(
            (folder / f"{name}.bin").stat().st_size
            for name in rec.field_names
            if name not in recording.format.FIELDS and name not in ("particles", "log_weights")
        )
        open_s = [_open_all(folder) for _ in range(open_repeats)]
    pf_median = float(np.median(pf_ms))
    rec_median = float(np.median(record_ms))
    per_1000 = total / 1e6 * 1000.0 / max(n, 1)
    without_scans = (total - scan_points) / 1e6 * 1000.0 / max(n, 1)
    mean_particles = float(np.mean(particles))
    return {
        "steps": n,
        "particles_mean": round(mean_particles, 1),
        "record_ms_median": round(rec_median, 3),
        "record_ms_p95": round(float(np.percentile(record_ms, 95)), 3),
        "pf_ms_median": round(pf_median, 2),
        "record_share_of_pf": round(rec_median / pf_median, 4),
        "target_share": TARGET_SHARE,
        "writer_thread_cpu_ms_per_step": round(writer_cpu_ms, 3),
        "writer_thread_cpu_share_of_pf": round(writer_cpu_ms / pf_median, 4),
        "mb_per_1000_steps": round(per_1000, 1),
        "mb_per_1000_steps_without_scan_points": round(without_scans, 1),
        "s2m_scan_points_mb_per_1000_steps": round(scan_points / 1e6 * 1000.0 / max(n, 1), 1),
        "resume_payload_mb_per_1000_steps": round(resume / 1e6 * 1000.0 / max(n, 1), 1),
        "target_mb_per_1000": TARGET_MB_PER_1000,
        "open_s_median": round(float(np.median(open_s)), 3),
        "open_s_scaled_to_1000_steps": round(float(np.median(open_s)) * 1000.0 / max(n, 1), 3),
        "target_open_s": TARGET_OPEN_S,
        "met": bool(
            rec_median / pf_median <= TARGET_SHARE
            and without_scans <= TARGET_MB_PER_1000
            and float(np.median(open_s)) * 1000.0 / max(n, 1) <= TARGET_OPEN_S
        ),
        "load_average_1min": round(load_avg(), 2),
        "machine": machine(),
    }
