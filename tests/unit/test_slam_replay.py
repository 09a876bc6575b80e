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
from agent.fusion import PoseFilter
from agent.recording.messages import (
    CHANNELS,
    SlamFixSample,
    SlamScanSample,
    SlamStartSample,
    TruthSample,
    messages_for,
)
from agent.recording.reader import RecordedMessage, Recording, read_recording
from agent.recording.slam_replay import SlamReplayResult, replay_slam, slam_setup
from agent.recording.writer import McapRecorder
from agent.runtime.mapper import Pose, RbpfMapper
from agent.runtime.types import AbsoluteFix
from agent.slam.simlog import SimulatedRun, simulate_log
from drivers.samples import Scan
from drivers.sim.worldfile import load_world
from tests.unit.test_recording import FakeClock, recorder

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


def live_recording(
    run: SimulatedRun,
    taken: set[int],
    writer: tuple[McapRecorder, FakeClock] | None = None,
    with_truth: bool = True,
    restart_at: int | None = None,
) -> tuple[Recording, int]:
    """A live run of the SLAM loop's calls, recorded as the agent records them (through JSON): every scan on
    /laser/scan_raw, only the ``taken`` ones given to the mapper. Returns the recording and how many poses
    the live mapper gave. ``writer``: also through the flight recorder into its file, a chunk every 0.2 s
    of a fake clock that a scan moves on by 0.1 s. ``with_truth``: the simulation's truth at each scan on
    /sim/truth, as ``vlp-agent sim`` records it. ``restart_at``: at that scan the mapper starts again with
    a new map, as the agent's does when its SLAM process died and a new one started."""
    messages: list[RecordedMessage] = []

    def record(kind: str, t_ns: int, sample: Any) -> None:
        if writer is not None:
            writer[0].record(kind, t_ns, sample)
        for topic, message in messages_for(kind, sample):
            messages.append(RecordedMessage(topic, CHANNELS[topic], t_ns, json.loads(json.dumps(message))))

    truth = run.truth[0]

    def start_pose(t_ns: int) -> Pose | None:
        pose = (float(truth[0]), float(truth[1]), float(truth[2]))
        record("slam_start", t_ns, SlamStartSample(t_ns, pose))
        return pose

    config = SlamConfig(particles=8, seed=11, process=False)
    mapper = RbpfMapper(config, MountConfig(), start_pose)
    record("fusion_setup", T0_NS, PoseFilter(np.zeros(3), np.eye(3), T0_NS).parameters)
    record("slam_setup", T0_NS, slam_setup(config, MountConfig(), mapper.name))
    fixes = list(run.fixes)
    poses = restarts = 0
    for i, scan in enumerate(_scans(run)):
        if i == restart_at:
            mapper = RbpfMapper(config, MountConfig(), start_pose)
            restarts += 1
        if writer is not None:
            writer[1].t_s += 0.1
            writer[0].pump()
        record("scan", scan.host_time_ns, scan)
        if with_truth:
            x, y, yaw = (float(v) for v in run.truth[i])
            record("sim_truth", scan.host_time_ns, TruthSample(scan.host_time_ns, x, y, yaw))
        while fixes and T0_NS + round(fixes[0].t_s * 1e9) <= scan.host_time_ns:
            timed = fixes.pop(0)
            f = timed.fix
            fix = AbsoluteFix(T0_NS + round(timed.t_s * 1e9), f.x_m, f.y_m, f.yaw_rad, f.covariance)
            odom = tuple(float(v) for v in timed.odom_pose)
            mapper.add_fix(fix, odom)  # type: ignore[arg-type]
            record("slam_fix", fix.t_ns, SlamFixSample(fix, odom, restarts))  # type: ignore[arg-type]
        if i not in taken:
            continue  # the SLAM loop's queue dropped it
        odom_pose = tuple(float(v) for v in run.log.records[i].odom_pose)
        step = mapper.update(scan, odom_pose)  # type: ignore[arg-type]
        record("slam_scan", scan.host_time_ns, SlamScanSample(scan, odom_pose, step.kind, restarts))  # type: ignore[arg-type]
        if step.fix is not None:
            record("slam_pose", step.fix.t_ns, step.fix)
            poses += 1
    if writer is not None:
        writer[0].close()
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


def test_a_slam_process_restart_is_followed_with_a_new_map(drive: SimulatedRun) -> None:
    """The live SLAM process died at a scan and a new one started a new map there: the replay starts a new
    mapper at the same input and matches every pose; one that went on with the old map would not."""
    n = len(drive.log.records)
    recording, live_poses = live_recording(drive, set(range(n)), restart_at=n // 2)
    result = _result(recording)
    assert result.restarts == 1 and result.poses_compared == live_poses >= 5
    assert result.poses_unmatched == 0 and result.max_diff_m == 0.0

    def without_restarts(m: RecordedMessage) -> RecordedMessage:
        return RecordedMessage(m.topic, m.schema_name, m.log_time_ns, {**m.data, "restarts": 0})

    ignored = Recording(Path("ignored.mcap"), [without_restarts(m) for m in recording.messages])
    went_on = _result(ignored)
    assert went_on.poses_unmatched > 0 or (went_on.max_diff_m or 0.0) > 0.0


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


def test_eval_slam_runs_on_a_flight_recording_and_says_where_a_cut_one_stopped(
    drive: SimulatedRun, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from agent.cli import main

    n = len(drive.log.records)
    taken = {i for i in range(n) if i % 4 != 2}
    rec, clock, _ = recorder(tmp_path / "rec", chunk_s=0.2)
    live_recording(drive, taken, (rec, clock))
    [path] = rec.files
    assert read_recording(path).complete

    assert main(["eval", "slam", "--log", str(path), "--json", "--out", str(tmp_path / "out")]) == 0
    whole = json.loads(capsys.readouterr().out)
    assert whole["format"] == "mcap" and whole["scans"] == len(taken) and whole["updates"] >= 5
    recording = whole["recording"]
    assert recording["complete"] and recording["stopped"] is None and recording["truth"] == "/sim/truth"
    assert recording["odometry"] == "slam_input" and recording["scans_left_out"] == n - len(taken)
    assert whole["fixes_used"] == 0  # fixes only with --vlp-fixes
    # The truth at the scans the filter took: its trajectory error (a map started at the true pose).
    assert 0.0 < whole["ate_m"] < 0.1 and whole["ate_max_m"] >= whole["ate_m"]
    assert (tmp_path / "out" / "map.yaml").exists()

    assert (
        main(["eval", "slam", "--log", str(path), "--json", "--vlp-fixes", "--out", str(tmp_path / "o2")])
        == 0
    )
    assert json.loads(capsys.readouterr().out)["fixes_used"] > 50

    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    assert main(["eval", "slam", "--log", str(cut), "--json", "--out", str(tmp_path / "o3")]) == 0
    captured = capsys.readouterr()
    part = json.loads(captured.out)
    stopped = part["recording"]["stopped"]
    assert not part["recording"]["complete"] and stopped["file"] == str(cut)
    assert 0 < stopped["at_byte"] <= len(data) // 2 and stopped["error"]
    assert 10 < part["scans"] < len(taken)
    assert f"readable up to byte {stopped['at_byte']}" in captured.err


def test_without_slam_inputs_the_log_takes_every_scan_with_the_fusions_wheel_odometry(
    drive: SimulatedRun,
) -> None:
    """SLAM off in the live run: every raw scan, the odometry integrated from /fusion/input's records."""
    from agent.recording.slam_log import slam_log_from_recording
    from agent.slam.pose import between

    messages = []
    scans = _scans(drive)
    for s in scans:
        for topic, message in messages_for("scan", s):
            messages.append(RecordedMessage(topic, CHANNELS[topic], s.host_time_ns, message))
    odometry = drive.log.odometry_poses()
    for k in range(1, len(scans)):
        (x0, y0, a0), (x1, y1, a1) = odometry[k - 1], odometry[k]
        record = {
            "k": "odometry",
            "t0": scans[k - 1].host_time_ns,
            "t1": scans[k].host_time_ns,
            "ds": float(np.hypot(x1 - x0, y1 - y0)),
            "dyaw": float(np.remainder(a1 - a0 + np.pi, 2 * np.pi) - np.pi),
            "a": scans[k].host_time_ns,
        }
        messages.append(RecordedMessage("/fusion/input", CHANNELS["/fusion/input"], record["a"], record))
    recorded = slam_log_from_recording([Recording(Path("r.mcap"), messages, complete=True)], "r.mcap")
    assert recorded.odometry == "fusion_input" and recorded.skipped == 0 and recorded.fixes == ()
    assert len(recorded.log) == len(scans)
    got = recorded.log.odometry_poses()
    # The same odometry, up to where it starts (the fusion's records are increments from zero).
    expected = between(odometry[0][None, :], odometry)
    assert np.max(np.hypot(*(got[:, :2] - expected[:, :2]).T)) < 0.01
    assert np.max(np.abs(np.remainder(got[:, 2] - expected[:, 2] + np.pi, 2 * np.pi) - np.pi)) < 1e-9


@pytest.mark.parametrize("damage", ["cut", "corrupt"])
def test_replay_and_eval_slam_on_a_damaged_recording_use_what_is_readable_and_say_where_it_stopped(
    drive: SimulatedRun, tmp_path: Path, capsys: pytest.CaptureFixture[str], damage: str
) -> None:
    """A file cut short (a kill, a full disk) or with a flipped byte in a chunk (a bad card): both commands
    run on the records before the damage, and report the file, the byte and the error."""
    from agent.cli import main

    n = len(drive.log.records)
    rec, clock, _ = recorder(tmp_path / "rec", chunk_s=0.2)
    live_recording(drive, set(range(n)), (rec, clock), with_truth=False)  # a robot's: no truth
    data = bytearray(rec.files[0].read_bytes())
    damaged_at = len(data) // 2  # the first byte that is not as written
    if damage == "cut":
        data = data[:damaged_at]
    else:
        data[damaged_at] ^= 0xFF
    bad = tmp_path / f"{damage}.mcap"
    bad.write_bytes(bytes(data))

    assert main(["replay", str(bad), "--json"]) == 0
    replayed = json.loads(capsys.readouterr().out)
    stopped = replayed["stopped"]
    assert not replayed["complete"] and stopped["file"] == str(bad) and stopped["error"]
    assert 0 < stopped["at_byte"] <= damaged_at
    slam = replayed["slam"]
    assert 10 < slam["scans"] < n and slam["scans_missing"] == 0 and slam["steps_differing"] == 0
    # The last scan read may have lost its recorded pose to the damage: at most that one unmatched.
    assert slam["poses_compared"] >= 2 and slam["poses_unmatched"] <= 1
    assert replayed["max_slam_diff_m"] == 0.0

    assert main(["eval", "slam", "--log", str(bad), "--json", "--out", str(tmp_path / "out")]) == 0
    captured = capsys.readouterr()
    evaluated = json.loads(captured.out)
    assert evaluated["recording"]["stopped"] == stopped and evaluated["scans"] == slam["scans"]
    assert evaluated["recording"]["truth"] is None and "ate_m" not in evaluated
    assert f"{bad} is readable up to byte {stopped['at_byte']}" in captured.err
