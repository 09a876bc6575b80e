"""The pose frame: what the agent sends to controller firmware over a serial line (``docs/wire-format.md``).

One frame per fused pose::

    wire  = COBS(payload || CRC) || 00
    CRC   = CRC-16/CCITT-FALSE over the payload (poly 0x1021, init 0xFFFF, check 0x29B1), little-endian

Payload, version 1.0 (30 bytes, little-endian, offsets in bytes)::

     0  u8   version        major << 4 | minor: 0x10
     1  u8   reset_counter  +1 (wrapping) whenever the pose jumps (relocalisation, map reload)
     2  u16  flags          :class:`PoseFlags`: live sources, faults
     4  u32  sequence       +1 per frame, wrapping; a gap means frames were lost
     8  u64  t_us           capture time of the newest measurement in the pose, microseconds, agent's
                            CLOCK_MONOTONIC
    16  i32  x              0.1 mm (1e-4 m), map frame
    20  i32  y              0.1 mm
    24  i16  yaw            2*pi/65536 rad (a binary angle: wraps at +-pi by itself), counter-clockwise
    26  u16  sigma_xy       0.1 mm, 1-sigma position error (square root of the larger eigenvalue of the
                            2x2 covariance); 0xFFFF = unknown or >= 6.5535 m
    28  u16  sigma_yaw      1e-4 rad, 1-sigma yaw error; 0xFFFF = unknown or >= 6.5535 rad

Fixed-point, not float: controllers without an FPU decode it with integer code, a round trip is exact, and
there is no NaN to misread. 0.1 mm is ten times finer than the VLP's millimetre accuracy and an i32 still
spans +-214 km; the binary-angle yaw is 0.0055 deg per step (0.1 mm of arc at 1 m).

A v1.0 frame is always 34 bytes on the wire (32 bytes stuffed: COBS adds one byte below 254; then 0x00).

**Versioning.** The major version changes when an existing field changes meaning, size or place;
decoders reject every major version but their own. A minor version only appends fields after the last one
or gives meaning to reserved flag bits; decoders accept any minor of their major, ignore fields they do not
know, and require a v1.0 payload to be exactly 30 bytes and a v1.x payload to be 30..64 bytes.

:func:`encode_pose` / :func:`decode_pose` work on one frame; :class:`PoseFrameDecoder` finds frames in a
byte stream, resyncs at the next 0x00 and counts what it rejects. Every rejection is a
:class:`PoseFrameError` carrying the bytes. The C reference decoder in ``firmware_protocol/c/`` makes the
same decisions byte for byte (``tests/unit/test_c_decoder.py``).
"""

from __future__ import annotations

import enum
import math
import struct
from dataclasses import dataclass

from firmware_protocol.cobs import CobsError, cobs_decode, cobs_encode, max_encoded_length
from firmware_protocol.crc import crc16_ccitt_false
from firmware_protocol.errors import ProtocolError

__all__ = [
    "CRC_LENGTH",
    "MAX_ENCODED_LENGTH",
    "MAX_PAYLOAD_LENGTH",
    "NO_FLAGS",
    "PAYLOAD_LENGTH",
    "POSITION_LSB_M",
    "SIGMA_UNKNOWN",
    "SIGMA_XY_LSB_M",
    "SIGMA_YAW_LSB_RAD",
    "WIRE_LENGTH",
    "WIRE_VERSION",
    "WIRE_VERSION_MAJOR",
    "WIRE_VERSION_MINOR",
    "YAW_LSB_RAD",
    "PoseCobsError",
    "PoseCrcError",
    "PoseFlags",
    "PoseFrame",
    "PoseFrameDecoder",
    "PoseFrameError",
    "PoseLengthError",
    "PoseVersionError",
    "decode_payload",
    "decode_pose",
    "encode_payload",
    "encode_pose",
]

WIRE_VERSION_MAJOR = 1
WIRE_VERSION_MINOR = 0
WIRE_VERSION = WIRE_VERSION_MAJOR << 4 | WIRE_VERSION_MINOR

_LAYOUT = struct.Struct("<BBHIQiihHH")
PAYLOAD_LENGTH = _LAYOUT.size  # 30: a v1.0 payload
MAX_PAYLOAD_LENGTH = 64  # the longest payload a later v1.x may send; bounds every decoder's buffer
CRC_LENGTH = 2
MAX_ENCODED_LENGTH = max_encoded_length(MAX_PAYLOAD_LENGTH + CRC_LENGTH)  # 67, without the delimiter
WIRE_LENGTH = max_encoded_length(PAYLOAD_LENGTH + CRC_LENGTH) + 1  # 34: every v1.0 frame, delimiter included

POSITION_LSB_M = 1e-4
SIGMA_XY_LSB_M = 1e-4
SIGMA_YAW_LSB_RAD = 1e-4
YAW_LSB_RAD = math.pi / 32768
SIGMA_UNKNOWN = 0xFFFF
# Decoding divides by these (not multiplies by the LSB) so that every decoder gets the same double.
_PER_M = 10_000
_PER_RAD_SIGMA = 10_000

_U16, _U32, _U64 = 0xFFFF, 0xFFFF_FFFF, 0xFFFF_FFFF_FFFF_FFFF


class PoseFlags(enum.IntFlag):
    """The status word: which sources the pose is built from now, and what is wrong.

    Bits 0-7 say which sources are live (fused within their timeout), bits 8-15 flag faults. Bits not
    named here are reserved: senders write 0, decoders ignore them (a later minor version may define them),
    and :class:`PoseFrameDecoder` keeps them in the value it returns.
    """

    VLP = 1 << 0  # a VLP fix was fused within the timeout
    SLAM = 1 << 1  # the SLAM pose is fused (laser scans arriving, scan matching converged)
    ODOMETRY = 1 << 2  # wheel odometry is arriving
    IMU = 1 << 3  # IMU yaw rate is fused, beside a position source (alone it is a stale hold: no bit)
    DEGRADED = 1 << 8  # usable but worse than nominal: fewer sources than configured; see sigma_xy
    LASER_LOST = 1 << 9  # the laser scanner stopped answering (SLAM frozen; VLP + odometry carry on)
    CAMERA_STALLED = 1 << 10  # no camera frame within the timeout (no VLP; SLAM + odometry carry on)
    SERVO_FAULT = 1 << 11  # a wheel servo stopped answering or reported a hardware error


NO_FLAGS = PoseFlags(0)


class PoseFrameError(ProtocolError):
    """A pose frame that cannot be encoded, or bytes that are not a valid pose frame."""


class PoseCobsError(PoseFrameError):
    """The bytes between two 0x00 delimiters are not valid COBS (usually a frame cut short)."""


class PoseLengthError(PoseFrameError):
    """The decoded frame is too short or too long for its version."""


class PoseCrcError(PoseFrameError):
    """The CRC does not match (line noise, or two frames run together)."""


class PoseVersionError(PoseFrameError):
    """A major version this decoder does not know."""


@dataclass(frozen=True, slots=True)
class PoseFrame:
    """One pose, in SI units; the wire quantises it (see the module docstring).

    ``sigma_*`` are 1-sigma errors; ``math.inf`` (or NaN, which encodes the same) means unknown.
    Decoding returns the quantised values, so ``decode_pose(encode_pose(f))`` equals ``f`` only to within
    half a step, while ``encode_pose(decode_pose(w)) == w`` for every valid v1.0 frame ``w``.
    """

    sequence: int
    t_us: int
    x_m: float
    y_m: float
    yaw_rad: float
    sigma_xy_m: float = math.inf
    sigma_yaw_rad: float = math.inf
    flags: PoseFlags = NO_FLAGS
    reset_counter: int = 0


# -- payload -----------------------------------------------------------------------------------------


def _unsigned(value: int, limit: int, what: str) -> int:
    if not 0 <= value <= limit:
        raise PoseFrameError(f"{what} {value} does not fit in 0..{limit}")
    return value


def _fixed_i32(value_m: float, what: str) -> int:
    scaled = value_m * _PER_M
    if not math.isfinite(scaled):
        raise PoseFrameError(f"{what} must be finite, got {value_m}")
    q = round(scaled)
    if not -(1 << 31) <= q < 1 << 31:
        raise PoseFrameError(f"{what} {value_m} m is outside +-214748.3647 m")
    return q


def _sigma(value: float, per_unit: int, what: str) -> int:
    if math.isnan(value):
        return SIGMA_UNKNOWN
    if value < 0:
        raise PoseFrameError(f"{what} must be >= 0 (or inf / NaN for unknown), got {value}")
    scaled = value * per_unit
    return SIGMA_UNKNOWN if scaled >= SIGMA_UNKNOWN else min(round(scaled), SIGMA_UNKNOWN)


def _yaw_bam(yaw_rad: float) -> int:
    scaled = yaw_rad / YAW_LSB_RAD
    if not math.isfinite(scaled):
        raise PoseFrameError(f"yaw must be finite, got {yaw_rad}")
    return (round(scaled) + 0x8000) % 0x10000 - 0x8000


def encode_payload(frame: PoseFrame) -> bytes:
    """The 30-byte v1.0 payload of ``frame`` (no CRC); :class:`PoseFrameError` if a field does not fit."""
    return _LAYOUT.pack(
        WIRE_VERSION,
        _unsigned(frame.reset_counter, 0xFF, "reset_counter"),
        _unsigned(int(frame.flags), _U16, "flags"),
        _unsigned(frame.sequence, _U32, "sequence"),
        _unsigned(frame.t_us, _U64, "t_us"),
        _fixed_i32(frame.x_m, "x"),
        _fixed_i32(frame.y_m, "y"),
        _yaw_bam(frame.yaw_rad),
        _sigma(frame.sigma_xy_m, _PER_M, "sigma_xy"),
        _sigma(frame.sigma_yaw_rad, _PER_RAD_SIGMA, "sigma_yaw"),
    )


def _sigma_value(q: int, per_unit: int) -> float:
    return math.inf if q == SIGMA_UNKNOWN else q / per_unit


def decode_payload(payload: bytes | bytearray | memoryview) -> PoseFrame:
    """Decode a payload (CRC already checked and removed), applying the versioning rule."""
    payload = bytes(payload)
    if not payload:
        raise PoseLengthError("empty pose payload")
    major, minor = payload[0] >> 4, payload[0] & 0x0F
    if major != WIRE_VERSION_MAJOR:
        raise PoseVersionError(
            f"pose frame version {major}.{minor}: this decoder reads major version {WIRE_VERSION_MAJOR}",
            payload,
        )
    if minor == 0 and len(payload) != PAYLOAD_LENGTH:
        raise PoseLengthError(f"a v1.0 pose payload is {PAYLOAD_LENGTH} bytes, got {len(payload)}", payload)
    if not PAYLOAD_LENGTH <= len(payload) <= MAX_PAYLOAD_LENGTH:
        raise PoseLengthError(
            f"a v1.{minor} pose payload is {PAYLOAD_LENGTH}..{MAX_PAYLOAD_LENGTH} bytes, got {len(payload)}",
            payload,
        )
    _, reset, flags, seq, t_us, x, y, yaw, sxy, syaw = _LAYOUT.unpack_from(payload)
    return PoseFrame(
        sequence=seq,
        t_us=t_us,
        x_m=x / _PER_M,
        y_m=y / _PER_M,
        yaw_rad=yaw * YAW_LSB_RAD,
        sigma_xy_m=_sigma_value(sxy, _PER_M),
        sigma_yaw_rad=_sigma_value(syaw, _PER_RAD_SIGMA),
        flags=PoseFlags(flags),
        reset_counter=reset,
    )


# -- one frame ---------------------------------------------------------------------------------------


def encode_pose(frame: PoseFrame) -> bytes:
    """The bytes to write for ``frame``: ``COBS(payload || CRC-LE) || 00``, :data:`WIRE_LENGTH` bytes."""
    payload = encode_payload(frame)
    return cobs_encode(payload + crc16_ccitt_false(payload).to_bytes(2, "little")) + b"\x00"


def _decode_unstuffed(decoded: bytes) -> PoseFrame:
    """Checks in the order the C decoder makes them: length bounds, CRC, then version and its length."""
    if not PAYLOAD_LENGTH + CRC_LENGTH <= len(decoded) <= MAX_PAYLOAD_LENGTH + CRC_LENGTH:
        raise PoseLengthError(
            f"pose frame is {len(decoded)} bytes after COBS, not "
            f"{PAYLOAD_LENGTH + CRC_LENGTH}..{MAX_PAYLOAD_LENGTH + CRC_LENGTH}",
            decoded,
        )
    payload, sent = decoded[:-CRC_LENGTH], int.from_bytes(decoded[-CRC_LENGTH:], "little")
    computed = crc16_ccitt_false(payload)
    if sent != computed:
        raise PoseCrcError(f"pose frame CRC {sent:04X} != computed {computed:04X}", decoded)
    return decode_payload(payload)


def decode_pose(wire: bytes | bytearray | memoryview) -> PoseFrame:
    """Decode one frame as :func:`encode_pose` writes it (the final 0x00 may be left off).

    Raises a :class:`PoseFrameError` subclass for anything else, including a second 0x00.
    """
    wire = bytes(wire)
    body = wire[:-1] if wire.endswith(b"\x00") else wire
    try:
        decoded = cobs_decode(body)
    except CobsError as exc:
        raise PoseCobsError(exc.reason, wire) from exc
    return _decode_unstuffed(decoded)


# -- stream ------------------------------------------------------------------------------------------


class PoseFrameDecoder:
    """Finds pose frames in a byte stream.

    ``feed`` returns the frames completed so far; bytes after the last 0x00 wait for the next call. Every
    0x00 ends a candidate frame: a bad one (COBS, length, CRC, version) is counted, its bytes plus the
    delimiter go to ``discarded_bytes``, and decoding resumes right after it, so one bad frame never costs a
    good one. An empty candidate (two 0x00 in a row, or a 0x00 at the start) is idle fill, not an error.
    The buffer never holds more than :data:`MAX_ENCODED_LENGTH` bytes: beyond that the candidate is counted
    once in ``overflows`` and skipped up to the next 0x00. The overflow is counted as soon as the byte that
    cannot be a frame arrives, not when a 0x00 ends the run: a line that sends noise and never a 0x00 shows
    up in the counters at once. Either way the count depends only on the bytes, never on how they were cut
    into ``feed`` calls. The run's bytes go to ``discarded_bytes`` when its 0x00 comes.
    """

    def __init__(self) -> None:
        self._buf = bytearray()
        self._raw = 0  # bytes since the last delimiter, also those not kept after an overflow
        self._overflow = False
        self.frames = 0
        self.crc_errors = 0
        self.length_errors = 0
        self.cobs_errors = 0
        self.version_errors = 0
        self.overflows = 0
        self.discarded_bytes = 0
        self.last_error: PoseFrameError | None = None

    @property
    def pending(self) -> int:
        """Bytes received since the last 0x00 (a frame not yet complete, or junk being skipped)."""
        return self._raw

    @property
    def bad_frames(self) -> int:
        return self.crc_errors + self.length_errors + self.cobs_errors + self.version_errors + self.overflows

    def counters(self) -> dict[str, int]:
        """For ``health()``; the same names as the C decoder's ``pose_decoder_stats_t``."""
        return {
            "frames": self.frames,
            "crc_errors": self.crc_errors,
            "length_errors": self.length_errors,
            "cobs_errors": self.cobs_errors,
            "version_errors": self.version_errors,
            "overflows": self.overflows,
            "discarded_bytes": self.discarded_bytes,
        }

    def reset(self) -> None:
        """Forget a partial frame (e.g. after reopening the port) without counting it; counters are kept."""
        self._buf.clear()
        self._raw = 0
        self._overflow = False

    def feed(self, data: bytes | bytearray | memoryview) -> list[PoseFrame]:
        data = bytes(data)
        out: list[PoseFrame] = []
        start = 0
        while True:
            end = data.find(0, start)
            self._take(data[start:] if end < 0 else data[start:end])
            if end < 0:
                return out
            frame = self._end_of_frame()
            if frame is not None:
                out.append(frame)
            start = end + 1

    def _take(self, chunk: bytes) -> None:
        if not chunk:
            return
        self._raw += len(chunk)
        if self._overflow:
            return
        if len(self._buf) + len(chunk) > MAX_ENCODED_LENGTH:
            self._overflow = True
            self.overflows += 1
            self.last_error = PoseLengthError(
                f"no 0x00 within {MAX_ENCODED_LENGTH} bytes: skipping to the next one",
                bytes(self._buf + chunk[: MAX_ENCODED_LENGTH + 1 - len(self._buf)]),
            )
            self._buf.clear()
            return
        self._buf += chunk

    def _end_of_frame(self) -> PoseFrame | None:
        raw, overflow, body = self._raw, self._overflow, bytes(self._buf)
        self.reset()
        if raw == 0:
            return None
        if not overflow:
            try:
                frame = decode_pose(body)
            except PoseFrameError as exc:
                self._count(exc)
            else:
                self.frames += 1
                return frame
        self.discarded_bytes += raw + 1
        return None

    def _count(self, exc: PoseFrameError) -> None:
        if isinstance(exc, PoseCrcError):
            self.crc_errors += 1
        elif isinstance(exc, PoseCobsError):
            self.cobs_errors += 1
        elif isinstance(exc, PoseVersionError):
            self.version_errors += 1
        else:
            self.length_errors += 1
        self.last_error = exc
