"""viser's message buffers wake their readers from the thread that writes a message; this makes
that wake-up go through the server's event loop.

``AsyncMessageBuffer.push`` (viser 1.1) raises its ``asyncio.Event`` with ``set()`` on the writing
thread (the viewer's display thread) as well as through the event loop. ``asyncio.Event`` is not
thread-safe: ``set()`` walks the connections waiting on it, a list the server's loop changes
whenever a tab connects or leaves, and completes their futures off their loop. A display update
that met a connecting tab failed with "deque mutated during iteration" (once in ~17 500
connections of ``lidarloc bench clients --churn-s 600``).

:func:`install` (idempotent) gives every buffer made afterwards an event whose ``set()``, off the
loop, only raises the flag (which the buffer reads at once in synchronous code) and leaves waking
the readers to the loop: ``push`` schedules that wake itself (``call_soon_threadsafe``), and
``atomic_end`` does for writes inside an atomic block. On the loop, ``set()`` wakes every reader
even when the flag is already up: a reader that started waiting just before another thread raised
the flag must still be woken by the scheduled call.
"""

from __future__ import annotations

import asyncio
import threading

_installed = threading.Lock()
_done = False


class LoopWakeEvent(asyncio.Event):
    """An ``asyncio.Event`` that may be set from any thread: its readers are woken only on
    ``loop``, the loop they wait on."""

    def __init__(self, loop: asyncio.AbstractEventLoop):
        super().__init__()
        self.owner_loop = loop

    def _on_owner_loop(self) -> bool:
        try:
            return asyncio.get_running_loop() is self.owner_loop
        except RuntimeError:  # no loop runs on this thread
            return False

    def set(self) -> None:
        self._value = True
        if not self._on_owner_loop():
            return  # the writer scheduled a set() on the loop, which wakes the readers
        for waiter in list(self._waiters):
            if not waiter.done():
                waiter.set_result(True)


def install() -> None:
    """Give every viser message buffer made from now on a :class:`LoopWakeEvent` for its
    ``message_event`` (called before a viewer's server is made; a second call does nothing)."""
    global _done
    from viser.infra._async_message_buffer import AsyncMessageBuffer

    with _installed:
        if _done:
            return
        made = AsyncMessageBuffer.__init__

        def __init__(self, *args, **kwargs) -> None:
            made(self, *args, **kwargs)
            # fresh from the constructor: nothing waits on the event it made yet
            self.message_event = LoopWakeEvent(self.event_loop)

        AsyncMessageBuffer.__init__ = __init__
        _done = True
