"""SLAM replayed from a flight recording (agent.recording.slam_replay): a live mapper that skipped scans (as
the live SLAM loop does when its queue overflows) is reproduced bit for bit by a replay that follows the
recorded decisions, and a replay that took every scan would not have been; a scan missing from the
recording is counted, not guessed."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from agent.config import MountConfig, SlamConfig
from agent.recording.messages import (
    CHANNELS,
    SlamFixSample,
    SlamScanSample,
    SlamStartSample,
    messages_for,
)
from agent.recording.reader import RecordedMessage, Recording
from agent.recording.slam_replay import SlamReplayResult, replay_slam, slam_setup
from agent.runtime.mapper import Pose, RbpfMapper
from agent.runtime.types import AbsoluteFix
from agent.slam.simlog import SimulatedRun, simulate_log
from drivers.samples import Scan
from drivers.sim.worldfile import load_world

OFFICE = Path(__file__).resolve().parents[2] / "examples" / "worlds" / "office.toml"
T0_NS = 5_000_000_000


@pytest.fixture(scope="module")
def drive() -> SimulatedRun:
    return simulate_log(load_world(OFFICE), 15.0, seed=3)


def _scans(run: SimulatedRun) -> list[Scan]:
    angles = run.log.geometry.angles_rad
    out = []
    for i, r in enumerate(run.log.records):
        ranges_mm = np.rint(np.asarray(r.ranges_m) * 1000.0).astype(np.int32)
        t_ns = T0_NS + round(r.t_s * 1e9)
        out.append(
            Scan(ranges_mm, float(angles[0]), float(angles[1] - angles[0]), 20, 5599, i, t_ns, i * 100)
        )
    return out


def live_recording(run: SimulatedRun, taken: set[int]) -> tuple[Recording, int]:
    """A live run of the SLAM loop's calls, recorded as the agent records them (through JSON): every scan on
    /laser/scan_raw, only the ``taken`` ones given to the mapper. Returns the recording and how many poses
    the live mapper gave."""
    messages: list[RecordedMessage] = []

    def record(kind: str, t_ns: int, sample: Any) -> None:
        for topic, message in messages_for(kind, sample):
            messages.append(RecordedMessage(topic, CHANNELS[topic], t_ns, json.loads(json.dumps(message))))

    truth = run.truth[0]

    def start_pose(t_ns: int) -> Pose | None:
        pose = (float(truth[0]), float(truth[1]), float(truth[2]))
        record("slam_start", t_ns, SlamStartSample(t_ns, pose))
        return pose

    config = SlamConfig(particles=8, seed=11, process=False)
    mapper = RbpfMapper(config, MountConfig(), start_pose)
    record("slam_setup", T0_NS, slam_setup(config, MountConfig(), mapper.name))
    fixes = list(run.fixes)
    poses = 0
    for i, scan in enumerate(_scans(run)):
        record("scan", scan.host_time_ns, scan)
        while fixes and T0_NS + round(fixes[0].t_s * 1e9) <= scan.host_time_ns:
            timed = fixes.pop(0)
            f = timed.fix
            fix = AbsoluteFix(T0_NS + round(timed.t_s * 1e9), f.x_m, f.y_m, f.yaw_rad, f.covariance)
            odom = tuple(float(v) for v in timed.odom_pose)
            mapper.add_fix(fix, odom)  # type: ignore[arg-type]
            record("slam_fix", fix.t_ns, SlamFixSample(fix, odom))  # type: ignore[arg-type]
        if i not in taken:
            continue  # the SLAM loop's queue dropped it
        odom_pose = tuple(float(v) for v in run.log.records[i].odom_pose)
        step = mapper.update(scan, odom_pose)  # type: ignore[arg-type]
        record("slam_scan", scan.host_time_ns, SlamScanSample(scan, odom_pose, step.kind))  # type: ignore[arg-type]
        if step.fix is not None:
            record("slam_pose", step.fix.t_ns, step.fix)
            poses += 1
    return Recording(Path("live.mcap"), messages, complete=True), poses


def _result(recording: Recording) -> SlamReplayResult:
    result = replay_slam([recording])
    assert isinstance(result, SlamReplayResult), result
    return result


def test_a_replay_following_the_recorded_decisions_reproduces_the_live_poses_exactly(
    drive: SimulatedRun,
) -> None:
    n = len(drive.log.records)
    taken = {i for i in range(n) if i % 4 != 2}  # a quarter of the scans dropped by a busy SLAM loop
    recording, live_poses = live_recording(drive, taken)
    result = _result(recording)
    given = [m for m in recording.messages if m.topic == "/slam/input" and m.data["k"] == "fix"]
    assert live_poses >= 5 and result.fixes == len(given) > 100
    assert result.scans == len(taken) and result.scans_missing == 0 and result.steps_differing == 0
    assert result.poses == result.poses_compared == live_poses and result.poses_unmatched == 0
    assert result.max_diff_m == 0.0 and result.max_yaw_diff_rad == 0.0


def test_taking_every_scan_instead_would_not_reproduce_the_live_run(drive: SimulatedRun) -> None:
    """Why the replay follows what the live loop took: with the dropped scans put back, the filter's
    updates fall at other scans and the poses move."""
    n = len(drive.log.records)
    recording, _ = live_recording(drive, {i for i in range(n) if i % 4 != 2})
    every, _ = live_recording(drive, set(range(n)))
    # The live run's recording, its scan decisions replaced by "every scan".
    inputs = [m for m in every.messages if m.topic == "/slam/input" and m.data["k"] == "scan"]
    others = [m for m in recording.messages if not (m.topic == "/slam/input" and m.data["k"] == "scan")]
    mixed = Recording(Path("mixed.mcap"), others + inputs, complete=True)
    result = _result(mixed)
    assert result.poses_unmatched > 0 or (result.max_diff_m or 0.0) > 0.0


def test_a_scan_missing_from_the_recording_is_counted_not_replayed(drive: SimulatedRun) -> None:
    recording, _ = live_recording(drive, set(range(len(drive.log.records))))
    raw = [m for m in recording.messages if m.topic == "/laser/scan_raw"]
    gone = raw[len(raw) // 2].data["host_time_ns"]
    kept = [
        m for m in recording.messages if not (m.topic == "/laser/scan_raw" and m.data["host_time_ns"] == gone)
    ]
    result = _result(Recording(Path("gap.mcap"), kept, complete=True))
    assert result.scans_missing == 1 and result.scans == len(raw) - 1


def test_a_recording_without_slam_inputs_says_why() -> None:
    result = replay_slam([Recording(Path("old.mcap"), [], complete=True)])
    assert isinstance(result, str) and "/slam/setup" in result
