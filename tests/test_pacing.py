"""The viewer lets new websocket connections in at a bounded rate (app/viewer/pacing.py): a burst
at once, then a steady rate; beyond the longest wait, a refusal; pages and assets are never held."""

from __future__ import annotations

import http.client
import time

import pytest
from lidarloc.app.viewer.pacing import ConnectionPacer


class Clock:
    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t


def test_a_burst_opens_at_once_then_one_connection_an_interval():
    clock = Clock()
    pacer = ConnectionPacer(rate_per_s=5.0, burst=3, max_wait_s=1.0, clock=clock)
    waits = [pacer.reserve() for _ in range(8)]
    assert waits[:3] == [0.0, 0.0, 0.0]
    assert waits[3:] == pytest.approx([0.2, 0.4, 0.6, 0.8, 1.0])
    assert pacer.reserve() is None  # would wait 1.2 s: refused, and takes no place
    assert (pacer.admitted, pacer.delayed, pacer.refused) == (8, 5, 1)
    clock.t += 2.0  # the queue has drained: the burst is back
    assert [pacer.reserve() for _ in range(3)] == [0.0, 0.0, 0.0]
    assert pacer.reserve() == pytest.approx(0.2)


def test_connections_at_the_rate_never_wait():
    clock = Clock()
    pacer = ConnectionPacer(rate_per_s=5.0, burst=1, max_wait_s=0.0, clock=clock)
    for _ in range(20):
        assert pacer.reserve() == 0.0
        clock.t += 0.2
    assert pacer.reserve() == 0.0 and pacer.reserve() is None  # two at once: the second refused


@pytest.mark.parametrize("bad", [dict(rate_per_s=0.0), dict(burst=0), dict(max_wait_s=-1.0)])
def test_an_impossible_pacing_is_refused(bad):
    with pytest.raises(ValueError, match="pacing"):
        ConnectionPacer(**bad)


def test_the_viewer_server_paces_websockets_and_never_its_pages():
    import viser
    from lidarloc.app.viewer.pacing import BURST
    from lidarloc.app.viewer.token_gate import start_server
    from websockets.sync.client import connect

    server = start_server(None, host="127.0.0.1", port=0, verbose=False)
    sockets = []
    try:
        port = server.get_port()
        pacer = server.lidarloc_pacer
        for _ in range(3 * BURST):  # a page loads many assets: none of them is held
            conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
            conn.request("GET", "/")
            assert conn.getresponse().status == 200
            conn.close()
        assert pacer.admitted == 0
        # one connection a second past the burst: a loaded machine opening the burst's sockets
        # slowly must not use up the wait the test looks for
        interval = 1.0
        pacer.interval, pacer.tolerance = interval, (BURST - 1) * interval
        t0 = time.perf_counter()
        extra = 3
        for _ in range(BURST + extra):
            sockets.append(
                connect(f"ws://127.0.0.1:{port}", subprotocols=[f"viser-v{viser.__version__}"], open_timeout=10)
            )
        took = time.perf_counter() - t0
        assert pacer.admitted == BURST + extra and pacer.delayed >= 1 and pacer.refused == 0
        # the last one waited for its turn: `extra` intervals after the first opened
        assert took >= (extra - 0.5) * interval, took
    finally:
        for ws in sockets:
            ws.close()
        server.stop()
