"""The flight recorder (agent.recording): every kind of sample becomes messages that validate against their
channel's JSON schema; rotation by size and by time, the total cap, the free-disk guard and a full queue,
on a fake clock and a fake free-space function (no thread); a file cut anywhere reads up to its last whole
record; no image channel exists or can be configured."""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from agent.config import MountConfig, RecorderConfig, SlamConfig, SlamMode, parse_config
from agent.fusion import Estimate, PoseFilter
from agent.recording.messages import (
    CHANNELS,
    KINDS,
    CommandSample,
    FusedSample,
    GoalSample,
    HealthSample,
    SlamFixSample,
    SlamScanSample,
    SlamStartSample,
    TruthSample,
    WheelCommandSample,
    fusion_record_time,
    messages_for,
    occupancy_cells,
)
from agent.recording.reader import RecordingFormatError, read_recording
from agent.recording.schemas import SCHEMAS
from agent.recording.slam_replay import scan_from_message, slam_config_from_json, slam_setup
from agent.recording.writer import McapRecorder, recording_files
from agent.runtime.recorder import replay
from agent.runtime.types import AbsoluteFix, NoFix
from agent.slam.render import OccupancyImage
from agent.vlp.model import LedObservation
from drivers.errors import ConfigError
from drivers.samples import ImuSample, Scan, TagRead, WheelState
from firmware_protocol.command_frame import GoalCommand, GoalReason, GoalState, GoalStatus, VelocityCommand

OFFICE = Path(__file__).resolve().parents[2] / "examples" / "worlds" / "office.toml"

_TYPES: dict[str, Any] = {
    "object": dict,
    "array": list,
    "string": str,
    "boolean": bool,
    "null": type(None),
}


def schema_errors(value: Any, schema: dict[str, Any], where: str = "$") -> list[str]:
    """The ways ``value`` breaks ``schema``: the JSON Schema subset the recording's schemas use (type,
    properties, required, items, minimum, maximum); no jsonschema package in the test extras."""
    errors: list[str] = []
    types = schema.get("type")
    if types is not None:
        names = types if isinstance(types, list) else [types]
        ok = False
        for name in names:
            if name == "number":
                ok |= isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
            elif name == "integer":
                ok |= isinstance(value, int) and not isinstance(value, bool)
            else:
                ok |= isinstance(value, _TYPES[name]) and not (name != "boolean" and isinstance(value, bool))
        if not ok:
            return [f"{where}: {value!r} is not {names}"]
    if "minimum" in schema and isinstance(value, int | float) and value < schema["minimum"]:
        errors.append(f"{where}: {value} < {schema['minimum']}")
    if "maximum" in schema and isinstance(value, int | float) and value > schema["maximum"]:
        errors.append(f"{where}: {value} > {schema['maximum']}")
    if isinstance(value, dict):
        for key in schema.get("required", ()):
            if key not in value:
                errors.append(f"{where}: {key!r} missing")
        for key, sub in schema.get("properties", {}).items():
            if key in value:
                errors += schema_errors(value[key], sub, f"{where}.{key}")
    if isinstance(value, list) and "items" in schema:
        for i, item in enumerate(value):
            errors += schema_errors(item, schema["items"], f"{where}[{i}]")
    return errors


def scan(i: int, t_ns: int) -> Scan:
    ranges = (np.arange(682, dtype=np.int32) * 7 + i) % 6000
    ranges[::50] = 3  # an error code
    return Scan(ranges, -2.09, 0.00614, 20, 5600, i, t_ns, 1000 + i * 100)


def one_of_each(t_ns: int) -> list[tuple[str, Any]]:
    led = LedObservation(
        3, (401.5, 288.25), 11.0, "full", 0.1, "A7", 0.9, "A7", 0.95, 2000.0, 0.5, 380, map_index=2, used=True
    )
    fix = AbsoluteFix(
        t_ns,
        1.0,
        2.0,
        0.5,
        np.eye(3) * 1e-4,
        False,
        {"ids": ("A7", "B2"), "residual_rms": 0.8, "flags": (), "leds": (led, led)},
    )
    estimate = Estimate(t_ns, 1.0, 2.0, 0.5, 0.1, 0.0, np.eye(5) * 1e-4, 0, 0.2, 17)
    pixels = np.full((40, 60), 205, dtype=np.uint8)
    pixels[:10] = 254
    pixels[10:12] = 0
    return [
        ("scan", scan(1, t_ns)),
        ("wheels", WheelState((0.1, 0.2), (1.0, 1.1), t_ns)),
        ("wheel_command", WheelCommandSample(t_ns, 1.0, -1.0, 0.0, -0.5)),
        ("imu", ImuSample((0.0, 0.1, 9.8), (0.0, 0.0, 0.3), 31.0, t_ns)),
        ("tag", TagRead("E200", t_ns, "m6e", rssi_dbm=-63.0, antenna=1)),
        ("vlp_fix", fix),
        ("no_fix", NoFix(t_ns, "fewer than two LEDs")),
        ("pose", FusedSample(estimate, 0x0F)),
        ("slam_pose", AbsoluteFix(t_ns, 1.0, 2.0, 0.5, np.eye(3) * 1e-3)),
        ("map", (t_ns, OccupancyImage(pixels, 0.05, (-1.0, -2.0, 0.0)))),
        ("command", CommandSample(t_ns, GoalCommand(4, 9, 7.5, 2.5, None))),
        ("command", CommandSample(t_ns, VelocityCommand(5, 0.1, 0.2, 0.5))),
        ("goal_status", GoalSample(t_ns, GoalStatus(1, 4, 9, GoalState.ACTIVE, GoalReason.NONE, 3.2))),
        ("health", HealthSample(t_ns, "laser", False, "lost: gone")),
        ("fusion_setup", PoseFilter(np.zeros(3), np.eye(3), t_ns).parameters),
        ("fusion_input", {"k": "gyro", "t": t_ns, "w": 0.1, "a": t_ns + 5}),
        ("slam_setup", slam_setup(SlamConfig(map_dir=Path("/var/lib/maps")), MountConfig(x_m=0.1), "slam")),
        ("slam_start", SlamStartSample(t_ns, (1.0, 2.0, 0.5))),
        ("slam_start", SlamStartSample(t_ns, None)),
        ("slam_fix", SlamFixSample(AbsoluteFix(t_ns, 1.0, 2.0, None, np.eye(2) * 1e-4), (0.1, 0.2, 0.3))),
        ("slam_scan", SlamScanSample(scan(2, t_ns), (0.1, 0.2, 0.3), "updated")),
        ("sim_truth", TruthSample(t_ns, 1.0, 2.0, 0.5)),
    ]


def test_every_kind_gives_messages_that_validate_against_their_schemas() -> None:
    seen = set()
    for kind, sample in one_of_each(1_500_000_000):
        for topic, message in messages_for(kind, sample):
            schema = SCHEMAS[CHANNELS[topic]]
            assert schema_errors(message, schema) == [], (topic, message)
            json.dumps(message, allow_nan=False)
            seen.add(topic)
    assert seen == set(CHANNELS)
    assert set(KINDS) == {kind for kind, _ in one_of_each(0)}


def test_the_slam_setup_and_a_raw_scan_read_back_as_they_were() -> None:
    config = SlamConfig(
        mode=SlamMode.LOCALIZATION,
        map=Path("/maps/office.yaml"),
        particles=17,
        laser_mount=MountConfig(x_m=0.12, yaw_rad=math.pi),
        sigma_yaw_rad=math.radians(1.5),
        seed=42,
    )
    setup = slam_setup(config, MountConfig(x_m=0.12, yaw_rad=math.pi), "mcl")
    [(_, message)] = messages_for("slam_setup", setup)
    again = json.loads(json.dumps(message))
    assert slam_config_from_json(again["config"]) == config
    assert MountConfig(**again["mount"]) == MountConfig(x_m=0.12, yaw_rad=math.pi)
    raw = scan(5, 123_456_789)
    [_, (_, data)] = messages_for("scan", raw)
    back = scan_from_message(json.loads(json.dumps(data)))
    assert np.array_equal(back.ranges_mm, raw.ranges_mm) and back.ranges_mm.dtype == raw.ranges_mm.dtype
    assert (back.angle_min_rad, back.angle_increment_rad, back.sequence, back.host_time_ns) == (
        raw.angle_min_rad,
        raw.angle_increment_rad,
        raw.sequence,
        raw.host_time_ns,
    )
    assert back.device_time_ms == raw.device_time_ms


def test_the_validator_catches_a_wrong_message() -> None:
    schema = SCHEMAS["vlp_agent.ImuSample"]
    good = messages_for("imu", ImuSample((0.0, 0.0, 9.8), (0.0, 0.0, 0.0), 30.0, 5))[0][1]
    assert schema_errors(good, schema) == []
    assert schema_errors({**good, "temperature_c": "hot"}, schema)
    assert schema_errors({k: v for k, v in good.items() if k != "gyro_radps"}, schema)


def test_foxglove_messages_carry_the_foxglove_field_names() -> None:
    t_ns = 3_250_000_001
    (laser, message), _raw = messages_for("scan", scan(0, t_ns))
    assert laser == "/laser/scan"
    fields = {"timestamp", "frame_id", "pose", "start_angle", "end_angle", "ranges", "intensities"}
    assert set(message) == fields
    assert message["timestamp"] == {"sec": 3, "nsec": 250_000_001}
    assert message["ranges"][0] == 0.0  # an error code: no range
    assert message["end_angle"] == pytest.approx(-2.09 + 681 * 0.00614)
    pose = dict(messages_for("pose", one_of_each(t_ns)[7][1]))
    q = pose["/pose"]["pose"]["orientation"]
    assert math.atan2(2 * q["w"] * q["z"], 1 - 2 * q["z"] ** 2) == pytest.approx(0.5)
    assert pose["/tf"]["transforms"][0]["child_frame_id"] == "base_link"


def test_a_map_snapshot_is_an_int8_occupancy_grid_with_the_lowest_row_first() -> None:
    pixels = np.array([[0, 0, 0], [254, 205, 254]], dtype=np.uint8)  # row 0 (top) occupied
    cells = occupancy_cells(pixels)
    assert cells.dtype == np.int8
    np.testing.assert_array_equal(cells, [[0, -1, 0], [100, 100, 100]])


def test_no_image_channel_exists_and_none_can_be_configured() -> None:
    assert not any("image" in name.lower() for name in SCHEMAS)
    assert not any("image" in topic or "camera" in topic for topic in CHANNELS)
    for topic in ("/camera/image", "/camera", "/image_raw"):
        with pytest.raises(ConfigError) as err:
            parse_config(f'[sim]\nworld = "{OFFICE}"\n[recorder]\nchannels = ["/pose", "{topic}"]\n')
        assert err.value.key == "recorder.channels"
        assert "camera images are never recorded" in err.value.reason


def test_the_recorder_config_keys() -> None:
    config = parse_config(
        f'[sim]\nworld = "{OFFICE}"\n[recorder]\npath = "/tmp/x/run.mcap"\n'
        'channels = ["/pose", "/laser/scan"]\n'
        "chunk_s = 0.5\nfile_mb = 10\nfile_s = 60\ntotal_mb = 100\nmin_free_mb = 50\nqueue_size = 1000\n"
        "map_period_s = 0\n"
    )
    r = config.recorder
    assert (r.path, r.channels) == (Path("/tmp/x/run.mcap"), ("/pose", "/laser/scan"))
    assert (r.chunk_s, r.file_mb, r.file_s, r.total_mb, r.min_free_mb, r.queue_size, r.map_period_s) == (
        0.5,
        10,
        60,
        100,
        50,
        1000,
        0,
    )
    assert parse_config(f'[sim]\nworld = "{OFFICE}"\n').recorder.channels == tuple(CHANNELS)
    for text, key in (
        ("file_mb = 200\ntotal_mb = 100", "recorder.file_mb"),
        ("chunk_s = 0", "recorder.chunk_s"),
        ("queue_size = 5", "recorder.queue_size"),
        ("channels = []", "recorder.channels"),
        ("rotate = 1", "recorder.rotate"),
    ):
        with pytest.raises(ConfigError) as err:
            parse_config(f'[sim]\nworld = "{OFFICE}"\n[recorder]\n{text}\n')
        assert err.value.key == key, err.value


class FakeClock:
    def __init__(self) -> None:
        self.t_s = 100.0

    def __call__(self) -> float:
        return self.t_s


class FakeDisk:
    def __init__(self, free_mb: float) -> None:
        self.free_mb = free_mb

    def __call__(self, folder: Path) -> int:
        return int(self.free_mb * 1e6)


def recorder(tmp_path: Path, **settings: Any) -> tuple[McapRecorder, FakeClock, FakeDisk]:
    clock, disk = FakeClock(), FakeDisk(settings.pop("free_mb", 10_000.0))
    config = RecorderConfig(path=tmp_path / "run.mcap", **settings)
    return McapRecorder(config, free_space=disk, clock_s=clock), clock, disk


def feed_scans(rec: McapRecorder, clock: FakeClock, first: int, n: int, dt_s: float = 0.1) -> None:
    """``n`` scans, one every ``dt_s`` on the fake clock, with a writer pass after each."""
    for i in range(first, first + n):
        clock.t_s += dt_s
        rec.record("scan", int(clock.t_s * 1e9), scan(i, int(clock.t_s * 1e9)))
        rec.pump()


def sequences(path: Path) -> list[int]:
    return [m.data["sequence"] for m in read_recording(path).messages if m.topic == "/laser/scan_raw"]


def test_rotation_by_size_loses_nothing_at_the_splits(tmp_path: Path) -> None:
    rec, clock, _ = recorder(tmp_path, file_mb=0.02, total_mb=1000, chunk_s=0.2)
    feed_scans(rec, clock, 0, 120)
    rec.close()
    files = [p for _, p in recording_files(tmp_path / "run.mcap")]
    assert len(files) >= 3 and files == rec.files
    got: list[int] = []
    for path in files:
        recording = read_recording(path)
        assert recording.complete and recording.stopped_at is None
        assert recording.metadata["vlp_agent"]["format_version"] == "1"
        got += sequences(path)
    assert got == list(range(120))
    # A file is closed at the first chunk past the size: at most one chunk (~0.2 s of scans) over.
    assert all(p.stat().st_size < 0.02e6 + 20_000 for p in files)


def test_rotation_by_duration(tmp_path: Path) -> None:
    rec, clock, _ = recorder(tmp_path, file_s=2.0, chunk_s=0.5)
    feed_scans(rec, clock, 0, 100)  # 10 s
    rec.close()
    got = [s for p in rec.files for s in sequences(p)]
    assert got == list(range(100))
    # A file is closed at the first chunk boundary at or past file_s: it spans file_s .. file_s + chunk_s.
    spans_s = []
    for path in rec.files:
        times = [m.log_time_ns for m in read_recording(path).messages]
        spans_s.append((max(times) - min(times)) * 1e-9)
    assert len(rec.files) >= 4
    assert all(2.0 - 0.1 - 1e-6 <= span <= 2.5 for span in spans_s[:-1]), spans_s


def test_the_total_cap_deletes_the_oldest_files_and_says_so(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING, logger="agent.recording.writer")
    rec, clock, _ = recorder(tmp_path, file_mb=0.02, total_mb=0.08, chunk_s=0.2)
    feed_scans(rec, clock, 0, 400)
    rec.close()
    left = [p for _, p in recording_files(tmp_path / "run.mcap")]
    assert rec.deleted and not any(p.exists() for p in rec.deleted)
    assert left == [p for p in rec.files if p not in rec.deleted]
    assert rec.deleted == rec.files[: len(rec.deleted)]  # the oldest ones
    assert sum(p.stat().st_size for p in left) <= 0.08e6 + 20_000
    assert sequences(left[-1])[-1] == 399  # the newest data kept
    assert any("deleted" in r.getMessage() and "0.08 MB" in r.getMessage() for r in caplog.records)
    assert rec.counters()["record_files_deleted"] == len(rec.deleted)


def test_a_restart_continues_the_numbering_and_the_cap_counts_the_old_files(tmp_path: Path) -> None:
    first, clock, _ = recorder(tmp_path, file_mb=0.02, total_mb=0.1, chunk_s=0.2)
    feed_scans(first, clock, 0, 60)
    first.close()
    survivors = [p for _, p in recording_files(tmp_path / "run.mcap")]
    second, clock, _ = recorder(tmp_path, file_mb=0.02, total_mb=0.1, chunk_s=0.2)
    feed_scans(second, clock, 60, 60)
    second.close()
    names = [p.name for p in second.files]
    assert names[0] == f"run-{len(first.files) + 1:04d}.mcap"
    assert second.deleted and second.deleted[0] == survivors[0]  # the cap counts the files left before


def test_the_disk_guard_pauses_and_resumes_and_the_agent_side_never_fails(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING, logger="agent.recording.writer")
    rec, clock, disk = recorder(tmp_path, min_free_mb=100, chunk_s=0.5)
    feed_scans(rec, clock, 0, 20)
    disk.free_mb = 50  # nearly full: the next chunk closes the file and the recorder pauses
    feed_scans(rec, clock, 20, 30)
    assert rec.paused and rec.counters()["record_paused"] == 1
    assert rec.counts["record_dropped_disk"] > 0
    assert any("less than 100 MB free" in r.getMessage() for r in caplog.records)
    assert read_recording(rec.files[0]).complete  # closed cleanly when pausing
    disk.free_mb = 500
    feed_scans(rec, clock, 50, 80)  # rechecked every 5 s of the clock
    rec.close()
    assert not rec.paused and len(rec.files) == 2
    assert any("recording again" in r.getMessage() for r in caplog.records)
    got = [s for p in rec.files for s in sequences(p)]
    dropped = rec.counts["record_dropped_disk"] // 2  # two channels per scan
    assert len(got) + dropped == 130 and got[-1] == 129


def test_a_full_queue_drops_and_counts_without_blocking(tmp_path: Path) -> None:
    rec, _, _ = recorder(tmp_path, queue_size=100)
    for i in range(250):  # no writer pass: the queue fills
        rec.record("imu", i, ImuSample((0.0, 0.0, 9.8), (0.0, 0.0, 0.0), 30.0, i))
    assert rec.dropped == 150 and rec.counters()["record_dropped"] == 150
    rec.close()
    assert len(read_recording(rec.files[0]).messages) == 100


def test_only_the_configured_channels_are_written(tmp_path: Path) -> None:
    rec, clock, _ = recorder(tmp_path, channels=("/laser/scan",))
    feed_scans(rec, clock, 0, 5)
    rec.close()
    assert {m.topic for m in read_recording(rec.files[0]).messages} == {"/laser/scan"}


def test_the_writer_thread_writes_chunks_while_recording(tmp_path: Path) -> None:
    rec = McapRecorder(RecorderConfig(path=tmp_path / "run.mcap", chunk_s=0.1))
    rec.start()
    try:
        for i in range(5):
            rec.record("imu", i, ImuSample((0.0, 0.0, 9.8), (0.0, 0.0, 0.0), 30.0, i))
        deadline = 50
        while deadline and not (rec.files and read_recording(rec.files[0]).messages):
            deadline -= 1
            clock_wait(0.05)
        # Readable while still open: the chunks closed so far, no footer yet.
        live = read_recording(rec.files[0])
        assert len(live.messages) == 5 and not live.complete
    finally:
        rec.close()
    assert read_recording(rec.files[0]).complete


def clock_wait(seconds: float) -> None:
    import time

    time.sleep(seconds)


def test_a_cut_file_reads_up_to_its_last_whole_record(tmp_path: Path) -> None:
    rec, clock, _ = recorder(tmp_path, chunk_s=0.3)
    feed_scans(rec, clock, 0, 60)
    rec.close()
    data = rec.files[0].read_bytes()
    full = sequences(rec.files[0])
    cut_path = tmp_path / "cut.mcap"
    previous = -1
    for cut in range(0, len(data), max(len(data) // 97, 1)):
        cut_path.write_bytes(data[:cut])
        recording = read_recording(cut_path)
        got = [m.data["sequence"] for m in recording.messages if m.topic == "/laser/scan_raw"]
        assert got == full[: len(got)]  # a prefix, never garbage
        assert len(got) >= previous  # more bytes never read less
        previous = len(got)
        assert not recording.complete and recording.stopped_at is not None and recording.stopped_at <= cut
        assert recording.error
    # Cut in the summary (after the last chunk), every message is there.
    cut_path.write_bytes(data[: len(data) - 30])
    assert len([m for m in read_recording(cut_path).messages if m.topic == "/laser/scan_raw"]) == 60


def test_a_corrupt_chunk_ends_the_reading_there(tmp_path: Path) -> None:
    rec, clock, _ = recorder(tmp_path, chunk_s=0.3)
    feed_scans(rec, clock, 0, 60)
    rec.close()
    data = bytearray(rec.files[0].read_bytes())
    data[len(data) // 2] ^= 0xFF
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    recording = read_recording(bad)
    got = [m.data["sequence"] for m in recording.messages if m.topic == "/laser/scan_raw"]
    assert got == list(range(len(got))) and len(got) < 60
    assert recording.stopped_at is not None and recording.error


def test_a_recording_from_a_newer_format_is_a_clear_error(tmp_path: Path) -> None:
    from mcap.writer import Writer

    path = tmp_path / "future.mcap"
    with open(path, "wb") as fp:
        writer = Writer(fp)
        writer.start(profile="vlp_agent", library="vlp-agent recorder 2")
        writer.add_metadata("vlp_agent", {"format_version": "2"})
        writer.finish()  # type: ignore[no-untyped-call]
    with pytest.raises(RecordingFormatError, match="format version 2"):
        read_recording(path)


def recorded_fusion_run(tmp_path: Path, **settings: Any) -> tuple[McapRecorder, PoseFilter, int]:
    """A seeded synthetic fusion run (tests.unit.test_fusion.Run) into a flight recording, as the agent
    wires it: the filter's observer -> /fusion/input, its setup first, every 7th estimate written."""
    from tests.unit.test_fusion import Run

    rec, clock, _ = recorder(tmp_path, **settings)
    fusion = PoseFilter(
        np.zeros(3),
        np.eye(3) * 1e-4,
        0,
        observer=lambda r: rec.record("fusion_input", fusion_record_time(r), r),
    )
    rec.record("fusion_setup", 0, fusion.parameters)
    run = Run(seed=9)
    outputs = 0
    for k, event in enumerate(run.events(4.0)):
        run.feed(fusion, [event])
        if k % 7 == 0:
            estimate = fusion.estimate()
            rec.record("pose", estimate.t_ns, FusedSample(estimate, 0x0F))
            outputs += 1
        if k % 20 == 0:
            clock.t_s += 0.1
            rec.pump()
    rec.close()
    return rec, fusion, outputs


def test_the_fusion_replays_bit_for_bit_from_a_flight_recording(tmp_path: Path) -> None:
    rec, fusion, outputs = recorded_fusion_run(tmp_path, chunk_s=0.5)
    assert len(rec.files) == 1 and rec.dropped == 0
    result = replay(rec.files[0])
    assert result.outputs == outputs > 50
    assert result.max_position_difference_m == 0.0 and result.max_yaw_difference_rad == 0.0
    assert result.inputs == fusion.inputs
    final = fusion.estimate()
    assert (result.final.x_m, result.final.y_m, result.final.yaw_rad) == (final.x_m, final.y_m, final.yaw_rad)


def test_the_fusion_replays_across_rotated_files_by_the_recording_name(tmp_path: Path) -> None:
    rec, fusion, outputs = recorded_fusion_run(tmp_path, chunk_s=0.2, file_mb=0.01)
    assert len(rec.files) >= 3
    result = replay(tmp_path / "run.mcap")  # names run-0001.mcap, run-0002.mcap, ...
    assert result.outputs == outputs and result.inputs == fusion.inputs
    assert result.max_position_difference_m == 0.0


def test_a_cut_flight_recording_replays_up_to_the_cut_and_says_where(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    rec, fusion, outputs = recorded_fusion_run(tmp_path, chunk_s=0.2)
    data = rec.files[0].read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    with caplog.at_level(logging.WARNING, logger="agent.recording.reader"):
        result = replay(cut)
    assert 0 < result.outputs < outputs and 0 < result.inputs < fusion.inputs
    assert result.max_position_difference_m == 0.0
    assert any("the replay stops there" in r.getMessage() for r in caplog.records)


def test_the_writer_gives_way_before_each_sample_and_each_chunk(tmp_path: Path) -> None:
    rec, clock, _ = recorder(tmp_path, chunk_s=0.5)
    calls: list[int] = []
    rec.give_way = lambda: calls.append(len(rec._queue))
    for i in range(10):
        t_ns = round(clock.t_s * 1e9) + i  # stamped now: no chunk due yet by the stamps
        rec.record("imu", t_ns, ImuSample((0.0, 0.0, 9.8), (0.0, 0.0, 0.0), 30.0, t_ns))
    rec.pump()  # ten samples: the hot path is asked before each one is encoded
    assert calls == list(range(10, 0, -1))
    clock.t_s += 1.0
    rec.pump()  # nothing queued, a chunk to close: asked once more
    assert len(calls) == 11
    rec.close()


def test_the_replay_command_on_a_whole_and_on_a_cut_recording(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from agent.cli import main

    rec, fusion, outputs = recorded_fusion_run(tmp_path, chunk_s=0.2)
    assert main(["replay", str(tmp_path / "run.mcap"), "--json"]) == 0
    whole = json.loads(capsys.readouterr().out)
    assert whole["complete"] and whole["stopped"] is None and whole["format"] == "mcap"
    assert whole["messages"] == len(read_recording(rec.files[0]).messages)
    assert whole["poses_compared"] == outputs and whole["inputs"] == fusion.inputs
    assert whole["max_pose_diff_m"] == 0.0 and whole["max_slam_diff_m"] is None

    data = rec.files[0].read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    assert main(["replay", str(cut), "--json"]) == 0
    part = json.loads(capsys.readouterr().out)
    assert not part["complete"] and part["stopped"]["file"] == str(cut)
    assert 0 < part["stopped"]["at_byte"] <= len(data) // 2 and part["stopped"]["error"]
    assert 0 < part["poses_compared"] < outputs and part["max_pose_diff_m"] == 0.0


def test_the_replay_command_refuses_what_it_cannot_replay(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from mcap.writer import Writer

    from agent.cli import main

    assert main(["replay", str(tmp_path / "absent.mcap")]) == 1
    assert "no such recording" in capsys.readouterr().err
    future = tmp_path / "future.mcap"
    with open(future, "wb") as fp:
        writer = Writer(fp)
        writer.start(profile="vlp_agent", library="vlp-agent recorder 2")
        writer.add_metadata("vlp_agent", {"format_version": "2"})
        writer.finish()  # type: ignore[no-untyped-call]
    assert main(["replay", str(future)]) == 1
    assert "format version 2; this agent reads up to 1" in capsys.readouterr().err
    rec, clock, _ = recorder(tmp_path / "scans")
    feed_scans(rec, clock, 0, 5)  # a recording without the fusion's channels
    rec.close()
    assert main(["replay", str(rec.files[0])]) == 1
    assert "no fusion setup" in capsys.readouterr().err
