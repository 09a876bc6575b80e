"""The pose frame: CRC catalog values, the test vectors of ``docs/wire-format.md``, quantisation, the
versioning rule, and the stream decoder whole / byte by byte / with trailing bytes / with junk, truncated
and corrupted frames between good ones, plus property tests ("any input decodes or raises
PoseFrameError; the stream decoder never raises, and how the stream is cut never changes what it finds").
"""

from __future__ import annotations

import math
import re
import struct
from dataclasses import dataclass, replace
from pathlib import Path

import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from firmware_protocol.cobs import cobs_decode, cobs_encode
from firmware_protocol.crc import CRC16_CCITT_FALSE, CRC16_MCRF4XX, Crc16, crc16_ccitt_false
from firmware_protocol.errors import ProtocolError
from firmware_protocol.pose_frame import (
    MAX_ENCODED_LENGTH,
    PAYLOAD_LENGTH,
    WIRE_LENGTH,
    WIRE_VERSION,
    YAW_LSB_RAD,
    PoseCobsError,
    PoseCrcError,
    PoseFlags,
    PoseFrame,
    PoseFrameDecoder,
    PoseFrameError,
    PoseLengthError,
    PoseVersionError,
    decode_payload,
    decode_pose,
    encode_payload,
    encode_pose,
)

WIRE_FORMAT_MD = Path(__file__).resolve().parents[2] / "docs" / "wire-format.md"
F = PoseFlags


# -- the vectors of docs/wire-format.md ----------------------------------------------------------------


@dataclass(frozen=True)
class DocVector:
    title: str
    frame: PoseFrame
    raw: dict[str, int]
    payload: bytes
    crc: int
    wire: bytes


def _pairs(text: str) -> dict[str, str]:
    return dict(item.split("=", 1) for item in text.split())


def doc_vectors() -> list[DocVector]:
    """The ``fields`` / ``raw`` / ``payload`` / ``crc`` / ``wire`` blocks under "Test vectors"."""
    text = WIRE_FORMAT_MD.read_text(encoding="utf-8")
    section = text[text.index("## Test vectors") :]
    out = []
    for title, block in re.findall(r"### (Vector [^\n]*)\n.*?```text\n(.*?)```", section, re.S):
        lines = dict(line.split(":", 1) for line in block.strip().splitlines())
        f = _pairs(lines["fields"])
        frame = PoseFrame(
            sequence=int(f["sequence"]),
            t_us=int(f["t_us"]),
            x_m=float(f["x_m"]),
            y_m=float(f["y_m"]),
            yaw_rad=float(f["yaw_rad"]),
            sigma_xy_m=float(f["sigma_xy_m"]),
            sigma_yaw_rad=float(f["sigma_yaw_rad"]),
            flags=PoseFlags(int(f["flags"], 16)),
            reset_counter=int(f["reset_counter"]),
        )
        raw = {k: int(v, 0) for k, v in _pairs(lines["raw"]).items()}
        out.append(
            DocVector(
                title,
                frame,
                raw,
                bytes.fromhex(lines["payload"]),
                int(lines["crc"], 16),
                bytes.fromhex(lines["wire"]),
            )
        )
    return out


VECTORS = doc_vectors()


def test_the_doc_has_at_least_three_vectors() -> None:
    assert len(VECTORS) >= 3


@pytest.mark.parametrize("v", VECTORS, ids=lambda v: v.title)
def test_doc_vector_encodes_to_its_bytes(v: DocVector) -> None:
    assert encode_payload(v.frame) == v.payload
    assert crc16_ccitt_false(v.payload) == v.crc
    assert cobs_encode(v.payload + v.crc.to_bytes(2, "little")) + b"\x00" == v.wire
    assert encode_pose(v.frame) == v.wire
    assert len(v.wire) == WIRE_LENGTH == 34


@pytest.mark.parametrize("v", VECTORS, ids=lambda v: v.title)
def test_doc_vector_decodes_to_its_fields(v: DocVector) -> None:
    names = (
        "version",
        "reset_counter",
        "flags",
        "sequence",
        "t_us",
        "x",
        "y",
        "yaw",
        "sigma_xy",
        "sigma_yaw",
    )
    assert dict(zip(names, struct.unpack("<BBHIQiihHH", v.payload), strict=True)) == v.raw
    assert cobs_decode(v.wire[:-1]) == v.payload + v.crc.to_bytes(2, "little")
    got = decode_pose(v.wire)
    assert got == decode_pose(v.wire[:-1])  # the delimiter is optional for the one-shot decoder
    assert got.sequence == v.raw["sequence"] and got.t_us == v.raw["t_us"]
    assert got.flags == v.raw["flags"] and got.reset_counter == v.raw["reset_counter"]
    assert got.x_m == v.raw["x"] / 10_000 and got.y_m == v.raw["y"] / 10_000
    assert got.yaw_rad == v.raw["yaw"] * YAW_LSB_RAD
    for name in ("sigma_xy", "sigma_yaw"):
        q = v.raw[name]
        assert getattr(got, f"{name}_{'m' if name == 'sigma_xy' else 'rad'}") == (
            math.inf if q == 0xFFFF else q / 10_000
        )
    assert encode_pose(got) == v.wire
    assert PoseFrameDecoder().feed(v.wire) == [got]


# -- CRC ---------------------------------------------------------------------------------------------

CATALOG = [
    # name, poly, init, refin, refout, xorout, check  (reveng CRC catalogue; devices.md section 6)
    ("CRC-16/XMODEM", 0x1021, 0x0000, False, False, 0x0000, 0x31C3),
    ("CRC-16/KERMIT", 0x1021, 0x0000, True, True, 0x0000, 0x2189),
    ("CRC-16/X-25", 0x1021, 0xFFFF, True, True, 0xFFFF, 0x906E),
    ("CRC-16/MODBUS", 0x8005, 0xFFFF, True, True, 0x0000, 0x4B37),
    ("CRC-16/UMTS", 0x8005, 0x0000, False, False, 0x0000, 0xFEE8),
]


def test_crc_presets_match_their_check_values() -> None:
    assert crc16_ccitt_false(b"123456789") == 0x29B1 == CRC16_CCITT_FALSE.check
    assert CRC16_MCRF4XX.crc(b"123456789") == 0x6F91 == CRC16_MCRF4XX.check
    assert crc16_ccitt_false(b"") == 0xFFFF


@pytest.mark.parametrize("params", CATALOG, ids=lambda p: p[0])
def test_the_generic_crc_matches_the_catalog(params: tuple[str, int, int, bool, bool, int, int]) -> None:
    crc = Crc16(*params)
    assert crc.crc(b"123456789") == crc.check


def test_crc_bitwise_reference_agrees_with_the_table() -> None:
    def bitwise(data: bytes) -> int:
        reg = 0xFFFF
        for byte in data:
            reg ^= byte << 8
            for _ in range(8):
                reg = ((reg << 1) ^ 0x1021) & 0xFFFF if reg & 0x8000 else (reg << 1) & 0xFFFF
        return reg

    data = bytes(range(256)) * 3
    for n in (0, 1, 2, 30, 255, 768):
        assert crc16_ccitt_false(data[:n]) == bitwise(data[:n])


@given(st.binary(max_size=300))
def test_the_pose_frame_crc_is_the_generic_table_crc(data: bytes) -> None:
    # crc16_ccitt_false is binascii.crc_hqx from 0xFFFF; the parametrised table walk is the independent one.
    assert crc16_ccitt_false(data) == CRC16_CCITT_FALSE.crc(data)
    assert crc16_ccitt_false(memoryview(data)) == crc16_ccitt_false(bytearray(data))


def test_devices_md_example_frame() -> None:
    payload = bytes.fromhex("01020003")
    assert crc16_ccitt_false(payload) == 0xAC77
    assert cobs_encode(payload + b"\x77\xac") + b"\x00" == bytes.fromhex("03 01 02 04 03 77 ac 00")


# -- layout and quantisation -------------------------------------------------------------------------

NOMINAL = PoseFrame(1234, 12_345_678_901, 3.1416, -2.5, 1.5, 0.0021, 0.0087, F.VLP | F.SLAM, 3)


def test_payload_layout() -> None:
    assert PAYLOAD_LENGTH == 30
    assert WIRE_VERSION == 0x10
    p = encode_payload(NOMINAL)
    assert p[0] == 0x10 and p[1] == 3
    assert int.from_bytes(p[2:4], "little") == F.VLP | F.SLAM
    assert int.from_bytes(p[4:8], "little") == 1234
    assert int.from_bytes(p[8:16], "little") == 12_345_678_901
    assert int.from_bytes(p[16:20], "little", signed=True) == 31416
    assert int.from_bytes(p[20:24], "little", signed=True) == -25000


def test_flag_bits_are_as_documented() -> None:
    assert [int(f) for f in PoseFlags] == [0x1, 0x2, 0x4, 0x8, 0x100, 0x200, 0x400, 0x800]
    md = WIRE_FORMAT_MD.read_text(encoding="utf-8")
    for flag in PoseFlags:
        assert f"`0x{int(flag):04X}` | `{flag.name}`" in md


@pytest.mark.parametrize(
    ("yaw", "steps"),
    [
        (0.0, 0),
        (math.pi / 2, 16384),
        (-math.pi / 2, -16384),
        (math.pi, -32768),  # +pi and -pi are the same angle: the binary angle keeps -pi
        (-math.pi, -32768),
        (3 * math.pi / 2, -16384),
        (2 * math.pi, 0),
        (-5 * math.pi / 2, -16384),
        (YAW_LSB_RAD * 0.49, 0),
        (YAW_LSB_RAD * 0.51, 1),
    ],
)
def test_yaw_is_a_wrapping_binary_angle(yaw: float, steps: int) -> None:
    payload = encode_payload(replace(NOMINAL, yaw_rad=yaw))
    assert int.from_bytes(payload[24:26], "little", signed=True) == steps


@pytest.mark.parametrize(
    ("sigma", "q"),
    [
        (0.0, 0),
        (0.00004, 0),
        (0.00006, 1),
        (6.5534, 65534),
        (6.5535, 0xFFFF),
        (1e9, 0xFFFF),
        (math.inf, 0xFFFF),
    ],
)
def test_sigma_saturates_to_unknown(sigma: float, q: int) -> None:
    payload = encode_payload(replace(NOMINAL, sigma_xy_m=sigma, sigma_yaw_rad=sigma))
    assert struct.unpack_from("<HH", payload, 26) == (q, q)


def test_nan_sigma_is_unknown_and_decodes_to_inf() -> None:
    frame = decode_pose(encode_pose(replace(NOMINAL, sigma_xy_m=math.nan, sigma_yaw_rad=math.nan)))
    assert frame.sigma_xy_m == math.inf and frame.sigma_yaw_rad == math.inf


def test_position_range_is_the_i32_range() -> None:
    edge = replace(NOMINAL, x_m=214748.3647, y_m=-214748.3648)
    got = decode_pose(encode_pose(edge))
    assert (got.x_m, got.y_m) == (214748.3647, -214748.3648)


@pytest.mark.parametrize(
    "bad",
    [
        {"x_m": 214748.3648},
        {"y_m": -214748.3649},
        {"x_m": math.nan},
        {"y_m": math.inf},
        {"x_m": 1e308},
        {"yaw_rad": math.nan},
        {"yaw_rad": -math.inf},
        {"sigma_xy_m": -0.001},
        {"sigma_yaw_rad": -math.inf},
        {"sequence": -1},
        {"sequence": 1 << 32},
        {"t_us": -1},
        {"t_us": 1 << 64},
        {"reset_counter": 256},
        {"flags": PoseFlags(0x10000)},
    ],
    ids=repr,
)
def test_values_that_do_not_fit_raise_pose_frame_error(bad: dict[str, object]) -> None:
    with pytest.raises(PoseFrameError):
        encode_pose(replace(NOMINAL, **bad))  # type: ignore[arg-type]


def test_unknown_flag_bits_survive_decoding() -> None:
    frame = decode_pose(encode_pose(replace(NOMINAL, flags=PoseFlags(0x8001))))
    assert int(frame.flags) == 0x8001 and F.VLP in frame.flags


# -- one-shot decoding and the versioning rule --------------------------------------------------------


def wire_for(payload: bytes) -> bytes:
    """A correctly framed wire frame for any payload (for versions and lengths we do not encode)."""
    return cobs_encode(payload + crc16_ccitt_false(payload).to_bytes(2, "little")) + b"\x00"


def test_a_newer_minor_version_with_appended_fields_is_accepted() -> None:
    v11 = bytes([0x11]) + encode_payload(NOMINAL)[1:] + b"\xaa\xbb\x00\x01"
    assert decode_pose(wire_for(v11)) == decode_pose(encode_pose(NOMINAL))
    longest = bytes([0x1F]) + encode_payload(NOMINAL)[1:] + bytes(34)
    assert decode_pose(wire_for(longest)) == decode_pose(encode_pose(NOMINAL))


@pytest.mark.parametrize(
    ("payload", "error"),
    [
        (bytes([0x20]) + encode_payload(NOMINAL)[1:], PoseVersionError),
        (bytes([0x00]) + encode_payload(NOMINAL)[1:], PoseVersionError),
        (encode_payload(NOMINAL) + b"\x00", PoseLengthError),  # v1.0 must be exactly 30 bytes
        (bytes([0x11]) + encode_payload(NOMINAL)[1:29], PoseLengthError),
        (bytes([0x11]) + encode_payload(NOMINAL)[1:] + bytes(35), PoseLengthError),
        (b"", PoseLengthError),
    ],
)
def test_versioning_rule(payload: bytes, error: type[PoseFrameError]) -> None:
    with pytest.raises(error):
        decode_pose(wire_for(payload))
    if payload:
        with pytest.raises(error):
            decode_payload(payload)


def test_one_shot_errors_carry_the_bytes() -> None:
    good = encode_pose(NOMINAL)
    bad_crc = bytearray(cobs_decode(good[:-1]))
    bad_crc[-1] ^= 0x01
    with pytest.raises(PoseCrcError) as crc_info:
        decode_pose(cobs_encode(bytes(bad_crc)))
    assert crc_info.value.data == bytes(bad_crc)
    with pytest.raises(PoseCobsError) as cobs_info:
        decode_pose(good[:10] + b"\x00")
    assert cobs_info.value.data == good[:10] + b"\x00"
    assert isinstance(cobs_info.value, ProtocolError)
    with pytest.raises(PoseCobsError):
        decode_pose(good + good)  # a second delimiter
    with pytest.raises(PoseLengthError):
        decode_pose(b"\x01\x00")
    with pytest.raises(PoseCobsError):
        decode_pose(b"")


# -- the stream decoder ------------------------------------------------------------------------------


def frames(n: int, start: int = 0) -> list[PoseFrame]:
    return [
        decode_pose(
            encode_pose(
                PoseFrame(
                    sequence=start + i,
                    t_us=1_000_000 + 10_000 * i,
                    x_m=1.0 + 0.01 * i,
                    y_m=-2.0 + 0.003 * i,
                    yaw_rad=0.1 * i - 3.0,
                    sigma_xy_m=0.002,
                    sigma_yaw_rad=0.01,
                    flags=F.VLP | F.ODOMETRY | F.IMU,
                    reset_counter=i // 7,
                )
            )
        )
        for i in range(n)
    ]


def stream(items: list[PoseFrame]) -> bytes:
    return b"".join(encode_pose(f) for f in items)


def test_whole_byte_by_byte_and_every_split_agree() -> None:
    good = frames(5)
    data = stream(good)
    assert PoseFrameDecoder().feed(data) == good
    dec = PoseFrameDecoder()
    assert [f for i in range(len(data)) for f in dec.feed(data[i : i + 1])] == good
    for cut in range(len(data) + 1):
        dec = PoseFrameDecoder()
        assert dec.feed(data[:cut]) + dec.feed(data[cut:]) == good
        assert dec.counters()["frames"] == 5 and dec.bad_frames == 0


def test_trailing_bytes_wait_for_their_delimiter() -> None:
    good = frames(2)
    data = stream(good)
    dec = PoseFrameDecoder()
    assert dec.feed(data[:-1]) == good[:1]
    assert dec.pending == WIRE_LENGTH - 1
    assert dec.feed(b"") == []
    assert dec.feed(data[-1:]) == good[1:]
    assert dec.pending == 0 and dec.bad_frames == 0


def test_idle_zeros_are_not_errors() -> None:
    good = frames(3)
    data = b"\x00\x00" + b"\x00".join(encode_pose(f) for f in good) + b"\x00\x00\x00"
    dec = PoseFrameDecoder()
    assert dec.feed(data) == good
    assert dec.bad_frames == 0 and dec.discarded_bytes == 0


def test_junk_and_corrupted_frames_between_good_ones_cost_only_themselves() -> None:
    good = frames(6)
    wires = [encode_pose(f) for f in good]
    payload = encode_payload(good[1])
    bad_crc = cobs_encode(payload + ((crc16_ccitt_false(payload) ^ 0x0100).to_bytes(2, "little"))) + b"\x00"
    # The sender was cut off mid-frame: the longest prefix that ends inside a COBS block.
    cut = max(k for k in range(1, WIRE_LENGTH - 1) if _raises(PoseCobsError, wires[2][:k]))
    assert cut > WIRE_LENGTH // 2
    truncated = wires[2][:cut] + b"\x00"
    junk = b"\x02\x37\x01\x01\x00"  # valid COBS for 37 00 00: too short
    short = cobs_encode(b"\x10\x00\x00") + b"\x00"
    other_major = wire_for(bytes([0x20]) + encode_payload(good[0])[1:])
    data = (
        b"\x42\x42\x00"  # the tail of a frame sent before we opened the port
        + wires[0]
        + bad_crc
        + truncated
        + wires[3]
        + junk
        + short
        + other_major
        + wires[4]
        + wires[5]
    )
    splits = (
        [data],
        [data[i : i + 1] for i in range(len(data))],
        [data[i : i + 7] for i in range(0, len(data), 7)],
    )
    for chunks in splits:
        dec = PoseFrameDecoder()
        out = [f for c in chunks for f in dec.feed(c)]
        assert out == [good[0], good[3], good[4], good[5]]
        assert dec.counters() == {
            "frames": 4,
            "crc_errors": 1,
            "length_errors": 2,  # junk, short
            "cobs_errors": 2,  # the tail (its code byte points past the end), the truncated frame
            "version_errors": 1,
            "overflows": 0,
            "discarded_bytes": len(data) - 4 * WIRE_LENGTH,
        }
        assert isinstance(dec.last_error, PoseVersionError)
        assert dec.last_error.data[0] == 0x20


def _raises(error: type[Exception], wire: bytes) -> bool:
    try:
        decode_pose(wire)
    except error:
        return True
    except PoseFrameError:
        return False
    return False


def test_long_junk_without_zero_overflows_once_and_the_buffer_stays_bounded() -> None:
    good = frames(2)
    junk = bytes(range(1, 256)) * 4  # 1020 bytes, no zero
    dec = PoseFrameDecoder()
    out = dec.feed(encode_pose(good[0]))
    for i in range(0, len(junk), 50):
        out += dec.feed(junk[i : i + 50])
        assert len(dec._buf) <= MAX_ENCODED_LENGTH
    assert dec.pending == len(junk)
    assert dec.overflows == 1
    out += dec.feed(b"\x00" + encode_pose(good[1]))
    assert out == good
    assert dec.overflows == 1 and dec.bad_frames == 1
    assert dec.discarded_bytes == len(junk) + 1
    assert isinstance(dec.last_error, PoseLengthError)


def test_the_overflow_bound_is_exact() -> None:
    longest = cobs_encode(bytes([0x1F]) + bytes(range(1, 66)))  # 66 bytes un-stuffed, 67 stuffed: fits
    assert len(longest) == MAX_ENCODED_LENGTH
    dec = PoseFrameDecoder()
    dec.feed(longest + b"\x00")
    assert dec.overflows == 0 and dec.crc_errors == 1
    dec.feed(longest + b"\x01\x00")
    assert dec.overflows == 1 and dec.bad_frames == 2


def test_a_zero_lost_on_the_line_costs_both_frames_it_joined() -> None:
    good = frames(3)
    data = bytearray(stream(good))
    data[WIRE_LENGTH - 1] = 0x55
    dec = PoseFrameDecoder()
    assert dec.feed(bytes(data)) == good[2:]
    assert dec.bad_frames == 1


def test_reset_forgets_a_partial_frame_without_counting_it() -> None:
    good = frames(1)
    dec = PoseFrameDecoder()
    dec.feed(b"\x05\x01\x02")
    dec.reset()
    assert dec.pending == 0
    assert dec.feed(encode_pose(good[0])) == good
    assert dec.bad_frames == 0 and dec.discarded_bytes == 0


# -- properties --------------------------------------------------------------------------------------


def finite(lo: float, hi: float) -> st.SearchStrategy[float]:
    return st.floats(lo, hi, allow_nan=False, allow_infinity=False)


pose_frames = st.builds(
    PoseFrame,
    sequence=st.integers(0, 0xFFFF_FFFF),
    t_us=st.integers(0, (1 << 64) - 1),
    x_m=finite(-214748.3, 214748.3),
    y_m=finite(-214748.3, 214748.3),
    yaw_rad=finite(-100.0, 100.0),
    sigma_xy_m=st.one_of(finite(0, 10), st.just(math.inf), st.just(math.nan)),
    sigma_yaw_rad=st.one_of(finite(0, 10), st.just(math.inf)),
    flags=st.integers(0, 0xFFFF).map(PoseFlags),
    reset_counter=st.integers(0, 255),
)


@settings(max_examples=300, deadline=None)
@given(pose_frames)
def test_round_trip_is_within_half_a_step_and_re_encoding_is_exact(frame: PoseFrame) -> None:
    wire = encode_pose(frame)
    assert len(wire) == WIRE_LENGTH and wire.index(0) == WIRE_LENGTH - 1
    got = decode_pose(wire)
    assert encode_pose(got) == wire
    assert (got.sequence, got.t_us, got.flags, got.reset_counter) == (
        frame.sequence,
        frame.t_us,
        frame.flags,
        frame.reset_counter,
    )
    assert abs(got.x_m - frame.x_m) <= 0.5e-4 + 1e-9 and abs(got.y_m - frame.y_m) <= 0.5e-4 + 1e-9
    assert abs(math.remainder(got.yaw_rad - frame.yaw_rad, math.tau)) <= YAW_LSB_RAD / 2 + 1e-12
    assert -math.pi <= got.yaw_rad < math.pi
    for name in ("sigma_xy_m", "sigma_yaw_rad"):
        sent, back = getattr(frame, name), getattr(got, name)
        if math.isnan(sent) or sent >= 6.5535:
            assert back == math.inf
        elif back != math.inf:
            assert abs(back - sent) <= 0.5e-4 + 1e-9


def _mutate(data: bytearray, draw: st.DrawFn) -> None:
    for _ in range(draw(st.integers(0, 5))):
        if not data:
            return
        op = draw(st.sampled_from(["flip", "drop", "insert", "zero"]))
        at = draw(st.integers(0, len(data) - 1))
        if op == "flip":
            data[at] ^= 1 << draw(st.integers(0, 7))
        elif op == "drop":
            del data[at]
        elif op == "insert":
            data.insert(at, draw(st.sampled_from([0x00, 0x01, 0x10, 0xFF])))
        else:
            data[at] = 0


@st.composite
def mutated_streams(draw: st.DrawFn) -> bytes:
    """Good frames with junk between them, then bits flipped, bytes dropped, inserted or zeroed."""
    parts = draw(st.lists(st.one_of(pose_frames.map(encode_pose), st.binary(max_size=20)), max_size=8))
    data = bytearray(b"".join(parts))
    _mutate(data, draw)
    return bytes(data)


STREAMS = st.one_of(mutated_streams(), st.binary(max_size=400))


@settings(max_examples=300, deadline=None)
@given(STREAMS)
def test_one_shot_decoding_of_anything_decodes_or_raises_pose_frame_error(data: bytes) -> None:
    try:
        frame = decode_pose(data)
    except PoseFrameError:
        return
    assert isinstance(frame, PoseFrame)


@settings(max_examples=300, deadline=None)
@given(STREAMS, st.lists(st.integers(0, 500), max_size=6))
# Issue 17: a run longer than the buffer with no 0x00 after it is an overflow the moment its 68th byte
# arrives (a noisy line may never send the 0x00): one bad frame, though no delimiter has ended it yet.
@example(data=b"\x01" * (MAX_ENCODED_LENGTH + 1), cuts=[])
@example(data=b"\x01" * (MAX_ENCODED_LENGTH + 1), cuts=[1, MAX_ENCODED_LENGTH, MAX_ENCODED_LENGTH + 1])
@example(data=b"\x01" * MAX_ENCODED_LENGTH, cuts=[MAX_ENCODED_LENGTH // 2])
def test_the_stream_decoder_never_raises_and_cuts_do_not_matter(data: bytes, cuts: list[int]) -> None:
    whole = PoseFrameDecoder()
    expected = whole.feed(data)
    points = sorted({min(c, len(data)) for c in cuts})
    pieces = [data[a:b] for a, b in zip([0, *points], [*points, len(data)], strict=True)]
    split = PoseFrameDecoder()
    assert [f for p in pieces for f in split.feed(p)] == expected
    assert split.counters() == whole.counters() and split.pending == whole.pending
    assert len(whole._buf) <= MAX_ENCODED_LENGTH
    # Every frame found is one a candidate between two zeros decodes to on its own; every other candidate
    # is discarded whole, its 0x00 included.
    runs = data.split(b"\x00")
    candidates, tail = [c for c in runs[:-1] if c], runs[-1]
    decoded, discarded = [], 0
    for c in candidates:
        try:
            decoded.append(decode_pose(c))
        except PoseFrameError:
            discarded += len(c) + 1
    assert expected == decoded
    assert whole.discarded_bytes == discarded and whole.pending == len(tail)
    # An over-long run is counted when it overflows, not when (or if) a 0x00 ends it, so a tail still
    # waiting for its 0x00 counts once it is longer than the buffer.
    tail_overflowed = len(tail) > MAX_ENCODED_LENGTH
    assert whole.overflows == sum(len(r) > MAX_ENCODED_LENGTH for r in runs)
    assert whole.frames + whole.bad_frames == len(candidates) + tail_overflowed
