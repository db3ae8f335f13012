"""``view --foxglove-port``: a Foxglove client connected to the viewer's stream is told of every
channel of ``export --foxglove`` and receives each step the viewer plays."""

from __future__ import annotations

import asyncio
import json

import pytest
from helpers import make_localizer, wait_for
from lidarloc.app import export_foxglove as fx


async def _client(url: str, step, steps: int) -> tuple[list[str], list[bytes]]:
    """Connect, subscribe to the estimate, have the viewer play ``steps`` steps (``step()``), and
    return the advertised topics and the binary messages received on the subscription."""
    import websockets

    async with websockets.connect(url, subprotocols=["foxglove.sdk.v1"]) as ws:
        channels = {}
        while fx.POSE not in channels:
            msg = await asyncio.wait_for(ws.recv(), 10)
            if isinstance(msg, str) and json.loads(msg).get("op") == "advertise":
                channels.update({c["topic"]: c["id"] for c in json.loads(msg)["channels"]})
        await ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": 7, "channelId": channels[fx.POSE]}]}))
        await asyncio.sleep(0.3)  # the server takes the subscription before the steps
        got: list[bytes] = []
        for _ in range(steps):
            await asyncio.get_running_loop().run_in_executor(None, step)
        while len(got) < steps:
            msg = await asyncio.wait_for(ws.recv(), 10)
            # opcode 1: message data, then the subscription id (uint32, little-endian)
            if isinstance(msg, bytes) and msg[0] == 1 and int.from_bytes(msg[1:5], "little") == 7:
                got.append(msg)
        return sorted(channels), got


@pytest.mark.slow
@pytest.mark.timeout(120)
def test_a_foxglove_client_gets_every_channel_and_each_step(street, cache_root):
    pytest.importorskip("websockets")
    from lidarloc.app.viewer.serve import serve

    loc = make_localizer(street, cache_root)
    handle = serve(loc, port=0, autoplay=False, foxglove_port=0)
    try:
        assert handle.foxglove_url and handle.foxglove_url.startswith("ws://127.0.0.1:")
        sink = handle.viewer.sinks[0]

        def step():
            before = len(loc.records)
            handle.viewer.step_once()
            wait_for(lambda: sink.counts.get(fx.FIGURES, 0) > before, 60, "a step sent")

        step()  # the channels exist from the first step on
        topics, got = asyncio.run(_client(handle.foxglove_url, step, 3))
        assert set(topics) == {
            fx.POSE,
            fx.TRUTH,
            fx.TF,
            fx.PARTICLES,
            fx.PARTICLE_CLOUD,
            fx.SCAN,
            fx.MAP,
            fx.SCENE,
            fx.LOG,
            fx.FIGURES,
        }
        assert len(got) == 3 and not sink.failed
        assert sink.counts[fx.MAP] == 1
    finally:
        handle.stop()
        loc.close()
