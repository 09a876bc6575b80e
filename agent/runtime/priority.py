"""Real-time scheduling for the latency-critical threads, where the system allows it.

The camera thread and the hot path (frame -> VLP fix -> fusion -> pose bytes) are a few milliseconds of work
thirty times a second. Under the default time-sharing policy any other runnable task on their core (the
SLAM worker, a device loop, another program on the robot's computer) can run first when a frame arrives,
or take the core in the middle of one, and the frame's pose waits. ``SCHED_FIFO`` at a modest priority
makes the kernel run these two threads as soon as they are runnable and leave them alone until they block
again, which they do between frames (the mailbox, the camera driver's wait). It is the usual policy of the
control threads of robot software; the kernel's real-time throttling (``sched_rt_runtime_us``, 95 % of each
second by default) keeps a runaway thread from taking a core for good.

A process may set it when it runs as root, has ``CAP_SYS_NICE``, or has an ``RLIMIT_RTPRIO`` at least the
priority asked for (systemd: ``LimitRTPRIO=``; PAM: ``rtprio`` in ``limits.conf``). Where none holds, the
thread stays as it was and the agent says so once: the agent works the same, with a longer latency tail.

Only the calling thread changes (Linux schedules threads on their own; the thread id is the ``pid``
``sched_setscheduler`` takes), so the SLAM thread and the device loops stay time-shared, and so does any
process the thread starts (``SCHED_RESET_ON_FORK``).
"""

from __future__ import annotations

import os
import struct
import threading

from agent.config import MAX_REALTIME_PRIORITY

__all__ = ["CPU_LATENCY_DEVICE", "SWITCH_INTERVAL_S", "CpuLatencyRequest", "realtime_thread"]

# The GIL hands over every 5 ms by default: a thread in a long numpy-free Python stretch (SLAM's
# bookkeeping) would hold the hot path that long. 1 ms bounds that wait (benchmarks/agent_latency.py).
# ``vlp-agent run`` and ``vlp-agent sim`` set it for their process (``sys.setswitchinterval``).
SWITCH_INTERVAL_S = 0.001

# The kernel's CPU latency QoS request (Documentation/power/pm_qos_interface.rst).
CPU_LATENCY_DEVICE = "/dev/cpu_dma_latency"


def realtime_thread(priority: int) -> str | None:
    """Put the calling thread under ``SCHED_FIFO`` at ``priority`` (1..49: the kernel's IRQ threads, at
    50, stay above).

    Returns None when it took, else why not (not permitted, no such policy on this system). ``priority``
    0 asks for nothing and returns "off".
    """
    if priority == 0:
        return "off"
    if not 1 <= priority <= MAX_REALTIME_PRIORITY:
        raise ValueError(f"real-time priority must be 1..{MAX_REALTIME_PRIORITY}, got {priority}")
    if not hasattr(os, "sched_setscheduler") or not hasattr(os, "SCHED_FIFO"):
        return "this system has no SCHED_FIFO"
    tid = threading.get_native_id()
    try:
        # SCHED_RESET_ON_FORK: a process this thread starts (a camera SDK's helper, the simulator's renderer
        # when the camera is opened here) begins time-shared, not real-time.
        policy = os.SCHED_FIFO | getattr(os, "SCHED_RESET_ON_FORK", 0)
        os.sched_setscheduler(tid, policy, os.sched_param(priority))
    except PermissionError:
        return (
            f"not permitted (RLIMIT_RTPRIO {_rtprio_limit()}, needs {priority}: run with CAP_SYS_NICE, or "
            "systemd's LimitRTPRIO= / limits.conf rtprio)"
        )
    except OSError as exc:
        return f"refused: {exc.strerror or exc}"
    return None


def _rtprio_limit() -> str:
    import resource

    soft, _ = resource.getrlimit(resource.RLIMIT_RTPRIO)
    return "unlimited" if soft == resource.RLIM_INFINITY else str(soft)


class CpuLatencyRequest:
    """A CPU wake-up latency limit for the whole system, held while the agent runs: the kernel's PM QoS
    request through ``/dev/cpu_dma_latency`` (the file held open with a 32-bit target in microseconds
    written to it; closing it withdraws the request), as ``cyclictest`` and the real-time tuning guides
    do.

    An idle core goes to sleep: into a deep C-state on a PC, halted by the hypervisor in a virtual
    machine. The frame that wakes it then starts cold and slow (on the development VM, 45 ms of sleep
    between frames took the VLP median from 1.0 to 2.0 ms of CPU: docs/benchmarks.md). With a limit of 0
    the cores idle in a polling loop instead (as ``idle=poll``, while the request is held), at the cost
    of the idle power the sleep states would have saved; 1 allows the shallowest halt. Needs write access
    to the device (root only by default; ``systemd/99-vlp-agent.rules`` gives it to the service's
    group)."""

    def __init__(self, latency_us: int, path: str = CPU_LATENCY_DEVICE) -> None:
        if latency_us < 0:
            raise ValueError(f"a CPU latency limit is >= 0 us, got {latency_us}")
        self.latency_us = latency_us
        self.path = path
        self._fd: int | None = None

    @property
    def held(self) -> bool:
        return self._fd is not None

    def acquire(self) -> str | None:
        """Make the request; None when it holds, else why not (the system has no such device, not
        permitted). Idempotent."""
        if self._fd is not None:
            return None
        try:
            fd = os.open(self.path, os.O_WRONLY | os.O_CLOEXEC)
        except FileNotFoundError:
            return f"this system has no {self.path} (no CPU latency QoS)"
        except PermissionError:
            return f"not permitted to open {self.path} (root, or the group the udev rule gives it to)"
        except OSError as exc:
            return f"{self.path}: {exc.strerror or exc}"
        try:
            os.write(fd, struct.pack("=i", self.latency_us))
        except OSError as exc:
            os.close(fd)
            return f"{self.path} refused the value {self.latency_us}: {exc.strerror or exc}"
        self._fd = fd
        return None

    def release(self) -> None:
        """Withdraw the request (closing the file does it). Idempotent."""
        fd, self._fd = self._fd, None
        if fd is not None:
            os.close(fd)
