"""Record and replay: a recording of a run (``vlp-agent sim --record-fusion``) holds every input the
fusion took in the order it took them, and a fresh filter replaying it reproduces every pose the agent
wrote, exactly, although the live inputs came from six threads."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

from agent.runtime.recorder import read_recording, replay
from tests.integration.test_agent_accuracy import REPO, vlp_agent


def test_a_replayed_recording_reproduces_every_pose_written(tmp_path: Path) -> None:
    recording = tmp_path / "run.jsonl"
    proc = subprocess.run(
        vlp_agent(
            "sim", "--seconds", "8", "--json", "--out", str(tmp_path), "--record-fusion", str(recording)
        ),
        capture_output=True,
        text=True,
        timeout=90,
        cwd=REPO,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads(proc.stdout)
    records = list(read_recording(recording))
    kinds = {r["k"] for r in records}
    assert records[0]["k"] == "header" and {"odometry", "gyro", "pose", "out"} <= kinds
    assert {r["src"] for r in records if r["k"] == "pose"} >= {"vlp"}
    result = replay(recording)
    assert result.outputs == summary["frames_out"] > 100
    assert result.max_position_difference_m < 1e-9
    assert result.max_yaw_difference_rad < 1e-9
    assert result.inputs == sum(r["k"] in ("odometry", "gyro", "pose") for r in records)


def test_a_recording_cut_by_a_kill_still_replays(tmp_path: Path) -> None:
    recording = tmp_path / "run.jsonl"
    subprocess.run(
        vlp_agent(
            "sim", "--seconds", "3", "--json", "--out", str(tmp_path), "--record-fusion", str(recording)
        ),
        capture_output=True,
        timeout=90,
        cwd=REPO,
        check=True,
    )
    data = recording.read_bytes()
    cut = tmp_path / "cut.jsonl"
    cut.write_bytes(data[: len(data) - 40])  # the last line half written, as a SIGKILL could leave it
    result = replay(cut)
    assert result.outputs > 0 and result.max_position_difference_m < 1e-9
