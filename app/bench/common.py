"""What the benchmarks share: where the real data is, opening the source, the state of the machine
the numbers were taken on, medians, memory, and pose errors against the ground truth."""

from __future__ import annotations

import math
import os
import platform
from pathlib import Path

import numpy as np

from ...core.config import Config
from ...core.errors import LidarlocError
from ...core.geometry import inv_pose
from ...core.sequences.factory import SourceSpec, open_sequence
from ...core.sequences.registry import COMMON_OPTIONS, RECORDING_OPTIONS

# The real KITTI data is not shipped (licence): $LIDARLOC_DATA, else ../shared/data from where
# the command runs (the repository root).
DATA_ENV = "LIDARLOC_DATA"
DEFAULT_DATA = Path("../shared/data")
# The KITTI raw drive the real-data figures of BENCHMARKS.md are measured on.
REAL_DRIVE_DATE, REAL_DRIVE = "2011_09_26", "0013"


def data_dir() -> Path:
    env = os.environ.get(DATA_ENV)
    return Path(env) if env else DEFAULT_DATA


def real_drive(scans: int | None = None) -> SourceSpec | None:
    """The reference real drive in the data directory, or None where it is absent."""
    root = data_dir() / "kitti_raw"
    if not (root / REAL_DRIVE_DATE / f"{REAL_DRIVE_DATE}_drive_{REAL_DRIVE}_sync").is_dir():
        return None
    return SourceSpec(kitti_raw=root, date=REAL_DRIVE_DATE, drive=REAL_DRIVE, scans=scans)


def require_real_drive(bench: str, scans: int | None = None) -> SourceSpec:
    spec = real_drive(scans)
    if spec is None:
        raise LidarlocError(
            f"bench {bench} reads KITTI raw {REAL_DRIVE_DATE} drive {REAL_DRIVE} by default, not found "
            f"under {data_dir() / 'kitti_raw'} (set ${DATA_ENV}, or choose a source such as --town-seed 0)"
        )
    return spec


def is_town(spec: SourceSpec) -> bool:
    return spec.kind == "town"


def require_town(spec: SourceSpec, bench: str, what: str) -> None:
    if not is_town(spec):
        raise LidarlocError(f"bench {bench} measures {what}; --kitti-odometry and --kitti-raw do not apply")


def open_source(spec: SourceSpec, cfg: Config, bench: str, need_poses: bool = False):
    """The sequence; ``need_poses``: the measurement compares with the ground truth."""
    seq = open_sequence(spec, cfg)
    if need_poses and not seq.has_poses:
        raise LidarlocError(f"bench {bench} compares with the ground truth, which {seq.name} does not have")
    return seq


def source_args(spec: SourceSpec) -> list[str]:
    """The source options that select ``spec`` on a ``lidarloc`` command line (for the benchmarks
    that time a command in a fresh process): its source's options, a recording's, the common ones."""
    source = spec.source
    options = source.options + (RECORDING_OPTIONS if source.recording else ()) + COMMON_OPTIONS
    args = []
    for option in options:
        value = getattr(spec, option.name)
        if value is not None:
            args += [option.flag, str(value)]
    return args


# ------------------------------------------------------------------------------------ machine
def load_avg() -> float:
    """1-minute load average: the machine may be shared, and a slow number under load says so."""
    return os.getloadavg()[0]


def machine() -> str:
    return f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs"


def rss_mb() -> float:
    """This process's resident memory now (MB)."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return float(line.split()[1]) / 1024.0
    return float("nan")


def child_result(queue, proc, bench: str) -> dict:
    """What a measuring child process put on ``queue``, or its end as one line: a child that
    died (killed for memory, a crash in C) puts nothing, and a plain ``queue.get()`` would wait
    for it for ever."""
    import queue as queue_mod

    while True:
        try:
            return queue.get(timeout=1.0)
        except queue_mod.Empty:
            if not proc.is_alive():
                raise LidarlocError(f"bench {bench}: the measuring process ended with status {proc.exitcode}") from None


def end_child(proc) -> None:
    """Join a measuring child, killing it if it does not end by itself within 10 s."""
    proc.join(timeout=10)
    if proc.is_alive():
        proc.kill()
        proc.join()


# ------------------------------------------------------------------------------------ numbers
def median(values) -> float | None:
    """Median of the known values (None and non-finite left out); None if there are none."""
    vals = [v for v in values if v is not None and math.isfinite(v)]
    return float(np.median(vals)) if vals else None


def median_ms(seconds) -> float:
    return float(np.median(seconds) * 1000.0)


def pose_error(T: np.ndarray, G: np.ndarray) -> tuple[float, float]:
    """Translation (m) and rotation (deg) of the difference between pose T and the truth G."""
    D = inv_pose(G) @ T
    return float(np.linalg.norm(D[:3, 3])), math.degrees(math.acos(np.clip((np.trace(D[:3, :3]) - 1) / 2, -1, 1)))


def record_run(spec, seq, cfg, out: Path, cache_root: Path | None = None, progress=None) -> Path:
    """Run ``seq`` to its end with a recording into ``out`` (what ``lidarloc run --out`` records);
    ``progress(i, n)`` after each scan."""
    from ...core.localizer import Localizer
    from ...core.runs import recording

    loc = Localizer(seq, cfg, cache_root)
    try:
        writer = recording.RecordingWriter(out, spec, cfg, seq)
        while not loc.done:
            writer.on_scan(loc, loc.step())
            if progress is not None:
                progress(loc.k, loc.n_scans)
        writer.close(None)
    finally:
        loc.close()
    return out
