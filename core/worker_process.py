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
"""

from __future__ import annotations

import os
import pickle
import struct
import subprocess
import sys
import threading
from collections.abc import Callable
from typing import Any

_LEN = struct.Struct("<Q")
_STOP = "__stop__"
_PING = "__ping__"  # answered by the serving loop itself, once the handler is built


def _read_exact(stream, n: int) -> bytes:
    buf = bytearray()
    while len(buf) < n:
        chunk = stream.read(n - len(buf))
        if not chunk:
            raise EOFError
        buf += chunk
    return bytes(buf)


def _send(stream, obj: Any) -> None:
    data = pickle.dumps(obj, protocol=5)
    stream.write(_LEN.pack(len(data)) + data)
    stream.flush()


def _receive(stream) -> Any:
    (n,) = _LEN.unpack(_read_exact(stream, _LEN.size))
    return pickle.loads(_read_exact(stream, n))


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
        self._lock = threading.Lock()
        self._init_sent = False
        self._init = init
        self._answered = False  # it has answered a call: its set-up is over

    def call(self, request: Any) -> Any:
        with self._lock:
            try:
                self._send_init_once()
                _send(self._proc.stdin, request)
                status, value = _receive(self._proc.stdout)
                self._answered = True
            except (BrokenPipeError, EOFError, OSError, ValueError):  # ValueError: pipe closed by close()
                raise RuntimeError(f"{self.name} process exited (code {self._proc.poll()})") from None
        if status == "error":
            raise RuntimeError(value)
        return value

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
            _send(self._proc.stdin, self._init)

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

    def __del__(self):
        try:
            self.close()
        except Exception:
            pass


class WorkerProxy:
    """Base of a block's parent-side object: starts the child process running ``module`` with
    the set-up message ``init`` (it prepares while the caller goes on), and gives the members
    every block shares. Subclasses add the block's own calls on top of ``_worker.call``."""

    def __init__(self, module: str, init: Any, name: str):
        self._worker = WorkerProcess(module, init, name)
        self._worker.start()

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


def serve(make_handler: Callable[[Any], Callable[[Any], Any]]) -> None:
    """The child side: read the set-up message, build the handler from it, then answer requests
    until the parent says stop or goes away. An exception in the handler is sent back as a
    one-line error and the loop goes on (the parent decides what a failure means)."""
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
