"""Dynamixel Protocol 2.0 codec: CRC, stuffing, the e-Manual's example packets, the streaming decoder.

``exercise_decoder`` is the fuzz entry point: it feeds any bytes in any chunking and checks the decoder's
invariants; benchmarks/ can call it with far more inputs than the property test here runs.
"""

from __future__ import annotations

import contextlib
import random
from collections.abc import Sequence
from pathlib import Path

import pytest
from dynamixel_sdk.protocol2_packet_handler import Protocol2PacketHandler
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from firmware_protocol.dynamixel import (
    BROADCAST_ID,
    HEADER,
    MAX_PACKET_BYTES,
    BulkRead,
    BulkReadEntry,
    BulkWrite,
    BulkWriteEntry,
    Clear,
    Command,
    DynamixelDecoder,
    DynamixelError,
    ErrorNumber,
    FactoryReset,
    FastBulkRead,
    FastReadItem,
    FastSyncRead,
    Instruction,
    InstructionPacket,
    Packet,
    Ping,
    Read,
    Reboot,
    RegWrite,
    StatusError,
    StatusPacket,
    SyncRead,
    SyncWrite,
    Write,
    command_params,
    crc16,
    decode_packet,
    encode_fast_read_status,
    encode_instruction,
    encode_packet,
    encode_ping,
    encode_read,
    encode_status,
    encode_sync_write,
    encode_write,
    parse_command,
    parse_fast_read_status,
    parse_ping_reply,
    stuff,
    unstuff,
)

SDK = Protocol2PacketHandler()


def crc16_bitwise(data: bytes) -> int:
    """The CRC as the catalogue defines it, one bit at a time: an independent reference for the table."""
    crc = 0
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x8005) & 0xFFFF if crc & 0x8000 else (crc << 1) & 0xFFFF
    return crc


# -- fuzz entry point --------------------------------------------------------------------------------


def exercise_decoder(
    data: bytes, chunk_sizes: Sequence[int] = (1,), max_length: int | None = None
) -> list[Packet]:
    """Feed ``data`` in chunks (cycling through ``chunk_sizes``), check every invariant, return the packets.

    Invariants: only packets or DynamixelError come out of anything that parses bytes; every byte fed is
    either in an accepted frame, counted as discarded, or still buffered; the buffer never holds more
    than one maximal packet.
    """
    decoder = DynamixelDecoder() if max_length is None else DynamixelDecoder(max_length)
    packets: list[Packet] = []
    i = n = 0
    while i < len(data):
        size = max(1, chunk_sizes[n % len(chunk_sizes)])
        packets += decoder.feed(data[i : i + size])
        i = min(i + size, len(data))
        n += 1
        assert decoder.buffered <= 7 + decoder.max_length
        assert decoder.packet_bytes + decoder.discarded_bytes + decoder.buffered == i
    for packet in packets:
        assert isinstance(packet, InstructionPacket | StatusPacket)
        if isinstance(packet, InstructionPacket):
            try:
                command = parse_command(packet)
            except DynamixelError:
                continue
            # A command that parsed re-encodes to the same parameters.
            assert command_params(command) == (packet.instruction, packet.params)
        elif packet.id == BROADCAST_ID:
            with contextlib.suppress(DynamixelError):
                parse_fast_read_status(packet, [len(packet.params) - 1])
    for error in decoder.take_errors():
        assert isinstance(error, DynamixelError)
    with contextlib.suppress(DynamixelError):
        decode_packet(data)
    return packets


# -- CRC ---------------------------------------------------------------------------------------------


def test_crc_check_value_of_the_catalogue() -> None:
    assert crc16(b"123456789") == 0xFEE8  # CRC-16/UMTS (alias BUYPASS) check value
    assert crc16(b"") == 0


def test_crc_of_an_emanual_packet() -> None:
    # PING ID 1 from the e-Manual: CRC 0x4E19 sent as 19 4E.
    assert crc16(bytes.fromhex("FF FF FD 00 01 03 00 01")) == 0x4E19


@given(st.binary(max_size=300), st.binary(max_size=50))
@settings(max_examples=300, deadline=None)
def test_crc_table_matches_bitwise_and_sdk_and_continues(head: bytes, tail: bytes) -> None:
    data = head + tail
    assert crc16(data) == crc16_bitwise(data) == SDK.updateCRC(0, list(data), len(data))
    assert crc16(tail, crc16(head)) == crc16(data)


# -- the e-Manual's packets --------------------------------------------------------------------------


def emanual_packets(shared_data: Path) -> list[tuple[str, bytes]]:
    path = shared_data / "dynamixel" / "protocol2_emanual_packets.tsv"
    if not path.is_file():
        pytest.skip(f"{path} not found")
    rows = []
    for line in path.read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            name, hexbytes = line.split("\t")
            rows.append((name, bytes.fromhex(hexbytes)))
    return rows


def test_emanual_packets_decode_and_reencode_byte_for_byte(shared_data: Path) -> None:
    rows = emanual_packets(shared_data)
    assert len(rows) == 20
    for name, frame in rows:
        packet = decode_packet(frame)
        assert packet.encode() == frame, name
        if isinstance(packet, InstructionPacket):
            assert encode_instruction(packet.id, parse_command(packet)) == frame, name


def test_emanual_packets_have_the_documented_meaning(shared_data: Path) -> None:
    packets = {name: decode_packet(frame) for name, frame in emanual_packets(shared_data)}

    def command(name: str) -> Command:
        packet = packets[name]
        assert isinstance(packet, InstructionPacket)
        return parse_command(packet)

    def status(name: str) -> StatusPacket:
        packet = packets[name]
        assert isinstance(packet, StatusPacket)
        return packet

    reply = parse_ping_reply(status("ping id1 status XM430 1030 fw38"))
    assert (reply.id, reply.model_number, reply.firmware_version) == (1, 1030, 38)
    assert packets["ping broadcast"].id == BROADCAST_ID
    assert command("read id1 pos(132,4)") == Read(132, 4)
    assert int.from_bytes(status("read status 166").params, "little") == 166
    assert command("write goal pos 512") == Write(116, (512).to_bytes(4, "little"))
    assert command("reg_write goal vel 200") == RegWrite(104, (200).to_bytes(4, "little"))
    assert command("factory reset opt1") == FactoryReset(0x01)
    assert command("reboot id1") == Reboot()
    assert command("clear multiturn") == Clear(0x01, b"\x44\x58\x4c\x22")
    assert command("sync read pos ids 1,2") == SyncRead(132, 4, (1, 2))
    assert command("sync write goal 150/170") == SyncWrite(
        116, 4, {1: (150).to_bytes(4, "little"), 2: (170).to_bytes(4, "little")}
    )
    assert command("bulk read") == BulkRead((BulkReadEntry(1, 144, 2), BulkReadEntry(2, 146, 1)))
    assert command("bulk write") == BulkWrite(
        (BulkWriteEntry(1, 32, (160).to_bytes(2, "little")), BulkWriteEntry(2, 31, b"\x50"))
    )
    assert status("empty status id1").params == b"" and status("empty status id1").status == StatusError(
        False, 0
    )
    assert status("bulk read id2 status 36").params == b"\x24"


# Fast Sync Read example from the e-Manual (protocol2.md, "Fast Sync Read (0x8A)"): three XC330s.
FAST_SYNC_READ = bytes.fromhex("FF FF FD 00 FE 0A 00 8A 84 00 04 00 03 07 04 20 F2")
FAST_SYNC_REPLY = bytes.fromhex(
    "FF FF FD 00 FE 19 00 55 00 03 A6 00 00 00 84 08 00 07 1F 08 00 00 16 CA 00 04 FF 03 00 00 D1 9E"
)


def test_fast_sync_read_example_round_trips_with_intermediate_crcs() -> None:
    packet = decode_packet(FAST_SYNC_READ)
    assert isinstance(packet, InstructionPacket)
    assert parse_command(packet) == FastSyncRead(132, 4, (3, 7, 4))
    items = (
        FastReadItem(3, 0, (166).to_bytes(4, "little")),
        FastReadItem(7, 0, (2079).to_bytes(4, "little")),
        FastReadItem(4, 0, (1023).to_bytes(4, "little")),
    )
    assert encode_fast_read_status(items) == FAST_SYNC_REPLY
    reply = decode_packet(FAST_SYNC_REPLY)
    assert isinstance(reply, StatusPacket)
    assert parse_fast_read_status(reply, [4, 4, 4]) == items


def test_fast_read_reply_is_not_stuffed_and_a_bad_inner_crc_is_caught() -> None:
    data = b"\xff\xff\xfd\xfd"  # would be unstuffed to FF FF FD if the decoder treated it as stuffed
    frame = encode_fast_read_status([FastReadItem(1, 0x80, data), FastReadItem(2, 0, b"\x01\x02\x03\x04")])
    (packet,) = DynamixelDecoder().feed(frame)
    assert isinstance(packet, StatusPacket)
    items = parse_fast_read_status(packet, [4, 4])
    assert items[0] == FastReadItem(1, 0x80, data) and items[1].data == b"\x01\x02\x03\x04"
    damaged = StatusPacket(
        packet.id, packet.error, packet.params[:5] + bytes((packet.params[5] ^ 1,)) + packet.params[6:]
    )
    with pytest.raises(DynamixelError) as info:
        parse_fast_read_status(damaged, [4, 4])
    assert info.value.crc_mismatch
    with pytest.raises(DynamixelError):
        parse_fast_read_status(packet, [4, 3])


# -- stuffing ----------------------------------------------------------------------------------------


def sdk_frame(packet_id: int, instruction: int, params: bytes) -> bytes:
    """The SDK's own way to frame a packet (addStuffing, then updateCRC): an independent encoder."""
    length = len(params) + 3
    packet = [0xFF, 0xFF, 0xFD, 0x00, packet_id, length & 0xFF, length >> 8, instruction, *params, 0, 0]
    packet = SDK.addStuffing(packet)
    total = (packet[5] | packet[6] << 8) + 7
    crc = SDK.updateCRC(0, packet, total - 2)
    packet[total - 2 : total] = [crc & 0xFF, crc >> 8]
    return bytes(packet[:total])


def test_stuffing_of_ff_ff_fd_in_a_write() -> None:
    frame = encode_write(1, 116, b"\xff\xff\xfd\x00")
    # LEN grows from 9 to 10; the stuffed FD follows FF FF FD; the CRC covers the stuffed bytes.
    assert frame[:7] == HEADER + b"\x01\x0a\x00"
    assert frame[7:-2] == b"\x03\x74\x00\xff\xff\xfd\xfd\x00"
    assert frame == sdk_frame(1, Instruction.WRITE, b"\x74\x00\xff\xff\xfd\x00")
    packet = decode_packet(frame)
    assert packet == InstructionPacket(1, Instruction.WRITE, b"\x74\x00\xff\xff\xfd\x00")


def test_status_with_ff_ff_fd_is_stuffed_and_unstuffed() -> None:
    frame = encode_status(1, 0, b"\xff\xff\xfd\x00")  # READ of 0x00FDFFFF
    assert b"\xff\xff\xfd\xfd" in frame[7:]
    assert DynamixelDecoder().feed(frame) == [StatusPacket(1, 0, b"\xff\xff\xfd\x00")]
    (sdk_view := list(frame))
    assert bytes(SDK.removeStuffing(sdk_view)[9:13]) == b"\xff\xff\xfd\x00"


@given(st.binary(max_size=200))
@settings(max_examples=300, deadline=None)
def test_stuffing_round_trips_and_leaves_no_false_header(data: bytes) -> None:
    assert unstuff(stuff(data)) == data
    frame = encode_packet(3, Instruction.WRITE, data)
    assert frame == sdk_frame(3, Instruction.WRITE, data)
    region = frame[7:-2]
    # After stuffing, every FF FF FD inside the packet is followed by FD: no receiver can see a header.
    for i in range(len(region) - 2):
        if region[i : i + 3] == b"\xff\xff\xfd":
            assert region[i + 3 : i + 4] == b"\xfd"
    assert decode_packet(frame) == InstructionPacket(3, Instruction.WRITE, data)


# -- typed instructions ------------------------------------------------------------------------------

COMMANDS: list[tuple[int, Command]] = [
    (1, Ping()),
    (BROADCAST_ID, Ping()),
    (2, Read(132, 4)),
    (2, Write(104, (-200).to_bytes(4, "little", signed=True))),
    (2, RegWrite(104, b"\x01\x00\x00\x00")),
    (BROADCAST_ID, FactoryReset(0xFF)),
    (7, Clear()),
    (BROADCAST_ID, SyncRead(128, 8, (1, 2))),
    (BROADCAST_ID, FastSyncRead(128, 8, (2, 1))),
    (BROADCAST_ID, SyncWrite(104, 4, {2: b"\x00\x00\x00\x00", 1: b"\xff\xff\xfd\x00"})),
    (BROADCAST_ID, BulkRead((BulkReadEntry(1, 132, 4), BulkReadEntry(2, 70, 1)))),
    (BROADCAST_ID, FastBulkRead((BulkReadEntry(5, 146, 1),))),
    (BROADCAST_ID, BulkWrite((BulkWriteEntry(1, 64, b"\x01"), BulkWriteEntry(2, 104, b"\x10\x00\x00\x00")))),
]


@pytest.mark.parametrize(("packet_id", "command"), COMMANDS, ids=lambda c: type(c).__name__)
def test_every_instruction_round_trips(packet_id: int, command: Command) -> None:
    frame = encode_instruction(packet_id, command)
    instruction, params = command_params(command)
    assert frame == sdk_frame(packet_id, instruction, params)
    packet = decode_packet(frame)
    assert isinstance(packet, InstructionPacket) and packet.id == packet_id
    assert parse_command(packet) == command


def test_sync_write_keeps_wire_order_and_is_frozen() -> None:
    data = {2: b"\x02\x00\x00\x00", 1: b"\x01\x00\x00\x00"}
    command = SyncWrite(104, 4, data)
    data[3] = b"\x03\x00\x00\x00"  # the caller's dict is not the message's
    assert list(command.data) == [2, 1]
    assert hash(command) == hash(SyncWrite(104, 4, {2: b"\x02\x00\x00\x00", 1: b"\x01\x00\x00\x00"}))
    assert encode_sync_write(104, 4, {2: b"\x02\x00\x00\x00", 1: b"\x01\x00\x00\x00"})[12] == 2


@pytest.mark.parametrize(
    ("instruction", "params"),
    [
        (Instruction.READ, b"\x84\x00\x04"),
        (Instruction.PING, b"\x00"),
        (Instruction.WRITE, b"\x74"),
        (Instruction.FACTORY_RESET, b""),
        (Instruction.SYNC_READ, b"\x84\x00\x04\x00"),
        (Instruction.SYNC_READ, b"\x84\x00\x04\x00\x01\x01"),
        (Instruction.SYNC_WRITE, b"\x68\x00\x04\x00\x01\x00\x00\x00"),
        (Instruction.SYNC_WRITE, b"\x68\x00\x00\x00\x01"),
        (Instruction.BULK_READ, b"\x01\x84\x00\x04"),
        (Instruction.BULK_WRITE, b"\x01\x40\x00\x02\x00\x01"),
        (Instruction.BULK_WRITE, b""),
        (Instruction.CLEAR, b""),
        (Instruction.STATUS, b""),
        (0x77, b""),
    ],
)
def test_malformed_parameters_raise_dynamixel_error(instruction: int, params: bytes) -> None:
    with pytest.raises(DynamixelError) as info:
        parse_command(InstructionPacket(1, instruction, params))
    assert info.value.packet_id == 1


def test_encoders_reject_invalid_arguments() -> None:
    with pytest.raises(ValueError):
        encode_ping(0xFD)
    with pytest.raises(ValueError):
        encode_read(1, 0x10000, 1)
    with pytest.raises(ValueError):
        encode_sync_write(104, 4, {1: b"\x00"})
    with pytest.raises(ValueError):
        encode_instruction(BROADCAST_ID, SyncRead(128, 8, (1, 1)))
    with pytest.raises(ValueError):
        encode_write(1, 0, bytes(MAX_PACKET_BYTES))


def test_status_error_byte() -> None:
    assert StatusError.from_byte(0x87) == StatusError(alert=True, number=ErrorNumber.ACCESS)
    assert StatusError.from_byte(0x87).failed and not StatusError.from_byte(0x80).failed
    assert StatusError.from_byte(0x84).byte == 0x84
    assert (
        "access" in StatusError.from_byte(7).describe() and "alert" in StatusError.from_byte(0x80).describe()
    )
    assert "unknown" in StatusError.from_byte(0x42).describe()


# -- whole-packet decoding ---------------------------------------------------------------------------


def test_decode_packet_rejects_damage_with_the_bytes() -> None:
    good = encode_read(1, 132, 4)
    with pytest.raises(DynamixelError) as info:
        decode_packet(good[:-1] + bytes((good[-1] ^ 0x40,)))
    assert (
        info.value.crc_mismatch
        and info.value.packet_id == 1
        and info.value.data == good[:-1] + bytes((good[-1] ^ 0x40,))
    )
    for bad in (
        good[:9],
        b"\x00" + good[1:],
        good + b"\x00",
        good[:4] + b"\xfd" + good[5:],
        HEADER + b"\x01\x02\x00\x01\x00\x00",
        encode_packet(1, Instruction.STATUS, b""),
    ):
        with pytest.raises(DynamixelError):
            decode_packet(bad)


# -- the streaming decoder ---------------------------------------------------------------------------

STREAM = [
    encode_ping(1),
    encode_status(1, 0, b"\x64\x04\x2e"),
    encode_read(2, 128, 8),
    encode_status(2, 0x80, b"\xff\xff\xfd\x00\x10\x00\x00\x00"),
    encode_sync_write(104, 4, {1: b"\x10\x00\x00\x00", 2: b"\xf0\xff\xff\xff"}),
]


def expected_stream_packets() -> list[Packet]:
    return [decode_packet(frame) for frame in STREAM]


def test_decoder_whole_and_byte_by_byte() -> None:
    data = b"".join(STREAM)
    expected = expected_stream_packets()
    assert exercise_decoder(data, [len(data)]) == expected
    assert exercise_decoder(data, [1]) == expected
    assert exercise_decoder(data, [3, 1, 7, 2]) == expected


def test_decoder_keeps_trailing_bytes_for_the_next_feed() -> None:
    decoder = DynamixelDecoder()
    tail = encode_read(1, 132, 4)
    assert decoder.feed(STREAM[0] + tail[:9]) == [decode_packet(STREAM[0])]
    assert decoder.buffered == 9 and decoder.discarded_bytes == 0
    assert decoder.feed(tail[9:]) == [decode_packet(tail)]
    assert decoder.buffered == 0 and decoder.packets == 2


def test_decoder_resyncs_after_junk_and_a_bad_crc() -> None:
    junk = b"\x00\x13\xff\xfe\xff\xff\xfd\xfd\x42"  # includes a stuffed FF FF FD FD, which is no header
    damaged = bytearray(encode_read(1, 132, 4))
    damaged[-1] ^= 0xFF
    data = STREAM[0] + junk + bytes(damaged) + STREAM[2] + b"\xff\xff\xfd" + STREAM[3]
    for chunks in ([len(data)], [1], [5, 2]):
        decoder = DynamixelDecoder()
        packets: list[Packet] = []
        for i in range(0, len(data), chunks[0]):
            packets += decoder.feed(data[i : i + chunks[0]])
        assert packets == [decode_packet(STREAM[0]), decode_packet(STREAM[2]), decode_packet(STREAM[3])]
        assert decoder.discarded_bytes == len(junk) + len(damaged) + 3
        assert decoder.crc_errors == 1
        errors = decoder.take_errors()
        crc_errors = [e for e in errors if e.crc_mismatch]
        assert len(crc_errors) == 1 and crc_errors[0].packet_id == 1 and crc_errors[0].data == bytes(damaged)
        assert decoder.take_errors() == []


def test_a_false_header_does_not_swallow_the_packets_it_spans() -> None:
    # Junk that looks like a header announcing 32 bytes: the real packets inside those 32 bytes must
    # still come out once the false frame's CRC fails, so the decoder resyncs one byte after the false header.
    false_header = HEADER + b"\x01\x20\x00"
    data = false_header + STREAM[0] + STREAM[2] + bytes(30)
    decoder = DynamixelDecoder()
    assert decoder.feed(data) == [decode_packet(STREAM[0]), decode_packet(STREAM[2])]
    assert decoder.crc_errors == 1 and decoder.discarded_bytes == len(false_header) + 30 - decoder.buffered


def test_decoder_rejects_impossible_headers_at_once() -> None:
    # A header with ID 0xFF, or a LEN above the bound, must not make the decoder wait for that many bytes.
    decoder = DynamixelDecoder(max_length=64)
    bad = HEADER + b"\xff\x03\x00" + HEADER + b"\x01\xff\x00" + HEADER + b"\x01\x02\x00"
    assert decoder.feed(bad + STREAM[0]) == [decode_packet(STREAM[0])]
    assert decoder.bad_headers == 3 and decoder.discarded_bytes == len(bad) and decoder.buffered == 0


def test_decoder_reset_drops_a_partial_packet() -> None:
    decoder = DynamixelDecoder()
    decoder.feed(STREAM[2][:8])
    assert decoder.reset() == 8 and decoder.discarded_bytes == 8
    assert decoder.feed(STREAM[2]) == [decode_packet(STREAM[2])]


# -- properties --------------------------------------------------------------------------------------

_chunkings = st.lists(st.integers(min_value=1, max_value=64), min_size=1, max_size=5)


@given(st.binary(max_size=600), _chunkings)
@settings(max_examples=2000, deadline=None, suppress_health_check=[HealthCheck.too_slow])
def test_random_bytes_give_packets_or_dynamixel_error_only(data: bytes, chunks: list[int]) -> None:
    exercise_decoder(data, chunks)
    exercise_decoder(data, chunks, max_length=16)


@st.composite
def packet_streams(draw: st.DrawFn) -> list[bytes]:
    frames = []
    for _ in range(draw(st.integers(min_value=1, max_value=5))):
        packet_id = draw(st.integers(min_value=0, max_value=0xFC))
        if draw(st.booleans()):
            frames.append(encode_status(packet_id, draw(st.integers(0, 255)), draw(st.binary(max_size=40))))
        else:
            frames.append(
                encode_packet(
                    packet_id,
                    draw(st.integers(0, 255).filter(lambda i: i != 0x55)),
                    draw(st.binary(max_size=40)),
                )
            )
    return frames


@given(
    packet_streams(),
    st.lists(st.binary(max_size=30).map(lambda b: b.replace(b"\xfd", b"")), min_size=6, max_size=6),
    _chunkings,
)
@settings(max_examples=500, deadline=None)
def test_junk_without_headers_between_packets_loses_nothing(
    frames: list[bytes], junk: list[bytes], chunks: list[int]
) -> None:
    # Junk that cannot hold a header (no FD byte) is skipped exactly; each packet still decodes.
    data = junk[0] + b"".join(frame + junk[i + 1] for i, frame in enumerate(frames))
    packets = exercise_decoder(data, chunks)
    assert packets == [decode_packet(frame) for frame in frames]


# Junk made of random bytes and pieces of headers, so that false headers (with plausible IDs and LENs)
# turn up often rather than once in 2**32 bytes.
_junk = st.lists(
    st.one_of(
        st.binary(max_size=12),
        st.sampled_from([HEADER, HEADER[:3], HEADER[:2]]),
        st.builds(lambda i, n: HEADER + bytes((i, n, 0)), st.integers(0, 0xFE), st.integers(0, 60)),
    ),
    max_size=4,
).map(b"".join)


@given(packet_streams(), st.lists(_junk, min_size=6, max_size=6), _chunkings)
@settings(max_examples=500, deadline=None)
def test_any_junk_between_packets_resyncs(frames: list[bytes], junk: list[bytes], chunks: list[int]) -> None:
    # Junk may hold false headers; once enough bytes follow to complete any frame they announce (and fail
    # its CRC), every real packet is found again, in order.
    data = junk[0] + b"".join(frame + junk[i + 1] for i, frame in enumerate(frames)) + bytes(MAX_PACKET_BYTES)
    packets = iter(exercise_decoder(data, [*chunks, 97]))
    for frame in frames:
        assert decode_packet(frame) in packets  # a subsequence: junk can hold a valid packet of its own


@given(packet_streams(), st.integers(min_value=0, max_value=2**32 - 1), st.integers(1, 6))
@settings(max_examples=500, deadline=None)
def test_mutated_streams_give_packets_or_dynamixel_error_only(
    frames: list[bytes], seed: int, mutations: int
) -> None:
    rng = random.Random(seed)
    data = bytearray(b"".join(frames))
    for _ in range(mutations):
        where = rng.randrange(len(data) + 1)
        match rng.randrange(4):
            case 0 if where < len(data):
                data[where] ^= 1 << rng.randrange(8)
            case 1:
                data[where:where] = bytes(rng.randrange(256) for _ in range(rng.randrange(1, 8)))
            case 2:
                del data[where : where + rng.randrange(1, 8)]
            case _:
                data[where:where] = HEADER[: rng.randrange(1, 5)]
    exercise_decoder(bytes(data), [rng.randrange(1, 40) for _ in range(3)])
