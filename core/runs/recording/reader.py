"""Reading a recording back (see :mod:`.format`), up to its last complete step; in a notebook
too: ``recording.open("out/run0")``. A run recorded in segments under a size budget
(:mod:`.segments`) reads as one recording of the steps it kept."""

from __future__ import annotations

import bisect
import json
from pathlib import Path

import numpy as np

from ...rules.truth import truth_alarm
from ...snapshot import Event, S2MView, Snapshot
from .format import FIELDS, FOLDER, INDEX, LOG_WEIGHTS, PARTICLES, S2M_STATUSES, RecordingError
from .segments import CARRIED, Part, continuation_folders, kept, read_index


def open(path) -> Recording:  # noqa: A001 - the documented name: recording.open(dir)
    """The recording of a run folder (or the ``recording/`` folder itself)."""
    return Recording(path)


class Recording:
    """A recorded run, read-only (see the module docstring). Per-step fields are attributes
    (``rec.mean_pose``, ``rec.error_m``, …) of length :attr:`n`.

    A run recorded under a size budget may hold only a rolling window of its newest steps
    (:mod:`.segments`): row 0 is then the run's step :attr:`first_step`, and :attr:`dropped`
    steps before it are gone. Without a window the rows are the recording's steps from its
    start (``meta["first_step"]``: 0, or the step after a branch point)."""

    def __init__(self, path):
        path = Path(path).expanduser()
        if not path.exists():
            raise RecordingError(f"{path}: no such run folder")
        if (path / FOLDER / INDEX).is_file():
            path = path / FOLDER
        if not (path / INDEX).is_file():
            raise RecordingError(
                f"{path}: not a recorded run (no {FOLDER}/{INDEX}; record with lidarloc run, without --no-record)"
            )
        self.path = path
        self.run_dir = path.parent
        top = Part(path, read_index(path))
        parts = [top]
        for folder in continuation_folders(path):
            if (folder / INDEX).is_file():  # else its start was cut short: no step in it
                try:
                    parts.append(Part(folder, read_index(folder)))
                except RecordingError:
                    if (folder / INDEX).is_file():
                        raise
                    # dropped by the recording budget while being opened: its steps are gone
        keep = kept([(p.first_step, p.n) for p in parts])
        self._parts = [parts[i] for i in keep]
        self._offsets = [0]
        for part in self._parts:
            self._offsets.append(self._offsets[-1] + part.n)
        self.n = int(self._offsets[-1])
        #: the run's step of row 0 (where nothing was dropped: the recording's first step)
        self.first_step = self._parts[0].first_step if self._parts else parts[-1].first_step
        #: steps dropped from the front by the recording budget (0: the recording is whole)
        self.dropped = self.first_step - top.first_step
        #: events of the dropped steps (the events' count a checkpoint names includes them)
        self.events_dropped = self._parts[0].events_before if self._parts else 0
        self.meta: dict = dict(top.meta)
        for key in ("closed", "summary"):  # the newest segment is the one closed last
            if key in parts[-1].meta:
                self.meta[key] = parts[-1].meta[key]
        self._fields: dict = {}
        for part in self._parts or [top]:
            for name, info in part.fields.items():
                self._fields.setdefault(name, info)
        self._cache: dict[str, np.ndarray] = {}
        self._s2m_cache: dict[tuple[int, int], S2MView] = {}
        self._s2m_index: list[tuple[int, int, int]] | None = None
        self._events: list | None = None

    # ------------------------------------------------------------------ fields
    @property
    def field_names(self) -> list[str]:
        return list(self._fields)

    def field(self, name: str, n: int | None = None) -> np.ndarray:
        """A per-step field as an array of length ``n`` (default: :attr:`n`); steps before the field
        first appeared are NaN (floats) or 0."""
        n = self.n if n is None else min(n, self.n)
        key = f"{name}:{n}"
        if key in self._cache:
            return self._cache[key]
        if name not in self._fields:
            raise RecordingError(f"{self.path}: no field {name!r} in this recording")
        chunks = []
        for part, offset in zip(self._parts, self._offsets):
            m = min(part.n, n - offset)
            if m <= 0:
                break
            chunks.append(part.field(name, m) if name in part.fields else self._missing(name, m))
        if len(chunks) == 1:
            arr = chunks[0]
        elif chunks:
            arr = np.concatenate(chunks)
        else:
            arr = self._missing(name, 0)
        self._cache[key] = arr
        return arr

    def _missing(self, name: str, m: int) -> np.ndarray:
        """``m`` rows of a field a segment does not have: NaN (floats) or 0."""
        info = self._fields[name]
        dtype, shape = np.dtype(info["dtype"]), tuple(info["shape"])
        if dtype == np.dtype("|u1") and name in FIELDS:
            dtype = np.dtype(bool)
        return np.full((m,) + shape, np.nan if dtype.kind == "f" else 0, dtype=dtype)

    def __getattr__(self, name: str):
        if name.startswith("_"):
            raise AttributeError(name)
        fields = self.__dict__.get("_fields", {})
        if name in fields and name not in (PARTICLES[0], LOG_WEIGHTS[0]):
            return self.field(name)
        raise AttributeError(f"Recording has no field or attribute {name!r}")

    def _check(self, i: int) -> int:
        if not -self.n <= i < self.n:
            raise RecordingError(f"step {i} is outside the recording (0…{self.n - 1})")
        return i % self.n

    def _locate(self, i: int) -> tuple[Part, int]:
        """(segment, its own step) of row i."""
        i = self._check(i)
        at = bisect.bisect_right(self._offsets, i) - 1
        return self._parts[at], i - self._offsets[at]

    def particles(self, i: int) -> np.ndarray:
        """(N, 11) float32 particles after step i (see config.STATE_NAMES)."""
        part, j = self._locate(i)
        return part.rows(PARTICLES[0], j)

    def log_weights(self, i: int) -> np.ndarray:
        part, j = self._locate(i)
        return part.rows(LOG_WEIGHTS[0], j)

    def weights(self, i: int) -> np.ndarray:
        """Normalised float64 weights after step i (from the log-weights: no underflow to all-zero)."""
        lw = self.log_weights(i).astype(np.float64)
        if lw.size == 0:
            return lw
        w = np.exp(lw - lw.max())
        return w / w.sum()

    # ------------------------------------------------------------------ events, S2M, summary
    @property
    def events(self) -> list[tuple[int, Event]]:
        """(step, event) of every event of the recorded steps; step -1: before the first scan (or,
        in a rolling window, after the last dropped step)."""
        if self._events is None:
            self._events = [
                (offset + s, ev) for part, offset in zip(self._parts, self._offsets) for s, ev in part.events
            ]
        return self._events

    def _s2m_entries(self) -> list[tuple[int, int, int]]:
        """(row, segment, its own step) of every stored S2M view, sorted; a segment's carried
        view counts at the row before its first."""
        if self._s2m_index is None:
            entries = []
            for at, (part, offset) in enumerate(zip(self._parts, self._offsets)):
                entries += [(offset + s, at, s) for s in part.s2m_steps]
            self._s2m_index = sorted(entries)
        return self._s2m_index

    @property
    def s2m_steps(self) -> list[int]:
        """Steps at which an S2M match landed (listed once: the recording is read as it was opened)."""
        return [row for row, at, s in self._s2m_entries() if s != CARRIED]

    def s2m(self, i: int) -> S2MView | None:
        """The last S2M match that landed at or before step i."""
        i = self._check(i)
        entries = self._s2m_entries()
        found = bisect.bisect_right(entries, (i, len(self._parts), 0))
        if found == 0:
            return None
        _, at, step = entries[found - 1]
        if (at, step) not in self._s2m_cache:
            self._s2m_cache[(at, step)] = self._parts[at].s2m(step)
        return self._s2m_cache[(at, step)]

    @property
    def summary(self) -> dict | None:
        """The run folder's summary.json (or the summary the recording was closed with)."""
        f = self.run_dir / "summary.json"
        if f.is_file():
            try:
                return json.loads(f.read_text())
            except ValueError:
                pass
        return self.meta.get("summary")

    def resume_steps(self, name: str) -> list[int]:
        return [offset + s for part, offset in zip(self._parts, self._offsets) for s in part.resume_steps(name)]

    def resume_file(self, step: int, name: str) -> dict[str, np.ndarray] | None:
        if not 0 <= step < self.n:
            return None
        part, j = self._locate(step)
        return part.resume_file(j, name)

    # ------------------------------------------------------------------ source and config
    def source_spec(self):
        """The source options the run was made with (a SourceSpec)."""
        from ...sequences.factory import SourceSpec

        return SourceSpec.from_dict(self.meta.get("source", {}), ignore_unknown=True)

    def check_source(self) -> None:
        """One line naming the path the run expected, if its source has moved."""
        for key, value in self.meta.get("source", {}).items():
            if isinstance(value, str) and key in (
                "kitti_odometry",
                "kitti_raw",
                "trajectory",
                "calib",
                "map",
                "bag",
                "scans_dir",
                "gt",
                "gt_times",
                "extrinsic",
            ):
                if not Path(value).exists():
                    raise RecordingError(
                        f"{value}: the run's source is not there any more (named by "
                        f"{self.path / INDEX} as --{key.replace('_', '-')}); put it back or "
                        "rerun"
                    )

    def open_sequence(self):
        """The run's sequence, rebuilt from its source (one-line error if the source moved)."""
        from ...sequences.factory import open_sequence

        self.check_source()
        return open_sequence(self.source_spec(), self.config())

    def config(self):
        """The configuration the run started with (a Config)."""
        from ...config import Config, update_from_dict

        return update_from_dict(Config(), self.meta.get("config", {}))

    @property
    def _max_elevation(self) -> float:
        """The run's pf.max_elevation (a scan is re-prepared as the run prepared it)."""
        value = getattr(self, "_max_elevation_cache", None)
        if value is None:
            value = self._max_elevation_cache = float(self.config().pf.max_elevation)
        return value

    # ------------------------------------------------------------------ snapshots
    def events_until(self, i: int) -> list[Event]:
        return [ev for step, ev in self.events if step <= i]

    def prepared_scan(self, i: int, seq) -> np.ndarray:
        """(M, 3) float32: step i's scan as the filter weighed it (one random point per voxel, the
        run's seed and voxel), in the LiDAR's frame, recomputed from the run's sequence ``seq``."""
        from ...filter.scanprep import voxel_downsample_random

        i = self._check(i)
        k = int(self.scan_index[i])
        rng = np.random.default_rng([int(self.meta.get("seed", 0)), k, 1])
        return voxel_downsample_random(seq.scan(k), float(self.scan_voxel[i]), rng, self._max_elevation)

    def snapshot(self, i: int, seq=None) -> Snapshot:
        """Step i as a :class:`~lidarloc.core.snapshot.Snapshot` (what the viewer draws). With the run's
        sequence ``seq``, ``scan_world`` is the prepared scan at the estimate, recomputed from the
        source; without, it is empty."""
        from ...geometry import transform_points

        i = self._check(i)
        k = int(self.scan_index[i])
        pose = self.mean_pose[i]
        scan_world = np.zeros((0, 3), np.float32)
        if seq is not None:
            scan_world = transform_points(pose, self.prepared_scan(i, seq)).astype(np.float32)
        gt = self.gt_pose[i]
        since = int(self.localized_since[i])
        inside = int(self.inside_2sigma[i])

        def opt(v):
            return None if not np.isfinite(v) else float(v)

        def recorded(name, default):  # a field recordings made before it appeared do not have
            return self.field(name)[i] if name in self._fields else default

        confirmed_at = int(recorded("confirmed_at", -1))
        status = S2M_STATUSES[int(recorded("s2m_status", 0))]

        return Snapshot(
            scan_index=k,
            n_scans=int(self.meta.get("n_source_scans", self.n)),
            timestamp=float(self.timestamp[i]),
            particles=self.particles(i).astype(np.float64),
            weights=self.weights(i),
            log_weights=self.log_weights(i).astype(np.float64),
            best_index=int(self.best_index[i]),
            mean_pose=pose.copy(),
            cov_xyz=self.cov_xyz[i].copy(),
            std_xyz=self.std_xyz[i].copy(),
            ellipse_xy=tuple(float(v) for v in self.ellipse_xy[i]),
            n_eff=float(self.n_eff[i]),
            localized=bool(self.localized[i]),
            localized_since=None if since < 0 else since,
            scan_world=scan_world,
            gt_pose=None if not np.all(np.isfinite(gt)) else gt.copy(),
            error_m=opt(self.error_m[i]),
            pf_ms=float(self.pf_ms[i]),
            rpe_ms=opt(self.rpe_ms[i]),
            s2m=self.s2m(i),
            s2m_running=bool(self.s2m_running[i]),
            s2m_acceptance=float(self.s2m_acceptance[i]),
            s2m_pending=bool(self.s2m_pending[i]),
            n_particles=int(self.n_particles[i]),
            converged=bool(self.converged[i]),
            inlier_share=opt(self.inlier_share[i]),
            mean_residual_m=opt(self.mean_residual_m[i]),
            inside_2sigma=None if inside < 0 else bool(inside),
            events=tuple(self.events_until(i)[-50:]),
            done=bool(self.done[i]),
            awaiting_confirmation=bool(recorded("awaiting_confirmation", False)),
            confirmed_at=None if confirmed_at < 0 else confirmed_at,
            s2m_status=status,
            truth_alarm=truth_alarm(bool(self.localized[i]), opt(self.error_m[i])),
        )

    def size_bytes(self) -> int:
        """Bytes on disk of the whole recording."""
        return sum(f.stat().st_size for f in self.path.rglob("*") if f.is_file())
