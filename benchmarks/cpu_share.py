"""How the machine's CPUs spent an interval, from ``/proc/stat``: the share of time the hypervisor gave to
other guests (``steal``) beside the shares busy and idle.

On a virtual machine whose host is overcommitted, ``steal`` is time the guest's virtual CPUs were ready to
run and were not run: every thread of every process stops for it, a few milliseconds at a time, without
the guest's scheduler knowing. A latency tail measured while a third of the time was stolen says more
about the host than about the program, so the benchmarks print the share beside their figures.

    with CpuShare() as share:       # or share = CpuShare().start() ... share.stop()
        ...
    share.result()  # {"steal": 0.31, "busy": 0.42, "idle": 0.27}, or {} where /proc/stat is not there
"""

from __future__ import annotations

from pathlib import Path
from types import TracebackType

__all__ = ["CpuShare", "cpu_times"]

# /proc/stat's "cpu" line: user nice system idle iowait irq softirq steal guest guest_nice (guest time is
# already counted in user and nice).
_FIELDS = ("user", "nice", "system", "idle", "iowait", "irq", "softirq", "steal")


def cpu_times(path: Path = Path("/proc/stat")) -> dict[str, int] | None:
    """The all-CPU counters of ``/proc/stat`` in clock ticks, None where the file is missing or odd."""
    try:
        first = path.read_text().split("\n", 1)[0].split()
    except OSError:
        return None
    if len(first) < 1 + len(_FIELDS) or first[0] != "cpu":
        return None
    return dict(zip(_FIELDS, (int(v) for v in first[1 : 1 + len(_FIELDS)]), strict=True))


class CpuShare:
    """The shares of an interval (a ``with`` block) the CPUs spent stolen, busy and idle."""

    def __init__(self) -> None:
        self._start: dict[str, int] | None = None
        self._end: dict[str, int] | None = None

    def start(self) -> CpuShare:
        self._start, self._end = cpu_times(), None
        return self

    def stop(self) -> None:
        self._end = cpu_times()

    def __enter__(self) -> CpuShare:
        return self.start()

    def __exit__(
        self, kind: type[BaseException] | None, value: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stop()

    def result(self) -> dict[str, float]:
        if self._start is None or self._end is None:
            return {}
        d = {k: self._end[k] - self._start[k] for k in _FIELDS}
        total = sum(d.values())
        if total <= 0:
            return {}
        idle = d["idle"] + d["iowait"]
        return {
            "steal": round(d["steal"] / total, 3),
            "busy": round((total - idle - d["steal"]) / total, 3),
            "idle": round(idle / total, 3),
        }
