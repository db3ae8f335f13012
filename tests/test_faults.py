"""Faults in a run's blocks (core/worker_process.py, core/matching/matchers.py, core/odometry/feed.py,
core/failures.py): a child process killed mid-run is restarted once and the run goes on (the same
run every time in the replay clock); one killed at every start stops the run with one line; an
exception in a thread names its block."""

import json
import os
import signal
import threading
import time

import numpy as np
import pytest
from helpers import process_gone, short_town, wait_for
from lidarloc.core.config import Config
from lidarloc.core.errors import LidarlocError
from lidarloc.core.failures import BlockError, FirstFailure, in_block
from lidarloc.core.localizer import Localizer

N_SCANS = 14
# Only catches a hang: the failure itself surfaces within a scan or two.
HANG_BOUND_S = 60


@pytest.fixture(scope="module")
def town(cache_root):
    return short_town(N_SCANS)


def make(seq, cache_root) -> Localizer:
    cfg = Config()
    cfg.pf.n_particles = 300
    # at the PF's priority: on a loaded shared machine a niced S2M child starves for minutes
    cfg.s2m.replay_process_nice = 0
    return Localizer(seq, cfg, cache_root)


def kill(proxy) -> None:
    """SIGKILL the proxy's child and wait until it is gone, so that the localizer finds it dead at
    the same scan every time."""
    pid = proxy.pid
    os.kill(pid, signal.SIGKILL)
    wait_for(lambda: process_gone(pid), timeout=10, what="the killed child to exit")


def run_killing(town, cache_root, which: str, after: int = 3):
    with make(town, cache_root) as loc:
        loc.run(after)
        kill(loc.s2m.matcher if which == "S2M" else loc.odometry.process)
        loc.run()
        assert loc.done and len(loc.records) == N_SCANS  # every scan was finished and kept
        return (
            [(r.x, r.y, r.yaw, r.n_eff) for r in loc.records],
            [(e.scan, e.kind, e.detail) for e in loc.events],
            loc.pf.states.copy(),
        )


@pytest.mark.slow  # four 14-scan runs: ~40 s per block on 2 cores
@pytest.mark.parametrize("which", ["S2M", "RPE"])
def test_a_child_killed_once_is_restarted_and_the_replay_stays_deterministic(town, cache_root, which):
    first = run_killing(town, cache_root, which)
    restarts = [e for e in first[1] if e[1] == "restarted"]
    assert len(restarts) == 1, first[1]
    scan, _, detail = restarts[0]
    assert scan == 3 and detail.startswith(f"{which}: ") and "killed by SIGKILL" in detail
    if which == "S2M":  # the match in flight was cancelled: it can no longer land
        assert any(e[1] == "s2m_cancelled" and e[0] == 3 for e in first[1])
        assert any(e[1] in ("s2m_accepted", "s2m_rejected") and e[0] > 3 for e in first[1])
    second = run_killing(town, cache_root, which)
    assert first[0] == second[0]
    assert first[1] == second[1]
    assert np.array_equal(first[2], second[2])


def test_a_child_killed_at_every_start_stops_the_run_with_one_line(town, cache_root, tmp_path):
    """As ``lidarloc run`` runs it (app/headless.py): one line naming the block, and the results
    of every scan finished before are written, with what stopped the run."""
    import io

    from lidarloc.app.headless import localize
    from rich.console import Console

    loc = make(town, cache_root)
    loc.run(2)
    stop = threading.Event()
    killed: set[int] = set()

    def killer():  # kills every S2M child it sees, the restarted ones as soon as they start
        while not stop.is_set():
            pid = loc.s2m.matcher.pid
            if pid not in killed:
                killed.add(pid)
                try:
                    os.kill(pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
            stop.wait(0.005)

    thread = threading.Thread(target=killer, daemon=True)
    thread.start()
    t0 = time.monotonic()
    try:
        with pytest.raises(BlockError, match=r"^S2M: the S2M process died again right after its restart") as err:
            localize(loc, tmp_path, Console(file=io.StringIO()))
    finally:
        stop.set()
        thread.join()
        loc.close()
    assert time.monotonic() - t0 < HANG_BOUND_S
    assert isinstance(err.value, LidarlocError) and "\n" not in str(err.value)
    assert err.value.block == "S2M"
    assert len(killed) == 2  # the first child and its one restart
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["stopped_by"] == str(err.value) and not summary["interrupted"]
    rows = (tmp_path / "scans.csv").read_text().splitlines()
    assert len(rows) - 1 == len(loc.records) >= 2  # every scan finished before is written
    assert any(e["kind"] == "error" for e in json.loads((tmp_path / "events.json").read_text()))


def test_an_exception_in_a_block_is_one_line_naming_it():
    with pytest.raises(BlockError, match=r"^PF block failed at scan 7: ValueError: bad weights$") as err:
        with in_block("PF", " at scan 7"):
            raise ValueError("bad weights\nsecond line of detail")
    assert err.value.block == "PF"
    # an error the user can fix passes unchanged
    with pytest.raises(LidarlocError, match="^no such file: x$"):
        with in_block("recording"):
            raise LidarlocError("no such file: x")


def test_the_first_failure_of_a_runs_threads_stops_the_run():
    failures = FirstFailure()

    def boom():
        raise OSError("No space left on device")

    thread = threading.Thread(target=failures.guard("recording", boom))
    thread.start()
    thread.join()
    assert failures.stop.is_set() and failures.failed
    failures.fail("display", RuntimeError("later"))  # only the first is reported
    with pytest.raises(BlockError, match=r"^recording block failed: OSError: No space left on device$"):
        failures.raise_if_failed()


def test_large_messages_survive_signals_arriving_mid_write():
    """A signal handled while a large request is written to the child (Ctrl-C, SIGTERM, a
    debugger) must not cut the message short: the child would wait for its rest forever."""
    from lidarloc.core.odometry.worker import KissICPProcess

    t0 = time.monotonic()
    interrupts = 0

    def tick(*_):
        nonlocal interrupts
        interrupts += 1
        if time.monotonic() - t0 > HANG_BOUND_S:
            raise TimeoutError("the child never answered: a message was cut short")

    previous = signal.signal(signal.SIGALRM, tick)
    icp = KissICPProcess()
    try:
        icp.wait_ready()
        signal.setitimer(signal.ITIMER_REAL, 0.0005, 0.0005)
        rng = np.random.default_rng(0)
        for _ in range(6):
            icp.register_frame(rng.uniform(-30, 30, (120_000, 3)))
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)
        icp.close()
    assert interrupts > 0
    assert np.isfinite(icp.last_pose).all()


@pytest.mark.parametrize("waiting_to", ["write", "read"])
def test_a_call_to_a_child_this_process_killed_gives_up_at_once(waiting_to):
    """A child killed by its parent (Ctrl-C, closing the viewer) keeps its pipes open until the
    kernel has freed its memory, a few hundred milliseconds for one holding a map on a busy
    machine; a call in flight must not wait for that (Python's exit waits for the thread making
    it). Here something else holds the child's pipe ends open, so its pipes never close: the call
    must give up because this process killed it, not because the pipe closed."""
    from lidarloc.core.odometry.worker import KissICPProcess
    from lidarloc.core.worker_process import WorkerDied

    icp = KissICPProcess()
    icp.wait_ready()
    pid = icp.pid
    # the child's ends of its two pipes, held open past its death (opening /proc/PID/fd/N of a
    # pipe opens that pipe)
    held = [
        os.open(f"/proc/{pid}/fd/0", os.O_RDONLY | os.O_NONBLOCK),
        os.open(f"/proc/{pid}/fd/1", os.O_WRONLY | os.O_NONBLOCK),
    ]
    os.kill(pid, signal.SIGSTOP)  # it reads nothing more and answers nothing
    # a scan far larger than a pipe holds waits to be written; a small one waits for its answer
    n = 200_000 if waiting_to == "write" else 10
    outcome: list = []

    def call():
        try:
            icp.register_frame(np.zeros((n, 3), np.float32))
            outcome.append("answered")
        except WorkerDied as exc:
            outcome.append(exc)

    thread = threading.Thread(target=call, daemon=True)
    try:
        thread.start()
        thread.join(0.5)
        assert thread.is_alive(), f"the call ended before the kill: {outcome}"
        t0 = time.monotonic()
        icp.kill()
        thread.join(HANG_BOUND_S)
        gave_up_s = time.monotonic() - t0
    finally:
        icp.kill()
        for fd in held:
            os.close(fd)
    assert not thread.is_alive(), "the call still waits for a child killed by this process"
    assert len(outcome) == 1 and isinstance(outcome[0], WorkerDied)
    assert "killed by SIGKILL" in str(outcome[0])
    assert gave_up_s < 1.0, f"gave up after {gave_up_s:.2f} s"
    # killed on purpose (a run closing): the feeders' fault handling must not start a new child
    with pytest.raises(WorkerDied, match="stopped"):
        icp.revive(outcome[0].worker)
    assert icp.restarts == 0
