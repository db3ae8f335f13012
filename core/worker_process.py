"""A block of the localizer in its own Python process, called like a function.

Why processes: KISS-ICP's and small_gicp's C++ code hold the GIL while they work (50–150 ms per
call, measured with ``lidarloc bench s2m``), so on threads they stall the particle filter. A child
process runs them truly in parallel; arrays cross a pipe (a 120k-point scan in float32 is
~1.4 MB, well under a millisecond to copy).

Plain ``subprocess`` + ``python -m module`` instead of ``multiprocessing``: the caller's
``__main__`` is never re-imported, so scripts without a main guard work too. Each child gets its
own session, so a Ctrl-C at the terminal reaches only the parent, which then closes its workers
in order. A child may lower its own priority (:func:`lower_priority`, from its set-up message):
a best-effort block (S2M) then only gets the CPU the real-time blocks (PF, RPE) leave.

Wire protocol (stdin → child, child → stdout): one length-prefixed pickle per message (protocol
5). A request is any picklable object; the reply is ``("ok", value)`` or ``("error", message)``.

A child that dies (killed, out of memory, a crash in C++) fails the call in flight at once with
:class:`WorkerDied` (its pipe closes), and :attr:`WorkerProcess.alive` says so between calls.
:meth:`WorkerProxy.revive` starts a new child in its place, once: a restarted child that dies
again before it answered anything is a :class:`~lidarloc.core.failures.BlockError` (something
kills it at every start, or its set-up cannot work), and the run stops. A child never outlives its
parent: it exits when its parent's pipe closes, and a thread of its own ends it within
``PARENT_POLL_S`` when the parent is gone (killed with SIGKILL, its pipe still held open by a
sibling), so no orphan keeps computing and writing into a broken pipe.
"""

from __future__ import annotations

import gc
import os
import pickle
import select
import signal
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

from .failures import BlockError

_LEN = struct.Struct("<Q")
_STOP = "__stop__"
_PING = "__ping__"  # answered by the serving loop itself, once the handler is built
#: How often a child checks that its parent is still there (seconds).
PARENT_POLL_S = 0.25
#: How often a call in flight checks whether its child was killed by this process (milliseconds).
ABANDON_POLL_MS = 20


class WorkerDied(RuntimeError):
    """The child process is gone (killed, crashed, out of memory): the call in flight, and every
    later one, can never be answered. ``worker`` is the :class:`WorkerProcess` that died."""

    def __init__(self, message: str, worker: WorkerProcess | None = None):
        super().__init__(message)
        self.worker = worker


def exit_words(code: int | None) -> str:
    """How a process ended, in words: "killed by SIGKILL", "exit code 1"."""
    if code is None:
        return "its pipe closed"
    if code < 0:
        try:
            return f"killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"killed by signal {-code}"
    return f"exit code {code}"


def _wait_for(stream, events: int, abandon: threading.Event | None) -> None:
    """Block until ``stream``'s pipe is ready for ``events`` (or hung up). With ``abandon``, give
    up with ``BrokenPipeError`` once it is set: a child this process killed keeps its pipes open
    until the kernel has freed its memory (``exit_mm`` comes before ``exit_files``), which for a
    child holding a map takes a few hundred milliseconds on a busy machine; a call in flight
    would wait that long, and Python's exit waits for the thread making it."""
    poller = select.poll()
    poller.register(stream.fileno(), events | select.POLLHUP | select.POLLERR)
    while True:
        if abandon is not None and abandon.is_set():
            raise BrokenPipeError("the process was killed")
        if poller.poll(ABANDON_POLL_MS if abandon is not None else None):
            return


def _read_exact(stream, n: int, abandon: threading.Event | None = None) -> bytes:
    buf = bytearray()
    while len(buf) < n:
        if abandon is not None:
            _wait_for(stream, select.POLLIN, abandon)
        chunk = stream.read(n - len(buf))
        if not chunk:
            raise EOFError
        buf += chunk
    return bytes(buf)


def _send(stream, obj: Any, abandon: threading.Event | None = None) -> None:
    """Write one message. ``stream`` may be non-blocking (the parent's pipes to its children
    are): a full pipe is then waited for here, where ``abandon`` can end the wait."""
    data = pickle.dumps(obj, protocol=5)
    view = memoryview(_LEN.pack(len(data)) + data)
    # An unbuffered pipe's write may take only part of a large message when a signal arrives
    # mid-way (Ctrl-C, SIGTERM, a debugger attaching), or when the pipe is non-blocking and full:
    # the rest must follow, or the child waits for it forever while the parent waits for the answer.
    while view:
        written = stream.write(view)
        if not written:  # None: a non-blocking pipe is full
            _wait_for(stream, select.POLLOUT, abandon)
            continue
        view = view[written:]
    stream.flush()


def _receive(stream, abandon: threading.Event | None = None) -> Any:
    (n,) = _LEN.unpack(_read_exact(stream, _LEN.size, abandon))
    return pickle.loads(_read_exact(stream, n, abandon))


class WorkerProcess:
    """The parent side: ``call(request)`` sends one request and returns the child's reply
    (thread-safe; calls are serialised). A failure inside the child raises ``RuntimeError`` with
    its one-line message; a dead child raises ``RuntimeError`` naming its exit code."""

    def __init__(self, module: str, init: Any, name: str):
        self.name = name
        self._proc = subprocess.Popen(
            [sys.executable, "-m", module],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            bufsize=0,
            start_new_session=True,
        )
        # writes wait in _send, where a kill by this process ends the wait (see _wait_for)
        os.set_blocking(self._proc.stdin.fileno(), False)
        self._killed = threading.Event()  # set by kill(): a call in flight gives up at once
        self._lock = threading.Lock()
        self._init_sent = False
        self._init = init
        self._answered = False  # it has answered a call: its set-up is over

    def call(self, request: Any) -> Any:
        with self._lock:
            try:
                self._send_init_once()
                _send(self._proc.stdin, request, self._killed)
                status, value = _receive(self._proc.stdout, self._killed)
                self._answered = True
            except (BrokenPipeError, EOFError, OSError, ValueError):  # ValueError: pipe closed by close()
                # killed here: say so without waiting for the kernel to reap it (see _wait_for)
                how = exit_words(-signal.SIGKILL) if self.killed_here else self.exit_words()
                raise WorkerDied(f"{self.name} process exited ({how})", self) from None
        if status == "error":
            raise RuntimeError(value)
        return value

    @property
    def alive(self) -> bool:
        """Whether the child is still running (a cheap check: no call is made). A child that has
        exited but is not reaped yet counts as dead: ``poll()`` alone says "running" while another
        thread waits for it, and the answer would depend on that thread's timing."""
        if self._proc.poll() is not None:
            return False
        try:
            with open(f"/proc/{self._proc.pid}/stat") as f:
                state = f.read().rsplit(")", 1)[1].split()[0]
        except FileNotFoundError:
            return False
        except (OSError, IndexError):  # no /proc (not Linux): poll() has the last word
            return True
        return state not in ("Z", "X")

    @property
    def killed_here(self) -> bool:
        """Whether this process killed the child (:meth:`kill`, or :meth:`close` of a busy one)."""
        return self._killed.is_set()

    @property
    def answered(self) -> bool:
        """Whether the child has answered a call (its set-up is over)."""
        return self._answered

    def exit_words(self) -> str:
        """How the child ended (:func:`exit_words`), once it has (waits up to a second for a
        child whose pipe closed to be reaped)."""
        try:
            code = self._proc.wait(timeout=1.0)
        except subprocess.TimeoutExpired:
            code = None
        return exit_words(code)

    def wait_ready(self) -> None:
        """Block until the child has finished its set-up (a set-up failure raises here)."""
        self.call(_PING)

    @property
    def pid(self) -> int:
        """The child's process id (for the operating system: its priority, signals)."""
        return self._proc.pid

    def cpu_seconds(self) -> float | None:
        """CPU time (user + system, all its threads) the child has used so far; None where
        ``/proc`` cannot tell (not Linux, or the child is gone)."""
        try:
            with open(f"/proc/{self._proc.pid}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()  # after "pid (name)": state is field 3
            return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime, stime
        except (OSError, ValueError, IndexError):
            return None

    def start(self) -> None:
        """Send the set-up message now, so the child prepares while the parent does other work."""
        with self._lock:
            try:
                self._send_init_once()
            except (BrokenPipeError, OSError):
                pass  # reported by the first call

    def _send_init_once(self) -> None:
        """The set-up message goes first, exactly once (caller holds the lock)."""
        if not self._init_sent:
            self._init_sent = True
            _send(self._proc.stdin, self._init, self._killed)

    def close(self) -> None:
        """Stop the child: an idle one is asked to exit. One that is busy (a call in flight,
        whose answer nobody will read; that call then raises ``RuntimeError`` in its thread) or
        may still be in its set-up (it has answered nothing yet) is killed at once: it would
        read the stop request only when done, and waiting for that made Ctrl-C in the first
        scans take 2 s. Its caches are safe: they are written to a temporary name, then renamed."""
        proc = self._proc
        if proc.poll() is None:
            asked = False
            if self._lock.acquire(blocking=False):  # no call in flight …
                try:
                    if self._answered:  # … and past its set-up: ask it to exit
                        _send(proc.stdin, _STOP)
                        proc.stdin.close()
                        asked = True
                except (BrokenPipeError, OSError, ValueError):
                    pass
                finally:
                    self._lock.release()
            if not asked:
                self._killed.set()
                proc.kill()
            try:
                proc.wait(timeout=2.0)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        for stream in (proc.stdin, proc.stdout):
            try:
                stream.close()
            except OSError:
                pass

    def kill(self) -> None:
        """SIGKILL the child without waiting for it: the parent is about to exit and cannot wait
        for :meth:`close` (the kernel reaps the child once the parent is gone). A call in
        flight gives up within ``ABANDON_POLL_MS`` (:class:`WorkerDied`)."""
        self._killed.set()
        try:
            if self._proc.poll() is None:
                self._proc.kill()
        except OSError:
            pass

    def __del__(self):
        try:
            self.close()
        except Exception:
            pass


class WorkerProxy:
    """Base of a block's parent-side object: starts the child process running ``module`` with
    the set-up message ``init`` (it prepares while the caller goes on), and gives the members
    every block shares. Subclasses add the block's own calls on top of ``_worker.call``.
    ``block`` names the localizer's block the child serves, in errors (default: ``name``)."""

    def __init__(self, module: str, init: Any, name: str, block: str | None = None):
        self._spec = (module, init, name)
        self.name = name
        self.block = block or name
        self._worker = WorkerProcess(module, init, name)
        self._worker.start()
        self._revive_lock = threading.Lock()
        self.restarts = 0  # children started in place of a dead one
        self.restarted_at: float | None = None  # time.monotonic() of the last restart

    @property
    def alive(self) -> bool:
        """Whether the current child is running."""
        return self._worker.alive

    def revive(self, died: WorkerProcess | None = None) -> str | None:
        """Start a new child in place of the current one if it died (or if it is ``died``, the one
        a :class:`WorkerDied` names); returns what happened in words, or None when there was
        nothing to do (it runs, or ``died`` was replaced already). The new child sets up in the
        background, as the first did. Raises :class:`~lidarloc.core.failures.BlockError` when the
        child that died was itself a restart that never answered: it died again at once; and
        :class:`WorkerDied` when this process killed it (closing): no new child is started then."""
        with self._revive_lock:
            old = self._worker
            if died is not None and died is not old:
                return None
            if died is None and old.alive:
                return None
            if old.killed_here:  # stopped on purpose (the run is closing): not a death to mend
                raise WorkerDied(f"{self.name} process was stopped", old)
            how = old.exit_words()
            if self.restarts and not old.answered:
                raise BlockError(
                    f"{self.block}: the {self.name} process died again right after its restart ({how}); "
                    "the run stops here",
                    self.block,
                )
            old.close()
            self._worker = WorkerProcess(*self._spec)
            self._worker.start()
            self.restarts += 1
            self.restarted_at = time.monotonic()
            return f"the {self.name} process died ({how}); a new one was started"

    def ensure_alive(self) -> str | None:
        """:meth:`revive` if the child died; what happened in words, or None."""
        return None if self._worker.alive else self.revive()

    def wait_ready_reviving(self) -> str | None:
        """:meth:`wait_ready`, starting a new child once if the first dies in its set-up; what
        happened in words, or None. A failed set-up (not a death) raises ``RuntimeError``."""
        try:
            self.wait_ready()
            return None
        except WorkerDied as exc:
            words = self.revive(exc.worker)
        try:
            self.wait_ready()
        except WorkerDied as exc:
            self.revive(exc.worker)  # raises: died again at once
            raise
        return words

    def wait_ready(self) -> None:
        """Block until the child has finished its set-up (a set-up failure raises ``RuntimeError``)."""
        self._worker.wait_ready()

    def cpu_seconds(self) -> float | None:
        """CPU time the child has used so far (see :meth:`WorkerProcess.cpu_seconds`)."""
        return self._worker.cpu_seconds()

    @property
    def pid(self) -> int:
        """The child's process id (see :attr:`WorkerProcess.pid`)."""
        return self._worker.pid

    def close(self) -> None:
        self._worker.close()

    def kill(self) -> None:
        """Kill the current child at once (see :meth:`WorkerProcess.kill`)."""
        self._worker.kill()


def _next_message(stream) -> tuple[bool, Any]:
    """(False, None) when the parent closed the pipe or said stop, else (True, message)."""
    try:
        message = _receive(stream)
    except EOFError:
        return False, None
    if isinstance(message, str) and message == _STOP:
        return False, None
    return True, message


def lower_priority(nice: int) -> None:
    """Raise this process's nice value by ``nice``, best effort.

    The child runs in its own session, and with the kernel's scheduler autogroups (on by default
    on desktop and server distributions, ``/proc/sys/kernel/sched_autogroup_enabled``) a session is
    its own scheduling group: CPU is shared between groups first, and ``os.nice`` only orders the
    threads *inside* a group. So the group's own nice value is set too (``/proc/self/autogroup``;
    raising it needs no privilege). Measured: with ``os.nice`` alone, two benchmark runs' S2M
    children at nice 19 still took as much CPU from the PF as at nice 0 (PF 96 ms either way)."""
    try:
        os.nice(nice)
    except OSError:
        pass
    try:
        with open("/proc/self/autogroup", "w") as f:
            f.write(str(max(-20, min(19, int(nice)))))
    except OSError:  # no autogroups (kernel option off, not Linux): os.nice is then what counts
        pass


def _exit_with_parent() -> None:
    """A daemon thread that ends this process when its parent is gone (see the module docstring);
    its parent is then init or a subreaper, so ``getppid`` changes."""
    parent = os.getppid()

    def watch():
        while os.getppid() == parent:
            time.sleep(PARENT_POLL_S)
        os._exit(0)

    threading.Thread(target=watch, name="lidarloc-parent-watch", daemon=True).start()


def serve(make_handler: Callable[[Any], Callable[[Any], Any]]) -> None:
    """The child side: read the set-up message, build the handler from it, then answer requests
    until the parent says stop or goes away. An exception in the handler is sent back as a
    one-line error and the loop goes on (the parent decides what a failure means). A parent gone
    mid-request ends the child quietly: nobody is left to read a traceback."""
    _exit_with_parent()
    # Ctrl-C reaches the parent, which stops its children in order; a SIGINT sent to a child
    # alone ends it without a traceback (the parent then sees it exit).
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    try:
        _serve(make_handler)
    except (OSError, EOFError):
        # the parent closed the pipe: it no longer wants an answer. _exit, not return: the
        # interpreter's exit would flush the broken pipe again and print that it failed.
        os._exit(0)
    # Stopped by the parent: nothing is left to write (a child writes files, numba's kernel cache
    # included, only while it computes an answer), so the interpreter's own exit — tearing down
    # numba, open3d and the map's objects, a long while for a child at a low priority on a busy
    # machine, with the parent's close waiting for it — is skipped.
    try:
        sys.stderr.flush()
    finally:
        os._exit(0)


def _serve(make_handler: Callable[[Any], Callable[[Any], Any]]) -> None:
    inp, out = sys.stdin.buffer, sys.stdout.buffer
    # Anything the handler prints must not corrupt the protocol stream.
    sys.stdout = sys.stderr
    running, init = _next_message(inp)
    if not running:
        return
    try:
        handler = make_handler(init)
        failure = None
    except Exception as exc:
        handler, failure = None, f"{type(exc).__name__}: {exc}"
    # The modules and the handler's state live as long as the child: out of the garbage
    # collector's reach, a full collection walks only what requests made since (a 90 ms one
    # otherwise, holding up an answer the filter may be waiting for). Frozen objects are never
    # collected, so this is done once, here; requests' garbage is collected as always.
    gc.freeze()
    while True:
        running, request = _next_message(inp)
        if not running:
            return
        if failure is not None:
            _send(out, ("error", f"set-up failed: {failure}"))
            continue
        if isinstance(request, str) and request == _PING:
            _send(out, ("ok", True))
            continue
        try:
            reply = ("ok", handler(request))
        except Exception as exc:
            reply = ("error", f"{type(exc).__name__}: {exc}")
        _send(out, reply)
