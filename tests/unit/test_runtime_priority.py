"""Real-time scheduling of the calling thread (agent.runtime.priority): it takes where permitted, says why
not where it is refused, touches no other thread, and does not pass to a process the thread starts. The
CPU latency QoS request: the kernel's 32-bit value written to a file held open, withdrawn by closing it."""

from __future__ import annotations

import os
import stat
import struct
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from agent.config import parse_config
from agent.runtime import priority
from agent.runtime.priority import CPU_LATENCY_DEVICE, CpuLatencyRequest, realtime_thread

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


def test_the_config_key_cpu_latency_defaults_to_zero_and_minus_one_turns_it_off() -> None:
    base = '[servos]\nbackend = "dynamixel"\nport = "/dev/dynamixel"\n[output]\nurl = "/dev/ttyS0"\n'
    assert parse_config(base).scheduling.cpu_latency_us == 0
    assert parse_config(base + "[scheduling]\ncpu_latency_us = -1\n").scheduling.cpu_latency_us == -1
    assert parse_config(base + "[scheduling]\ncpu_latency_us = 20\n").scheduling.cpu_latency_us == 20


def test_the_request_writes_the_kernels_32_bit_value_and_holds_the_file_until_released(
    tmp_path: Path,
) -> None:
    # A FIFO stands in for the device: what the request writes can be read back byte for byte, and the
    # reader sees end-of-file exactly when the request lets go of it.
    path = os.path.join(str(tmp_path), "cpu_dma_latency")
    os.mkfifo(path)
    reader = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    request = CpuLatencyRequest(7, path)
    try:
        assert request.acquire() is None and request.held
        assert request.acquire() is None  # idempotent: one request, one open file
        assert os.read(reader, 16) == struct.pack("=i", 7)
        with pytest.raises(BlockingIOError):
            os.read(reader, 16)  # still held open: no end-of-file
        request.release()
        assert not request.held
        assert os.read(reader, 16) == b""  # withdrawn
        request.release()  # idempotent
    finally:
        os.close(reader)
        request.release()


def test_a_request_that_cannot_be_made_says_why(tmp_path: Path) -> None:
    missing = CpuLatencyRequest(0, os.path.join(str(tmp_path), "nope"))
    answer = missing.acquire()
    assert answer is not None and "no " in answer and "QoS" in answer and not missing.held
    if os.geteuid() != 0:
        locked = os.path.join(str(tmp_path), "locked")
        open(locked, "w").close()
        os.chmod(locked, stat.S_IRUSR)
        answer = CpuLatencyRequest(0, locked).acquire()
        assert answer is not None and "not permitted" in answer
    with pytest.raises(ValueError):
        CpuLatencyRequest(-1)


@pytest.mark.skipif(not os.path.exists(CPU_LATENCY_DEVICE), reason="no CPU latency QoS device here")
def test_the_real_device_takes_the_request_where_permitted() -> None:
    request = CpuLatencyRequest(0)
    answer = request.acquire()
    if answer is not None:
        assert "not permitted" in answer
        pytest.skip(answer)
    try:
        # Reading the device gives the system's effective target: ours is the strictest there can be.
        with open(CPU_LATENCY_DEVICE, "rb") as device:
            assert struct.unpack("=i", device.read(4))[0] == 0
    finally:
        request.release()
