"""A block's failure as one line naming the block, and a clean stop.

Every part of a run that works on a thread or in a child process of its own — the particle
filter's step, the RPE and S2M feeders, a recording's writer, a viewer's display — may fail with
an exception nobody can fix by hand (a bug, a library's internal error). The run must then stop
cleanly, keep what it finished, and tell the user in one line which block failed and why, never
with a traceback. Two tools do that here:

- :func:`in_block` (a context manager): an exception raised inside becomes a :class:`BlockError`
  ``"<block> block failed[ at scan k]: <Type>: <first line of the message>"``. Errors the user
  can fix (:class:`~lidarloc.core.errors.LidarlocError`) pass unchanged: their message is already
  one line and names the file or parameter.
- :class:`FirstFailure`: shared by a run's threads. ``guard(block, fn)`` wraps a thread's target so
  that its first failure is kept (as a BlockError) and ``stop`` is set; the thread that owns the
  run checks ``stop`` between its steps and calls :meth:`FirstFailure.raise_if_failed` when it
  winds down, after writing its results, so the error surfaces once, in that thread, as one line.

The command line prints any LidarlocError as ``lidarloc: error: …`` and exits with status 2.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable, Iterator
from typing import Any

from .errors import LidarlocError


class BlockError(LidarlocError):
    """A block (a thread or a child process of the run) failed; the run stops with this one-line
    message. ``block`` names it ("PF", "RPE", "S2M", "recording", "display", …)."""

    def __init__(self, message: str, block: str | None = None):
        super().__init__(message)
        self.block = block


def one_line(exc: BaseException) -> str:
    """``Type: first line of the message`` (a LidarlocError: its message alone)."""
    text = str(exc).strip()
    first = text.splitlines()[0] if text else ""
    if isinstance(exc, LidarlocError):
        return first or type(exc).__name__
    return f"{type(exc).__name__}: {first}" if first else type(exc).__name__


def block_failure(block: str, exc: BaseException, where: str = "") -> BlockError:
    """The BlockError of ``exc`` raised in ``block`` (``where``: " at scan 12", or "")."""
    if isinstance(exc, BlockError):
        return exc
    error = BlockError(f"{block} block failed{where}: {one_line(exc)}", block)
    error.__cause__ = exc
    return error


@contextlib.contextmanager
def in_block(block: str, where: str = "") -> Iterator[None]:
    """Run the body as part of ``block``: any exception but a LidarlocError becomes a
    :class:`BlockError` naming it (see the module docstring)."""
    try:
        yield
    except LidarlocError:
        raise
    except Exception as exc:
        raise block_failure(block, exc, where) from exc


class FirstFailure:
    """The first failure of a run's threads (see the module docstring). Thread-safe."""

    def __init__(self, stop: threading.Event | None = None):
        #: set by the first failure (and by whoever else stops the run, if they share it)
        self.stop = stop if stop is not None else threading.Event()
        self._lock = threading.Lock()
        self.error: LidarlocError | None = None

    def fail(self, block: str, exc: BaseException) -> LidarlocError:
        """Keep ``exc`` (from ``block``) if it is the first failure, set :attr:`stop`, and return
        the error the run will report."""
        error = exc if isinstance(exc, LidarlocError) else block_failure(block, exc)
        with self._lock:
            if self.error is None:
                self.error = error
        self.stop.set()
        return error

    def guard(self, block: str, fn: Callable[..., Any]) -> Callable[..., Any]:
        """``fn`` as a thread's target: its exception is kept (:meth:`fail`), not printed."""

        def run(*args, **kwargs):
            try:
                return fn(*args, **kwargs)
            except Exception as exc:
                self.fail(block, exc)
                return None

        return run

    @property
    def failed(self) -> bool:
        return self.error is not None

    def raise_if_failed(self) -> None:
        """Raise the first failure, if there was one."""
        if self.error is not None:
            raise self.error
