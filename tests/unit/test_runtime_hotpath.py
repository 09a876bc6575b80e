"""HotPath: background work waits while a frame is pending or being processed, and only that long."""

from __future__ import annotations

import threading
import time

from agent.runtime.hotpath import HotPath


def test_an_idle_hot_path_does_not_hold_anyone_up() -> None:
    hot = HotPath(lambda: False)
    hot.give_way()
    assert hot.waits == 0 and not hot.active()


def test_background_work_waits_until_the_frame_is_done() -> None:
    pending = threading.Event()
    pending.set()
    hot = HotPath(pending.is_set, max_wait_s=5.0)
    hot.frame_queued()
    done_at: list[float] = []

    def frame() -> None:
        with hot.busy():
            pending.clear()  # taken from the mailbox, now being processed
            time.sleep(0.05)
        done_at.append(time.monotonic())

    worker = threading.Thread(target=frame)
    worker.start()
    hot.give_way()
    returned_at = time.monotonic()
    worker.join()
    assert done_at and returned_at >= done_at[0] - 0.01  # not before the frame's pose was written
    assert hot.waits == 1 and hot.timeouts == 0 and hot.waited_s > 0.03


def test_a_stuck_hot_path_delays_background_work_by_the_bound_only() -> None:
    hot = HotPath(lambda: True, max_wait_s=0.02)
    hot.frame_queued()
    start = time.monotonic()
    hot.give_way()
    assert 0.015 < time.monotonic() - start < 0.5
    assert hot.timeouts == 1


def test_a_closed_hot_path_holds_nobody_up_even_with_a_frame_left_behind() -> None:
    hot = HotPath(lambda: True, max_wait_s=5.0)
    hot.frame_queued()  # a frame handed over just before the agent stopped; nobody will process it
    hot.close()
    start = time.monotonic()
    hot.give_way()
    hot.frame_queued()
    with hot.busy():
        pass
    hot.give_way()
    assert time.monotonic() - start < 0.5
    assert hot.timeouts == 0 and not hot.active()
