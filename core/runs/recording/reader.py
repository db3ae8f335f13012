"""Reading a recording back (see :mod:`.format`), up to its last complete step; in a notebook
too: ``recording.open("out/run0")``."""

from __future__ import annotations

import bisect
import dataclasses
import json
from pathlib import Path

import numpy as np

from ...rules.truth import truth_alarm
from ...snapshot import Event, S2MView, Snapshot
from .format import (
    FIELDS,
    FOLDER,
    FORMAT,
    INDEX,
    LOG_WEIGHTS,
    PARTICLES,
    S2M_STATUSES,
    STEPS,
    VERSION,
    RecordingError,
    load_s2m,
    named_field,
)


def open(path) -> Recording:  # noqa: A001 - the documented name: recording.open(dir)
    """The recording of a run folder (or the ``recording/`` folder itself)."""
    return Recording(path)


class Recording:
    """A recorded run, read-only (see the module docstring). Per-step fields are attributes
    (``rec.mean_pose``, ``rec.error_m``, …) of length :attr:`n`."""

    def __init__(self, path):
        path = Path(path).expanduser()
        if not path.exists():
            raise RecordingError(f"{path}: no such run folder")
        if (path / FOLDER / INDEX).is_file():
            path = path / FOLDER
        index_file = path / INDEX
        if not index_file.is_file():
            raise RecordingError(
                f"{path}: not a recorded run (no {FOLDER}/{INDEX}; record with lidarloc run, without --no-record)"
            )
        try:
            index = json.loads(index_file.read_text())
        except (OSError, ValueError) as exc:
            raise RecordingError(f"{index_file}: unreadable recording index ({exc})") from None
        if not isinstance(index, dict) or index.get("format") != FORMAT:
            raise RecordingError(f"{index_file}: not a lidarloc recording")
        if index.get("version") != VERSION:
            raise RecordingError(
                f"{index_file}: recording format version {index.get('version')}, this lidarloc reads version {VERSION}"
            )
        self.path = path
        self.run_dir = path.parent
        self.meta: dict = index.get("meta", {})
        self._fields: dict = index.get("fields", {})
        steps_file = path / STEPS
        n = steps_file.stat().st_size // 8 if steps_file.is_file() else 0
        self._cache: dict[str, np.ndarray] = {}
        try:
            for name, info in self._fields.items():  # a step counts only if every field has its row
                if name in (PARTICLES[0], LOG_WEIGHTS[0]):
                    continue
                rows = self._rows_on_disk(name, info)
                n = min(n, info["first_step"] + rows) if rows >= 0 else n
            if n > 0:  # the particles of the last steps may be cut short too
                n_rows = min(
                    self._rows_on_disk(*named_field(self._fields, PARTICLES[0])),
                    self._rows_on_disk(*named_field(self._fields, LOG_WEIGHTS[0])),
                )
                while n > 0 and self.field("particle_rows", n)[n - 1].sum() > n_rows:
                    n -= 1
        except (KeyError, TypeError, ValueError) as exc:
            raise RecordingError(f"{index_file}: corrupt recording index ({exc})") from None
        self.n = int(n)
        self._cache.clear()
        self._s2m_cache: dict[int, S2MView] = {}
        self._s2m_steps: list[int] | None = None
        self._events: list | None = None

    # ------------------------------------------------------------------ fields
    def _rows_on_disk(self, name: str, info: dict) -> int:
        f = self.path / f"{name}.bin"
        size = np.dtype(info["dtype"]).itemsize * int(np.prod(info["shape"], dtype=np.int64))
        return f.stat().st_size // size if f.is_file() else 0

    @property
    def field_names(self) -> list[str]:
        return list(self._fields)

    def field(self, name: str, n: int | None = None) -> np.ndarray:
        """A per-step field as an array of length ``n`` (default: :attr:`n`); steps before the field
        first appeared are NaN (floats) or 0."""
        n = self.n if n is None else n
        key = f"{name}:{n}"
        if key in self._cache:
            return self._cache[key]
        if name not in self._fields:
            raise RecordingError(f"{self.path}: no field {name!r} in this recording")
        info = self._fields[name]
        dtype, shape, first = np.dtype(info["dtype"]), tuple(info["shape"]), int(info["first_step"])
        count = max(n - first, 0)
        raw = np.fromfile(self.path / f"{name}.bin", dtype=dtype, count=count * int(np.prod(shape, dtype=np.int64)))
        arr = raw.reshape((count,) + shape)
        if first > 0:
            head = np.full((min(first, n),) + shape, np.nan if dtype.kind == "f" else 0, dtype=dtype)
            arr = np.concatenate([head, arr])
        if dtype == np.dtype("|u1") and name in FIELDS:
            arr = arr.astype(bool)
        self._cache[key] = arr
        return arr

    def __getattr__(self, name: str):
        if name.startswith("_"):
            raise AttributeError(name)
        fields = self.__dict__.get("_fields", {})
        if name in fields and name not in (PARTICLES[0], LOG_WEIGHTS[0]):
            return self.field(name)
        raise AttributeError(f"Recording has no field or attribute {name!r}")

    def _memmap(self, name: str) -> np.ndarray:
        if name not in self._cache:
            dtype, shape = (
                (np.dtype(PARTICLES[1]), PARTICLES[2]) if name == PARTICLES[0] else (np.dtype(LOG_WEIGHTS[1]), ())
            )
            f = self.path / f"{name}.bin"
            rows = f.stat().st_size // (dtype.itemsize * int(np.prod(shape, dtype=np.int64))) if f.is_file() else 0
            self._cache[name] = (
                np.memmap(f, dtype=dtype, mode="r", shape=(rows,) + shape) if rows else np.zeros((0,) + shape, dtype)
            )
        return self._cache[name]

    def _check(self, i: int) -> int:
        if not -self.n <= i < self.n:
            raise RecordingError(f"step {i} is outside the recording (0…{self.n - 1})")
        return i % self.n

    def particles(self, i: int) -> np.ndarray:
        """(N, 11) float32 particles after step i (see config.STATE_NAMES)."""
        start, count = self.field("particle_rows")[self._check(i)]
        return np.asarray(self._memmap(PARTICLES[0])[start : start + count])

    def log_weights(self, i: int) -> np.ndarray:
        start, count = self.field("particle_rows")[self._check(i)]
        return np.asarray(self._memmap(LOG_WEIGHTS[0])[start : start + count])

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
        """(step, event) of every event of the recorded steps; step -1: before the first scan."""
        if self._events is None:
            out = []
            f = self.path / "events.jsonl"
            if f.is_file():
                # a damaged byte must not cost the events before it (a UnicodeDecodeError did)
                for line in f.read_text(encoding="utf-8", errors="replace").splitlines():
                    try:
                        d = json.loads(line)
                        if d["step"] >= self.n:
                            break
                        event = Event(int(d["scan"]), str(d["kind"]), str(d.get("detail", "")))
                        out.append((int(d["step"]), event))
                    except (ValueError, KeyError, TypeError, AttributeError):
                        break  # a line cut short by a crash (or damaged): the steps after it are not complete
            self._events = out
        return self._events

    @property
    def s2m_steps(self) -> list[int]:
        """Steps at which an S2M match landed (listed once: the recording is read as it was opened)."""
        if self._s2m_steps is None:
            steps = []
            for f in (self.path / "s2m").glob("*.json"):
                try:
                    step = int(f.stem)
                except ValueError:
                    continue
                if step < self.n:
                    steps.append(step)
            self._s2m_steps = sorted(steps)
        return self._s2m_steps

    def s2m(self, i: int) -> S2MView | None:
        """The last S2M match that landed at or before step i."""
        i = self._check(i)
        steps = self.s2m_steps
        at = bisect.bisect_right(steps, i)
        if at == 0:
            return None
        step = steps[at - 1]
        if step not in self._s2m_cache:
            try:
                self._s2m_cache[step] = load_s2m(self.path / "s2m", step)
            except (OSError, ValueError, KeyError, TypeError) as exc:
                raise RecordingError(f"{self.path}/s2m/{step:06d}.json: unreadable ({exc})") from None
        return self._s2m_cache[step]

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
        steps = []
        for f in (self.path / "resume").glob(f"*-{name}.npz"):
            try:
                step = int(f.name.split("-", 1)[0])
            except ValueError:
                continue
            if step < self.n:
                steps.append(step)
        return sorted(steps)

    def resume_file(self, step: int, name: str) -> dict[str, np.ndarray] | None:
        f = self.path / "resume" / f"{step:06d}-{name}.npz"
        if step >= self.n or not f.is_file():
            return None
        try:
            with np.load(f, allow_pickle=False) as z:
                return {k: z[k] for k in z.files}
        except (OSError, ValueError) as exc:
            raise RecordingError(f"{f}: unreadable ({exc})") from None

    # ------------------------------------------------------------------ source and config
    def source_spec(self):
        """The source options the run was made with (a SourceSpec)."""
        from ...sequences.factory import SourceSpec

        names = {f.name: f for f in dataclasses.fields(SourceSpec)}
        kw = {}
        for key, value in self.meta.get("source", {}).items():
            if key not in names:
                continue
            if value is not None and key in (
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
                value = Path(value)
            kw[key] = value
        return SourceSpec(**kw)

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
    def step_of_scan(self, scan: int) -> int | None:
        """The step that processed source scan ``scan`` (None if none did)."""
        hits = np.flatnonzero(self.scan_index == scan)
        return int(hits[0]) if hits.size else None

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
