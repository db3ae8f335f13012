"""``lidarloc view --foxglove-port PORT``: the live run streamed to a Foxglove client beside the
viser viewer, through ``foxglove-sdk``'s WebSocket server (Foxglove: Open connection → Foxglove
WebSocket, ``ws://HOST:PORT``). Each step the viewer plays goes out on the channels and in the
schemas of ``lidarloc export --foxglove`` (:mod:`lidarloc.app.export_foxglove`), so the layout
written beside an export (``NAME.layout.json``) reads the stream too.

The stream is a consumer of the viewer's steps like its recorder: it never changes the localizer,
and a failure to send turns the stream off with one message instead of stopping the viewer.
"""

from __future__ import annotations

import threading

import numpy as np

from ...core.geometry import inv_pose, transform_points
from ..run_steps import LOCAL_FRAME, MAP_FRAME, display_map, in_map, make_step, stamps_of


class _LiveRun:
    """What :class:`~lidarloc.app.export_foxglove.FoxgloveWriter` reads of a run, for a live localizer."""

    def __init__(self, loc):
        self.seq = loc.seq
        self.prior = loc.prior_map
        self.origin = np.asarray(self.prior.origin, np.float64).reshape(3)
        self.local_frame = LOCAL_FRAME if self.origin.any() else MAP_FRAME
        self.name = getattr(loc.seq, "name", "run")

    def in_map(self, T):
        return in_map(T, self.origin)

    def map_points(self, max_points: int):
        return display_map(self.prior.points, max_points, float(self.prior.voxel_size))


class FoxgloveLive:
    """The WebSocket server and the channels; :meth:`on_step` after each step the viewer plays."""

    def __init__(self, host: str = "127.0.0.1", port: int = 8765, on_failure=None):
        import foxglove

        self.context = foxglove.Context()
        self.server = foxglove.start_server(name="lidarloc", host=host, port=port, context=self.context)
        self.port = int(self.server.port)
        self.url = f"ws://{'localhost' if host in ('0.0.0.0', '::') else host}:{self.port}"
        self.on_failure = on_failure
        self.failed = False
        self._writer = None
        self._loc = None
        self._events = 0
        self._last_s2m = None
        self._lock = threading.Lock()

    @property
    def counts(self) -> dict:
        """Messages sent so far per channel (empty before the first step)."""
        return {} if self._writer is None else dict(self._writer.counts)

    def on_step(self, loc, snap) -> None:
        if self.failed:
            return
        try:
            with self._lock:
                self._send(loc, snap)
        except Exception as exc:  # noqa: BLE001 - the viewer goes on without the stream
            self.failed = True
            if self.on_failure is not None:
                self.on_failure(f"Foxglove stream stopped: {type(exc).__name__}: {exc}")

    def _send(self, loc, snap) -> None:
        from ..export_foxglove import FoxgloveWriter

        stamp = int(stamps_of(loc.seq, np.array([snap.scan_index]), np.array([snap.timestamp]))[0])
        if loc is not self._loc:  # a new run (a start, a restart): its map again
            run = _LiveRun(loc)
            if self._writer is None:
                self._writer = FoxgloveWriter(self.context, run)
            self._writer.steps = run
            self._writer.write_map(stamp, 400_000)
            self._loc, self._events, self._last_s2m = loc, 0, None
        events = list(loc.events)
        new, self._events = events[self._events :], len(events)
        s2m = snap.s2m if snap.s2m is not None and snap.s2m is not self._last_s2m else None
        self._last_s2m = snap.s2m
        record = loc.records[-1] if loc.records else None
        step = make_step(
            snap.scan_index,
            snap.scan_index,
            stamp,
            self._writer.steps.origin,
            snap.mean_pose,
            snap.gt_pose,
            snap.particles,
            snap.weights,
            snap.cov_xyz,
            snap.std_xyz,
            snap.ellipse_xy,
            snap.n_eff,
            snap.n_particles or len(snap.particles),
            snap.localized,
            {
                "error_m": snap.error_m,
                "pf_ms": snap.pf_ms,
                "rpe_ms": snap.rpe_ms,
                "s2m_ms": None if record is None else record.s2m_ms,
            },
            new,
            s2m,
        )
        scan = (
            transform_points(inv_pose(snap.mean_pose), snap.scan_world).astype(np.float32)
            if len(snap.scan_world)
            else None
        )
        self._writer.write_step(step, scan)

    def stop(self) -> None:
        self.server.stop()
