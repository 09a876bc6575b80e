"""RFID codecs: published vectors, real captures, whole / byte-by-byte / trailing bytes, junk, bad checksums,
and property tests ("any input decodes or raises RfidError; the stream decoders never invent a frame").

Vectors: ID-12LA frame from WildernessLabs/Meadow.Foundation ``IDxxLA.cs``; RDM6300 checksum from
``../shared/reference/devices.md``; Mercury bytes from sparkfun/SparkFun_Simultaneous_RFID_Tag_Reader_Library
(``src/SparkFun_UHF_RFID_Reader.cpp`` comments, and "Example Communication Logs/5-596F569F 7 counts
-63dbm.txt", a transport log of a real M6e Nano).

:func:`fuzz` runs the stream-decoder properties with any number of examples, for ``benchmarks/``.
"""

from __future__ import annotations

import itertools
import random
from collections.abc import Callable

import pytest
from hypothesis import given, seed, settings
from hypothesis import strategies as st

from firmware_protocol.errors import ProtocolError
from firmware_protocol.rfid import (
    ASCII_FRAME_LENGTH,
    MERCURY_MAX_FRAME,
    AsciiFormat,
    AsciiFrameDecoder,
    AsciiTag,
    MercuryKeepAlive,
    MercuryRequest,
    MercuryRequestDecoder,
    MercuryResponse,
    MercuryResponseDecoder,
    MercuryStatus,
    MercuryTagRead,
    RfidChecksumError,
    RfidError,
    crc16_gen2,
    crc16_thingmagic,
    decode_ascii_frame,
    decode_request_frame,
    decode_response_frame,
    decode_stream_message,
    decode_tag_read,
    decode_version,
    encode_ascii_frame,
    encode_request,
    encode_response,
    encode_set_antenna_search_list,
    encode_set_read_power,
    encode_set_reader_option,
    encode_set_region,
    encode_set_tag_protocol,
    encode_start_continuous_read,
    encode_stop_continuous_read,
    encode_tag_read,
    encode_version_request,
    xor_checksum,
)


def h(text: str) -> bytes:
    return bytes.fromhex(text.replace(" ", ""))


ID12LA_FRAME = b"\x02" + b"7C0055F8C4" + b"15" + b"\r\n\x03"
RDM6300_FRAME = b"\x02" + b"13005D1DA5" + b"F6" + b"\x03"

# From the SparkFun transport log of a real M6e Nano (file named in the module docstring).
LOG_VERSION_RESPONSE = h("FF 14 03 00 00 14 12 08 00 30 00 00 02 20 15 03 10 01 03 01 47 00 00 00 10 EB FF")
LOG_KEEPALIVE = h("FF 00 22 04 00 84 E0")
LOG_START_ACK = h("FF 04 2F 00 00 01 22 00 00 6D C3")
LOG_STOP_ACK = h("FF 01 2F 00 00 02 30 E6")
_RECORD_HEAD = "FF 20 22 00 00 10 00 1B 01 FF 01 01"
_RECORD_EPC = "00 00 05 00 00 0F 00 40 10 00 59 6F 59 6F F3 13"
LOG_TAG_RECORDS = [
    # RSSI, antenna, frequency, timestamp | phase ... EPC | message CRC
    h(f"{_RECORD_HEAD} C1 11 0E 16 40 00 00 00 2E {_RECORD_EPC} 0E B0"),
    h(f"{_RECORD_HEAD} C3 11 0E 16 40 00 00 00 43 {_RECORD_EPC} 61 B0"),
    h(f"{_RECORD_HEAD} C1 11 0E 24 50 00 00 03 CC {_RECORD_EPC} AE E5"),
    h(f"{_RECORD_HEAD} C3 11 0E 0C E0 00 00 00 55 {_RECORD_EPC} B6 AE"),
]
# The example in SparkFun's parseResponse() comment: a 96-bit EPC read at -60 dBm.
SPARKFUN_COMMENT_RECORD = h(
    "FF 28 22 00 00 10 00 1B 01 FF 01 01 C4 11 0E 16 40 00 00 01 27 00 00 05 00 00 0F 00 80 30 00 00"
    "00 00 00 00 00 00 00 00 00 15 45 E9 4A 56 1D"
)


# ---------------------------------------------------------------------------------------------------
# 125 kHz vectors
# ---------------------------------------------------------------------------------------------------


def test_xor_checksum_vectors() -> None:
    assert xor_checksum(h("7C0055F8C4")) == 0x15
    assert xor_checksum(h("13005D1DA5")) == 0xF6


@pytest.mark.parametrize(
    ("fmt", "frame", "data"),
    [
        (AsciiFormat.ID12LA, ID12LA_FRAME, h("7C0055F8C4")),
        (AsciiFormat.RDM6300, RDM6300_FRAME, h("13005D1DA5")),
    ],
)
def test_ascii_encode_decode_vectors(fmt: AsciiFormat, frame: bytes, data: bytes) -> None:
    assert len(frame) == ASCII_FRAME_LENGTH[fmt]
    assert encode_ascii_frame(data, fmt) == frame
    tag = decode_ascii_frame(frame, fmt)
    assert tag == AsciiTag(data, fmt)
    assert tag.tag_id == data.hex().upper()
    assert tag.version == data[0]
    assert tag.card_number == int.from_bytes(data[1:], "big")


def test_ascii_lower_case_hex_is_accepted() -> None:
    frame = b"\x02" + b"7c0055f8c4" + b"15" + b"\r\n\x03"
    assert decode_ascii_frame(frame, "id12la").tag_id == "7C0055F8C4"


@pytest.mark.parametrize(
    ("frame", "reason"),
    [
        (ID12LA_FRAME[:-1], "must be 16 bytes"),
        (ID12LA_FRAME + b"\x00", "must be 16 bytes"),
        (b"\x03" + ID12LA_FRAME[1:], "must start with STX"),
        (ID12LA_FRAME[:13] + b"\n\r\x03", "must end with"),
        (b"\x02" + b"7C0055F8C 15" + b"\r\n\x03", "not ASCII hex"),  # bytes.fromhex would skip the space
        (b"\x02" + b"7C0055F8C4" + b"16" + b"\r\n\x03", "checksum 16 != XOR of data 15"),
    ],
)
def test_ascii_decode_rejects_with_the_bytes(frame: bytes, reason: str) -> None:
    with pytest.raises(RfidError) as info:
        decode_ascii_frame(frame, "id12la")
    assert reason in info.value.reason
    assert info.value.data == frame
    assert isinstance(info.value, ProtocolError)


def test_ascii_bad_checksum_is_its_own_class() -> None:
    with pytest.raises(RfidChecksumError):
        decode_ascii_frame(b"\x0213005D1DA5F7\x03", "rdm6300")


def test_rdm6300_frame_is_not_an_id12la_frame() -> None:
    with pytest.raises(RfidError):
        decode_ascii_frame(RDM6300_FRAME, "id12la")
    decoder = AsciiFrameDecoder("id12la")
    assert decoder.feed(RDM6300_FRAME * 3) == []
    assert decoder.frames == 0


def test_ascii_encoder_refuses_wrong_length() -> None:
    with pytest.raises(RfidError):
        encode_ascii_frame(b"\x01\x02\x03\x04", "rdm6300")


# ---------------------------------------------------------------------------------------------------
# 125 kHz streaming
# ---------------------------------------------------------------------------------------------------


def _ascii_stream(fmt: AsciiFormat, n: int, rng: random.Random) -> tuple[bytes, list[AsciiTag]]:
    tags = [AsciiTag(bytes(rng.randrange(256) for _ in range(5)), fmt) for _ in range(n)]
    return b"".join(encode_ascii_frame(t.data, fmt) for t in tags), tags


@pytest.mark.parametrize("fmt", list(AsciiFormat))
def test_ascii_stream_whole_and_byte_by_byte(fmt: AsciiFormat) -> None:
    stream, tags = _ascii_stream(fmt, 20, random.Random(1))
    whole = AsciiFrameDecoder(fmt)
    assert whole.feed(stream) == tags
    single = AsciiFrameDecoder(fmt)
    got = [tag for byte in stream for tag in single.feed(bytes([byte]))]
    assert got == tags
    for decoder in (whole, single):
        assert decoder.counters() == {"frames": 20, "discarded_bytes": 0, "resyncs": 0, "bad_checksums": 0}
        assert decoder.pending == 0


def test_ascii_trailing_bytes_wait_for_the_rest() -> None:
    decoder = AsciiFrameDecoder("id12la")
    assert len(decoder.feed(ID12LA_FRAME + ID12LA_FRAME[:7])) == 1
    assert decoder.pending == 7
    assert len(decoder.feed(ID12LA_FRAME[7:])) == 1
    assert decoder.pending == 0
    assert decoder.discarded_bytes == 0


def test_ascii_junk_and_bad_checksums_between_frames_resync_and_count() -> None:
    bad = b"\x02" + b"7C0055F8C4" + b"16" + b"\r\n\x03"  # checksum off by one
    junk = b"hello\r\n\x03\x00\xff"
    stream = junk + ID12LA_FRAME + bad + bad + ID12LA_FRAME + junk + b"\x02\x02" + ID12LA_FRAME + junk
    decoder = AsciiFrameDecoder("id12la")
    tags = decoder.feed(stream)
    assert [t.tag_id for t in tags] == ["7C0055F8C4"] * 3
    assert decoder.bad_checksums == 2
    # Every byte is accounted for: in a frame, discarded, or (here: none) pending.
    assert decoder.discarded_bytes == 3 * len(junk) + 2 * len(bad) + 2
    assert decoder.resyncs == 4  # junk runs: leading junk, the two bad frames, junk + STXs, trailing junk
    assert isinstance(decoder.last_error, RfidError)


def test_ascii_truncated_frame_followed_by_a_good_one() -> None:
    decoder = AsciiFrameDecoder("rdm6300")
    tags = decoder.feed(RDM6300_FRAME[:9] + RDM6300_FRAME)
    assert [t.tag_id for t in tags] == ["13005D1DA5"]
    assert decoder.discarded_bytes == 9


def test_ascii_flush_drops_a_partial_frame() -> None:
    decoder = AsciiFrameDecoder("rdm6300")
    assert decoder.feed(RDM6300_FRAME[:5]) == []
    assert decoder.flush() == []
    assert decoder.pending == 0
    assert decoder.discarded_bytes == 5
    assert decoder.feed(RDM6300_FRAME)[0].tag_id == "13005D1DA5"


# ---------------------------------------------------------------------------------------------------
# Mercury vectors
# ---------------------------------------------------------------------------------------------------


def _crc16_ccitt_false(data: bytes) -> int:
    crc = 0xFFFF
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) & 0xFFFF if crc & 0x8000 else (crc << 1) & 0xFFFF
    return crc


def test_thingmagic_crc_vectors() -> None:
    assert crc16_thingmagic(b"123456789") == 0xA69D
    # Same polynomial and init, but not the same CRC: ThingMagic shifts the data in (augmented form).
    assert _crc16_ccitt_false(b"123456789") == 0x29B1
    assert crc16_thingmagic(h("00 03")) == 0x1D0C


def test_request_vectors() -> None:
    assert encode_version_request() == h("FF 00 03 1D 0C")
    # SparkFun writeData() comment: timeout 1000 ms, option 0, address 0, bank 3, data 00 EE.
    assert encode_request(0x24, h("03 E8 00 00 00 00 00 03 00 EE")) == h(
        "FF 0A 24 03 E8 00 00 00 00 00 03 00 EE 58 9D"
    )
    # The connect sequence as the transport log has it.
    assert encode_set_region(0x0D) == h("FF 01 97 0D 4B B0")
    assert encode_set_tag_protocol() == h("FF 02 93 00 05 51 7D")
    assert encode_set_antenna_search_list([(1, 1)]) == h("FF 03 91 02 01 01 42 C5")
    assert encode_set_read_power(2700) == h("FF 02 92 0A 8C 4B D5")
    assert encode_set_reader_option(0x0C, 0x00) == h("FF 03 9A 01 0C 00 A3 5D")
    assert encode_start_continuous_read() == h(
        "FF 10 2F 00 00 01 22 00 00 05 07 22 10 00 1B 03 E8 01 FF DD 2B"
    )
    assert encode_stop_continuous_read() == h("FF 03 2F 00 00 02 5E 86")


def test_request_frames_round_trip() -> None:
    frame = encode_set_read_power(500)
    assert decode_request_frame(frame) == MercuryRequest(0x92, h("01 F4"))
    with pytest.raises(RfidChecksumError):
        decode_request_frame(frame[:-1] + bytes([frame[-1] ^ 1]))


def test_encoders_refuse_what_does_not_fit() -> None:
    with pytest.raises(RfidError):
        encode_request(0x100)
    with pytest.raises(RfidError):
        encode_request(0x03, bytes(256))
    with pytest.raises(RfidError):
        encode_response(0x22, 0x10000)
    with pytest.raises(RfidError):
        encode_set_read_power(40000)
    with pytest.raises(RfidError):
        encode_set_antenna_search_list([])


def test_real_version_response() -> None:
    response = decode_response_frame(LOG_VERSION_RESPONSE)
    assert (response.opcode, response.status, len(response.data)) == (0x03, 0, 20)
    version = decode_version(response)
    assert version.bootloader == h("14 12 08 00")
    assert version.hardware == h("30 00 00 02")
    assert version.firmware_date == h("20 15 03 10")
    assert version.firmware == "01.03.01.47"
    assert version.protocols == 0x10


def test_real_keepalive_and_acks() -> None:
    keepalive = decode_stream_message(decode_response_frame(LOG_KEEPALIVE))
    assert keepalive == MercuryKeepAlive(MercuryStatus.NO_TAGS_FOUND)
    assert not keepalive.temperature_throttled
    start = decode_stream_message(decode_response_frame(LOG_START_ACK))
    assert start == MercuryResponse(0x2F, 0, h("01 22 00 00"))
    stop = decode_stream_message(decode_response_frame(LOG_STOP_ACK))
    assert stop == MercuryResponse(0x2F, 0, h("02"))


def test_real_tag_records() -> None:
    reads = [decode_tag_read(decode_response_frame(frame)) for frame in LOG_TAG_RECORDS]
    assert [r.rssi_dbm for r in reads] == [-63, -61, -63, -61]
    assert [r.frequency_khz for r in reads] == [923_200, 923_200, 926_800, 920_800]
    assert [r.timestamp_ms for r in reads] == [0x2E, 0x43, 0x3CC, 0x55]
    for read, frame in zip(reads, LOG_TAG_RECORDS, strict=True):
        assert read.epc_hex == "596F596F"
        assert (read.tx_antenna, read.rx_antenna, read.antenna_byte) == (1, 1, 0x11)
        assert (read.protocol, read.phase_deg, read.pc) == (5, 0, 0x1000)
        assert read.epc_crc == 0xF313
        assert read.epc_crc_ok
        assert read.embedded_data == b""
        assert encode_tag_read(read) == frame  # the encoder reproduces the module's bytes exactly


def test_sparkfun_comment_record() -> None:
    read = decode_stream_message(decode_response_frame(SPARKFUN_COMMENT_RECORD))
    assert isinstance(read, MercuryTagRead)
    assert read.rssi_dbm == -60  # 0xC4
    assert read.frequency_khz == 0x0E1640
    assert read.timestamp_ms == 0x127
    assert read.pc == 0x3000
    assert read.epc_hex == "000000000000000000001545"
    assert read.epc_crc == 0xE94A
    assert read.epc_crc_ok


def test_gen2_crc_matches_real_tags() -> None:
    assert crc16_gen2(h("1000 596F596F")) == 0xF313
    assert crc16_gen2(h("3000 000000000000000000001545")) == 0xE94A


def test_tag_record_with_embedded_data_round_trips() -> None:
    read = MercuryTagRead(
        rssi_dbm=-71,
        tx_antenna=2,
        rx_antenna=2,
        frequency_khz=915_250,
        timestamp_ms=123_456,
        phase_deg=97,
        protocol=5,
        pc=0x3000,
        epc=bytes(range(12)),
        epc_crc=crc16_gen2(h("3000") + bytes(range(12))),
        embedded_data=h("AA BB CC"),
    )
    frame = encode_tag_read(read)
    assert decode_stream_message(decode_response_frame(frame)) == read


@pytest.mark.parametrize(
    ("data", "reason"),
    [
        (bytes(27), "too short"),
        # embedded data length promising more than there is
        (LOG_TAG_RECORDS[0][5:24] + h("FF FF") + LOG_TAG_RECORDS[0][26:-2], "embedded data"),
        # EPC length that is not whole bytes
        (LOG_TAG_RECORDS[0][5:27] + h("00 41") + LOG_TAG_RECORDS[0][29:-2], "not whole bytes"),
        # EPC length that disagrees with the record length
        (LOG_TAG_RECORDS[0][5:27] + h("00 50") + LOG_TAG_RECORDS[0][29:-2], "implied by"),
    ],
)
def test_bad_tag_records_raise(data: bytes, reason: str) -> None:
    with pytest.raises(RfidError) as info:
        decode_tag_read(MercuryResponse(0x22, 0, data))
    assert reason in info.value.reason


def test_stream_message_passes_other_responses_through() -> None:
    notice = MercuryResponse(0x22, 0, bytes(8))  # SparkFun's "unknown" 8-byte notice
    assert decode_stream_message(notice) is notice
    failed = MercuryResponse(0x97, MercuryStatus.INVALID_PARAMETER_VALUE)
    assert decode_stream_message(failed) is failed
    assert not failed.ok


@pytest.mark.parametrize(
    ("frame", "reason"),
    [
        (LOG_KEEPALIVE[:-1], "at least 7 bytes"),
        (LOG_KEEPALIVE + b"\x00", "LEN 0 needs 7 bytes"),
        (b"\xfe" + LOG_KEEPALIVE[1:], "must start with FF"),
        (LOG_KEEPALIVE[:-1] + b"\xe1", "CRC 84E1 != computed 84E0"),
        (b"\xff\x00", "at least 7 bytes"),
    ],
)
def test_response_decode_rejects_with_the_bytes(frame: bytes, reason: str) -> None:
    with pytest.raises(RfidError) as info:
        decode_response_frame(frame)
    assert reason in info.value.reason
    assert info.value.data == frame


# ---------------------------------------------------------------------------------------------------
# Mercury streaming
# ---------------------------------------------------------------------------------------------------

REAL_STREAM = (
    LOG_START_ACK + LOG_KEEPALIVE + b"".join(LOG_TAG_RECORDS) + LOG_KEEPALIVE + SPARKFUN_COMMENT_RECORD
)


def test_mercury_stream_whole_byte_by_byte_and_trailing() -> None:
    whole = MercuryResponseDecoder()
    expected = whole.feed(REAL_STREAM)
    assert len(expected) == 8
    assert [type(decode_stream_message(r)).__name__ for r in expected] == (
        ["MercuryResponse", "MercuryKeepAlive"]
        + ["MercuryTagRead"] * 4
        + ["MercuryKeepAlive", "MercuryTagRead"]
    )
    single = MercuryResponseDecoder()
    assert [r for byte in REAL_STREAM for r in single.feed(bytes([byte]))] == expected
    trailing = MercuryResponseDecoder()
    assert trailing.feed(REAL_STREAM + LOG_KEEPALIVE[:4]) == expected
    assert trailing.pending == 4
    assert trailing.feed(LOG_KEEPALIVE[4:]) == [MercuryResponse(0x22, 0x0400)]
    for decoder in (whole, single, trailing):
        assert decoder.discarded_bytes == 0
        assert decoder.resyncs == 0


def test_mercury_junk_and_bad_crc_between_frames_resync_and_count() -> None:
    corrupt = bytearray(LOG_TAG_RECORDS[0])
    corrupt[20] ^= 0x01  # the timestamp: the CRC no longer matches
    junk = b"\x00\x13\x37 noise "
    stream = junk + LOG_KEEPALIVE + bytes(corrupt) + LOG_TAG_RECORDS[1] + junk + LOG_TAG_RECORDS[2]
    decoder = MercuryResponseDecoder()
    got = decoder.feed(stream)
    assert [decode_stream_message(r) for r in got][1:] == [
        decode_tag_read(decode_response_frame(LOG_TAG_RECORDS[1])),
        decode_tag_read(decode_response_frame(LOG_TAG_RECORDS[2])),
    ]
    assert decoder.bad_checksums == 1  # the FF inside the bad record is re-tried but not counted again
    assert decoder.discarded_bytes == 2 * len(junk) + len(corrupt)
    assert decoder.resyncs == 3


def test_mercury_stray_header_with_a_long_len_is_released_at_idle() -> None:
    # FF 80 promises a 135-byte frame: the keep-alive behind it waits until the line goes idle.
    decoder = MercuryResponseDecoder()
    assert decoder.feed(b"\xff\x80" + LOG_KEEPALIVE) == []
    assert decoder.pending == 9
    assert decoder.flush() == [MercuryResponse(0x22, 0x0400)]
    assert decoder.pending == 0
    assert decoder.discarded_bytes == 2


def test_mercury_request_decoder_reads_the_connect_sequence() -> None:
    requests = [
        encode_stop_continuous_read(),
        encode_version_request(),
        encode_set_region(0x0D),
        encode_set_read_power(500),
        encode_start_continuous_read(),
    ]
    decoder = MercuryRequestDecoder()
    got = decoder.feed(b"\x00junk" + b"".join(requests))
    assert [r.opcode for r in got] == [0x2F, 0x03, 0x97, 0x92, 0x2F]
    assert got[3].data == h("01 F4")
    assert decoder.discarded_bytes == 5


def test_decoder_buffer_is_bounded() -> None:
    for decoder in (AsciiFrameDecoder("id12la"), MercuryResponseDecoder(), MercuryRequestDecoder()):
        for _ in range(50):
            decoder.feed(b"\xff\xfe" + bytes(range(200)))
            assert decoder.pending <= decoder.max_buffer
    with pytest.raises(ValueError):
        MercuryResponseDecoder(max_buffer=100)


# ---------------------------------------------------------------------------------------------------
# properties
# ---------------------------------------------------------------------------------------------------


def _reencode(message: object) -> bytes:
    if isinstance(message, AsciiTag):
        return encode_ascii_frame(message.data, message.format)
    if isinstance(message, MercuryResponse):
        return encode_response(message.opcode, message.status, message.data)
    assert isinstance(message, MercuryRequest)
    return encode_request(message.opcode, message.data)


def _decoders() -> list[AsciiFrameDecoder | MercuryResponseDecoder | MercuryRequestDecoder]:
    return [
        AsciiFrameDecoder("id12la"),
        AsciiFrameDecoder("rdm6300"),
        MercuryResponseDecoder(),
        MercuryRequestDecoder(),
    ]


_ONE_SHOT: list[Callable[[bytes], object]] = [
    lambda d: decode_ascii_frame(d, "id12la"),
    lambda d: decode_ascii_frame(d, "rdm6300"),
    decode_request_frame,
    decode_response_frame,
    lambda d: decode_stream_message(MercuryResponse(0x22, 0, d)),
    lambda d: decode_tag_read(MercuryResponse(0x22, 0, d)),
    lambda d: decode_version(MercuryResponse(0x03, 0, d)),
]


def check_invariants(data: bytes, cuts: list[int]) -> None:
    """What must hold for any input (the property the fuzz harness drives).

    * a one-shot decoder returns a message or raises :class:`RfidError` carrying bytes, nothing else;
    * a streaming ``feed`` never raises, and feeding ``data`` whole or cut at ``cuts`` gives the same
      messages;
    * every message re-encodes to bytes that occur in the input: a decoder never invents a frame;
    * every input byte is accounted for exactly once: in a message, discarded, or still pending;
    * the buffer stays within its bound, and ``flush`` empties it.
    """
    for decode in _ONE_SHOT:
        try:
            decode(data)
        except RfidError as exc:
            assert isinstance(exc.data, bytes)
    bounds = sorted({c % (len(data) + 1) for c in cuts} | {0, len(data)})
    pieces = [data[a:b] for a, b in itertools.pairwise(bounds)]
    for whole, chunked in zip(_decoders(), _decoders(), strict=True):
        messages = whole.feed(data)
        assert [m for piece in pieces for m in chunked.feed(piece)] == messages
        encoded = [_reencode(m) for m in messages]
        for frame, message in zip(encoded, messages, strict=True):
            # 125 kHz readers may send lower-case hex; the encoder writes upper case.
            assert frame in data if not isinstance(message, AsciiTag) else frame.upper() in data.upper()
        assert sum(map(len, encoded)) + whole.discarded_bytes + whole.pending == len(data)
        assert whole.pending <= whole.max_buffer
        assert whole.pending < (
            whole.frame_length if isinstance(whole, AsciiFrameDecoder) else MERCURY_MAX_FRAME
        )
        flushed = whole.flush()
        assert whole.pending == 0
        encoded += [_reencode(m) for m in flushed]
        assert sum(map(len, encoded)) + whole.discarded_bytes == len(data)
        assert whole.frames == len(encoded)


def _valid_frames() -> st.SearchStrategy[bytes]:
    five = st.binary(min_size=5, max_size=5)
    return st.one_of(
        five.map(lambda d: encode_ascii_frame(d, "id12la")),
        five.map(lambda d: encode_ascii_frame(d, "rdm6300")),
        st.sampled_from(
            [LOG_KEEPALIVE, LOG_VERSION_RESPONSE, LOG_START_ACK, SPARKFUN_COMMENT_RECORD, *LOG_TAG_RECORDS]
        ),
        st.builds(encode_response, st.integers(0, 255), st.integers(0, 0xFFFF), st.binary(max_size=40)),
        st.builds(encode_request, st.integers(0, 255), st.binary(max_size=40)),
    )


@st.composite
def _mutated_streams(draw: st.DrawFn) -> bytes:
    """Valid frames of both families with junk between them, then bytes flipped, dropped and inserted."""
    parts = draw(st.lists(st.one_of(_valid_frames(), st.binary(max_size=12)), max_size=8))
    data = bytearray(b"".join(parts))
    for _ in range(draw(st.integers(0, 4))):
        if not data:
            break
        op = draw(st.sampled_from(["flip", "drop", "insert"]))
        at = draw(st.integers(0, len(data) - 1))
        if op == "flip":
            data[at] ^= 1 << draw(st.integers(0, 7))
        elif op == "drop":
            del data[at]
        else:
            data.insert(at, draw(st.sampled_from([0x02, 0x03, 0xFF, 0x00, 0x0D])))
    return bytes(data)


_STREAMS = st.one_of(_mutated_streams(), st.binary(max_size=600))
_CUTS = st.lists(st.integers(0, 10_000), max_size=8)


def fuzz(max_examples: int = 2000, seed_value: int | None = None) -> None:
    """Run :func:`check_invariants` on ``max_examples`` random and mutated streams (for benchmarks)."""

    @settings(max_examples=max_examples, deadline=None, database=None)
    @given(_STREAMS, _CUTS)
    def run(data: bytes, cuts: list[int]) -> None:
        check_invariants(data, cuts)

    (seed(seed_value)(run) if seed_value is not None else run)()


def test_decoders_hold_their_invariants_on_random_and_mutated_input() -> None:
    fuzz(max_examples=2000)
