"""KISS-ICP in its own process.

KISS-ICP's Python binding holds the GIL while it registers a scan (~90 ms on this project's
2-core reference machine, measured: a Python thread beside it ran at ~20 % of its normal rate).
In a thread it would stall the particle filter's Python code for that long every scan. Running it
in a child process makes the RPE block truly parallel; the parent sends each scan (float32,
~1.4 MB for a 120k-point scan) through a pipe and receives the 4×4 odometry pose.

:class:`KissICPProcess` mimics the two members of ``kiss_icp.kiss_icp.KissICP`` that
:class:`~lidarloc.core.rpe.RelativePoseEstimator` uses (``register_frame``, ``last_pose``) plus
``reset()`` (a fresh odometry, e.g. after a kidnap) and ``close()``.
"""

from __future__ import annotations

import struct
import subprocess
import sys
import threading

import numpy as np

# Wire protocol on the child's stdin/stdout: a request is a 1-byte kind + uint32 point count,
# followed for a scan by count × 3 float32; the reply is a 1-byte status + 16 float64 (the pose)
# or, on error, a uint32 length + UTF-8 message. A plain subprocess (not multiprocessing) so the
# caller's __main__ is never re-imported: scripts without a main guard work too.
_REQ = struct.Struct("<cI")
_SCAN, _RESET, _STOP = b"S", b"R", b"Q"


def _serve(config_args: tuple) -> None:
    from kiss_icp.kiss_icp import KissICP

    from .rpe import _kiss_config

    inp, out = sys.stdin.buffer, sys.stdout.buffer
    icp = KissICP(_kiss_config(*config_args))
    while True:
        head = inp.read(_REQ.size)
        if len(head) < _REQ.size:
            return
        kind, n = _REQ.unpack(head)
        if kind == _STOP:
            return
        if kind == _RESET:
            icp = KissICP(_kiss_config(*config_args))
            out.write(b"o" + np.eye(4).tobytes())
            out.flush()
            continue
        data = inp.read(n * 12)
        try:
            pts = np.frombuffer(data, dtype=np.float32).reshape(-1, 3).astype(np.float64)
            icp.register_frame(pts, np.zeros(0))
            out.write(b"o" + np.ascontiguousarray(icp.last_pose, dtype=np.float64).tobytes())
        except Exception as exc:  # reported in the parent as the RPE block's failure
            msg = f"{type(exc).__name__}: {exc}".encode()
            out.write(b"e" + struct.pack("<I", len(msg)) + msg)
        out.flush()


class KissICPProcess:
    def __init__(self, max_range: float = 100.0, min_range: float = 2.5, voxel_size: float | None = None):
        args = repr((float(max_range), float(min_range), None if voxel_size is None else float(voxel_size)))
        self._proc = subprocess.Popen([sys.executable, "-m", "lidarloc.core.rpe_worker", args],
                                      stdin=subprocess.PIPE, stdout=subprocess.PIPE, bufsize=0,
                                      # its own session: a Ctrl-C at the terminal reaches the parent
                                      # only, which then closes this worker in order
                                      start_new_session=True)
        self._lock = threading.Lock()
        self.last_pose = np.eye(4)

    def _request(self, kind: bytes, payload: bytes = b"", n: int = 0) -> np.ndarray:
        with self._lock:
            try:
                self._proc.stdin.write(_REQ.pack(kind, n) + payload)
                status = self._proc.stdout.read(1)
                if status == b"o":
                    return np.frombuffer(self._read(128), dtype=np.float64).reshape(4, 4).copy()
                if status == b"e":
                    (length,) = struct.unpack("<I", self._read(4))
                    raise RuntimeError(self._read(length).decode(errors="replace"))
            except (BrokenPipeError, OSError):
                pass
        raise RuntimeError(f"KISS-ICP process exited (code {self._proc.poll()})")

    def _read(self, n: int) -> bytes:
        buf = b""
        while len(buf) < n:
            chunk = self._proc.stdout.read(n - len(buf))
            if not chunk:
                raise BrokenPipeError
            buf += chunk
        return buf

    def register_frame(self, points: np.ndarray, timestamps=None) -> None:
        pts = np.ascontiguousarray(np.asarray(points)[:, :3], dtype=np.float32)
        self.last_pose = self._request(_SCAN, pts.tobytes(), len(pts))

    def reset(self) -> None:
        self.last_pose = self._request(_RESET)

    def close(self) -> None:
        proc = self._proc
        if proc.poll() is None:
            try:
                with self._lock:
                    proc.stdin.write(_REQ.pack(_STOP, 0))
                    proc.stdin.close()
            except (BrokenPipeError, OSError):
                pass
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


if __name__ == "__main__":
    import ast

    _serve(ast.literal_eval(sys.argv[1]))
