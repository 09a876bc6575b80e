"""SCIP 2.0 codec: the real URG captures, the spec's vectors, streaming, resync, and a fuzz property.

The fake URG's bytes are held to the same independent checks as the real captures (line checksums, 64-char
blocks, 682 values, LF LF), by a checker that does not use the decoder under test.
"""

from __future__ import annotations

import functools
import itertools
import math
import random
from datetime import timedelta
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from drivers.fakes.urg import FakeUrg
from drivers.sim.simulation import Simulation
from drivers.sim.world import LaserModel, Pose2D, RobotSpec, Wall, World
from firmware_protocol import scip
from firmware_protocol.errors import ProtocolError
from tests.conftest import DATA

CAPTURES = {
    "A_VV": "A_VV_URG-04LX-UG01_H1510998.bin",
    "A_BM": "A_BM_already_on_02R.bin",
    "B": "B_GD0044072501_URG-04LX-UG01_H1620274.bin",
    "C": "C_GD0044072501_havso.bin",
    "D": "D_GD0044072501_french_script.bin",
}
# From PROVENANCE.md: timestamps and number of error codes (< 20) in each GD capture.
GD_FACTS = {"B": (11149560, 85), "C": (513, 358), "D": (4106836, 0)}


@pytest.fixture
def captures(shared_data: Path) -> dict[str, bytes]:
    urg = shared_data / "urg"
    if not urg.is_dir():
        pytest.skip(f"URG captures not found in {urg}")
    return {key: (urg / name).read_bytes() for key, name in CAPTURES.items()}


def check_like_real_capture(frame: bytes, nchars: int = 3) -> list[int]:
    """The checks ``verify_captures.py`` makes on the real captures, written without the codec: LF LF at the
    end, every line after the echo ends with ``(sum & 0x3F) + 0x30`` of the rest, data cut in 64-char
    blocks. Returns the decoded values of a data reply."""
    assert frame.endswith(b"\n\n") and not frame.endswith(b"\n\n\n")
    lines = frame[:-2].split(b"\n")
    for line in lines[1:]:
        assert line[-1] == (sum(line[:-1]) & 0x3F) + 0x30, line
    blocks = [line[:-1] for line in lines[3:]]
    assert blocks and all(len(b) == 64 for b in blocks[:-1]) and 0 < len(blocks[-1]) <= 64
    data = b"".join(blocks)
    assert len(data) % nchars == 0
    values = []
    for i in range(0, len(data), nchars):
        v = 0
        for c in data[i : i + nchars]:
            assert 0x30 <= c <= 0x6F
            v = v * 64 + (c - 0x30)
        values.append(v)
    return values


# -- 6-bit encoding and checksums ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("value", "nchars", "chars"), [(1234, 2, b"CB"), (5432, 3, b"1Dh"), (16000000, 4, b"m2@0")]
)
def test_spec_encoding_vectors(value: int, nchars: int, chars: bytes) -> None:
    assert scip.encode_value(value, nchars) == chars
    assert scip.decode_value(chars) == value


@pytest.mark.parametrize(
    ("status", "char"), [("00", "P"), ("99", "b"), ("0E", "e"), ("02", "R"), ("10", "Q")]
)
def test_status_checksums(status: str, char: str) -> None:
    assert chr(scip.checksum(status.encode())) == char


def test_encode_value_range_and_decode_rejects_non_scip_bytes() -> None:
    assert scip.encode_value(4095, 2) == b"oo"
    assert scip.encode_value(0, 3) == b"000"
    with pytest.raises(ValueError, match="does not fit"):
        scip.encode_value(4096, 2)
    with pytest.raises(ValueError, match="does not fit"):
        scip.encode_value(-1, 3)
    with pytest.raises(scip.ScipError) as info:
        scip.decode_value(b"0p0")
    assert info.value.data == b"0p0"
    with pytest.raises(scip.ScipError, match="multiple of 3"):
        scip.decode_values(b"00000", 3)


def test_parameter_lines_match_the_urgnetwork_wiki_examples() -> None:
    # Independent vectors: PP/VV replies of a URG-04LX as printed on the urgnetwork wiki (scip_status_en).
    for key, value, line in [("DMIN", "20", b"DMIN:20;4\n"), ("DMAX", "5600", b"DMAX:5600;_\n"),
                             ("ARES", "1024", b"ARES:1024;\\\n"), ("AMIN", "44", b"AMIN:44;7\n"),
                             ("AMAX", "725", b"AMAX:725;o\n"), ("AFRT", "384", b"AFRT:384;6\n"),
                             ("SCAN", "600", b"SCAN:600;e\n"), ("PROT", "SCIP 2.0", b"PROT:SCIP 2.0;N\n"),
                             ("SERI", "H0614967", b"SERI:H0614967;V\n")]:  # fmt: skip
        assert scip.encode_param_line(key, value) == line


def test_a_data_line_may_end_with_semicolon() -> None:
    # ';' is the 6-bit digit 11: a timestamp or block ending with it is summed whole.
    ts = scip.encode_value(5323, 4)
    assert ts.endswith(b";")
    reply = scip.encode_reply(b"GD0044004401", "00", timestamp_ms=5323, payload=b"00;")
    parsed = scip.parse_reply(reply)
    assert parsed.timestamp_ms == 5323 and parsed.values == (11,)


# -- commands ----------------------------------------------------------------------------------------------


def test_command_encoders() -> None:
    assert scip.encode_qt() == b"QT\n"
    assert scip.encode_scip2() == b"SCIP2.0\n"
    assert scip.encode_vv("a1") == b"VV;a1\n"
    assert scip.encode_pp() == b"PP\n"
    assert scip.encode_ii() == b"II\n"
    assert scip.encode_bm() == b"BM\n"
    assert scip.encode_rs() == b"RS\n"
    assert [scip.encode_tm(m) for m in (0, 1, 2)] == [b"TM0\n", b"TM1\n", b"TM2\n"]
    assert scip.encode_ss(115200) == b"SS115200\n"
    assert scip.encode_gd(44, 725) == b"GD0044072501\n"
    assert scip.encode_gs(0, 768, 3, tag="x.y") == b"GS0000076803;x.y\n"
    assert scip.encode_md(44, 725, 1, 0, 0, tag="tag") == b"MD0044072501000;tag\n"
    assert scip.encode_ms(10, 750, 2, 1, 5) == b"MS0010075002105\n"


@pytest.mark.parametrize("tag", ["x" * 17, "semi;colon", "tab\t", "é"])
def test_command_tags_the_sensor_would_refuse_are_rejected(tag: str) -> None:
    with pytest.raises(ValueError, match="tags"):
        scip.encode_bm(tag)


def test_command_parameters_out_of_range_are_rejected() -> None:
    with pytest.raises(ValueError):
        scip.encode_gd(44, 10000)
    with pytest.raises(ValueError):
        scip.encode_md(44, 725, 1, 10, 0)
    with pytest.raises(ValueError):
        scip.encode_tm(3)


# -- the real captures -------------------------------------------------------------------------------------


def test_vv_capture_parses_with_checksums_without_semicolon(captures: dict[str, bytes]) -> None:
    (reply,) = scip.ScipDecoder().feed(captures["A_VV"])
    assert (reply.command, reply.status, reply.meaning.kind) == ("VV", "00", scip.StatusKind.OK)
    assert dict(reply.params) == {
        "VEND": "Hokuyo Automatic Co.,Ltd.",
        "PROD": "SOKUIKI Sensor URG-04LX-UG01(Simple-URG)",
        "FIRM": "3.4.03(17/Dec./2012)",
        "PROT": "SCIP 2.0",
        "SERI": "H1510998",
    }
    # The capture sums without ';' ...
    assert b"PROT:SCIP 2.0;N\n" in captures["A_VV"]
    # ... later models sum with it: both variants decode to the same parameters.
    with_semicolon = scip.encode_reply(b"VV", "00", params=reply.params.items(), sum_includes_semicolon=True)
    assert with_semicolon != captures["A_VV"]
    assert scip.parse_reply(with_semicolon).params == reply.params
    # A parameter line that matches neither variant is refused.
    broken = captures["A_VV"].replace(b"PROT:SCIP 2.0;N", b"PROT:SCIP 2.0;M")
    with pytest.raises(scip.ScipError, match="parameter line checksum"):
        scip.parse_reply(broken)


def test_bm_capture_is_laser_already_on(captures: dict[str, bytes]) -> None:
    reply = scip.parse_reply(captures["A_BM"])
    assert (reply.command, reply.status) == ("BM", "02")
    assert reply.meaning.kind is scip.StatusKind.ALREADY_SET and not reply.meaning.is_error


@pytest.mark.parametrize("key", sorted(GD_FACTS))
def test_gd_captures(captures: dict[str, bytes], key: str) -> None:
    timestamp, n_errors = GD_FACTS[key]
    (reply,) = scip.ScipDecoder().feed(captures[key])
    assert reply.is_scan and (reply.command, reply.status) == ("GD", "00")
    assert (reply.first_step, reply.last_step, reply.cluster) == (44, 725, 1)
    assert reply.timestamp_ms == timestamp
    assert len(reply.values) == 682 and len(reply.data) == 682 * 3
    assert sum(v < 20 for v in reply.values) == n_errors
    assert reply.values == tuple(check_like_real_capture(captures[key]))


def test_values_straddling_blocks_are_decoded_from_joined_blocks(captures: dict[str, bytes]) -> None:
    frame = captures["B"]
    lines = frame.split(b"\n")
    # Value 21 of capture B is made of the last character of block 1 and two of block 2.
    straddling = lines[3][63:64] + lines[4][:2]
    assert scip.parse_reply(frame).values[21] == scip.decode_value(straddling)
    # A synthetic reply with a value cut after every possible character.
    for n in (21, 22, 43, 100):
        values = [(i * 7919) % 262144 for i in range(n)]
        reply = scip.encode_reply(b"GD0000%04d01" % (n - 1), "00", timestamp_ms=1,
                                  payload=scip.encode_values(values, 3))  # fmt: skip
        assert list(scip.parse_reply(reply).values) == values


@pytest.mark.parametrize("key", sorted(CAPTURES))
def test_each_capture_whole_byte_by_byte_and_with_trailing_bytes(
    captures: dict[str, bytes], key: str
) -> None:
    frame = captures[key]
    whole = scip.ScipDecoder().feed(frame)
    assert len(whole) == 1 and whole[0].raw == frame

    dec = scip.ScipDecoder()
    got = []
    for i in range(len(frame)):
        out = dec.feed(frame[i : i + 1])
        assert out == [] or i == len(frame) - 1  # nothing before the final LF
        got += out
    assert got == whole and dec.buffered == 0

    dec = scip.ScipDecoder()
    trailing = b"GD00440725"  # the start of the next reply
    assert dec.feed(frame + trailing) == whole
    assert dec.buffered == len(trailing) and dec.bad_frames == 0


def test_junk_and_corrupted_checksum_between_replies(captures: dict[str, bytes]) -> None:
    b, c, d = captures["B"], captures["C"], captures["D"]
    corrupted = bytearray(c)
    corrupted[200] = ord("0") if corrupted[200] != ord("0") else ord("1")  # inside a data block
    junk = b"\x00\xff\x13garbage\n\nmore junk GD00"
    stream = b + junk + bytes(corrupted) + b"ZZ" + d
    for chunk in (len(stream), 1, 7, 64):
        dec = scip.ScipDecoder()
        replies = [r for i in range(0, len(stream), chunk) for r in dec.feed(stream[i : i + chunk])]
        assert [r.timestamp_ms for r in replies] == [11149560, 4106836]
        assert dec.discarded_bytes == len(junk) + len(corrupted) + 2
        assert dec.bad_frames >= 2
        errors = dec.take_errors()
        assert errors and all(isinstance(e, scip.ScipError) and e.data for e in errors)
        assert b"".join(e.data for e in errors) == junk + bytes(corrupted) + b"ZZ"
        assert dec.take_errors() == []


def test_junk_glued_to_a_reply_does_not_become_a_command() -> None:
    dec = scip.ScipDecoder()
    (reply,) = dec.feed(b"ZZQT\n00P\n\n")
    assert reply.command == "QT" and dec.discarded_bytes == 2


def test_buffer_is_bounded_and_decoding_continues(captures: dict[str, bytes]) -> None:
    dec = scip.ScipDecoder(max_buffer=4096)
    rng = random.Random(1)
    junk = bytes(rng.choice(b"0123456789ABCDEFabcdef;:@") for _ in range(20000))  # no LF at all
    for i in range(0, len(junk), 1000):
        assert dec.feed(junk[i : i + 1000]) == []
        assert dec.buffered <= 4096
    assert dec.discarded_bytes > 10000
    replies = dec.feed(b"\n\n" + captures["B"])
    assert [r.timestamp_ms for r in replies] == [11149560]


# -- replies built from the spec ---------------------------------------------------------------------------


def test_md_ack_and_scans_carry_remaining_count() -> None:
    payload = scip.encode_values(range(100, 110), 3)
    ack = scip.encode_reply(b"MD0044005301003;t1", "00")
    scans = [scip.encode_reply(b"MD00440053010%02d;t1" % n, "99", timestamp_ms=16777215 + n, payload=payload)
             for n in (2, 1, 0)]  # fmt: skip
    replies = scip.ScipDecoder().feed(ack + b"".join(scans))
    assert [(r.status, r.remaining_scans, r.tag) for r in replies] == [
        ("00", 3, "t1"),
        ("99", 2, "t1"),
        ("99", 1, "t1"),
        ("99", 0, "t1"),
    ]
    assert not replies[0].is_scan and all(r.is_scan for r in replies[1:])
    assert replies[1].meaning.kind is scip.StatusKind.STREAMING
    assert [r.timestamp_ms for r in replies[1:]] == [1, 0, 16777215]  # 24-bit wrap on the wire
    assert replies[1].values == tuple(range(100, 110)) and replies[1].body == "MD0044005301002"


def test_scip11_replies() -> None:
    switched, qt, already = scip.ScipDecoder().feed(b"SCIP2.0\n0\n\nQT\nE\n\nSCIP2.0\n0Ee\n\n")
    assert switched.scip1 and switched.status == "0" and switched.meaning.kind is scip.StatusKind.OK
    assert qt.scip1 and qt.meaning.kind is scip.StatusKind.SCIP1
    assert not already.scip1 and already.meaning.kind is scip.StatusKind.ALREADY_SET


@pytest.mark.parametrize(("command", "status", "kind"), [
    ("GD", "10", scip.StatusKind.LASER_OFF), ("GS", "05", scip.StatusKind.PARAMETER_ERROR),
    ("MD", "07", scip.StatusKind.PARAMETER_ERROR), ("MD", "30", scip.StatusKind.HARDWARE_FAULT),
    ("MD", "75", scip.StatusKind.HARDWARE_FAULT), ("GD", "98", scip.StatusKind.HARDWARE_FAULT),
    ("MD", "98", scip.StatusKind.RESUMED), ("MS", "99", scip.StatusKind.STREAMING),
    ("BM", "01", scip.StatusKind.HARDWARE_FAULT), ("BM", "02", scip.StatusKind.ALREADY_SET),
    ("TM", "04", scip.StatusKind.WRONG_STATE), ("SS", "04", scip.StatusKind.UNSUPPORTED),
    ("XY", "0E", scip.StatusKind.COMMAND_ERROR), ("GD", "0G", scip.StatusKind.COMMAND_ERROR),
    ("QT", "00", scip.StatusKind.OK), ("GD", "99", scip.StatusKind.UNKNOWN),
    ("GD", "30", scip.StatusKind.UNKNOWN),
])  # fmt: skip
def test_status_meanings_per_command(command: str, status: str, kind: scip.StatusKind) -> None:
    meaning = scip.status_meaning(command, status)
    assert meaning.kind is kind and meaning.code == status and meaning.text


@pytest.mark.parametrize(("frame", "reason"), [
    (b"QT\n00P\n", "LF LF"),
    (b"QT\n00Q\n\n", "status line checksum"),
    (b"QT\n000P\n\n", "status line has 4"),
    (b"\x01QT\n00P\n\n", "printable"),
    (b"qt\n00P\n\n", "command code"),
    (b"QT\n\n", "status"),
    (b"QT\n00P\nextra;X\n\n", "unexpected lines"),
    (b"GD0044004401\n00P\n", "LF LF"),
    (b"GD0044004401\n00P\n0000\n\n", "timestamp and data"),
    (b"GD00440044x1\n00P\n0000\n0000\n\n", "malformed echo"),
    (b"GD0044004601\n00P\n00000\n000000P\n\n", "values"),  # 2 values for 3 steps
    (b"GD0044004401\n10Q\n0000\n\n", "followed by data"),
    (b"VV\n00P\nno-colon;X\n\n", "parameter line"),
    (b"TM1\n00P\n\n", "time line"),
])  # fmt: skip
def test_malformed_replies_raise_scip_error_with_bytes(frame: bytes, reason: str) -> None:
    with pytest.raises(scip.ScipError, match=reason) as info:
        scip.parse_reply(frame)
    assert isinstance(info.value, ProtocolError) and info.value.data


def test_dropped_data_line_is_caught_by_the_value_count(captures: dict[str, bytes]) -> None:
    lines = captures["B"].split(b"\n")
    del lines[10:13]  # every remaining checksum is fine, 3 blocks (64 whole values) are missing
    with pytest.raises(scip.ScipError, match="values"):
        scip.parse_reply(b"\n".join(lines))


# -- the fake's bytes against the same checks as the real captures ------------------------------------------


def _room() -> World:
    walls = (Wall(-2.0, -1.5, 3.0, -1.5), Wall(3.0, -1.5, 3.0, 2.0), Wall(3.0, 2.0, -2.0, 2.0),
             Wall(-2.0, 2.0, -2.0, -1.5), Wall(1.0, 0.3, 1.2, 0.5))  # fmt: skip
    return World("scip-test room", walls=walls, robot=RobotSpec(start=Pose2D(0.2, 0.1, 0.3)),
                 laser=LaserModel(range_noise_mm=10.0, dropout=0.02))  # fmt: skip


def test_fake_reproduces_real_captures_byte_for_byte(captures: dict[str, bytes]) -> None:
    values = scip.parse_reply(captures["B"]).values
    # Capture B at step 0 of scan 9: the motor started with the fake's clock at 11149560 - 900 ms.
    fake = FakeUrg(fixed_ranges_mm=values, clock_start_ms=11149560 - 900)
    fake.receive(b"BM\n", 0.0)
    assert fake.receive(b"GD0044072501\n", 1.0) == captures["B"]
    fake = FakeUrg(serial="H1510998")
    assert fake.receive(b"VV\n", 0.0) == captures["A_VV"]
    assert fake.receive(b"BM\n", 0.0) == b"BM\n00P\n\n"
    assert fake.receive(b"BM\n", 0.0) == captures["A_BM"]


def test_fake_ray_cast_scans_pass_the_capture_checks() -> None:
    now = [100.0]
    sim = Simulation(_room(), clock=lambda: now[0], seed=3)
    fake = FakeUrg(sim, seed=3)
    assert fake.receive(b"BM\n", 0.0) == b"BM\n00P\n\n"
    now[0] += 0.5
    frame = fake.receive(b"GD0044072501\n", 0.0)
    assert len(frame) == 2134  # 682 values: 36 lines like the real captures
    values = check_like_real_capture(frame)
    assert len(values) == 682 and tuple(values) == scip.parse_reply(frame).values
    codes = [v for v in values if v < 20]
    assert set(codes) == {1}  # a small closed room: every beam hits a wall, the only errors are dropouts
    assert all(20 <= v <= 5600 for v in values if v >= 20)
    # Clusters of 3: the smallest valid value of each group.
    frame3 = fake.receive(b"GD0044072503\n", 0.0)
    values3 = check_like_real_capture(frame3)
    assert len(values3) == math.ceil(682 / 3)
    for i, v in enumerate(values3):
        group = [x for x in values[3 * i : 3 * i + 3] if x >= 20]
        assert v == (min(group) if group else min(values[3 * i : 3 * i + 3]))
    two_char = check_like_real_capture(fake.receive(b"GS0044072501\n", 0.0), nchars=2)
    assert two_char == [v if v <= 4095 else 0 for v in values]


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.binary(min_size=682 * 3, max_size=682 * 3), st.integers(0, (1 << 24) - 1))
def test_fake_encodes_any_ranges_and_timestamps_like_the_sensor(raw: bytes, start_ms: int) -> None:
    # Any 18-bit values (one draw of bytes is much cheaper for hypothesis than a list of 682 integers).
    values = [int.from_bytes(raw[i : i + 3], "big") % 262144 for i in range(0, len(raw), 3)]
    fake = FakeUrg(fixed_ranges_mm=values, clock_start_ms=start_ms)
    fake.receive(b"BM\n", 0.0)
    frame = fake.receive(b"GD0044072501\n", 0.35)  # scan 2 is the latest complete one
    assert check_like_real_capture(frame) == values
    assert scip.parse_reply(frame).timestamp_ms == (start_ms + 200) % (1 << 24)


@pytest.mark.parametrize(("echo", "first", "last", "cluster", "nchars"), [
    (b"GD0044072501", 44, 725, 1, 3),
    (b"MD0044072501000;000001", 44, 725, 1, 3),
    (b"MS0300046804099", 300, 468, 4, 2),
    (b"GD0000000001", 0, 0, 1, 3),
    (b"GD0000006301", 0, 63, 1, 2),  # 128 characters: exactly two blocks
])  # fmt: skip
def test_scan_reply_size_is_the_length_on_the_wire(
    echo: bytes, first: int, last: int, cluster: int, nchars: int
) -> None:
    count = scip.expected_value_count(first, last, cluster)
    frame = scip.encode_reply(echo, "99", timestamp_ms=0, payload=scip.encode_values([20] * count, nchars))
    assert scip.scan_reply_size(len(echo), count, nchars) == len(frame)


def test_scan_reply_size_of_a_real_scan(captures: dict[str, bytes]) -> None:
    assert scip.scan_reply_size(len(b"GD0044072501"), 682, 3) == len(captures["B"]) == 2134


def test_fake_rs232_model_sends_at_its_line_rate_and_skips_what_it_cannot_send() -> None:
    fake = FakeUrg(link_bitrate=19200)
    t = 0.0
    out = fake.receive(b"MD0044072501000;s\n", t)
    ack = len(out)
    arrivals: list[tuple[float, int]] = []
    while t < 6.0:
        due = fake.next_output_in(t)
        assert due is not None  # a stream runs: something is always due
        t += max(due, 0.001)
        chunk = fake.poll(t)
        if chunk:
            arrivals.append((t, len(chunk)))
            out += chunk
    scans = [r for r in scip.ScipDecoder().feed(out) if r.status == "99"]
    # Never more than 1920 bytes a second (10 bits a byte), whenever one looks.
    sent = ack
    for tc, n in arrivals:
        sent += n
        assert sent <= ack + tc * 1920 + 1
    # A 2139-byte scan takes 1.114 s; the next one to go is the first finished after it left: every 12th.
    assert [r.timestamp_ms for r in scans] == [0, 1200, 2400, 3600, 4800]
    emitted = [e.device_time_ms for e in fake.emitted]
    assert emitted in (
        [0, 1200, 2400, 3600, 4800],
        [0, 1200, 2400, 3600, 4800, 6000],
    )  # 6000 may be on the line
    assert fake.scans_skipped == 11 * (len(emitted) - 1)  # the eleven finished while each scan was being sent


def test_fake_md_stream_is_paced_and_counts_down() -> None:
    fake = FakeUrg()
    t = 0.0
    out = [fake.receive(b"MD0044072501003;s\n", t)]
    chunks = []
    while t < 0.6:
        t += 0.002
        chunk = fake.poll(t)
        if chunk:
            chunks.append((t, chunk))
    replies = scip.ScipDecoder().feed(out[0] + b"".join(c for _, c in chunks))
    assert [(r.status, r.remaining_scans) for r in replies] == [("00", 3), ("99", 2), ("99", 1), ("99", 0)]
    # One scan per revolution, each sent once its last step is measured, never two in one read.
    assert len(chunks) == 3 and all(len(scip.ScipDecoder().feed(c)) == 1 for _, c in chunks)
    sent_at = [tc for tc, _ in chunks]
    assert all(abs((b - a) - 0.1) < 0.0021 for a, b in itertools.pairwise(sent_at))
    assert [r.timestamp_ms for r in replies[1:]] == [0, 100, 200]
    assert all(tc >= e.step0_time_s + 726 / 1024 * 0.1 for tc, e in zip(sent_at, fake.emitted, strict=True))
    assert not fake.laser_on and not fake.streaming  # the laser goes off after the last scan


@pytest.mark.parametrize(("command", "status"), [
    (b"GD0044072501", "10"),  # laser off
    (b"GDx044072501", "01"), (b"GD00440x2501", "02"), (b"GD004407250x", "03"),
    (b"GD0044099901", "04"), (b"GD0725004401", "05"), (b"GD00440725", "0C"), (b"GD004407250100", "0F"),
    (b"MD004407250100", "0C"), (b"MD0044072501x00", "06"), (b"MD00440725010x0", "07"),
    (b"XX", "0E"), (b"TM1", "04"), (b"TM2", "03"), (b"TM9", "01"), (b"SS11520x", "01"), (b"SS123456", "02"),
    (b"SS115200", "03"), (b"BM;" + b"x" * 17, "0G"), (b"BM;a,b", "0H"), (b"SCIP2.0", "0E"),
])  # fmt: skip
def test_fake_refuses_bad_commands_with_spec_statuses(command: bytes, status: str) -> None:
    fake = FakeUrg()
    reply = scip.parse_reply(fake.receive(command + b"\n", 0.0))
    assert reply.echo.encode() == command and reply.status == status


def test_fake_scip11_and_time_adjust_modes() -> None:
    fake = FakeUrg(boot_in_scip1=True)
    assert scip.parse_reply(fake.receive(b"QT\n", 0.0)).status == "E"
    assert fake.receive(b"SCIP2.0\n", 0.0) == b"SCIP2.0\n0\n\n"
    assert scip.parse_reply(fake.receive(b"TM0\n", 0.0)).status == "00"
    assert scip.parse_reply(fake.receive(b"QT\n", 0.0)).status == "0E"  # nothing else in adjust mode
    assert scip.parse_reply(fake.receive(b"TM0\n", 0.0)).status == "02"
    tm1 = scip.parse_reply(fake.receive(b"TM1;a\n", 1.2345))
    assert tm1.timestamp_ms == 1234 and tm1.tag == "a"
    assert scip.parse_reply(fake.receive(b"TM2\n", 1.5)).status == "00"
    assert scip.parse_reply(fake.receive(b"RS\n", 2.0)).status == "00"
    fake.receive(b"TM0\n", 2.5)
    assert scip.parse_reply(fake.receive(b"TM1\n", 2.5)).timestamp_ms == 500  # RS reset the clock


# -- fuzzing -----------------------------------------------------------------------------------------------


@functools.cache
def _seed_frames() -> tuple[bytes, ...]:
    """Real-looking replies from the fake: a ray-cast GD, an MD ack and scans, VV/PP/II, TM1, errors."""
    now = [10.0]
    sim = Simulation(_room(), clock=lambda: now[0], seed=1)
    fake = FakeUrg(sim, seed=1)
    frames = [
        fake.receive(c, 0.0) for c in (b"VV\n", b"PP\n", b"II;x\n", b"BM\n", b"XX\n", b"GD0044072599\n")
    ]
    now[0] += 0.3
    frames.append(fake.receive(b"GD0100020002;g\n", 0.0))
    frames.append(fake.receive(b"MS0044072510002\n", 0.0))
    now[0] += 0.5
    frames.append(fake.poll(0.0))
    frames += [fake.receive(b"TM0\nTM1\nTM2\n", 0.0), b"SCIP2.0\n0\n\n"]
    return tuple(f for f in frames if f)


def _mutate(data: bytes, rng: random.Random, n: int) -> bytes:
    buf = bytearray(data)
    for _ in range(n):
        op = rng.randrange(6)
        i = rng.randrange(len(buf) + 1)
        if op == 0 and buf:
            buf[min(i, len(buf) - 1)] = rng.randrange(256)
        elif op == 1:
            buf[i:i] = bytes(rng.randrange(256) for _ in range(rng.randrange(1, 8)))
        elif op == 2:
            del buf[i : i + rng.randrange(1, 70)]
        elif op == 3:
            buf[i:i] = rng.choice((b"\n", b"\n\n", b";", b"99b\n", b"00P\n", b"MD0044072501000\n"))
        elif op == 4 and buf:
            j = rng.randrange(len(buf))
            buf[i:i] = buf[j : j + rng.randrange(1, 200)]
        else:
            buf = buf[:i]
    return bytes(buf)


def check_decoder_on(data: bytes, cuts: list[int]) -> None:
    """Feed ``data`` cut at ``cuts``: only ScipReply out, only ScipError recorded, every byte accounted for,
    the buffer bounded; and parse_reply on any LF-LF-terminated piece raises nothing but ScipError."""
    dec = scip.ScipDecoder(max_buffer=4096)
    replies: list[scip.ScipReply] = []
    prev = 0
    for cut in [*sorted(cuts), len(data)]:
        replies += dec.feed(data[prev:cut])
        prev = max(prev, cut)
    assert all(isinstance(r, scip.ScipReply) for r in replies)
    assert all(isinstance(e, scip.ScipError) for e in dec.take_errors())
    assert sum(len(r.raw) for r in replies) + dec.discarded_bytes + dec.buffered == len(data)
    assert dec.buffered <= dec.max_buffer
    for piece in data.split(b"\n\n")[:4]:
        try:
            reply = scip.parse_reply(piece + b"\n\n")
        except scip.ScipError:
            continue
        assert reply.raw == piece + b"\n\n"


def fuzz_decoder(max_examples: int = 2000, seed: int | None = None) -> None:
    """Run the decoder property on ``max_examples`` inputs: random bytes and mutations of the real captures
    (when present) and of the fake's output. Benchmarks call this with many more examples."""
    corpus = list(_seed_frames())
    urg = DATA / "urg"
    if urg.is_dir():
        corpus += [(urg / name).read_bytes() for name in CAPTURES.values()]

    frames = st.lists(st.sampled_from(corpus), min_size=1, max_size=4)
    inputs = st.one_of(
        st.binary(max_size=3000),
        st.builds(lambda fs, r, n: _mutate(b"".join(fs), random.Random(r), n), frames, st.integers(0, 2**32),
                  st.integers(0, 12)),
        # Replies that lost their terminators: kilobytes without LF LF, to exercise the buffer bound.
        st.builds(lambda fs, r, n: _mutate(b"".join(fs).replace(b"\n\n", b"\n"), random.Random(r), n), frames,
                  st.integers(0, 2**32), st.integers(0, 4)),
    )  # fmt: skip

    @settings(max_examples=max_examples, deadline=timedelta(seconds=2), derandomize=seed is not None,
              suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])  # fmt: skip
    @given(data=inputs, cuts=st.lists(st.integers(0, 12000), max_size=8))
    def prop(data: bytes, cuts: list[int]) -> None:
        check_decoder_on(data, cuts)

    prop()


def test_decoder_fuzz() -> None:
    fuzz_decoder(max_examples=2000)
