"""viser's message buffer wakes the connections reading it on the server's event loop only, never
from the thread that writes a message (app/viewer/loop_wakeups.py)."""

from __future__ import annotations

import asyncio
import collections
import threading

import pytest
from lidarloc.app.viewer.loop_wakeups import LoopWakeEvent, install


class RecordingDeque(collections.deque):
    """The event's list of waiting readers, noting which threads walk it."""

    def __init__(self):
        super().__init__()
        self.walked_by: set[str] = set()

    def __iter__(self):
        self.walked_by.add(threading.current_thread().name)
        return super().__iter__()


@pytest.fixture
def loop():
    """An event loop running on a thread of its own, as viser's server runs it."""
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, name="server-loop", daemon=True)
    thread.start()
    yield loop
    loop.call_soon_threadsafe(loop.stop)
    thread.join(timeout=10)
    loop.close()


def on_loop(loop, coro, timeout=10.0):
    return asyncio.run_coroutine_threadsafe(coro, loop).result(timeout=timeout)


def start_reader(loop, event):
    """A reader waiting on ``event`` on ``loop`` (its task)."""

    async def start():
        return asyncio.ensure_future(event.wait())

    reader = on_loop(loop, start())
    on_loop(loop, asyncio.sleep(0))  # the reader is waiting
    return reader


def woken(loop, reader) -> bool:
    """What the reader's wait returned, within 5 s."""

    async def result():
        return await asyncio.wait_for(asyncio.shield(reader), timeout=5)

    return on_loop(loop, result())


def test_a_message_written_from_another_thread_wakes_its_readers_on_the_loop(loop):
    from viser._messages import RunJavascriptMessage
    from viser.infra._async_message_buffer import AsyncMessageBuffer

    install()
    install()  # a second call changes nothing
    buffer = AsyncMessageBuffer(loop, persistent_messages=True)
    assert isinstance(buffer.message_event, LoopWakeEvent)
    waiters = RecordingDeque()
    buffer.message_event._waiters = waiters

    reader = start_reader(loop, buffer.message_event)
    assert len(waiters) == 1
    buffer.push(RunJavascriptMessage(source="1"))  # the display thread writes a message
    assert woken(loop, reader) is True
    assert buffer.message_event.is_set()
    assert waiters.walked_by == {"server-loop"}  # never walked by the writing thread


def test_a_flag_raised_off_the_loop_still_wakes_a_reader_that_was_waiting(loop):
    """Off the loop set() only raises the flag; the set() the writer schedules on the loop wakes
    the readers even though the flag is already up."""
    event = LoopWakeEvent(loop)

    reader = start_reader(loop, event)
    event.set()  # from this thread: the flag, no wake
    assert event.is_set()
    on_loop(loop, asyncio.sleep(0.01))
    assert not reader.done()
    loop.call_soon_threadsafe(event.set)
    assert woken(loop, reader) is True
