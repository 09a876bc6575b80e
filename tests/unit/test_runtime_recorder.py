"""The fusion recorder and its replay, on a seeded synthetic run (no devices)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from agent.fusion import PoseFilter
from agent.runtime.recorder import Recorder, read_recording, replay
from tests.unit.test_fusion import Run


def recorded_run(path: Path, max_bytes: int = 10_000_000) -> tuple[Recorder, PoseFilter, int]:
    recorder = Recorder(path, max_bytes)
    fusion = PoseFilter(np.zeros(3), np.eye(3) * 1e-4, 0, observer=recorder.record_input)
    recorder.start(fusion.parameters)
    run = Run(seed=9)
    outputs = 0
    for k, event in enumerate(run.events(4.0)):
        run.feed(fusion, [event])
        if k % 7 == 0:
            recorder.record_output(fusion.estimate(), 0x0F)
            outputs += 1
    recorder.close()
    recorder.close()  # twice is fine
    return recorder, fusion, outputs


def test_replay_reproduces_the_outputs_and_the_final_state(tmp_path: Path) -> None:
    path = tmp_path / "run.jsonl"
    recorder, fusion, outputs = recorded_run(path)
    assert recorder.dropped == 0 and not recorder.full
    result = replay(path)
    assert result.outputs == outputs
    assert result.max_position_difference_m == 0.0 and result.max_yaw_difference_rad == 0.0
    assert result.inputs == fusion.inputs
    final = fusion.estimate()
    assert (result.final.x_m, result.final.y_m, result.final.yaw_rad) == (final.x_m, final.y_m, final.yaw_rad)
    np.testing.assert_array_equal(result.final.covariance, final.covariance)


def test_the_size_cap_stops_recording_with_whole_lines(tmp_path: Path) -> None:
    path = tmp_path / "run.jsonl"
    recorder, _, _ = recorded_run(path, max_bytes=20_000)
    assert recorder.full
    data = path.read_text()
    assert len(data) <= 20_000 and data.endswith("\n")
    assert all(json.loads(line) for line in data.splitlines())
    assert next(iter(read_recording(path)))["k"] == "header"
