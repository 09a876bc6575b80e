"""The reference C decoder (``firmware_protocol/c/``) against the Python encoder and decoder.

gcc builds it twice into a temporary directory: once with the flags firmware will use
(``-std=c99 -Wall -Wextra -Werror -pedantic`` plus ``-Wconversion``), once with AddressSanitizer and
UBSan for the random-input runs, so an out-of-bounds write or an overflow fails the test instead of passing
by luck. The tests skip, saying why, when gcc is missing. Every comparison is exact: the C program prints
positions and sigmas from their integers and yaw with ``%.17g``, which read back as the very doubles the
Python decoder returns.
"""

from __future__ import annotations

import math
import os
import random
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings

from firmware_protocol.cobs import cobs_encode
from firmware_protocol.crc import crc16_ccitt_false
from firmware_protocol.pose_frame import (
    WIRE_LENGTH,
    PoseFlags,
    PoseFrame,
    PoseFrameDecoder,
    decode_pose,
    encode_payload,
    encode_pose,
)
from tests.unit.test_pose_frame import STREAMS, VECTORS, pose_frames, wire_for

C_DIR = Path(__file__).resolve().parents[2] / "firmware_protocol" / "c"
SOURCES = [C_DIR / "test_pose_frame.c", C_DIR / "pose_frame.c"]
STRICT = [
    "-std=c99",
    "-Wall",
    "-Wextra",
    "-Werror",
    "-pedantic",
    "-Wshadow",
    "-Wconversion",
    "-Wsign-conversion",
]
SANITIZE = [
    "-O1",
    "-g",
    "-fsanitize=address,undefined",
    "-fno-sanitize-recover=all",
    "-fno-omit-frame-pointer",
]
RUN_ENV = {
    **os.environ,
    "ASAN_OPTIONS": "detect_leaks=0:abort_on_error=0",
    "UBSAN_OPTIONS": "print_stacktrace=1",
}


@dataclass(frozen=True)
class Binaries:
    strict: Path
    checked: Path  # sanitizers if this gcc has them, else the strict build
    sanitized: bool


def build_c(out: Path, name: str, sources: list[Path], probe_args: tuple[str, ...] = ()) -> Binaries:
    """``name`` built from ``sources`` into ``out`` warning-free with the firmware flags, and again with
    the sanitizers where this gcc has them (probed by running it with ``probe_args`` on no input);
    skips the test when gcc is missing."""
    gcc = shutil.which("gcc")
    if gcc is None:
        pytest.skip(f"gcc not found on PATH: {name} cannot be built here")
    strict = out / name
    build = subprocess.run(
        [gcc, *STRICT, "-O2", "-o", str(strict), *map(str, sources)], capture_output=True, text=True
    )
    assert build.returncode == 0, f"{name} does not build warning-free:\n{build.stderr}"
    checked = out / f"{name}_asan"
    build = subprocess.run(
        [gcc, *STRICT, *SANITIZE, "-o", str(checked), *map(str, sources)], capture_output=True, text=True
    )
    if build.returncode == 0 and run(checked, b"", *probe_args).returncode == 0:
        return Binaries(strict, checked, True)
    return Binaries(strict, strict, False)


@pytest.fixture(scope="module")
def c_decoder(tmp_path_factory: pytest.TempPathFactory) -> Binaries:
    return build_c(tmp_path_factory.mktemp("c_decoder"), "test_pose_frame", SOURCES)


def run(binary: Path, data: bytes, *args: str) -> subprocess.CompletedProcess[bytes]:
    # The timeout only keeps a hung decoder from hanging the suite; it measures nothing.
    return subprocess.run(
        [str(binary), *(args or ("-",))], input=data, capture_output=True, timeout=60, env=RUN_ENV
    )


Row = tuple[int, int, float, float, float, float, float, int, int, int]


def decode_with_c(binary: Path, data: bytes) -> tuple[list[Row], dict[str, int]]:
    proc = run(binary, data)
    assert proc.returncode == 0, (
        f"C decoder failed ({proc.returncode}):\n{proc.stderr.decode(errors='replace')}"
    )
    lines = proc.stdout.decode("ascii").splitlines()
    assert lines[0] == "seq,t_us,x_m,y_m,yaw_rad,sigma_xy_m,sigma_yaw_rad,flags,reset_counter,version"
    rows = []
    for line in lines[1:]:
        seq, t_us, x, y, yaw, sxy, syaw, flags, reset, version = line.split(",")
        rows.append(
            (
                int(seq),
                int(t_us),
                float(x),
                float(y),
                float(yaw),
                float(sxy),
                float(syaw),
                int(flags, 16),
                int(reset),
                int(version, 16),
            )
        )
    counters = {k: int(v) for k, v in (kv.split("=") for kv in proc.stderr.decode("ascii").split())}
    return rows, counters


def row(frame: PoseFrame, version: int = 0x10) -> Row:
    return (
        frame.sequence,
        frame.t_us,
        frame.x_m,
        frame.y_m,
        frame.yaw_rad,
        frame.sigma_xy_m,
        frame.sigma_yaw_rad,
        int(frame.flags),
        frame.reset_counter,
        version,
    )


def assert_same_as_python(binary: Path, data: bytes) -> list[Row]:
    """The C decoder finds exactly the Python decoder's frames (every field) and counts the same."""
    rows, counters = decode_with_c(binary, data)
    py = PoseFrameDecoder()
    frames = py.feed(data)
    assert [r[:9] for r in rows] == [row(f)[:9] for f in frames]
    assert counters == {**py.counters(), "pending": py.pending}
    return rows


# -- build, vectors ----------------------------------------------------------------------------------


def test_builds_warning_free_and_passes_its_vector_self_test(c_decoder: Binaries) -> None:
    proc = run(c_decoder.strict, b"", "--vectors")
    assert proc.returncode == 0, proc.stdout.decode()
    assert proc.stdout.decode().count("ok   vector") == len(VECTORS)


def test_the_vectors_in_the_c_source_are_the_docs(c_decoder: Binaries) -> None:
    proc = run(c_decoder.strict, b"", "--list-vectors")
    assert [bytes.fromhex(line) for line in proc.stdout.decode().splitlines()] == [v.wire for v in VECTORS]


def test_doc_vectors_decode_field_by_field(c_decoder: Binaries) -> None:
    rows = assert_same_as_python(c_decoder.strict, b"".join(v.wire for v in VECTORS))
    for v, r in zip(VECTORS, rows, strict=True):
        raw = v.raw
        assert r[:2] == (raw["sequence"], raw["t_us"])
        assert r[2:4] == (raw["x"] / 10_000, raw["y"] / 10_000)
        assert r[4] == raw["yaw"] * (math.pi / 32768)
        assert r[7:] == (raw["flags"], raw["reset_counter"], raw["version"])


def test_makefile_check_target(tmp_path: Path) -> None:
    make, gcc = shutil.which("make"), shutil.which("gcc")
    if make is None or gcc is None:
        pytest.skip("make or gcc not found on PATH")
    proc = subprocess.run([make, "-s", "-C", str(C_DIR), f"BUILD={tmp_path}", "check"], capture_output=True)
    assert proc.returncode == 0, proc.stdout.decode() + proc.stderr.decode()
    assert (tmp_path / "test_pose_frame").exists()


# -- against the Python encoder ----------------------------------------------------------------------


def random_frames(rng: random.Random, n: int) -> list[PoseFrame]:
    def sigma() -> float:
        return rng.choice([math.inf, rng.uniform(0, 0.01), rng.uniform(0, 7)])

    return [
        PoseFrame(
            sequence=rng.getrandbits(32),
            t_us=rng.getrandbits(rng.choice([20, 40, 64])),
            x_m=rng.uniform(-214748, 214748) if i % 5 == 0 else rng.uniform(-50, 50),
            y_m=rng.uniform(-214748, 214748) if i % 7 == 0 else rng.uniform(-50, 50),
            yaw_rad=rng.uniform(-4, 4),
            sigma_xy_m=sigma(),
            sigma_yaw_rad=sigma(),
            flags=PoseFlags(rng.getrandbits(16)),
            reset_counter=rng.getrandbits(8),
        )
        for i in range(n)
    ]


def test_thousands_of_encoded_frames_match_field_by_field(c_decoder: Binaries) -> None:
    frames = random_frames(random.Random(1), 3000)
    rows = assert_same_as_python(c_decoder.strict, b"".join(encode_pose(f) for f in frames))
    assert len(rows) == 3000


def test_junk_truncated_and_corrupted_frames_between_good_ones(c_decoder: Binaries) -> None:
    rng = random.Random(2)
    good = random_frames(rng, 38)
    parts: list[bytes] = [b"\x42\x42\x00"]  # the tail of a frame: the port opened mid-frame
    for i, frame in enumerate(good):
        wire = encode_pose(frame)
        parts.append(wire)
        kind = i % 8
        if kind == 0:  # corrupted CRC, framing intact
            payload = encode_payload(frame)
            bad = (crc16_ccitt_false(payload) ^ (1 << rng.randrange(16))).to_bytes(2, "little")
            parts.append(cobs_encode(payload + bad) + b"\x00")
        elif kind == 1:  # truncated
            parts.append(wire[: rng.randrange(1, WIRE_LENGTH - 1)] + b"\x00")
        elif kind == 2:  # a bit flipped anywhere
            flipped = bytearray(wire)
            flipped[rng.randrange(WIRE_LENGTH - 1)] ^= 1 << rng.randrange(8)
            parts.append(bytes(flipped))
        elif kind == 3:  # random junk, zeros and all, then a zero (a glitch that ends in a break, say)
            parts.append(rng.randbytes(rng.randrange(1, 40)) + b"\x00")
        elif kind == 4:  # a long run without zero: overflow
            parts.append(bytes(rng.randrange(1, 256) for _ in range(rng.randrange(68, 300))) + b"\x00")
        elif kind == 5:  # idle fill
            parts.append(b"\x00" * rng.randrange(1, 4))
        elif kind == 6:  # unknown major, and a newer minor with an appended field (accepted)
            payload = encode_payload(frame)
            parts.append(wire_for(bytes([0x20]) + payload[1:]))
            parts.append(wire_for(bytes([0x13]) + payload[1:] + b"\x01\x02\x03"))
        elif kind == 7:  # junk without a zero runs into the next frame, which is lost: COBS has no start mark
            parts.append(bytes(rng.randrange(1, 256) for _ in range(rng.randrange(1, 20))))
    parts.append(encode_pose(good[0])[:10])  # trailing bytes: still pending at the end
    data = b"".join(parts)
    rows = assert_same_as_python(c_decoder.checked, data)
    py = PoseFrameDecoder()
    found = py.feed(data)
    expected = []
    for i, frame in enumerate(good):
        if i % 8 != 0 or i == 0:  # the frame after a kind-7 run of junk is lost, no other
            expected.append(decode_pose(encode_pose(frame)))
        if i % 8 == 6:  # the v1.3 copy
            expected.append(decode_pose(encode_pose(frame)))
    assert found == expected
    assert {r[9] for r in rows} == {0x10, 0x13}
    assert py.crc_errors >= 5 and py.overflows == 5 and py.version_errors == 4 and py.pending == 10


@pytest.mark.parametrize(
    ("data", "frames", "overflows", "pending"),
    [
        (b"\x01" * 67, 0, 0, 67),  # as long as the longest frame: not (yet) an overflow
        (b"\x01" * 68, 0, 1, 68),  # issue 17: overflowed, counted though no 0x00 has ended it
        (b"\x01" * 68 + b"\x00", 0, 1, 0),
        (b"\x01" * 300, 0, 1, 300),  # counted once per run, not once per buffer-full
        (b"\xff" + bytes(range(1, 68)), 0, 1, 68),  # inside one 0xFF block: no implied zeros
        (b"\x44" + bytes(range(1, 68)), 0, 1, 68),
        (b"\x01" * 68 + b"\x00" + encode_pose(PoseFrame(7, 8, 1.0, 2.0, 0.5)), 1, 1, 0),
    ],
    ids=["67", "68", "68+00", "300", "ff-block", "44-block", "then-a-frame"],
)
def test_a_run_without_zero_overflows_at_the_same_byte_in_c_and_python(
    c_decoder: Binaries, data: bytes, frames: int, overflows: int, pending: int
) -> None:
    rows = assert_same_as_python(c_decoder.checked, data)
    _, counters = decode_with_c(c_decoder.checked, data)
    assert (len(rows), counters["overflows"], counters["pending"]) == (frames, overflows, pending)


def test_a_megabyte_of_noise_with_frames_in_it(c_decoder: Binaries) -> None:
    rng = random.Random(3)
    noise = bytearray(rng.randbytes(1 << 20))
    for frame in random_frames(rng, 500):
        at = rng.randrange(len(noise))
        noise[at:at] = b"\x00" + encode_pose(frame)
    assert_same_as_python(c_decoder.checked, bytes(noise))


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=STREAMS)
def test_random_and_mutated_input_never_crashes_and_matches_python(c_decoder: Binaries, data: bytes) -> None:
    assert_same_as_python(c_decoder.checked, data)


@settings(max_examples=40, deadline=None)
@given(frame=pose_frames)
def test_any_encodable_frame_decodes_identically(c_decoder: Binaries, frame: PoseFrame) -> None:
    rows = assert_same_as_python(c_decoder.checked, encode_pose(frame))
    assert len(rows) == 1


def test_sanitizers_were_available(c_decoder: Binaries) -> None:
    if not c_decoder.sanitized:
        pytest.skip("this gcc cannot build with -fsanitize=address,undefined: fuzzed the plain build only")
