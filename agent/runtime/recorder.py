"""Record what the fusion consumes, and replay it.

A recording is JSON lines: a header (``{"k": "header", "fusion": {...}}``: how the filter was set up), then
every input the fusion took, in the order it applied them (``odometry``, ``gyro``, ``pose`` from VLP or
SLAM, each with its measurement time and arrival time), and every pose the agent wrote (``out``: the
filter's input count ``v`` when it was read, the pose and the flags). The inputs are handed over under the
filter's lock, so the order in the file is the order they were fused in, whatever thread they came from.

:func:`replay` runs a fresh filter over a recording and reproduces every pose the agent wrote: a regression
check for the fusion on recorded runs (a change in ``agent.fusion`` shows up as poses that moved), and a
way to study a run offline (also from a flight recording, ``agent.recording``, which holds the same
records on its ``/fusion/*`` channels). Frames and scans are not in this file (30 frames/s of 480 kB would
not fit a robot's card); the VLP fixes and SLAM poses made from them are.

Writes never block the agent: records go through a bounded queue to a writer thread (a full queue drops
and counts), lines are written whole and flushed twice a second, and the file is closed cleanly on stop
(a reader ignores a cut last line, which only a kill can leave). ``max_bytes`` caps the file's size.
"""

from __future__ import annotations

import collections
import json
import logging
import math
import os
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from agent.fusion import Estimate, FixIntegrity, PoseFilter, Source

__all__ = ["Recorder", "ReplayResult", "read_recording", "replay", "replay_records"]

log = logging.getLogger(__name__)

_QUEUE_LIMIT = 20_000
_FLUSH_INTERVAL_S = 0.5


class Recorder:
    """Writes one recording. ``record_input`` is the fusion's observer; ``record_output`` is called for
    every pose written."""

    def __init__(self, path: Path, max_bytes: int = 200_000_000) -> None:
        self.path = path
        self.max_bytes = max_bytes
        self._queue: collections.deque[str] = collections.deque()
        self._cond = threading.Condition()
        self._closed = False
        self._thread: threading.Thread | None = None
        self._fp: Any = None
        self.written_bytes = 0
        self.records = 0
        self.dropped = 0
        self.full = False

    def start(self, parameters: dict[str, Any]) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._fp = open(self.path, "w", encoding="utf-8")  # noqa: SIM115  closed by close()
        self._put({"k": "header", "format": 1, "fusion": parameters})
        self._thread = threading.Thread(target=self._run, name="agent-recorder", daemon=True)
        self._thread.start()

    def record_input(self, record: dict[str, Any]) -> None:
        self._put(record)

    def record_output(self, estimate: Estimate, flags: int) -> None:
        self._put(
            {
                "k": "out",
                "v": estimate.version,
                "t": estimate.t_ns,
                "x": estimate.x_m,
                "y": estimate.y_m,
                "yaw": estimate.yaw_rad,
                "flags": flags,
            }
        )

    def _put(self, record: dict[str, Any]) -> None:
        line = json.dumps(record, separators=(",", ":")) + "\n"
        with self._cond:
            if self._closed or self.full:
                return
            if len(self._queue) >= _QUEUE_LIMIT:
                self.dropped += 1
                return
            self._queue.append(line)
            self.records += 1

    def _run(self) -> None:
        while True:
            with self._cond:
                if not self._queue and not self._closed:
                    self._cond.wait(_FLUSH_INTERVAL_S)
                lines = list(self._queue)
                self._queue.clear()
                closed = self._closed
            self._write(lines)
            if closed:
                return

    def _write(self, lines: list[str]) -> None:
        if self._fp is None or not lines:
            return
        data = "".join(lines)
        if self.written_bytes + len(data) > self.max_bytes:
            if not self.full:
                self.full = True
                log.warning("recording %s reached %d bytes: recording stops", self.path, self.max_bytes)
            return
        try:
            self._fp.write(data)
            self._fp.flush()
        except OSError as exc:
            log.warning("recording %s: %s; recording stops", self.path, exc)
            self.full = True
            return
        self.written_bytes += len(data)

    def close(self) -> None:
        """Write what is queued, flush, sync and close. Safe to call twice."""
        with self._cond:
            if self._closed:
                return
            self._closed = True
            self._cond.notify_all()
        if self._thread is not None:
            self._thread.join(5.0)
        if self._fp is not None:
            try:
                self._fp.flush()
                os.fsync(self._fp.fileno())
            except OSError as exc:
                log.warning("recording %s: %s", self.path, exc)
            self._fp.close()
            self._fp = None


def read_recording(path: Path) -> Iterator[dict[str, Any]]:
    """The records of a recording; a cut last line (the process was killed mid-write) is skipped."""
    with open(path, encoding="utf-8") as fp:
        for number, line in enumerate(fp, start=1):
            if not line.endswith("\n"):
                log.warning("%s: line %d is cut short (the recording was not closed): ignored", path, number)
                return
            yield json.loads(line)


@dataclass(frozen=True)
class ReplayResult:
    inputs: int
    outputs: int  # poses written during the recording that the replay reproduced
    max_position_difference_m: float
    max_yaw_difference_rad: float
    final: Estimate


def replay(path: Path) -> ReplayResult:
    """Run a fresh filter over a recording's inputs, in their order, and compare every pose written.

    ``path``: a JSON-lines recording of ``[record]``, or a flight recording (MCAP, ``[recorder]``: one
    file, or the name its files were written under, ``run.mcap`` for ``run-0001.mcap`` ...), whose
    ``/fusion/setup``, ``/fusion/input`` and ``/pose/fused`` channels hold the same records."""
    from agent.recording.reader import fusion_records, is_mcap

    records = list(fusion_records(path) if is_mcap(path) else read_recording(path))
    if not records or records[0].get("k") != "header":
        raise ValueError(f"{path} is not a recording (no header line)")
    return replay_records(records)


def replay_records(records: list[dict[str, Any]]) -> ReplayResult:
    """:func:`replay` on records already read (the header first)."""
    fusion = PoseFilter.from_parameters(records[0]["fusion"])
    outputs: dict[int, list[dict[str, Any]]] = collections.defaultdict(list)
    for r in records:
        if r["k"] == "out":
            outputs[int(r["v"])].append(r)
    worst_xy = worst_yaw = 0.0
    compared = 0

    def compare() -> None:
        nonlocal worst_xy, worst_yaw, compared
        if outputs.get(fusion.inputs):
            est = fusion.estimate()
            for out in outputs[fusion.inputs]:
                worst_xy = max(worst_xy, math.hypot(est.x_m - out["x"], est.y_m - out["y"]))
                worst_yaw = max(worst_yaw, abs(math.remainder(est.yaw_rad - out["yaw"], math.tau)))
                compared += 1

    compare()
    for r in records[1:]:
        kind = r["k"]
        if kind == "odometry":
            fusion.add_odometry(r["t0"], r["t1"], r["ds"], r["dyaw"], arrival_ns=r["a"])
        elif kind == "gyro":
            fusion.add_gyro(r["t"], r["w"], arrival_ns=r["a"])
        elif kind == "pose":
            fusion.add_pose(
                Source(r["src"]),
                r["t"],
                r["x"],
                r["y"],
                r["yaw"],
                r["cov"],
                arrival_ns=r["a"],
                relocalize=r["reloc"],
                integrity=FixIntegrity(bool(r["deg"]), float(r["pl"])) if "deg" in r else None,
            )
        else:
            continue
        compare()
    return ReplayResult(fusion.inputs, compared, worst_xy, worst_yaw, fusion.estimate())
