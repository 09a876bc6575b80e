"""The reference C command code (``firmware_protocol/c/command_frame.{h,c}``) against the Python codec.

gcc builds ``test_command_frame`` warning-free with the firmware flags, and again with AddressSanitizer and
UBSan for the random runs when this gcc has them. The C encoders must write the very bytes the Python
encoder writes for any field values, and the C goal-status decoder must return the same statuses and the
same counters as :class:`GoalStatusDecoder` on any stream, pose frames and junk included.
"""

from __future__ import annotations

import random
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from firmware_protocol.command_frame import (
    CancelCommand,
    Command,
    ExploreCommand,
    FollowAction,
    FollowCommand,
    GoalCommand,
    GoalStatus,
    GoalStatusDecoder,
    PlaceCommand,
    ResumeCommand,
    StopCommand,
    VelocityCommand,
    encode_command,
    encode_goal_status,
)
from firmware_protocol.pose_frame import PoseFrame, encode_pose
from tests.unit.test_c_decoder import build_c, run
from tests.unit.test_command_frame import DOC_MESSAGES, STREAMS

C_DIR = Path(__file__).resolve().parents[2] / "firmware_protocol" / "c"
SOURCES = [C_DIR / "test_command_frame.c", C_DIR / "command_frame.c", C_DIR / "pose_frame.c"]


@pytest.fixture(scope="module")
def c_program(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return build_c(tmp_path_factory.mktemp("c_commands"), "test_command_frame", SOURCES, ("-",)).checked


def as_line(command: Command) -> str:
    """The command as the integer fields ``test_command_frame --encode`` reads."""
    frame = encode_command(command)
    from firmware_protocol.cobs import cobs_decode

    payload = cobs_decode(frame[:-1])[:-2]
    u16 = [int.from_bytes(payload[i : i + 2], "little") for i in range(0, len(payload) - 1, 2)]

    def i16(v: int) -> int:
        return v - 0x10000 if v >= 0x8000 else v

    if isinstance(command, VelocityCommand):
        return f"v {u16[1]} {i16(u16[2])} {i16(u16[3])} {u16[4]}"
    if isinstance(command, GoalCommand):
        x = int.from_bytes(payload[8:12], "little", signed=True)
        y = int.from_bytes(payload[12:16], "little", signed=True)
        return f"g {u16[1]} {u16[2]} {payload[6]} {x} {y} {i16(u16[8])} {u16[9]} {u16[10]}"
    if isinstance(command, CancelCommand):
        return f"c {u16[1]} {u16[2]}"
    if isinstance(command, FollowCommand):
        return f"f {u16[1]} {u16[2]} {int(command.action)} {command.tag or '-'}"
    return f"{'s' if isinstance(command, StopCommand) else 'r'} {u16[1]}"


def encode_with_c(binary: Path, commands: list[Command]) -> list[bytes]:
    text = "".join(as_line(c) + "\n" for c in commands).encode()
    proc = run(binary, text, "--encode")
    assert proc.returncode == 0, proc.stderr.decode(errors="replace")
    return [bytes.fromhex(line) for line in proc.stdout.decode().splitlines()]


def decode_with_c(binary: Path, data: bytes) -> tuple[list[tuple[int, ...]], dict[str, int]]:
    proc = run(binary, data, "-")
    assert proc.returncode == 0, proc.stderr.decode(errors="replace")
    lines = proc.stdout.decode().splitlines()
    assert lines[0] == "seq,command_seq,goal_id,state,reason,remaining,version"
    rows = [tuple(int(v) for v in line.split(",")) for line in lines[1:]]
    stats = dict(item.split("=") for item in proc.stderr.decode().split())
    return rows, {k: int(v) for k, v in stats.items()}


def python_rows(data: bytes) -> tuple[list[tuple[int, ...]], dict[str, int]]:
    decoder = GoalStatusDecoder()
    rows = []
    for s in decoder.feed(data):
        remaining = 0xFFFF if s.remaining_m is None else round(s.remaining_m * 100)
        rows.append((s.sequence, s.command_sequence, s.goal_id, s.state, s.reason, remaining, 0x10))
    e = decoder.errors
    stats = {
        "frames": decoder.frames,
        "pose_frames": decoder.skipped,
        "cobs_errors": e["cobs"],
        "length_errors": e["length"],
        "crc_errors": e["crc"],
        "type_errors": e["type"],
        "version_errors": e["version"],
        "value_errors": e["value"],
        "overflows": e["overflow"],
    }
    return rows, stats


# The C encoders write the v1.0 commands and follow (v1.2); the mission frames of v1.1 (explore, go to place)
# are not in C yet.
DOC_COMMANDS = [
    m for m in DOC_MESSAGES.values() if not isinstance(m, (GoalStatus, ExploreCommand, PlaceCommand))
]
DOC_STATUSES = [m for m in DOC_MESSAGES.values() if isinstance(m, GoalStatus)]


def test_the_c_encoders_write_the_doc_vectors(c_program: Path) -> None:
    assert encode_with_c(c_program, DOC_COMMANDS) == [encode_command(c) for c in DOC_COMMANDS]


commands = st.one_of(
    st.builds(
        VelocityCommand,
        st.integers(0, 0xFFFF),
        st.integers(-32768, 32767).map(lambda q: q / 1000),
        st.integers(-32768, 32767).map(lambda q: q / 1000),
        st.integers(0, 0xFFFF).map(lambda q: q / 1000),
    ),
    st.builds(
        GoalCommand,
        st.integers(0, 0xFFFF),
        st.integers(0, 0xFFFF),
        st.integers(-(2**31), 2**31 - 1).map(lambda q: q / 10_000),
        st.integers(-(2**31), 2**31 - 1).map(lambda q: q / 10_000),
        st.one_of(st.none(), st.floats(-3.14159, 3.14159)),
        st.integers(0, 0xFFFF).map(lambda q: q / 1000),
        st.integers(0, 0xFFFF).map(lambda q: q / 10_000),
        st.booleans(),
    ),
    st.builds(CancelCommand, st.integers(0, 0xFFFF), st.integers(0, 0xFFFF)),
    st.builds(StopCommand, st.integers(0, 0xFFFF)),
    st.builds(ResumeCommand, st.integers(0, 0xFFFF)),
    st.builds(
        FollowCommand,
        st.integers(0, 0xFFFF),
        st.integers(0, 0xFFFF),
        st.just(FollowAction.START),
        st.one_of(st.none(), st.binary(min_size=1, max_size=16).map(lambda b: b.hex().upper())),
    ),
    st.builds(FollowCommand, st.integers(0, 0xFFFF), st.integers(0, 0xFFFF), st.just(FollowAction.STOP)),
)


@pytest.mark.parametrize("line", ["f 1 1 1 AB", "f 1 1 0 " + "00" * 17, "f 1 1 2 -"])
def test_the_c_follow_encoder_refuses_what_the_python_encoder_does(c_program: Path, line: str) -> None:
    """A stop naming a tag, a tag too long, an unknown action: no frame from C (the Python encoder raises)."""
    proc = run(c_program, (line + "\n").encode(), "--encode")
    assert proc.returncode == 2 and proc.stdout == b""


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.lists(commands, min_size=1, max_size=40))
def test_the_c_encoders_agree_with_python_on_any_fields(c_program: Path, batch: list[Command]) -> None:
    assert encode_with_c(c_program, batch) == [encode_command(c) for c in batch]


def test_the_c_status_decoder_skips_poses_and_counts_junk_as_python_does(c_program: Path) -> None:
    poses = [encode_pose(PoseFrame(i, i * 1000, 1.0, -1.0, 0.3)) for i in range(len(DOC_STATUSES))]
    stream = b"\x00\x07noise\x00" + b"".join(
        p + encode_goal_status(s) for p, s in zip(poses, DOC_STATUSES, strict=True)
    )
    stream += b"\x01" * 90 + b"\x00" + encode_command(StopCommand(1))
    rows, stats = decode_with_c(c_program, stream)
    assert (rows, stats) == python_rows(stream)
    assert stats["frames"] == len(DOC_STATUSES) and stats["pose_frames"] == len(poses)
    assert stats["overflows"] == 1 and stats["type_errors"] == 1


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(STREAMS)
def test_the_c_status_decoder_agrees_with_python_on_any_stream(c_program: Path, data: bytes) -> None:
    assert decode_with_c(c_program, data) == python_rows(data)


def test_every_single_bit_corruption_of_a_status_is_rejected_or_still_that_status(c_program: Path) -> None:
    rng = random.Random(5)
    for status in DOC_STATUSES:
        frame = encode_goal_status(status)
        for _ in range(20):
            bad = bytearray(frame)
            bit = rng.randrange(len(bad) * 8)
            bad[bit // 8] ^= 1 << (bit % 8)
            rows, _ = decode_with_c(c_program, bytes(bad))
            assert rows == python_rows(bytes(bad))[0]
            assert len(rows) <= 1
