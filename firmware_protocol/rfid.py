"""RFID reader wire formats: 125 kHz ASCII readers and the ThingMagic Mercury serial protocol.

Two families, both sans-I/O (bytes in, frozen dataclasses out):

* **125 kHz ASCII readers** (ID Innovations ID-12LA / ID-20LA, RDM6300). The reader sends one fixed frame
  per tag read and takes no commands::

      ID-12LA:  02 | 10 ASCII-hex data (5 bytes) | 2 ASCII-hex checksum | 0D 0A | 03   (16 bytes)
      RDM6300:  02 | 10 ASCII-hex data (5 bytes) | 2 ASCII-hex checksum | 03          (14 bytes)

  The checksum is the XOR of the five data bytes (ID-12LA example from WildernessLabs/Meadow.Foundation
  ``IDxxLA.cs``: ``02 "7C0055F8C4" "15" 0D 0A 03``; RDM6300 example ``13005D1DA5`` -> ``F6``).
  STX (0x02) can never occur inside a frame (the body is ASCII hex), which is what resync relies on.

* **ThingMagic Mercury serial protocol** (M6e Nano / Micro, e.g. the SparkFun Simultaneous RFID board),
  as implemented by sparkfun/SparkFun_Simultaneous_RFID_Tag_Reader_Library
  ``src/SparkFun_UHF_RFID_Reader.cpp`` (a stripped-down port of ThingMagic's ``serial_reader_l3.c``)::

      request:   FF | LEN | OPCODE | DATA[LEN] | CRC_HI CRC_LO                          (LEN + 5 bytes)
      response:  FF | LEN | OPCODE | STATUS_HI STATUS_LO | DATA[LEN] | CRC_HI CRC_LO    (LEN + 7 bytes)

  The CRC covers LEN through the last data byte, is sent big-endian, and is ThingMagic's nibble-table CRC
  (``calculateCRC``): poly 0x1021, init 0xFFFF, each data nibble shifted into the *low* end of the register.
  That makes it an augmented CRC, which is why it is not CRC-16/CCITT-FALSE although it uses the same
  polynomial. Vectors: version request ``FF 00 03 1D 0C``; ``FF 0A 24 03 E8 00 00 00 00 00 03 00 EE 58 9D``;
  ``b"123456789"`` -> 0xA69D.

Each family has a streaming decoder (``feed(data) -> list[message]``) that keeps partial input, resyncs on
junk while counting what it discarded, and bounds its buffer; ``flush()`` tells it the line went idle, so a
partial frame still buffered was junk. One-shot ``decode_*`` functions raise :class:`RfidError` (carrying the
offending bytes) for anything malformed; the streaming decoders never raise on bad input, they count it and
keep the last error for the log.
"""

from __future__ import annotations

import enum
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Generic, TypeVar

from firmware_protocol.errors import ProtocolError

__all__ = [
    "ASCII_FRAME_LENGTH",
    "GEN2_PROTOCOL",
    "MERCURY_KEEPALIVE_STATUS",
    "MERCURY_MAX_FRAME",
    "AsciiFormat",
    "AsciiFrameDecoder",
    "AsciiTag",
    "MercuryKeepAlive",
    "MercuryOpcode",
    "MercuryRequest",
    "MercuryRequestDecoder",
    "MercuryResponse",
    "MercuryResponseDecoder",
    "MercuryStatus",
    "MercuryTagRead",
    "MercuryVersion",
    "RfidChecksumError",
    "RfidError",
    "crc16_gen2",
    "crc16_thingmagic",
    "decode_ascii_frame",
    "decode_request_frame",
    "decode_response_frame",
    "decode_stream_message",
    "decode_tag_read",
    "decode_version",
    "encode_ascii_frame",
    "encode_request",
    "encode_response",
    "encode_set_antenna_port",
    "encode_set_antenna_search_list",
    "encode_set_read_power",
    "encode_set_reader_option",
    "encode_set_region",
    "encode_set_tag_protocol",
    "encode_start_continuous_read",
    "encode_stop_continuous_read",
    "encode_tag_read",
    "encode_version_request",
    "encode_version_response",
    "xor_checksum",
]


class RfidError(ProtocolError):
    """Bytes from (or for) an RFID reader that do not follow its protocol."""


class RfidChecksumError(RfidError):
    """A frame that is well formed except that its checksum / CRC does not match (line noise)."""


# ================================================================================================
# 125 kHz ASCII readers
# ================================================================================================

STX = 0x02
ETX = 0x03
_HEX_DIGITS = frozenset(b"0123456789ABCDEFabcdef")


class AsciiFormat(enum.StrEnum):
    ID12LA = "id12la"  # also ID-20LA / ID-3LA: same frame
    RDM6300 = "rdm6300"


_TRAILER = {AsciiFormat.ID12LA: b"\r\n\x03", AsciiFormat.RDM6300: b"\x03"}
ASCII_FRAME_LENGTH = {fmt: 1 + 10 + 2 + len(trailer) for fmt, trailer in _TRAILER.items()}


@dataclass(frozen=True, slots=True)
class AsciiTag:
    """One 125 kHz read: five data bytes (a version/manufacturer byte and a 32-bit card number)."""

    data: bytes
    format: AsciiFormat

    @property
    def tag_id(self) -> str:
        """The ten hex digits as printed on most cards' packaging (upper case)."""
        return self.data.hex().upper()

    @property
    def version(self) -> int:
        return self.data[0]

    @property
    def card_number(self) -> int:
        return int.from_bytes(self.data[1:], "big")


def xor_checksum(data: bytes) -> int:
    """The 125 kHz readers' checksum: XOR of the data bytes."""
    value = 0
    for byte in data:
        value ^= byte
    return value


def encode_ascii_frame(data: bytes, fmt: AsciiFormat | str) -> bytes:
    """The frame a reader in format ``fmt`` sends for the five data bytes ``data``."""
    fmt = AsciiFormat(fmt)
    if len(data) != 5:
        raise RfidError(f"a 125 kHz tag carries 5 data bytes, not {len(data)}", data)
    body = (data.hex() + f"{xor_checksum(data):02x}").upper().encode("ascii")
    return bytes([STX]) + body + _TRAILER[fmt]


def decode_ascii_frame(frame: bytes, fmt: AsciiFormat | str) -> AsciiTag:
    """Decode exactly one frame; raises :class:`RfidError` for anything else."""
    fmt = AsciiFormat(fmt)
    frame = bytes(frame)
    length = ASCII_FRAME_LENGTH[fmt]
    if len(frame) != length:
        raise RfidError(f"{fmt.value} frame must be {length} bytes, got {len(frame)}", frame)
    if frame[0] != STX:
        raise RfidError(f"{fmt.value} frame must start with STX 02", frame)
    if frame[13:] != _TRAILER[fmt]:
        raise RfidError(f"{fmt.value} frame must end with {_TRAILER[fmt].hex(' ')}", frame)
    body = frame[1:13]
    # bytes.fromhex would also accept spaces, so check the digits first.
    if not all(c in _HEX_DIGITS for c in body):
        raise RfidError(f"{fmt.value} frame body is not ASCII hex", frame)
    raw = bytes.fromhex(body.decode("ascii"))
    data, checksum = raw[:5], raw[5]
    expected = xor_checksum(data)
    if checksum != expected:
        raise RfidChecksumError(f"{fmt.value} checksum {checksum:02X} != XOR of data {expected:02X}", frame)
    return AsciiTag(data, fmt)


class _Counting:
    """Counters shared by the streaming decoders (read by drivers for ``health()``)."""

    def __init__(self, max_buffer: int, min_buffer: int) -> None:
        if max_buffer < min_buffer:
            raise ValueError(f"max_buffer must hold one whole frame ({min_buffer} bytes)")
        self.max_buffer = max_buffer
        self._buf = bytearray()
        self.frames = 0
        self.discarded_bytes = 0
        self.resyncs = 0
        self.bad_checksums = 0
        self.last_error: RfidError | None = None
        self._in_junk = False
        self._quiet_end = 0  # Mercury: buffer index before which a CRC failure belongs to one already counted

    @property
    def pending(self) -> int:
        """Bytes held back as the start of a frame not yet complete."""
        return len(self._buf)

    def reset(self) -> None:
        """Forget buffered bytes (e.g. after a reconnect); counters are kept."""
        self._buf.clear()
        self._in_junk = False
        self._quiet_end = 0

    def _discard(self, start: int, count: int, reason: str) -> None:
        self.discarded_bytes += count
        # One resync per run of junk, however many pieces the scan drops it in.
        if not self._in_junk:
            self.resyncs += 1
            self._in_junk = True
        self.last_error = RfidError(reason, bytes(self._buf[start : start + count]))

    def _emitted(self) -> None:
        self.frames += 1
        self._in_junk = False

    def _bound(self) -> None:
        # Never reached with the built-in framings (leftover < one frame), but a bound is a bound.
        excess = len(self._buf) - self.max_buffer
        if excess > 0:
            self._discard(0, excess, "buffer bound exceeded")
            del self._buf[:excess]

    def counters(self) -> dict[str, int]:
        return {
            "frames": self.frames,
            "discarded_bytes": self.discarded_bytes,
            "resyncs": self.resyncs,
            "bad_checksums": self.bad_checksums,
        }


class AsciiFrameDecoder(_Counting):
    """Streaming decoder for ID-12LA / RDM6300 frames."""

    def __init__(self, fmt: AsciiFormat | str, max_buffer: int = 64) -> None:
        self.format = AsciiFormat(fmt)
        self.frame_length = ASCII_FRAME_LENGTH[self.format]
        super().__init__(max_buffer, self.frame_length)

    def feed(self, data: bytes) -> list[AsciiTag]:
        self._buf += data
        return self._parse(idle=False)

    def flush(self) -> list[AsciiTag]:
        """The line went idle: a partial frame still buffered will never complete, drop it."""
        return self._parse(idle=True)

    def _parse(self, idle: bool) -> list[AsciiTag]:
        buf, length, out = self._buf, self.frame_length, []
        i, n = 0, len(buf)
        while i < n:
            start = buf.find(STX, i)
            if start < 0:
                self._discard(i, n - i, "junk without STX")
                i = n
                break
            if start > i:
                self._discard(i, start - i, "junk before STX")
                i = start
            if n - i < length:
                # A partial frame; an STX after its start means the start was junk.
                later = buf.find(STX, i + 1)
                if later >= 0:
                    self._discard(i, later - i, "truncated frame")
                    i = later
                    continue
                if idle:
                    self._discard(i, n - i, "partial frame at idle")
                    i = n
                break
            try:
                out.append(decode_ascii_frame(bytes(buf[i : i + length]), self.format))
            except RfidError as exc:
                if isinstance(exc, RfidChecksumError):
                    self.bad_checksums += 1
                later = buf.find(STX, i + 1, i + length)
                skip = later - i if later >= 0 else length
                self._discard(i, skip, exc.reason)
                self.last_error = exc
                i += skip
                continue
            self._emitted()
            i += length
        del buf[:i]
        self._bound()
        return out


# ================================================================================================
# ThingMagic Mercury serial protocol
# ================================================================================================

_M = TypeVar("_M")

MERCURY_HEADER = 0xFF
MERCURY_MAX_FRAME = 255 + 7
GEN2_PROTOCOL = 0x05  # TMR_TAG_PROTOCOL_GEN2


class MercuryOpcode(enum.IntEnum):
    """Opcodes from the SparkFun header (``TMR_SR_OPCODE_*`` in ThingMagic's ``serial_reader_imp.h``)."""

    VERSION = 0x03
    SET_BAUD_RATE = 0x06
    READ_TAG_ID_SINGLE = 0x21
    READ_TAG_ID_MULTIPLE = 0x22
    READ_TAG_DATA = 0x28
    MULTI_PROTOCOL_TAG_OP = 0x2F
    GET_READ_TX_POWER = 0x62
    SET_ANTENNA_PORT = 0x91
    SET_READ_TX_POWER = 0x92
    SET_TAG_PROTOCOL = 0x93
    SET_REGION = 0x97
    SET_READER_OPTIONAL_PARAMS = 0x9A


class MercuryStatus(enum.IntEnum):
    """Status words (``tmr_status.h`` codes, without the API's type byte)."""

    OK = 0x0000
    WRONG_NUMBER_OF_DATA = 0x0100
    INVALID_OPCODE = 0x0101
    UNIMPLEMENTED_OPCODE = 0x0102
    POWER_TOO_HIGH = 0x0103
    INVALID_PARAMETER_VALUE = 0x0105
    NO_TAGS_FOUND = 0x0400  # the continuous-read keep-alive carries this
    TEMPERATURE_EXCEED_LIMITS = 0x0504  # continuous-read "temperature throttle" notice


MERCURY_KEEPALIVE_STATUS = frozenset({MercuryStatus.NO_TAGS_FOUND, MercuryStatus.TEMPERATURE_EXCEED_LIMITS})

# serial_reader_l3.c / SparkFun calculateCRC(): the 0x1021 multiples of each nibble.
_CRC_TABLE = (
    0x0000, 0x1021, 0x2042, 0x3063, 0x4084, 0x50A5, 0x60C6, 0x70E7,
    0x8108, 0x9129, 0xA14A, 0xB16B, 0xC18C, 0xD1AD, 0xE1CE, 0xF1EF,
)  # fmt: skip


def crc16_thingmagic(data: bytes) -> int:
    """ThingMagic's message CRC (poly 0x1021, init 0xFFFF, nibbles shifted in at the low end)."""
    crc = 0xFFFF
    table = _CRC_TABLE
    for byte in data:
        crc = (((crc << 4) | (byte >> 4)) ^ table[crc >> 12]) & 0xFFFF
        crc = (((crc << 4) | (byte & 0x0F)) ^ table[crc >> 12]) & 0xFFFF
    return crc


def crc16_gen2(data: bytes) -> int:
    """EPC Gen2 CRC-16 over PC + EPC (CRC-16/GENIBUS: poly 0x1021, init 0xFFFF, xorout 0xFFFF).

    Checked against real records in the SparkFun logs: PC 1000 + EPC 596F596F -> F313.
    """
    crc = 0xFFFF
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) & 0xFFFF if crc & 0x8000 else (crc << 1) & 0xFFFF
    return crc ^ 0xFFFF


@dataclass(frozen=True, slots=True)
class MercuryRequest:
    opcode: int
    data: bytes = b""


@dataclass(frozen=True, slots=True)
class MercuryResponse:
    opcode: int
    status: int
    data: bytes = b""

    @property
    def ok(self) -> bool:
        return self.status == MercuryStatus.OK


def _check_u8(value: int, what: str) -> None:
    if not 0 <= value <= 0xFF:
        raise RfidError(f"{what} must fit in one byte, got {value}")


def encode_request(opcode: int, data: bytes = b"") -> bytes:
    _check_u8(opcode, "opcode")
    if len(data) > 255:
        raise RfidError(f"Mercury request data is at most 255 bytes, got {len(data)}", data[:64])
    body = bytes([len(data), opcode]) + data
    return bytes([MERCURY_HEADER]) + body + crc16_thingmagic(body).to_bytes(2, "big")


def encode_response(opcode: int, status: int = 0, data: bytes = b"") -> bytes:
    _check_u8(opcode, "opcode")
    if not 0 <= status <= 0xFFFF:
        raise RfidError(f"status must fit in 16 bits, got {status}")
    if len(data) > 255:
        raise RfidError(f"Mercury response data is at most 255 bytes, got {len(data)}", data[:64])
    body = bytes([len(data), opcode]) + status.to_bytes(2, "big") + data
    return bytes([MERCURY_HEADER]) + body + crc16_thingmagic(body).to_bytes(2, "big")


def _check_frame(frame: bytes, overhead: int, what: str) -> None:
    if len(frame) < overhead:
        raise RfidError(f"Mercury {what} needs at least {overhead} bytes, got {len(frame)}", frame)
    if frame[0] != MERCURY_HEADER:
        raise RfidError(f"Mercury {what} must start with FF", frame)
    if len(frame) != frame[1] + overhead:
        raise RfidError(
            f"Mercury {what} LEN {frame[1]} needs {frame[1] + overhead} bytes, got {len(frame)}", frame
        )
    crc = crc16_thingmagic(frame[1:-2])
    if int.from_bytes(frame[-2:], "big") != crc:
        raise RfidChecksumError(f"Mercury {what} CRC {frame[-2:].hex().upper()} != computed {crc:04X}", frame)


def decode_request_frame(frame: bytes) -> MercuryRequest:
    frame = bytes(frame)
    _check_frame(frame, 5, "request")
    return MercuryRequest(frame[2], frame[3:-2])


def decode_response_frame(frame: bytes) -> MercuryResponse:
    frame = bytes(frame)
    _check_frame(frame, 7, "response")
    return MercuryResponse(frame[2], int.from_bytes(frame[3:5], "big"), frame[5:-2])


class _MercuryDecoder(_Counting, Generic[_M]):
    """Framing shared by both directions; ``_overhead`` is 5 for requests, 7 for responses."""

    _overhead = 7

    def __init__(self, max_buffer: int = 1024) -> None:
        super().__init__(max_buffer, MERCURY_MAX_FRAME)

    def feed(self, data: bytes) -> list[_M]:
        self._buf += data
        return self._parse(idle=False)

    def flush(self) -> list[_M]:
        """The line went idle. A module never pauses inside a frame, so a partial frame still buffered
        was junk (e.g. a stray FF whose "LEN" promised more bytes): drop its header byte and re-scan, which
        releases any complete frames that were waiting behind it."""
        return self._parse(idle=True)

    def _make(self, frame: bytes) -> _M:
        raise NotImplementedError

    def _parse(self, idle: bool) -> list[_M]:
        buf, overhead = self._buf, self._overhead
        out: list[_M] = []
        i, n = 0, len(buf)
        while i < n:
            start = buf.find(MERCURY_HEADER, i)
            if start < 0:
                self._discard(i, n - i, "junk without FF header")
                i = n
                break
            if start > i:
                self._discard(i, start - i, "junk before FF header")
                i = start
            total = buf[i + 1] + overhead if n - i >= 2 else overhead
            if n - i < total:
                if not idle:
                    break
                self._discard(i, 1, "partial frame at idle")
                i += 1
                continue
            frame = bytes(buf[i : i + total])
            crc = crc16_thingmagic(frame[1:-2])
            if int.from_bytes(frame[-2:], "big") != crc:
                # LEN itself may be corrupt, so only the header byte is known bad: re-scan from the next byte.
                # An FF inside the rejected frame is tried too, but not counted as another bad frame.
                if i >= self._quiet_end:
                    self.bad_checksums += 1
                    self._quiet_end = i + total
                self._discard(i, 1, "bad CRC")
                self.last_error = RfidChecksumError(
                    f"Mercury CRC {frame[-2:].hex().upper()} != computed {crc:04X}", frame
                )
                i += 1
                continue
            out.append(self._make(frame))
            self._emitted()
            i += total
        del buf[:i]
        self._quiet_end = max(0, self._quiet_end - i)
        self._bound()
        return out


class MercuryResponseDecoder(_MercuryDecoder[MercuryResponse]):
    """Streaming decoder for what a Mercury module sends (responses and continuous-read records)."""

    _overhead = 7

    def _make(self, frame: bytes) -> MercuryResponse:
        return MercuryResponse(frame[2], int.from_bytes(frame[3:5], "big"), frame[5:-2])


class MercuryRequestDecoder(_MercuryDecoder[MercuryRequest]):
    """Streaming decoder for what a host sends a Mercury module (used by the fake reader)."""

    _overhead = 5

    def _make(self, frame: bytes) -> MercuryRequest:
        return MercuryRequest(frame[2], frame[3:-2])


# -- requests the driver sends ---------------------------------------------------------------------


def encode_version_request() -> bytes:
    """``FF 00 03 1D 0C``."""
    return encode_request(MercuryOpcode.VERSION)


def encode_set_region(region: int) -> bytes:
    """Region codes (SparkFun ``setRegion``): 04 IN, 05 JP, 06 PRC, 08 EU3, 09 KR2, 0B AU, 0C NZ,
    0D NAS2 (North America), FF open. ``0D`` gives ``FF 01 97 0D 4B B0``."""
    _check_u8(region, "region")
    return encode_request(MercuryOpcode.SET_REGION, bytes([region]))


def encode_set_tag_protocol(protocol: int = GEN2_PROTOCOL) -> bytes:
    """The opcode takes a 16-bit protocol id; Gen2 gives ``FF 02 93 00 05 51 7D`` (as in SparkFun's logs)."""
    if not 0 <= protocol <= 0xFFFF:
        raise RfidError(f"tag protocol must fit in 16 bits, got {protocol}")
    return encode_request(MercuryOpcode.SET_TAG_PROTOCOL, protocol.to_bytes(2, "big"))


def encode_set_antenna_port(tx: int = 1, rx: int = 1) -> bytes:
    """SparkFun ``setAntennaPort``: one TX and one RX port (the Nano's single port is 1/1)."""
    _check_u8(tx, "tx port")
    _check_u8(rx, "rx port")
    return encode_request(MercuryOpcode.SET_ANTENNA_PORT, bytes([tx, rx]))


def encode_set_antenna_search_list(ports: Sequence[tuple[int, int]]) -> bytes:
    """SparkFun ``setAntennaSearchList``: option 02 then (TX, RX) pairs; the M6e Micro's two ports are
    ``[(1, 1), (2, 2)]``. ``[(1, 1)]`` gives ``FF 03 91 02 01 01 42 C5`` (SparkFun's logs)."""
    if not ports:
        raise RfidError("antenna search list must name at least one port")
    data = bytearray([0x02])
    for tx, rx in ports:
        _check_u8(tx, "tx port")
        _check_u8(rx, "rx port")
        data += bytes([tx, rx])
    return encode_request(MercuryOpcode.SET_ANTENNA_PORT, bytes(data))


def encode_set_read_power(centi_dbm: int) -> bytes:
    """Read TX power in 1/100 dBm, big-endian signed 16 bits (2700 = 27.00 dBm, the module's maximum)."""
    if not -0x8000 <= centi_dbm <= 0x7FFF:
        raise RfidError(f"read power must fit in 16 bits, got {centi_dbm}")
    return encode_request(MercuryOpcode.SET_READ_TX_POWER, centi_dbm.to_bytes(2, "big", signed=True))


def encode_set_reader_option(key: int, value: int) -> bytes:
    """SparkFun ``setReaderConfiguration``: 01 (key-value form), key, value. ``(0x0C, 0x00)`` disables the
    read filter so a tag that stays in the field keeps being reported (``FF 03 9A 01 0C 00 A3 5D``)."""
    _check_u8(key, "option key")
    _check_u8(value, "option value")
    return encode_request(MercuryOpcode.SET_READER_OPTIONAL_PARAMS, bytes([0x01, key, value]))


# SparkFun startReading(): the blob Universal Reader Assistant sends for a Gen2 continuous read. Decoded in
# SparkFun's comment: timeout 0000, option 01 (continuous), sub-opcode 22 (read tag ID multiple), search
# flags 0000, protocol 05 (Gen2); the rest (07 22 10 00 1B 03 E8 01 FF) configures the embedded 0x22 read
# with metadata and a 1000 ms cycle. We send it verbatim, as SparkFun does.
_START_READING_BLOB = bytes.fromhex("00000122000005072210001b03e801ff")


def encode_start_continuous_read() -> bytes:
    """``FF 10 2F 00 00 01 22 00 00 05 07 22 10 00 1B 03 E8 01 FF DD 2B``."""
    return encode_request(MercuryOpcode.MULTI_PROTOCOL_TAG_OP, _START_READING_BLOB)


def encode_stop_continuous_read() -> bytes:
    """SparkFun stopReading(): timeout 0000, option 02 = stop (``FF 03 2F 00 00 02 5E 86``)."""
    return encode_request(MercuryOpcode.MULTI_PROTOCOL_TAG_OP, bytes([0x00, 0x00, 0x02]))


# -- what the module sends back ---------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class MercuryVersion:
    """Answer to opcode 0x03 (``TMR_SR_cmdVersion``: 4 x 4 bytes, then a 32-bit protocol bit mask)."""

    bootloader: bytes
    hardware: bytes
    firmware_date: bytes
    firmware_version: bytes
    protocols: int

    @property
    def firmware(self) -> str:
        return ".".join(f"{b:02X}" for b in self.firmware_version)


def decode_version(response: MercuryResponse) -> MercuryVersion:
    if response.opcode != MercuryOpcode.VERSION:
        raise RfidError(f"not a version response (opcode {response.opcode:02X})", response.data)
    if not response.ok:
        raise RfidError(f"version request failed with status {response.status:04X}", response.data)
    data = response.data
    if len(data) < 20:
        raise RfidError(f"version response carries 20 bytes, got {len(data)}", data)
    return MercuryVersion(data[0:4], data[4:8], data[8:12], data[12:16], int.from_bytes(data[16:20], "big"))


def encode_version_response(version: MercuryVersion) -> bytes:
    parts = (version.bootloader, version.hardware, version.firmware_date, version.firmware_version)
    if any(len(p) != 4 for p in parts):
        raise RfidError("version fields are 4 bytes each")
    data = b"".join(parts) + version.protocols.to_bytes(4, "big")
    return encode_response(MercuryOpcode.VERSION, 0, data)


@dataclass(frozen=True, slots=True)
class MercuryKeepAlive:
    """The continuous-read heartbeat (about once a second): LEN 0, opcode 22, status 0400 or 0504."""

    status: int

    @property
    def temperature_throttled(self) -> bool:
        return self.status == MercuryStatus.TEMPERATURE_EXCEED_LIMITS


@dataclass(frozen=True, slots=True)
class MercuryTagRead:
    """A continuous-read tag record (SparkFun ``parseResponse`` layout; see :func:`decode_tag_read`)."""

    rssi_dbm: int
    tx_antenna: int
    rx_antenna: int
    frequency_khz: int
    timestamp_ms: int
    phase_deg: int
    protocol: int
    pc: int
    epc: bytes
    epc_crc: int
    embedded_data: bytes = b""
    header: bytes = bytes.fromhex("10001b01ff0101")

    @property
    def epc_hex(self) -> str:
        return self.epc.hex().upper()

    @property
    def antenna_byte(self) -> int:
        return (self.tx_antenna << 4) | self.rx_antenna

    @property
    def epc_crc_ok(self) -> bool:
        """Whether the tag's own CRC-16 over PC + EPC matches (the module passes it through unchecked)."""
        return crc16_gen2(self.pc.to_bytes(2, "big") + self.epc) == self.epc_crc


# Offsets into the whole frame, as SparkFun's parseResponse() comment numbers them:
#   [0] FF  [1] LEN  [2] opcode 22  [3,4] status
#   [5..11]  7 bytes SparkFun calls RFU (10 00 1B 01 FF 01 01 in every record of its logs; the ThingMagic
#            API reads option / metadata flags here, which are fixed by the start-reading blob we send)
#   [12]     RSSI, signed dBm                      [13] antenna, TX port << 4 | RX port
#   [14..16] frequency, kHz                        [17..20] timestamp, ms since the last keep-alive
#   [21,22]  phase of the tag reply, 0..180 deg    [23] protocol id (05 = Gen2)
#   [24,25]  number of bits of embedded tag data, M bytes of data follow (rounded up)
#   [26+M]   RFU (0F)                              [27+M, 28+M] EPC length in bits, counting PC and EPC CRC
#   then PC (2), EPC (N - 4), EPC CRC (2), and the message CRC (2).
_RECORD_FIXED = 24  # data bytes of a record with no embedded data, not counting PC + EPC + EPC CRC
_RECORD_RFU = 0x0F


def decode_tag_read(response: MercuryResponse) -> MercuryTagRead:
    """Decode a continuous-read tag record; raises :class:`RfidError` if its lengths do not add up."""
    d = response.data
    # d[k] is frame[k + 5]; the offsets below are SparkFun's minus 5.
    if response.opcode != MercuryOpcode.READ_TAG_ID_MULTIPLE or not response.ok:
        raise RfidError(f"not a tag record (opcode {response.opcode:02X}, status {response.status:04X})", d)
    if len(d) < _RECORD_FIXED + 4:
        raise RfidError(f"tag record too short ({len(d)} data bytes)", d)
    embedded_bits = int.from_bytes(d[19:21], "big")
    m = (embedded_bits + 7) // 8
    if 21 + m + 3 > len(d):
        raise RfidError(f"tag record claims {embedded_bits} bits of embedded data, more than it carries", d)
    embedded = d[21 : 21 + m]
    epc_bits = int.from_bytes(d[22 + m : 24 + m], "big")
    if epc_bits % 8 or epc_bits < 32:
        raise RfidError(f"EPC length {epc_bits} bits is not whole bytes of PC + EPC + CRC", d)
    n = epc_bits // 8
    if 24 + m + n != len(d):
        raise RfidError(f"tag record length {len(d)} != {24 + m + n} implied by its EPC and data lengths", d)
    epc_block = d[24 + m :]
    antenna = d[8]
    return MercuryTagRead(
        rssi_dbm=d[7] - 256 if d[7] >= 128 else d[7],
        tx_antenna=antenna >> 4,
        rx_antenna=antenna & 0x0F,
        frequency_khz=int.from_bytes(d[9:12], "big"),
        timestamp_ms=int.from_bytes(d[12:16], "big"),
        phase_deg=int.from_bytes(d[16:18], "big"),
        protocol=d[18],
        pc=int.from_bytes(epc_block[:2], "big"),
        epc=epc_block[2:-2],
        epc_crc=int.from_bytes(epc_block[-2:], "big"),
        embedded_data=embedded,
        header=d[0:7],
    )


def encode_tag_read(read: MercuryTagRead) -> bytes:
    """The whole frame a module sends for ``read`` (the inverse of :func:`decode_tag_read`)."""
    if len(read.header) != 7:
        raise RfidError("tag record header is 7 bytes", read.header)
    if not -128 <= read.rssi_dbm <= 127:
        raise RfidError(f"RSSI {read.rssi_dbm} dBm does not fit in a signed byte")
    if not (0 <= read.tx_antenna <= 15 and 0 <= read.rx_antenna <= 15):
        raise RfidError("antenna ports are 4 bits each")
    epc_block = _u(read.pc, 2, "PC") + read.epc + _u(read.epc_crc, 2, "EPC CRC")
    data = (
        read.header
        + _u(read.rssi_dbm & 0xFF, 1, "RSSI")
        + _u(read.antenna_byte, 1, "antenna")
        + _u(read.frequency_khz, 3, "frequency")
        + _u(read.timestamp_ms, 4, "timestamp")
        + _u(read.phase_deg, 2, "phase")
        + _u(read.protocol, 1, "protocol")
        + _u(len(read.embedded_data) * 8, 2, "embedded data length")
        + read.embedded_data
        + bytes([_RECORD_RFU])
        + _u(len(epc_block) * 8, 2, "EPC length")
        + epc_block
    )
    return encode_response(MercuryOpcode.READ_TAG_ID_MULTIPLE, 0, data)


def _u(value: int, size: int, what: str) -> bytes:
    """``value`` as a big-endian unsigned field of ``size`` bytes; :class:`RfidError` if it does not fit."""
    if not 0 <= value < 1 << (8 * size):
        raise RfidError(f"{what} {value} does not fit in {size} byte(s)")
    return value.to_bytes(size, "big")


def decode_stream_message(response: MercuryResponse) -> MercuryTagRead | MercuryKeepAlive | MercuryResponse:
    """Classify what arrives during a continuous read, as SparkFun ``parseResponse`` does.

    Opcode 22 with no data and a keep-alive status is the heartbeat; opcode 22 with status 0 and at least a
    minimal record is a tag read (raises :class:`RfidError` if malformed); anything else (command answers,
    SparkFun's "unknown" 8-byte and "temperature" 10-byte notices) comes back unchanged.
    """
    if response.opcode == MercuryOpcode.READ_TAG_ID_MULTIPLE:
        if not response.data and response.status in MERCURY_KEEPALIVE_STATUS:
            return MercuryKeepAlive(response.status)
        if response.ok and len(response.data) >= _RECORD_FIXED + 4:
            return decode_tag_read(response)
    return response
