"""The flight recorder on the whole agent: ``vlp-agent sim --record`` for 15 s, driving to a goal the
simulated controller sent, with a laser fault in the middle. Every channel is there (the ones that depend on
what happened, when it happened), every message validates against the JSON schema embedded in the file,
and the counts match what the agent itself counted (nothing dropped): scans at ~10 Hz, a fix per camera
frame."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

from agent.recording.messages import CHANNELS
from agent.recording.reader import read_recording
from tests.integration.test_agent_accuracy import REPO, vlp_agent
from tests.unit.test_recording import schema_errors

SECONDS = 15.0


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

    # The schemas embedded in the file are the ones every message is checked against.
    for message in recording.messages:
        assert message.schema_name == CHANNELS[message.topic]
        errors = schema_errors(message.data, recording.schemas[message.schema_name])
        assert errors == [], (message.topic, errors[:3])

    counts = summary["counts"]
    optional = {"/vlp/no_fix": summary["no_fix"], "/rfid/tags": counts.get("tag_reads", 0)}
    expected = {topic for topic in CHANNELS if topic not in optional} | {t for t, n in optional.items() if n}
    assert set(by_topic) == expected, set(CHANNELS) - set(by_topic)

    def n(topic: str) -> int:
        return len(by_topic.get(topic, []))

    # Exactly what the agent counted: nothing dropped on the way.
    assert n("/laser/scan") == n("/laser/scan_raw") == counts["scans"]
    assert n("/wheels/state") == counts["wheel_reads"]
    assert n("/imu") == counts["imu_samples"]
    assert n("/vlp/fix") == summary["fixes"] and n("/vlp/no_fix") == summary["no_fix"]
    assert n("/rfid/tags") == counts.get("tag_reads", 0)
    assert n("/pose") == n("/pose/fused") == n("/tf") == summary["frames_out"]
    assert n("/commands/received") >= 1 and by_topic["/commands/received"][0].data["kind"] == "goal"
    assert n("/goals/status") == summary["goals"]["statuses_decoded"]
    # Rates: the URG's 10 Hz less the 2 s without the laser; a fix for nearly every 30 Hz camera frame.
    assert 0.7 * 10 * (SECONDS - 2) <= counts["scans"] <= 1.1 * 10 * SECONDS
    assert 0.5 * 30 * SECONDS <= n("/vlp/fix") + n("/vlp/no_fix") <= summary["camera_frames"]
    assert n("/map") >= 2 and n("/slam/pose") >= 5
    health = [(m.data["device"], m.data["ok"]) for m in by_topic["/health"]]
    assert ("laser", False) in health and health.index(("laser", False)) < len(health) - 1
    fix = by_topic["/vlp/fix"][len(by_topic["/vlp/fix"]) // 2].data
    assert len(fix["leds"]) >= 2 and len(fix["covariance"]) == 9
    assert {"u_px", "v_px", "id"} <= set(fix["leds"][0])
    scan = by_topic["/laser/scan_raw"][0].data
    assert scan["device_time_ms"] is not None and scan["host_time_ns"] > 0
