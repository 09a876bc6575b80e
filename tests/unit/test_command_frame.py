"""Command and goal-status frames: the vectors of ``docs/wire-format.md``, field ranges and quantisation,
the versioning rule, streams with junk and corrupted frames between good ones, pose frames interleaved with
statuses, and property tests ("any input decodes or raises CommandFrameError; cuts do not matter").
"""

from __future__ import annotations

import contextlib
import math
import re
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from firmware_protocol.command_frame import (
    NO_GOAL,
    NO_SEQUENCE,
    CancelCommand,
    Command,
    CommandDecoder,
    CommandFrameError,
    ExploreAction,
    ExploreCommand,
    FollowAction,
    FollowCommand,
    GoalCommand,
    GoalReason,
    GoalState,
    GoalStatus,
    GoalStatusDecoder,
    PlaceCommand,
    ResumeCommand,
    StopCommand,
    VelocityCommand,
    decode_command,
    decode_goal_status,
    encode_command,
    encode_goal_status,
)
from firmware_protocol.framing import encode_link_frame
from firmware_protocol.pose_frame import PoseFrame, PoseFrameDecoder, encode_pose

WIRE_FORMAT_MD = Path(__file__).resolve().parents[2] / "docs" / "wire-format.md"

DOC_MESSAGES: dict[str, Command | GoalStatus] = {
    "velocity": VelocityCommand(7, 0.25, -0.5, 0.5),
    "goal": GoalCommand(8, 42, 3.1416, -2.5, math.pi / 2, 0.05, 0.0873),
    "goal, any heading, through unknown space": GoalCommand(9, 43, 12.0, 4.0, None, allow_unknown=True),
    "cancel": CancelCommand(10, 42),
    "stop": StopCommand(11),
    "resume": ResumeCommand(12),
    "status: accepted": GoalStatus(1, 8, 42, GoalState.ACCEPTED),
    "status: active, 4.37 m to go": GoalStatus(2, NO_SEQUENCE, 42, GoalState.ACTIVE, remaining_m=4.37),
    "status: rejected, unreachable": GoalStatus(3, 9, 43, GoalState.REJECTED, GoalReason.UNREACHABLE),
    "status: reached": GoalStatus(4, NO_SEQUENCE, 42, GoalState.REACHED, remaining_m=0.0),
    "explore: start, mission 7": ExploreCommand(13, 7, ExploreAction.START),
    "explore: pause, mission 7": ExploreCommand(14, 7, ExploreAction.PAUSE),
    "go to place: S3 and back, mission 8": PlaceCommand(15, 8, "S3", come_back=True),
    "status: rejected, unknown place": GoalStatus(5, 15, 8, GoalState.REJECTED, GoalReason.UNKNOWN_PLACE),
    "follow: start, the configured tag, follow 9": FollowCommand(16, 9),
    "follow: start, tag E2000017221101441890ABCD, follow 9": FollowCommand(
        17, 9, tag="E2000017221101441890ABCD"
    ),
    "follow: stop, follow 9": FollowCommand(18, 9, FollowAction.STOP),
    "status: active, following, 1.23 m away": GoalStatus(
        6, NO_SEQUENCE, 9, GoalState.ACTIVE, GoalReason.FOLLOWING, 1.23
    ),
}


def doc_command_vectors() -> dict[str, bytes]:
    """The ``name: hex`` lines of the "Command test vectors" block."""
    text = WIRE_FORMAT_MD.read_text(encoding="utf-8")
    section = text[text.index("### Command test vectors") :]
    block = re.search(r"```text\n(.*?)```", section, re.S)
    assert block is not None
    out = {}
    for line in block.group(1).strip().splitlines():
        name, hexbytes = line.rsplit(":", 1)
        out[name.strip()] = bytes.fromhex(hexbytes)
    return out


def wire(message: Command | GoalStatus) -> bytes:
    return encode_goal_status(message) if isinstance(message, GoalStatus) else encode_command(message)


def test_the_doc_vectors_are_the_codecs_bytes_both_ways() -> None:
    vectors = doc_command_vectors()
    assert set(vectors) == set(DOC_MESSAGES)
    for name, message in DOC_MESSAGES.items():
        assert wire(message) == vectors[name], name
        decoded = decode_goal_status(vectors[name]) if isinstance(message, GoalStatus) else None
        if decoded is None:
            decoded = decode_command(vectors[name])
        assert decoded == message, name


def test_frame_lengths_on_the_wire() -> None:
    lengths = [14, 26, 26, 10, 8, 8, 16, 16, 16, 16, 12, 12, 28, 16, 28, 28, 28, 16]
    assert [len(wire(m)) for m in DOC_MESSAGES.values()] == lengths


def test_no_type_byte_looks_like_a_pose_version() -> None:
    for message in DOC_MESSAGES.values():
        payload = wire(message)
        assert payload[1] >> 4 != 1  # COBS code byte first, then the type byte


@given(
    st.integers(0, 0xFFFF),
    st.floats(-32.768, 32.767),
    st.floats(-32.768, 32.767),
    st.floats(0.0, 65.535),
)
def test_velocity_round_trip_is_within_half_a_step(seq: int, v: float, omega: float, timeout: float) -> None:
    out = decode_command(encode_command(VelocityCommand(seq, v, omega, timeout)))
    assert isinstance(out, VelocityCommand)
    assert out.sequence == seq
    assert abs(out.v_mps - v) <= 0.0005 + 1e-12
    assert abs(out.omega_radps - omega) <= 0.0005 + 1e-12
    assert abs(out.timeout_s - timeout) <= 0.0005 + 1e-12


@given(
    st.integers(0, 0xFFFF),
    st.floats(-200_000, 200_000),
    st.floats(-200_000, 200_000),
    st.one_of(st.none(), st.floats(-math.pi, math.pi)),
    st.booleans(),
)
def test_goal_round_trip(seq: int, x: float, y: float, yaw: float | None, unknown: bool) -> None:
    out = decode_command(encode_command(GoalCommand(seq, 5, x, y, yaw, 0.1, 0.05, unknown)))
    assert isinstance(out, GoalCommand)
    assert abs(out.x_m - x) <= 0.5e-4 + 1e-9 and abs(out.y_m - y) <= 0.5e-4 + 1e-9
    assert (out.yaw_rad is None) == (yaw is None)
    if yaw is not None and out.yaw_rad is not None:
        assert abs(math.remainder(out.yaw_rad - yaw, 2 * math.pi)) <= math.pi / 65536 + 1e-12
    assert out.allow_unknown is unknown
    assert (out.tolerance_xy_m, out.tolerance_yaw_rad) == (0.1, 0.05)


@pytest.mark.parametrize(
    "bad",
    [
        VelocityCommand(1, math.nan, 0.0, 0.5),
        VelocityCommand(1, 0.0, math.inf, 0.5),
        VelocityCommand(1, 40.0, 0.0, 0.5),
        VelocityCommand(1, 0.0, 0.0, -0.1),
        VelocityCommand(0x10000, 0.0, 0.0, 0.5),
        GoalCommand(1, 2, math.nan, 0.0),
        GoalCommand(1, 2, 0.0, 0.0, math.inf),
        GoalCommand(1, 0x10000, 0.0, 0.0),
        GoalCommand(1, 2, 0.0, 0.0, tolerance_xy_m=-1.0),
        GoalStatus(1, 2, 3, GoalState.ACTIVE, remaining_m=math.nan),
    ],
)
def test_values_that_cannot_cross_the_wire_raise(bad: Command | GoalStatus) -> None:
    with pytest.raises(CommandFrameError) as info:
        wire(bad)
    assert info.value.kind == "value"


def test_a_far_goal_saturates_its_remaining_distance_instead_of_reading_unknown() -> None:
    out = decode_goal_status(encode_goal_status(GoalStatus(1, 2, 3, GoalState.ACTIVE, remaining_m=1e6)))
    assert out.remaining_m == 655.34


@pytest.mark.parametrize(
    ("payload", "kind"),
    [
        (bytes([0x2F, 0x10, 0, 0]), "type"),  # an unknown type
        (bytes([0x10]) + bytes(29), "type"),  # a pose payload sent to the agent
        (bytes([0xA1, 0x10, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0]), "type"),  # a status sent to the agent
        (bytes([0x24, 0x20, 0, 0]), "version"),  # major 2
        (bytes([0x24, 0x10, 0, 0, 0]), "length"),  # v1.0 stop with a stray byte
        (bytes([0x21, 0x10, 0, 0, 0, 0]), "length"),  # a velocity cut short
    ],
)
def test_the_versioning_and_type_rules(payload: bytes, kind: str) -> None:
    with pytest.raises(CommandFrameError) as info:
        decode_command(encode_link_frame(payload))
    assert info.value.kind == kind
    assert info.value.data == payload


def test_a_newer_minor_version_with_appended_fields_is_accepted() -> None:
    payload = bytes([0x24, 0x13, 5, 0]) + b"later fields"
    assert decode_command(encode_link_frame(payload)) == StopCommand(5)


def test_an_unknown_reason_from_a_later_version_keeps_the_state() -> None:
    payload = bytes([0xA1, 0x11, 1, 0, 2, 0, 3, 0, GoalState.FAILED, 200, 0xFF, 0xFF])
    status = decode_goal_status(encode_link_frame(payload))
    assert (status.state, status.reason) == (GoalState.FAILED, GoalReason.NONE)


def test_an_unknown_state_is_a_value_error() -> None:
    payload = bytes([0xA1, 0x10, 1, 0, 2, 0, 3, 0, 9, 0, 0xFF, 0xFF])
    with pytest.raises(CommandFrameError) as info:
        decode_goal_status(encode_link_frame(payload))
    assert info.value.kind == "value"


def test_bad_crc_and_cobs_are_link_errors() -> None:
    good = encode_command(StopCommand(3))
    bad_crc = good[:-2] + bytes([good[-2] ^ 1]) + b"\x00"
    with pytest.raises(CommandFrameError) as info:
        decode_command(bad_crc)
    assert info.value.kind == "crc"
    with pytest.raises(CommandFrameError) as info:
        decode_command(b"\x05\x01\x02")
    assert info.value.kind == "cobs"


def test_junk_and_bad_frames_between_good_ones_cost_only_themselves() -> None:
    good = [VelocityCommand(1, 0.2, 0.0, 0.3), StopCommand(2), GoalCommand(3, 9, 1.0, 2.0)]
    corrupt = bytearray(encode_command(ResumeCommand(4)))
    corrupt[3] ^= 0x40
    stream = (
        b"\x07junk"
        + b"\x00"
        + encode_command(good[0])
        + bytes(corrupt)
        + encode_link_frame(bytes([0x2F, 0x10, 0, 0]))
        + encode_command(good[1])
        + b"\x01" * 300  # over-long line noise without a delimiter
        + b"\x00"
        + encode_command(good[2])
    )
    decoder = CommandDecoder()
    assert decoder.feed(stream) == good
    assert decoder.errors["crc"] == 1
    assert decoder.errors["type"] == 1
    assert decoder.errors["overflow"] == 1
    assert decoder.errors["cobs"] + decoder.errors["length"] == 1  # the leading junk
    rejected = decoder.take_rejected()
    assert [e.kind for e in rejected][1:] == ["crc", "type", "overflow"]
    assert decoder.take_rejected() == []


def test_the_status_decoder_skips_pose_frames_and_the_pose_decoder_is_unchanged_by_statuses() -> None:
    statuses = [GoalStatus(i, i, 42, GoalState.ACTIVE, remaining_m=float(i)) for i in range(3)]
    poses = [PoseFrame(i, 1000 * i, 1.0, 2.0, 0.5) for i in range(3)]
    stream = b"".join(encode_pose(p) + encode_goal_status(s) for p, s in zip(poses, statuses, strict=True))
    status_decoder = GoalStatusDecoder()
    assert status_decoder.feed(stream) == statuses
    assert status_decoder.skipped == 3 and status_decoder.bad_frames == 0
    assert len(PoseFrameDecoder().feed(stream)) == 3


STREAMS = st.one_of(
    st.binary(max_size=400),
    st.lists(
        st.sampled_from([wire(m) for m in DOC_MESSAGES.values()] + [b"\x00", b"\x01" * 70, b"\x05\x22"]),
        max_size=12,
    ).map(b"".join),
)


@settings(max_examples=300, deadline=None)
@given(STREAMS)
def test_one_shot_decoding_of_anything_decodes_or_raises_command_frame_error(data: bytes) -> None:
    for decode in (decode_command, decode_goal_status):
        with contextlib.suppress(CommandFrameError):
            decode(data)


@settings(max_examples=300, deadline=None)
@given(STREAMS, st.lists(st.integers(0, 500), max_size=6))
def test_the_stream_decoders_never_raise_and_cuts_do_not_matter(data: bytes, cuts: list[int]) -> None:
    for make in (CommandDecoder, GoalStatusDecoder):
        whole = make()
        expected = whole.feed(data)
        pieces = make()
        got = []
        start = 0
        for cut in sorted(c % (len(data) + 1) for c in cuts):
            got += pieces.feed(data[start:cut])
            start = cut
        got += pieces.feed(data[start:])
        assert got == expected
        assert pieces.counters() == whole.counters()


def test_cancel_defaults_to_whatever_goal_is_active() -> None:
    assert decode_command(encode_command(CancelCommand(1))) == CancelCommand(1, NO_GOAL)


# -- missions (v1.1) ----------------------------------------------------------------------------------------
@given(st.integers(0, 0xFFFF), st.integers(0, 0xFFFF), st.sampled_from(list(ExploreAction)))
def test_explore_round_trip(seq: int, mission: int, action: ExploreAction) -> None:
    command = ExploreCommand(seq, mission, action)
    assert decode_command(encode_command(command)) == command


@given(
    st.integers(0, 0xFFFF),
    st.text(st.characters(blacklist_characters="\x00", blacklist_categories=("Cs",)), min_size=1).filter(
        lambda t: len(t.encode("utf-8")) <= 16
    ),
    st.booleans(),
)
def test_place_round_trip(mission: int, name: str, back: bool) -> None:
    command = PlaceCommand(3, mission, name, back)
    assert decode_command(encode_command(command)) == command


@pytest.mark.parametrize(
    "bad",
    [
        PlaceCommand(1, 1, ""),
        PlaceCommand(1, 1, "a" * 17),
        PlaceCommand(1, 1, "é" * 9),  # 18 bytes of UTF-8
        PlaceCommand(1, 1, "a\x00b"),
        ExploreCommand(1, 0x10000),
    ],
)
def test_mission_values_that_cannot_cross_the_wire_raise(bad: Command) -> None:
    with pytest.raises(CommandFrameError) as info:
        encode_command(bad)
    assert info.value.kind == "value"


def place_payload(name: bytes, version: int = 0x11, extra: bytes = b"") -> bytes:
    return bytes([0x27, version, 1, 0, 8, 0, 0, 0]) + name.ljust(16, b"\x00")[:16] + extra


@pytest.mark.parametrize(
    ("payload", "kind"),
    [
        (bytes([0x26, 0x11, 1, 0, 7, 0, 9, 0]), "value"),  # no explore action 9
        (bytes([0x26, 0x10, 1, 0, 7, 0, 0, 0]), "version"),  # explore frames start at 1.1
        (bytes([0x26, 0x11, 1, 0, 7, 0, 0]), "length"),  # cut short
        (bytes([0x26, 0x11, 1, 0, 7, 0, 0, 0, 0]), "length"),  # a stray byte at 1.1
        (place_payload(b"S3", 0x10), "version"),
        (place_payload(b""), "value"),  # no name
        (place_payload(b"\xff\xfe"), "value"),  # not UTF-8
        (place_payload(b"S\x003"), "value"),  # a NUL inside
        (place_payload(b"S3")[:-1], "length"),
    ],
)
def test_malformed_mission_frames_are_rejected_with_their_kind(payload: bytes, kind: str) -> None:
    with pytest.raises(CommandFrameError) as info:
        decode_command(encode_link_frame(payload))
    assert info.value.kind == kind, info.value


def test_a_later_minor_mission_frame_with_appended_fields_is_read() -> None:
    assert decode_command(encode_link_frame(place_payload(b"S3", 0x12, b"later"))) == PlaceCommand(1, 8, "S3")


def test_mission_frames_in_a_stream_with_junk() -> None:
    decoder = CommandDecoder()
    good = [ExploreCommand(1, 7), PlaceCommand(2, 8, "N4", True)]
    stream = (
        b"\x13\x37\x00"
        + encode_command(good[0])
        + encode_link_frame(place_payload(b""))
        + encode_command(good[1])
    )
    assert decoder.feed(stream) == good
    assert decoder.errors["value"] == 1


# -- following (v1.2) -------------------------------------------------------------------------------------
@given(
    st.integers(0, 0xFFFF),
    st.integers(0, 0xFFFF),
    st.one_of(st.none(), st.binary(min_size=1, max_size=16).map(lambda b: b.hex().upper())),
)
def test_follow_round_trip(seq: int, follow_id: int, tag: str | None) -> None:
    for command in (FollowCommand(seq, follow_id, FollowAction.START, tag), FollowCommand(seq, follow_id, 1)):
        assert decode_command(encode_command(command)) == command


@pytest.mark.parametrize(
    "bad",
    [
        FollowCommand(1, 1, tag=""),
        FollowCommand(1, 1, tag="ABC"),  # an odd number of hex digits
        FollowCommand(1, 1, tag="XY"),
        FollowCommand(1, 1, tag="00" * 17),
        FollowCommand(1, 1, FollowAction.STOP, tag="AB"),  # a stop names no tag
        FollowCommand(1, 0x10000),
    ],
)
def test_follow_values_that_cannot_cross_the_wire_raise(bad: Command) -> None:
    with pytest.raises(CommandFrameError) as info:
        encode_command(bad)
    assert info.value.kind == "value"


def follow_payload(
    action: int = 0, tag: bytes = b"", version: int = 0x12, length: int | None = None, extra: bytes = b""
) -> bytes:
    n = len(tag) if length is None else length
    return bytes([0x28, version, 1, 0, 9, 0, action, n]) + tag.ljust(16, b"\x00")[:16] + extra


@pytest.mark.parametrize(
    ("payload", "kind"),
    [
        (follow_payload(action=2), "value"),  # no follow action 2
        (follow_payload(tag=b"\xe2\x01", length=1), "value"),  # a tag byte after tag_length
        (follow_payload(tag=b"\xe2", length=17), "value"),  # longer than the field
        (follow_payload(action=1, tag=b"\xe2"), "value"),  # a stop naming a tag
        (follow_payload(version=0x11), "version"),  # follow frames start at 1.2
        (follow_payload(version=0x10), "version"),
        (follow_payload(version=0x22), "version"),  # major 2
        (follow_payload()[:-1], "length"),  # cut short
        (follow_payload() + b"\x00", "length"),  # a stray byte at 1.2
    ],
)
def test_malformed_follow_frames_are_rejected_with_their_kind(payload: bytes, kind: str) -> None:
    with pytest.raises(CommandFrameError) as info:
        decode_command(encode_link_frame(payload))
    assert info.value.kind == kind, info.value


def test_a_later_minor_follow_frame_with_appended_fields_is_read() -> None:
    payload = follow_payload(tag=b"\x04\x15", version=0x13, extra=b"later")
    assert decode_command(encode_link_frame(payload)) == FollowCommand(1, 9, FollowAction.START, "0415")


def test_follow_frames_in_a_stream_with_junk_and_corruption() -> None:
    decoder = CommandDecoder()
    good = [FollowCommand(1, 9, tag="0415AB9C3D"), FollowCommand(2, 9, FollowAction.STOP)]
    corrupt = bytearray(encode_command(FollowCommand(3, 10)))
    corrupt[5] ^= 0x40  # a payload byte: the CRC fails
    stream = (
        b"\x13\x37\x00"
        + encode_command(good[0])
        + bytes(corrupt)
        + encode_link_frame(follow_payload(action=7))
        + encode_command(good[1])
    )
    assert decoder.feed(stream) == good
    assert decoder.errors["value"] == 1 and decoder.errors["crc"] == 1
