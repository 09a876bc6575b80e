"""Hand-over between the runtime's threads: the latest-frame mailbox and the bounded queue drop, and count."""

from __future__ import annotations

import threading
import time

import pytest

from agent.runtime.mailbox import BoundedQueue, LatestMailbox, MailboxClosed


def test_a_slow_consumer_gets_the_newest_item_and_the_rest_are_counted() -> None:
    box: LatestMailbox[int] = LatestMailbox()
    assert box.put(1) is False
    assert box.put(2) is True
    assert box.put(3) is True
    assert box.take(0.0) == 3
    assert (box.put_count, box.taken, box.dropped) == (3, 1, 2)
    assert box.take(0.01) is None


def test_take_waits_for_a_put_from_another_thread() -> None:
    box: LatestMailbox[str] = LatestMailbox()
    threading.Timer(0.05, box.put, args=("frame",)).start()
    assert box.take(5.0) == "frame"


def test_close_wakes_a_waiting_consumer_and_refuses_puts() -> None:
    box: LatestMailbox[int] = LatestMailbox()
    raised: list[BaseException] = []

    def consume() -> None:
        try:
            box.take(30.0)
        except MailboxClosed as exc:
            raised.append(exc)

    thread = threading.Thread(target=consume)
    thread.start()
    time.sleep(0.05)
    box.close()
    thread.join(5.0)
    assert not thread.is_alive() and len(raised) == 1
    with pytest.raises(MailboxClosed):
        box.put(1)


def test_a_full_queue_drops_its_oldest_item() -> None:
    queue: BoundedQueue[int] = BoundedQueue(3)
    assert [queue.put(i) for i in range(5)] == [False, False, False, True, True]
    assert queue.dropped == 2 and len(queue) == 3
    assert [queue.get(0.0) for _ in range(3)] == [2, 3, 4]
    assert queue.get(0.01) is None


def test_drain_takes_everything_and_close_ends_the_consumer() -> None:
    queue: BoundedQueue[int] = BoundedQueue(4)
    queue.put(1)
    queue.put(2)
    assert queue.drain() == [1, 2] and len(queue) == 0
    queue.close()
    with pytest.raises(MailboxClosed):
        queue.get(1.0)
    with pytest.raises(ValueError):
        BoundedQueue(0)
