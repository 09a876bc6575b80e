"""Snapshot-only flight recording on the whole agent: ``vlp-agent sim --record --snapshot S
--snapshot-only`` writes no continuous file, and writes the last S seconds, whole, on SIGUSR2 sent to the
whole process group (as ``systemctl kill`` does: the children must survive it) and when the injected laser
fault makes the laser go bad."""

from __future__ import annotations

import json
import signal
import time
from collections.abc import Callable
from pathlib import Path

from agent.recording.reader import read_recording
from agent.recording.snapshot import snapshot_files
from agent.recording.writer import recording_files
from tests.integration.sim_pty import SimOnPty

SPAN_S = 3.0


def test_snapshot_only_writes_on_sigusr2_and_on_a_fault(
    tmp_path: Path, sim_on_pty: Callable[..., SimOnPty]
) -> None:
    record = tmp_path / "rec" / "run.mcap"
    sim = sim_on_pty(
        "--seconds",
        "12",
        "--json",
        "--out",
        str(tmp_path / "out"),
        "--record",
        str(record),
        "--snapshot",
        str(SPAN_S),
        "--snapshot-only",
        "--fault",
        "laser@7+2",
        frames=60,
    )
    proc = sim.proc
    time.sleep(1.0)
    sim.signal_group(signal.SIGUSR2)
    signalled_ns = time.monotonic_ns()
    stdout, stderr = proc.communicate(timeout=90)
    assert proc.returncode == 0, stderr[-3000:]
    summary = json.loads(stdout.splitlines()[0])
    recording = summary["recording"]
    assert recording["files"] == [] and recording_files(record) == []  # snapshot-only: nothing else
    assert recording["snapshot_files"] == 2 and recording["record_dropped"] == 0
    assert recording["snapshot_ring_dropped"] > 0  # the ring did let the old go

    snaps = {read_recording(p).metadata["vlp_agent"]["snapshot_reason"]: p for p in snapshot_files(record)}
    assert len(snaps) == 2, snaps
    requested = read_recording(snaps["requested"])
    [fault_reason] = [r for r in snaps if r != "requested"]
    assert fault_reason.startswith("fault laser:"), fault_reason
    fault = read_recording(snaps[fault_reason])
    for snap in (requested, fault):
        assert snap.complete and snap.stopped_at is None
        topics = {m.topic for m in snap.messages}
        assert {"/fusion/setup", "/slam/setup", "/laser/scan", "/imu", "/pose", "/vlp/fix"} <= topics
        times = [m.log_time_ns for m in snap.messages if m.topic not in ("/fusion/setup", "/slam/setup")]
        assert (max(times) - min(times)) / 1e9 <= SPAN_S + 0.01
        assert (max(times) - min(times)) / 1e9 >= SPAN_S - 0.5  # the whole span, not a part
    # The commanded one ends about when it was asked for (the agent's clock is the test's: monotonic).
    newest_s = max(m.log_time_ns for m in requested.messages) / 1e9
    assert abs(newest_s - signalled_ns / 1e9) < 1.0
    # The fault one ends with the laser going bad.
    last_health = [m for m in fault.messages if m.topic == "/health"][-1]
    assert (last_health.data["device"], last_health.data["ok"]) == ("laser", False)
    slam = summary.get("slam") or {}
    assert slam.get("worker_restarts", 0) == 0  # SIGUSR2 to the group did not end the SLAM process
