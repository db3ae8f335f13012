"""What the viewer says when one of its own threads fails (the display, the recorder): one line
naming the block, on stderr and in the page, instead of a traceback per frame.

A failure that repeats (the same exception on every frame) is said once; a different one is said
again. With ``LIDARLOC_TRACEBACK=1`` in the environment the traceback is printed too (for whoever
debugs the viewer, not for its users)."""

from __future__ import annotations

import os
import sys
import threading
import traceback
from collections.abc import Callable


def one_line(exc: BaseException, limit: int = 300) -> str:
    """``Type: message`` on one line, at most ``limit`` characters."""
    text = " ".join(f"{type(exc).__name__}: {exc}".split())
    return text if len(text) <= limit else text[: limit - 1] + "…"


class BlockFailed(Exception):
    """A viewer block (``"recorder"``, ``"Foxglove stream"``) failed while handling a step: raised
    from the step's handler so that the player's one line names the block, not just the error."""

    def __init__(self, block: str, cause: BaseException):
        super().__init__(one_line(cause))
        self.block = block


def block_of(exc: BaseException) -> str:
    """The block a step handler's exception names (the display's own code when none)."""
    return getattr(exc, "block", "viewer display")


def describe(exc: BaseException) -> str:
    """One line for a step handler's failure: a BlockFailed's cause as it was, anything else typed."""
    return str(exc) if isinstance(exc, BlockFailed) else one_line(exc)


class FaultReporter:
    """Reports the failures of one block of the viewer: ``report(exc, what_now)`` prints
    ``lidarloc: BLOCK failed: Type: message; WHAT_NOW`` once per distinct failure and hands the
    same line to ``show`` (the page). ``count`` says how many failures there were in all."""

    def __init__(self, block: str, show: Callable[[str], None] | None = None):
        self.block = block
        self.count = 0
        self.last: str | None = None
        self._show = show
        self._lock = threading.Lock()

    def report(self, exc: BaseException, what_now: str = "") -> str:
        line = f"{self.block} failed: {one_line(exc)}" + (f"; {what_now}" if what_now else "")
        with self._lock:
            self.count += 1
            repeated = line == self.last
            self.last = line
        if repeated:
            return line
        try:
            sys.stderr.write(f"lidarloc: {line}\n")
            if os.environ.get("LIDARLOC_TRACEBACK"):
                traceback.print_exception(type(exc), exc, exc.__traceback__, file=sys.stderr)
            sys.stderr.flush()
        except (OSError, ValueError):  # no terminal any more (SIGHUP): the page still says it
            pass
        if self._show is not None:
            try:
                self._show(line)
            except Exception:  # the page is what failed: the console line stands
                pass
        return line

    def clear(self) -> None:
        """The block works again: the next failure is said even if it is the same."""
        with self._lock:
            self.last = None
