"""The agent <-> bridge local protocol (agent.fleet.local_protocol): whole frames, byte by byte, truncated,
oversized, trailing bytes and garbage."""

from __future__ import annotations

import contextlib
import math
import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from agent.fleet.local_protocol import (
    HEADER,
    MAGIC,
    MAX_PAYLOAD,
    VERSION,
    FrameDecoder,
    GoalMessage,
    GoalStateMessage,
    LocalProtocolError,
    PeerPoseMessage,
    PoseMessage,
    StatusMessage,
    decode_frame,
    encode,
)
from firmware_protocol.errors import ProtocolError

POSE = PoseMessage(123_456_789, 1.25, -3.5, 0.75, 0.015625, 0.03125, 0b1011)  # sigmas exact in float32
MESSAGES = [
    POSE,
    StatusMessage(5, 0b11, StatusMessage.READY | StatusMessage.LOCALIZED),
    GoalStateMessage(6, 42, 3, 0, 1.5),
    PeerPoseMessage("robot-2_b", POSE),
    GoalMessage(7, 0xFFFF, 4.0, 5.0, -1.0, GoalMessage.ALLOW_UNKNOWN),
]


@pytest.mark.parametrize("message", MESSAGES, ids=lambda m: type(m).__name__)
def test_round_trip_whole_and_byte_by_byte(message: object) -> None:
    frame = encode(message)  # type: ignore[arg-type]
    assert frame[:2] == MAGIC and frame[2] == VERSION
    assert struct.unpack_from("<I", frame, 4)[0] == len(frame) - HEADER.size
    assert decode_frame(frame) == message
    decoder = FrameDecoder()
    out = []
    for i in range(len(frame)):
        out += decoder.feed(frame[i : i + 1])
        assert decoder.pending == (0 if i == len(frame) - 1 else i + 1)
    assert out == [message]


def test_several_frames_in_one_read_and_a_split_across_reads() -> None:
    data = b"".join(encode(m) for m in MESSAGES)  # type: ignore[arg-type]
    decoder = FrameDecoder()
    cut = len(encode(POSE)) + 5  # the first frame and the start of the second
    assert decoder.feed(data[:cut]) == [MESSAGES[0]]
    assert decoder.pending == 5
    assert decoder.feed(data[cut:]) == MESSAGES[1:]
    assert decoder.pending == 0


def test_nan_goal_heading_and_unknown_remaining_distance_round_trip() -> None:
    goal = decode_frame(encode(GoalMessage(1, 2, 0.0, 0.0)))
    assert isinstance(goal, GoalMessage) and math.isnan(goal.yaw_rad)
    state = decode_frame(encode(GoalStateMessage(1, 2, 0, 0)))
    assert isinstance(state, GoalStateMessage) and math.isnan(state.remaining_m)


def test_truncated_frames_are_refused() -> None:
    frame = encode(POSE)
    for n in range(len(frame)):
        with pytest.raises(LocalProtocolError, match="truncated"):
            decode_frame(frame[:n])


def test_trailing_bytes_are_refused() -> None:
    with pytest.raises(LocalProtocolError, match="trailing"):
        decode_frame(encode(POSE) + b"\x00")


def test_oversized_length_is_refused_from_the_header_alone() -> None:
    header = HEADER.pack(MAGIC, VERSION, PoseMessage.TYPE, MAX_PAYLOAD + 1)
    decoder = FrameDecoder()
    with pytest.raises(LocalProtocolError, match="at most"):
        decoder.feed(header)  # refused before waiting for a megabyte that never comes
    with pytest.raises(LocalProtocolError):
        decoder.feed(encode(POSE))  # and the decoder stays failed: the connection is closed


@pytest.mark.parametrize(
    ("header", "match"),
    [
        (HEADER.pack(b"XX", VERSION, PoseMessage.TYPE, 44), "magic"),
        (HEADER.pack(MAGIC, VERSION + 1, PoseMessage.TYPE, 44), "version"),
        (HEADER.pack(MAGIC, VERSION, 0x7F, 44), "unknown message type"),
    ],
)
def test_bad_headers(header: bytes, match: str) -> None:
    with pytest.raises(LocalProtocolError, match=match):
        FrameDecoder().feed(header + bytes(44))


def test_a_payload_of_the_wrong_size_for_its_type() -> None:
    payload = POSE.payload()[:-1]
    frame = HEADER.pack(MAGIC, VERSION, PoseMessage.TYPE, len(payload)) + payload
    with pytest.raises(LocalProtocolError, match="expected"):
        decode_frame(frame)


@pytest.mark.parametrize("name", [b"", b"bad name", b"\xff\xfe", b"a/b", b"*"])
def test_peer_pose_with_a_bad_name(name: bytes) -> None:
    payload = bytes([len(name)]) + name + POSE.payload()
    with pytest.raises(LocalProtocolError):
        decode_frame(HEADER.pack(MAGIC, VERSION, PeerPoseMessage.TYPE, len(payload)) + payload)


def test_encoding_refuses_what_the_frame_cannot_carry() -> None:
    with pytest.raises(LocalProtocolError):
        encode(PeerPoseMessage("x" * 33, POSE))
    with pytest.raises(LocalProtocolError):
        encode(GoalStateMessage(0, 0x1_0000, 0, 0))


def test_a_goal_that_is_not_finite_is_refused() -> None:
    payload = struct.pack("<QHdddB", 0, 1, math.inf, 0.0, 0.0, 0)
    with pytest.raises(LocalProtocolError, match="finite"):
        decode_frame(HEADER.pack(MAGIC, VERSION, GoalMessage.TYPE, len(payload)) + payload)


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=300))
def test_garbage_parses_or_raises_protocol_error(data: bytes) -> None:
    with contextlib.suppress(ProtocolError):
        decode_frame(data)
    decoder = FrameDecoder()
    with contextlib.suppress(ProtocolError):
        decoder.feed(data)
    assert decoder.pending <= HEADER.size + MAX_PAYLOAD


def test_the_shared_reader_gives_messages_and_says_when_to_close() -> None:
    from agent.fleet.local_protocol import FrameReader, receive

    reader = FrameReader()
    stream = b"".join(encode(m) for m in MESSAGES)
    first = reader.received(stream[:60])
    assert first.close is None and first.messages == [POSE]
    rest = reader.received(stream[60:])
    assert rest.close is None and rest.messages == MESSAGES[1:]
    cut = reader.received(encode(POSE)[:10])
    assert cut.messages == [] and cut.close is None
    end = reader.received(b"")
    assert end.close is not None and "cut" in end.close and not end.malformed
    bad = FrameReader().received(encode(POSE) + b"XX" + bytes(20))
    assert bad.malformed and bad.close is not None and bad.messages == []
    assert FrameReader.failed(TimeoutError()).close is None
    assert FrameReader.failed(ConnectionResetError("reset")).close is not None

    class Sock:
        def __init__(self, data: bytes | OSError) -> None:
            self.data = data

        def recv(self, bufsize: int) -> bytes:
            if isinstance(self.data, OSError):
                raise self.data
            return self.data

    assert receive(Sock(encode(POSE)), FrameReader()).messages == [POSE]
    assert receive(Sock(BrokenPipeError()), FrameReader()).close is not None


def test_a_goal_with_option_bits_this_side_does_not_know_is_refused() -> None:
    payload = struct.pack("<QHdddB", 0, 1, 1.0, 0.0, 0.0, 0x80)
    with pytest.raises(LocalProtocolError, match="option"):
        decode_frame(HEADER.pack(MAGIC, VERSION, GoalMessage.TYPE, len(payload)) + payload)
