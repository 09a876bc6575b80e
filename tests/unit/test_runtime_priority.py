"""Real-time scheduling of the calling thread (agent.runtime.priority): it takes where permitted, says why
not where it is refused, touches no other thread, and does not pass to a process the thread starts."""

from __future__ import annotations

import os
import subprocess
import sys
import threading

import pytest

from agent.config import parse_config
from agent.runtime import priority
from agent.runtime.priority import realtime_thread

linux_only = pytest.mark.skipif(not hasattr(os, "SCHED_FIFO"), reason="needs Linux scheduling policies")


def _in_thread(priority_: int) -> tuple[str | None, int, int]:
    """Run realtime_thread in a fresh thread: (its answer, the thread's policy after, its child's)."""
    out: dict[str, object] = {}

    def body() -> None:
        out["answer"] = realtime_thread(priority_)
        tid = threading.get_native_id()
        out["policy"] = os.sched_getscheduler(tid)
        child = subprocess.run(
            [sys.executable, "-c", "import os; print(os.sched_getscheduler(0))"],
            capture_output=True,
            text=True,
            check=True,
        )
        out["child"] = int(child.stdout)

    t = threading.Thread(target=body)
    t.start()
    t.join()
    answer = out["answer"]
    assert answer is None or isinstance(answer, str)
    return answer, int(str(out["policy"])), int(str(out["child"]))


def _permitted(level: int) -> bool:
    import resource

    soft, _ = resource.getrlimit(resource.RLIMIT_RTPRIO)
    return os.geteuid() == 0 or soft == resource.RLIM_INFINITY or soft >= level


@linux_only
def test_the_thread_runs_fifo_where_permitted_and_nothing_else_changes() -> None:
    if not _permitted(5):
        pytest.skip("no permission for SCHED_FIFO here (not root, RLIMIT_RTPRIO below 5)")
    before = os.sched_getscheduler(threading.get_native_id())
    answer, policy, child = _in_thread(5)
    if answer is not None:
        # Root in a container without CAP_SYS_NICE, or a cgroup with no real-time budget, is refused too.
        pytest.skip(f"SCHED_FIFO refused here: {answer}")
    assert policy & ~getattr(os, "SCHED_RESET_ON_FORK", 0) == os.SCHED_FIFO
    # The process's other threads (this one) and a process the real-time thread starts stay time-shared.
    assert os.sched_getscheduler(threading.get_native_id()) == before == os.SCHED_OTHER
    assert child == os.SCHED_OTHER


@linux_only
def test_refused_without_permission_says_why(monkeypatch: pytest.MonkeyPatch) -> None:
    def refuse(pid: int, policy: int, param: object) -> None:
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(priority.os, "sched_setscheduler", refuse)
    answer = realtime_thread(10)
    assert answer is not None
    assert "not permitted" in answer and "RLIMIT_RTPRIO" in answer and "LimitRTPRIO" in answer


def test_zero_asks_for_nothing_and_bad_priorities_are_errors() -> None:
    assert realtime_thread(0) == "off"
    with pytest.raises(ValueError, match=r"1\.\.49"):
        realtime_thread(50)
    with pytest.raises(ValueError):
        realtime_thread(-1)


def test_the_config_key_defaults_to_ten_and_zero_turns_it_off() -> None:
    base = '[servos]\nbackend = "dynamixel"\nport = "/dev/dynamixel"\n[output]\nurl = "/dev/ttyS0"\n'
    assert parse_config(base).scheduling.realtime_priority == 10
    off = parse_config(base + "[scheduling]\nrealtime_priority = 0\n")
    assert off.scheduling.realtime_priority == 0
