"""What the benchmarks wait on ends their wait when it fails: a measuring child process
(app/bench/common.py) that dies without a result ends the benchmark with one line naming its exit
status, and the GIL probe's work (app/bench/s2m.py) that raises hands its error on."""

import multiprocessing as mp
import os
import time

import pytest
from lidarloc.app.bench.common import child_result, end_child
from lidarloc.core.errors import LidarlocError


def _dies(queue) -> None:
    os._exit(3)  # as a child killed in C or for memory: nothing put, no Python clean-up


def _answers(queue) -> None:
    queue.put({"build_s": 1.5})


def _start(target):
    ctx = mp.get_context("fork")  # the targets need no pickling; the helper does not mind how
    queue = ctx.Queue()
    proc = ctx.Process(target=target, args=(queue,), daemon=True)
    proc.start()
    return queue, proc


def test_a_child_that_dies_without_a_result_is_one_line_naming_its_status():
    queue, proc = _start(_dies)
    t0 = time.monotonic()
    with pytest.raises(LidarlocError, match=r"^bench pf: the measuring process ended with status 3$"):
        child_result(queue, proc, "pf")
    assert time.monotonic() - t0 < 10  # noticed on the helper's own 1-s poll, not on a test timeout
    end_child(proc)
    assert not proc.is_alive()


def test_a_child_that_answers_gives_its_result():
    queue, proc = _start(_answers)
    assert child_result(queue, proc, "pf") == {"build_s": 1.5}
    end_child(proc)
    assert proc.exitcode == 0


def test_the_gil_probe_hands_on_a_failure_of_its_work_instead_of_polling_for_ever():
    from lidarloc.app.bench.s2m import gil_hold_ms

    def fails():
        raise RuntimeError("the matcher broke")

    with pytest.raises(RuntimeError, match="the matcher broke"):
        gil_hold_ms(fails)
    held = gil_hold_ms(lambda: time.sleep(0.05))  # a sleep releases the GIL: the poll keeps waking
    assert held["median"] < 40.0
