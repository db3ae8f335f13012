"""New websocket connections to the viewer are let in at a bounded rate.

Each new connection is sent the whole scene (the map, the particles, the panels), work done on
the server's event-loop thread that holds the GIL the filter's thread needs. A client that
connects and disconnects as fast as it can (38 times a second in ``lidarloc bench clients``) took
84 % of a core of the viewer's process and made the filter's scans late on a 2-core machine. A
browser opens one websocket a tab (and one more at each reload), so people never meet the limit:
:data:`BURST` connections are let in at once (a room of people opening the page together), then
one every ``1 / RATE_PER_S`` seconds. A connection over the rate waits in its opening handshake
(the page shows "connecting" a moment longer); one that would wait more than :data:`MAX_WAIT_S`
is refused at once with 503 (viser's page retries on its own). HTTP requests (the page's assets)
and refused upgrades (no token) are never held: they cost the server little.

The rate is a generic cell rate: each admitted connection moves a "theoretical arrival time" one
interval on, and a connection may open once that time is at most ``BURST - 1`` intervals ahead of
the clock.
"""

from __future__ import annotations

import asyncio
import http
import math
import time
from collections.abc import Callable
from typing import Any

#: Websocket connections let in at once before pacing starts.
BURST = 10
#: … then at most this many a second.
RATE_PER_S = 5.0
#: A connection that would wait longer than this (seconds) is refused with 503 at once: under
#: websockets' 10-s opening timeout, and a queue that long means a client in a loop.
MAX_WAIT_S = 5.0
BUSY = "This lidarloc viewer is taking new connections more slowly; try again in a moment.\n"


class ConnectionPacer:
    """Admits websocket connections at ``rate_per_s`` after a burst of ``burst`` (see the module
    docstring). ``clock``: seconds, monotonic (tests give their own)."""

    def __init__(
        self,
        rate_per_s: float = RATE_PER_S,
        burst: int = BURST,
        max_wait_s: float = MAX_WAIT_S,
        clock: Callable[[], float] = time.monotonic,
    ):
        if not (rate_per_s > 0 and burst >= 1 and max_wait_s >= 0):
            raise ValueError("the pacing needs a positive rate, a burst of at least one and a wait ≥ 0")
        self.interval = 1.0 / rate_per_s
        self.tolerance = (burst - 1) * self.interval  # how far ahead the arrival time may run
        self.max_wait_s = float(max_wait_s)
        self.clock = clock
        self._tat = -math.inf  # the theoretical arrival time of the next connection
        self.admitted = 0
        self.delayed = 0
        self.refused = 0

    def reserve(self) -> float | None:
        """The seconds a connection arriving now waits before it opens (0: at once), its place
        taken; None: it would wait more than ``max_wait_s`` and is refused (no place taken)."""
        now = self.clock()
        tat = max(self._tat, now)
        wait = tat - now - self.tolerance
        wait = wait if wait > 1e-6 else 0.0  # (the sum of intervals carries rounding)
        if wait > self.max_wait_s + 1e-6:
            self.refused += 1
            return None
        self._tat = tat + self.interval
        self.admitted += 1
        self.delayed += wait > 0
        return wait

    def in_front_of(self, delegate: Callable[..., Any] | None) -> Callable[..., Any]:
        """A websockets ``process_request`` that paces the websocket upgrades ``delegate`` (the
        server's own hook, or None) lets through, and hands everything else to it unchanged."""

        def process_request(connection: Any, request: Any) -> Any:
            response = None if delegate is None else delegate(connection, request)
            if response is not None or request.headers.get("Upgrade", "").lower() != "websocket":
                return response  # a page, an asset or a refusal: never held
            wait = self.reserve()
            if wait is None:
                return connection.respond(http.HTTPStatus.SERVICE_UNAVAILABLE, BUSY)
            if wait == 0:
                return None

            async def after_wait() -> None:
                await asyncio.sleep(wait)

            return after_wait()

        return process_request
