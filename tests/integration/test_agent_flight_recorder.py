"""The flight recorder on the whole agent: ``vlp-agent sim --record`` for 15 s, driving to a goal the
simulated controller sent, with a laser fault in the middle. Every channel is there (the ones that depend on
what happened, when it happened), every message validates against the JSON schema embedded in the file
(the ``jsonschema`` package), the counts match what the agent itself counted (nothing dropped), and each
periodic channel runs at its device's rate (``agent.recording.check``: scans at the laser's 10 Hz, IMU
samples at 100 Hz, wheels at the servo loop's 50 Hz, a VLP result per camera frame and the frames at the
camera's 30 Hz), measured over the time the device was up by the recording's own stamps; and the fusion and
SLAM replayed from the recording reproduce every pose written. ``benchmarks/recording_check.py`` is the
same check on 60 s with tight tolerances."""

from __future__ import annotations

import json
import signal
import subprocess
import time
from pathlib import Path

import jsonschema

from agent.config import load_config
from agent.recording.check import Tolerance, check_channels, expected_rates
from agent.recording.messages import CHANNELS
from agent.recording.reader import read_recording
from agent.recording.slam_replay import SlamReplayResult, replay_slam
from agent.runtime.imu_loop import IMU_PERIOD_S
from agent.runtime.recorder import replay
from agent.shipped import DEFAULT_SIM_CONFIG
from tests.integration.test_agent_accuracy import REPO, vlp_agent

SECONDS = 15.0
# Beside a CPU hog a loop may miss periods and the renderer draws fewer frames: a rate within half to 1.15
# times its device's still shows a loop that stopped, or samples lost or doubled on the way; the benchmark
# holds the same rates to 10 %. Every VLP result is also checked against the frames the agent counted.
HOG_TOLERANCE = Tolerance(rate_low=0.5, rate_high=1.15, results_per_frame_low=0.8)


def test_a_sim_recording_has_every_channel_and_every_message_validates(tmp_path: Path) -> None:
    proc = subprocess.run(
        vlp_agent(
            "sim",
            "--seconds",
            str(SECONDS),
            "--json",
            "--out",
            str(tmp_path),
            "--goal",
            "7.5,2.5",
            "--fault",
            "laser@8+2",
            "--record",
            str(tmp_path / "rec" / "run.mcap"),
        ),
        capture_output=True,
        text=True,
        timeout=180,
        cwd=REPO,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads(proc.stdout)
    recorded = summary["recording"]
    assert recorded["record_dropped"] == 0 and recorded["record_paused"] == 0
    assert recorded["files"] == [str(tmp_path / "rec" / "run-0001.mcap")]
    recording = read_recording(Path(recorded["files"][0]))
    assert recording.complete and recording.stopped_at is None
    by_topic = recording.by_topic()

    # The schemas embedded in the file (each a valid JSON Schema) are the ones every message is checked
    # against, by an independent validator.
    validators = {}
    for name, schema in recording.schemas.items():
        cls = jsonschema.validators.validator_for(schema, default=jsonschema.Draft202012Validator)
        cls.check_schema(schema)
        validators[name] = cls(schema)
    for message in recording.messages:
        assert message.schema_name == CHANNELS[message.topic]
        errors = [e.message for e in validators[message.schema_name].iter_errors(message.data)]
        assert errors == [], (message.topic, errors[:3])

    # Every channel; each count what the agent counted (nothing dropped on the way); each periodic one at
    # its device's rate over the time the device was up (the laser less its fault), by the file's stamps.
    config = load_config(DEFAULT_SIM_CONFIG)
    assert config.sim is not None
    world = config.sim.world
    rates = expected_rates(
        laser_hz=world.laser.scan_rpm / 60.0,
        camera_hz=world.camera.frame_rate_hz,
        imu_hz=1.0 / IMU_PERIOD_S,
        servo_hz=config.control.loop_rate_hz,
    )
    checked = check_channels(recording.messages, summary, rates, HOG_TOLERANCE, config.recorder.map_period_s)
    assert checked["failures"] == [], checked
    channels = checked["channels"]
    assert {t for t, c in channels.items() if c["count"] and t in CHANNELS} >= set(CHANNELS) - {
        "/vlp/no_fix",
        "/rfid/tags",
    }
    assert channels["/laser/scan"]["up_s"] < channels["/imu"]["up_s"] - 1.5  # the fault's 2 s left out
    assert all(channels[t]["ratio"] > 0 for t in rates)
    counts = summary["counts"]

    def n(topic: str) -> int:
        return len(by_topic.get(topic, []))

    assert n("/commands/received") >= 1 and by_topic["/commands/received"][0].data["kind"] == "goal"
    # SLAM's poses, each handed to the fusion (fused or rejected) as it was recorded. How many there are
    # depends on how soon the SLAM process was up: 3 in 15 s beside a CPU hog (a hog run), ~13 idle.
    assert n("/slam/pose") == counts.get("slam_fused", 0) + counts.get("slam_rejected", 0) >= 1
    assert n("/map") >= 1
    health = [(m.data["device"], m.data["ok"]) for m in by_topic["/health"]]
    assert ("laser", False) in health and health.index(("laser", False)) < len(health) - 1
    fix = by_topic["/vlp/fix"][len(by_topic["/vlp/fix"]) // 2].data
    assert len(fix["leds"]) >= 2 and len(fix["covariance"]) == 9
    assert {"u_px", "v_px", "id"} <= set(fix["leds"][0])
    scan = by_topic["/laser/scan_raw"][0].data
    assert scan["device_time_ms"] is not None and scan["host_time_ns"] > 0

    # The fusion's inputs, in the order it took them from six threads: a fresh filter reproduces every
    # pose written, exactly.
    assert n("/fusion/setup") == 1
    result = replay(Path(recorded["files"][0]))
    assert result.outputs == summary["frames_out"] and result.inputs == n("/fusion/input")
    assert result.max_position_difference_m < 1e-9 and result.max_yaw_difference_rad < 1e-9

    # SLAM from the raw scans and the odometry they went with, taking the scans the live SLAM loop took (in
    # its child process): every filter update's pose again, exactly.
    slam = replay_slam([recording])
    assert isinstance(slam, SlamReplayResult), slam
    assert slam.scans == n("/slam/input") - sum(m.data["k"] != "scan" for m in by_topic["/slam/input"])
    assert slam.scans_missing == 0 and slam.steps_differing == 0 and slam.poses_unmatched == 0
    assert slam.poses_compared == n("/slam/pose") >= 1  # as many as the live run made (3 beside a hog)
    assert slam.max_diff_m == 0.0 and slam.max_yaw_diff_rad == 0.0


def test_a_recording_killed_mid_run_reads_up_to_its_last_chunk(tmp_path: Path) -> None:
    """SIGKILL while recording: the file has no footer, and reads whole up to within about one chunk
    (``chunk_s`` = 1 s, plus the writer's quarter-second pass) of the kill."""
    path = tmp_path / "rec" / "run.mcap"
    proc = subprocess.Popen(
        vlp_agent("sim", "--seconds", "60", "--json", "--out", str(tmp_path), "--record", str(path)),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        cwd=REPO,
    )
    try:
        first = tmp_path / "rec" / "run-0001.mcap"
        deadline = time.monotonic() + 120
        # Run until the recording holds a few seconds of chunks.
        while time.monotonic() < deadline and (not first.exists() or first.stat().st_size < 400_000):
            time.sleep(0.2)
        assert first.exists(), "no recording file appeared"
        # The size grows when a chunk is written: kill between two chunks, not right after one.
        time.sleep(0.6)
        killed_ns = time.monotonic_ns()
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait(30)
    recording = read_recording(first)
    assert not recording.complete
    topics = recording.by_topic()
    assert {"/laser/scan", "/imu", "/vlp/fix", "/pose"} <= set(topics)
    last_ns = max(m.log_time_ns for m in recording.messages)
    lost_s = (killed_ns - last_ns) * 1e-9
    print(f"killed: {len(recording.messages)} messages read, the last {lost_s:.2f} s before the kill lost")
    assert 0 <= lost_s < 2.5, lost_s
