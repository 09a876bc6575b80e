"""ShutdownRequest: a signal wakes the waiting main loop at once, and the handler takes no lock."""

from __future__ import annotations

import os
import signal
import threading
import time

from agent.runtime.shutdown import AgentRequests, ShutdownRequest


def test_signal_wakes_the_wait_at_once_and_is_remembered() -> None:
    with ShutdownRequest() as shutdown:
        assert not shutdown.requested
        assert not shutdown.wait(0.01)
        timer = threading.Timer(0.05, os.kill, (os.getpid(), signal.SIGTERM))
        timer.start()
        t0 = time.monotonic()
        assert shutdown.wait(5.0)
        assert time.monotonic() - t0 < 1.0
        assert shutdown.signum == signal.SIGTERM
        assert shutdown.wait(5.0)  # stays requested, returns at once
        assert shutdown.why("--seconds ran out") == "SIGTERM"  # for the stop's log line


def test_without_a_signal_the_stop_says_its_own_reason() -> None:
    with ShutdownRequest() as shutdown:
        assert shutdown.why("--seconds ran out") == "--seconds ran out"


def test_previous_handlers_come_back_on_exit() -> None:
    before = signal.getsignal(signal.SIGINT)
    with ShutdownRequest():
        assert signal.getsignal(signal.SIGINT) != before
    assert signal.getsignal(signal.SIGINT) == before


def test_handler_is_safe_while_the_main_thread_holds_a_lock() -> None:
    # The deadlock this class exists for: a handler that set a threading.Event while the main thread was
    # inside that event's lock never returned. Ours is called here with the lock held and must return.
    lock = threading.Lock()
    with ShutdownRequest() as shutdown, lock:
        os.kill(os.getpid(), signal.SIGINT)
        for _ in range(100):  # the handler runs at the next bytecode boundary of the main thread
            if shutdown.requested:
                break
        assert shutdown.requested


def test_the_agent_requests_are_dropped_until_attached_then_reach_the_agent() -> None:
    calls: list[str] = []
    before = (signal.getsignal(signal.SIGUSR1), signal.getsignal(signal.SIGUSR2))
    with AgentRequests() as requests:
        os.kill(os.getpid(), signal.SIGUSR1)  # before the agent exists: dropped, the process lives on
        os.kill(os.getpid(), signal.SIGUSR2)
        requests.attach(lambda: calls.append("map"), lambda: calls.append("snapshot"))
        os.kill(os.getpid(), signal.SIGUSR1)
        os.kill(os.getpid(), signal.SIGUSR2)
        requests.attach(lambda: calls.append("map again"), None)  # no flight recorder: SIGUSR2 dropped
        os.kill(os.getpid(), signal.SIGUSR2)
        os.kill(os.getpid(), signal.SIGUSR1)
    assert calls == ["map", "snapshot", "map again"]
    assert (signal.getsignal(signal.SIGUSR1), signal.getsignal(signal.SIGUSR2)) == before
