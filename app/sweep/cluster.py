"""Where many runs execute beside a local process pool: a Ray instance started on this machine
(``local``), or a running Ray cluster joined (``auto``, ``ray://HOST:PORT``, ``HOST:PORT``).

Ray is an optional dependency (``pip install 'lidarloc[ray]'``): asking for it without it is one
line. A local instance gets as many CPUs as the sweep has workers, no dashboard, and a small object
store: what crosses it is the sweep's table of runs (kilobytes); maps and lookup tables are read
from each node's memory-mapped cache instead, never shipped per run.
"""

from __future__ import annotations

import logging
import os

from ...core.errors import LidarlocError

#: bytes of a local instance's object store (Ray's minimum is 75 MB)
OBJECT_STORE_BYTES = 128 * 1024**2
RAY_HELP = "local (start Ray on this machine), auto (join the running cluster) or ray://HOST:PORT"


def check_address(address: str | None) -> None:
    """``--ray``'s value, checked before any work starts."""
    if address is None or address in ("local", "auto"):
        return
    host, _, port = address.removeprefix("ray://").rpartition(":")
    if not host or not port.isdigit():
        raise LidarlocError(f"--ray {address}: expected {RAY_HELP}")


def import_ray():
    """The ``ray`` module with Ray Tune, or a one-line error naming the extra to install."""
    try:
        import ray  # pyright: ignore[reportMissingImports]  (an optional extra)
        from ray import tune  # noqa: F401  pyright: ignore[reportMissingImports]
    except ImportError:
        raise LidarlocError("--ray needs Ray Tune: pip install 'lidarloc[ray]'") from None
    return ray


def connect(address: str | None, workers: int) -> None:
    """Join Ray: ``local`` (or None) starts an instance here with ``workers`` CPUs unless this
    process is connected already (a test's, or an earlier command's in the same process)."""
    check_address(address)
    # the classic one-line-per-event reporter instead of Ray's boxed console output: lidarloc
    # draws its own progress bar and prints its own one-line errors
    os.environ.setdefault("RAY_AIR_NEW_OUTPUT", "0")
    ray = import_ray()
    for name in ("ray.tune", "ray.train", "ray.air"):
        # a failed run is reported once, as one line, by the sweep (its traceback is in error.txt)
        logging.getLogger(name).setLevel(logging.CRITICAL)
    if ray.is_initialized():
        return
    local = address in (None, "local")
    # Ray gives its raylet 30 s to register: on a machine loaded far beyond its cores a local start
    # can miss that once (measured at load 38 on 2 cores), so a local start is tried twice
    for attempt in range(2 if local else 1):
        try:
            if local:
                ray.init(
                    num_cpus=workers,
                    include_dashboard=False,
                    object_store_memory=OBJECT_STORE_BYTES,
                    log_to_driver=False,
                    logging_level=logging.WARNING,
                )
            else:
                ray.init(address=address, log_to_driver=False, logging_level=logging.WARNING)
            return
        except Exception as exc:  # Ray raises bare Exceptions for a start that timed out
            ray.shutdown()
            if attempt == 0 and local:
                continue
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            raise LidarlocError(f"--ray {address or 'local'}: could not join Ray ({first})") from None


def cluster_cpus() -> int:
    """CPUs the joined Ray cluster offers (1 at least)."""
    ray = import_ray()
    return max(1, int(ray.cluster_resources().get("CPU", 1)))
