"""Dynamixel Protocol 2.0, sans I/O: CRC, byte stuffing, packets, typed instructions, a streaming decoder.

Wire format (ROBOTIS e-Manual, ``docs/en/dxl/protocol2.md``)::

    FF FF FD 00 | ID | LEN_L LEN_H | INST | PARAMS ... | CRC_L CRC_H          instruction
    FF FF FD 00 | ID | LEN_L LEN_H | 55   | ERR | PARAMS ... | CRC_L CRC_H    status

``LEN`` counts INST, (ERR,) the parameters and the CRC. The CRC is CRC-16 with polynomial 0x8005, initial
value 0, no reflection and no final xor (catalogued as CRC-16/UMTS, check value 0xFEE8), taken over
everything from the header up to the last parameter *after* byte stuffing, sent little-endian. Stuffing
inserts an extra ``FD`` after every ``FF FF FD`` between INST and the last parameter, so a receiver can
look for a header that is ``FF FF FD`` not followed by ``FD``.

Replies to FAST_SYNC_READ / FAST_BULK_READ are one status packet from the broadcast ID that all addressed
servos build together; they are *not* stuffed (e-Manual, "Fast Sync Read"), and each servo's part ends
with the running CRC of the packet so far. Status packets from the broadcast ID are therefore never
unstuffed here; :func:`parse_fast_read_status` splits and checks them.

Nothing in this module does I/O: bytes in, frozen dataclasses out, :class:`DynamixelError` for bad bytes.
"""

from __future__ import annotations

import collections
import enum
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field

from firmware_protocol.errors import ProtocolError

__all__ = [
    "ALERT_BIT",
    "BROADCAST_ID",
    "HEADER",
    "MAX_ID",
    "Action",
    "BulkRead",
    "BulkReadEntry",
    "BulkWrite",
    "BulkWriteEntry",
    "Clear",
    "Command",
    "DynamixelDecoder",
    "DynamixelError",
    "ErrorNumber",
    "FactoryReset",
    "FastBulkRead",
    "FastReadItem",
    "FastSyncRead",
    "Instruction",
    "InstructionPacket",
    "Packet",
    "Ping",
    "PingReply",
    "Read",
    "Reboot",
    "RegWrite",
    "StatusError",
    "StatusPacket",
    "SyncRead",
    "SyncWrite",
    "Write",
    "crc16",
    "decode_packet",
    "encode_action",
    "encode_bulk_read",
    "encode_bulk_write",
    "encode_clear",
    "encode_factory_reset",
    "encode_fast_bulk_read",
    "encode_fast_read_status",
    "encode_fast_sync_read",
    "encode_instruction",
    "encode_packet",
    "encode_ping",
    "encode_read",
    "encode_reboot",
    "encode_reg_write",
    "encode_status",
    "encode_sync_read",
    "encode_sync_write",
    "encode_write",
    "parse_command",
    "parse_fast_read_status",
    "parse_ping_reply",
    "stuff",
    "unstuff",
]

HEADER = b"\xff\xff\xfd\x00"
BROADCAST_ID = 0xFE
MAX_ID = 0xFC  # 0xFD and 0xFF would look like header bytes, so they are never IDs
ALERT_BIT = 0x80
MIN_LENGTH = 3  # INST + CRC
#: The SDK refuses packets longer than 1024 bytes in total, so nothing real is bigger.
MAX_PACKET_BYTES = 1024
_PREFIX = 7  # header(4) + ID + LEN_L + LEN_H
_STUFF_FROM = b"\xff\xff\xfd"
_STUFF_TO = b"\xff\xff\xfd\xfd"


class DynamixelError(ProtocolError):
    """Bytes that are not valid Dynamixel Protocol 2.0.

    ``packet_id`` is the ID field when the bytes got far enough to have one (a packet whose CRC fails
    still names the servo it was for, which is what a servo needs to answer with a CRC error).
    ``crc_mismatch`` tells a CRC failure apart from other damage.
    """

    def __init__(
        self, reason: str, data: bytes = b"", packet_id: int | None = None, crc_mismatch: bool = False
    ) -> None:
        self.packet_id = packet_id
        self.crc_mismatch = crc_mismatch
        super().__init__(reason, data)


class Instruction(enum.IntEnum):
    PING = 0x01
    READ = 0x02
    WRITE = 0x03
    REG_WRITE = 0x04
    ACTION = 0x05
    FACTORY_RESET = 0x06
    REBOOT = 0x08
    CLEAR = 0x10
    STATUS = 0x55
    SYNC_READ = 0x82
    SYNC_WRITE = 0x83
    FAST_SYNC_READ = 0x8A
    BULK_READ = 0x92
    BULK_WRITE = 0x93
    FAST_BULK_READ = 0x9A


class ErrorNumber(enum.IntEnum):
    """Bits 0-6 of a status packet's ERR byte (bit 7 is the alert flag)."""

    NONE = 0
    RESULT_FAIL = 1
    INSTRUCTION = 2
    CRC = 3
    DATA_RANGE = 4
    DATA_LENGTH = 5
    DATA_LIMIT = 6
    ACCESS = 7


_ERROR_TEXT = {
    ErrorNumber.NONE: "ok",
    ErrorNumber.RESULT_FAIL: "result fail: the instruction could not be processed",
    ErrorNumber.INSTRUCTION: "instruction error: undefined instruction, or ACTION without REG_WRITE",
    ErrorNumber.CRC: "CRC error: the instruction packet's CRC did not match",
    ErrorNumber.DATA_RANGE: "data range error: value outside the item's range",
    ErrorNumber.DATA_LENGTH: "data length error: data shorter than the item",
    ErrorNumber.DATA_LIMIT: "data limit error: value beyond the configured limit",
    ErrorNumber.ACCESS: "access error: read-only or undefined address, or EEPROM written with torque on",
}


@dataclass(frozen=True, slots=True)
class StatusError:
    """A decoded ERR byte: the alert flag (read Hardware Error Status) and the error number."""

    alert: bool
    number: int

    @classmethod
    def from_byte(cls, err: int) -> StatusError:
        return cls(bool(err & ALERT_BIT), err & 0x7F)

    @property
    def byte(self) -> int:
        return (ALERT_BIT if self.alert else 0) | self.number

    @property
    def failed(self) -> bool:
        """The instruction was not carried out (an alert alone does not mean that)."""
        return self.number != 0

    def describe(self) -> str:
        try:
            text = _ERROR_TEXT[ErrorNumber(self.number)]
        except ValueError:
            text = f"unknown error number {self.number}"
        return text + (" (alert: hardware error, read Hardware Error Status)" if self.alert else "")


# -- CRC and stuffing --------------------------------------------------------------------------------


def _make_crc_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x8005) if crc & 0x8000 else (crc << 1)
        table.append(crc & 0xFFFF)
    return tuple(table)


_CRC_TABLE = _make_crc_table()


def crc16(data: bytes | bytearray | memoryview, crc: int = 0) -> int:
    """CRC-16/UMTS (poly 0x8005, init 0, unreflected), continuing from ``crc``; table-driven."""
    table = _CRC_TABLE
    for byte in bytes(data):
        crc = ((crc << 8) & 0xFFFF) ^ table[(crc >> 8) ^ byte]
    return crc


def stuff(region: bytes) -> bytes:
    """Stuff INST..last param: every ``FF FF FD`` becomes ``FF FF FD FD``.

    ``bytes.replace`` is exact here because the pattern cannot overlap itself (it ends in FD, starts with FF).
    """
    return region.replace(_STUFF_FROM, _STUFF_TO)


def unstuff(region: bytes) -> bytes:
    """Undo :func:`stuff`. Left-to-right replacement is the inverse: ``FF FF FD FD`` cannot overlap itself."""
    return region.replace(_STUFF_TO, _STUFF_FROM)


# -- packets -----------------------------------------------------------------------------------------


def _check_id(packet_id: int, *, allow_broadcast: bool = True) -> None:
    if not (0 <= packet_id <= MAX_ID or (allow_broadcast and packet_id == BROADCAST_ID)):
        raise ValueError(
            f"Dynamixel ID must be 0..{MAX_ID}"
            + (" or 0xFE" if allow_broadcast else "")
            + f", not {packet_id}"
        )


def encode_packet(packet_id: int, instruction: int, body: bytes, *, stuffing: bool = True) -> bytes:
    """Frame INST + ``body`` (params, or ERR + params for a status) for ``packet_id``: stuff, LEN, CRC."""
    _check_id(packet_id)
    if not 0 <= instruction <= 0xFF:
        raise ValueError(f"instruction must be a byte, not {instruction}")
    region = bytes((instruction,)) + bytes(body)
    if stuffing:
        region = stuff(region)
    length = len(region) + 2
    if _PREFIX + length > MAX_PACKET_BYTES:
        raise ValueError(f"packet of {_PREFIX + length} bytes exceeds {MAX_PACKET_BYTES}")
    head = HEADER + bytes((packet_id, length & 0xFF, length >> 8)) + region
    return head + crc16(head).to_bytes(2, "little")


@dataclass(frozen=True, slots=True)
class InstructionPacket:
    """An instruction as sent by a controller. ``params`` are unstuffed; ``instruction`` is the raw byte."""

    id: int
    instruction: int
    params: bytes = b""

    def encode(self) -> bytes:
        return encode_packet(self.id, self.instruction, self.params)


@dataclass(frozen=True, slots=True)
class StatusPacket:
    """A servo's reply. ``error`` is the raw ERR byte; ``params`` are unstuffed (except fast-read replies,
    which are sent from the broadcast ID without stuffing)."""

    id: int
    error: int
    params: bytes = b""

    @property
    def status(self) -> StatusError:
        return StatusError.from_byte(self.error)

    def encode(self) -> bytes:
        return encode_status(self.id, self.error, self.params)


Packet = InstructionPacket | StatusPacket


def encode_status(packet_id: int, error: int, params: bytes = b"") -> bytes:
    """A status packet; stuffed, except from the broadcast ID (fast-read replies are never stuffed)."""
    if not 0 <= error <= 0xFF:
        raise ValueError(f"ERR must be a byte, not {error}")
    return encode_packet(
        packet_id, Instruction.STATUS, bytes((error,)) + bytes(params), stuffing=packet_id != BROADCAST_ID
    )


def _packet_from_frame(frame: bytes) -> Packet:
    """Build a packet from a frame whose header, ID, LEN and CRC are already checked."""
    packet_id = frame[4]
    region = frame[_PREFIX:-2]
    if region[0] == Instruction.STATUS:
        if len(region) < 2:
            raise DynamixelError("status packet without an ERR byte", frame, packet_id)
        if packet_id != BROADCAST_ID:
            region = unstuff(region)
        return StatusPacket(packet_id, region[1], bytes(region[2:]))
    region = unstuff(region)
    return InstructionPacket(packet_id, region[0], bytes(region[1:]))


def _valid_id(packet_id: int) -> bool:
    return packet_id <= MAX_ID or packet_id == BROADCAST_ID


def decode_packet(frame: bytes) -> Packet:
    """Decode exactly one whole packet; anything else raises :class:`DynamixelError`."""
    frame = bytes(frame)
    if len(frame) < _PREFIX + MIN_LENGTH:
        raise DynamixelError("too short for a Protocol 2.0 packet", frame)
    if frame[:4] != HEADER:
        raise DynamixelError("no FF FF FD 00 header", frame)
    packet_id = frame[4]
    if not _valid_id(packet_id):
        raise DynamixelError(f"invalid ID 0x{packet_id:02X}", frame, packet_id)
    length = frame[5] | frame[6] << 8
    if length < MIN_LENGTH:
        raise DynamixelError(f"LEN {length} below the minimum of {MIN_LENGTH}", frame, packet_id)
    if _PREFIX + length != len(frame):
        raise DynamixelError(
            f"LEN {length} means {_PREFIX + length} bytes, got {len(frame)}", frame, packet_id
        )
    expected = crc16(frame[:-2])
    got = frame[-2] | frame[-1] << 8
    if expected != got:
        raise DynamixelError(
            f"CRC mismatch: computed 0x{expected:04X}, packet says 0x{got:04X}",
            frame,
            packet_id,
            crc_mismatch=True,
        )
    return _packet_from_frame(frame)


# -- typed instructions ------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Ping:
    pass


@dataclass(frozen=True, slots=True)
class Read:
    address: int
    length: int


@dataclass(frozen=True, slots=True)
class Write:
    address: int
    data: bytes


@dataclass(frozen=True, slots=True)
class RegWrite:
    address: int
    data: bytes


@dataclass(frozen=True, slots=True)
class Action:
    pass


class FactoryResetOption(enum.IntEnum):
    ALL = 0xFF
    ALL_EXCEPT_ID = 0x01
    ALL_EXCEPT_ID_AND_BAUD = 0x02


@dataclass(frozen=True, slots=True)
class FactoryReset:
    option: int = FactoryResetOption.ALL_EXCEPT_ID


@dataclass(frozen=True, slots=True)
class Reboot:
    pass


#: CLEAR option 1 (reset the multi-turn count) must be followed by these fixed bytes ("DXL\"").
CLEAR_MULTI_TURN_KEY = b"\x44\x58\x4c\x22"


@dataclass(frozen=True, slots=True)
class Clear:
    option: int = 0x01
    data: bytes = CLEAR_MULTI_TURN_KEY


@dataclass(frozen=True, slots=True)
class SyncRead:
    address: int
    length: int
    ids: tuple[int, ...]


@dataclass(frozen=True, slots=True)
class FastSyncRead:
    address: int
    length: int
    ids: tuple[int, ...]


@dataclass(frozen=True, slots=True)
class SyncWrite:
    """Same address and length for every servo; ``data`` maps ID -> ``length`` bytes, in wire order."""

    address: int
    length: int
    data: Mapping[int, bytes] = field(default_factory=dict)

    def __post_init__(self) -> None:
        # A private copy, so the caller mutating their dict cannot change a "frozen" message.
        object.__setattr__(self, "data", {int(k): bytes(v) for k, v in self.data.items()})

    def __hash__(self) -> int:
        return hash((self.address, self.length, tuple(self.data.items())))


@dataclass(frozen=True, slots=True)
class BulkReadEntry:
    id: int
    address: int
    length: int


@dataclass(frozen=True, slots=True)
class BulkRead:
    entries: tuple[BulkReadEntry, ...]


@dataclass(frozen=True, slots=True)
class FastBulkRead:
    entries: tuple[BulkReadEntry, ...]


@dataclass(frozen=True, slots=True)
class BulkWriteEntry:
    id: int
    address: int
    data: bytes


@dataclass(frozen=True, slots=True)
class BulkWrite:
    entries: tuple[BulkWriteEntry, ...]


Command = (
    Ping
    | Read
    | Write
    | RegWrite
    | Action
    | FactoryReset
    | Reboot
    | Clear
    | SyncRead
    | FastSyncRead
    | SyncWrite
    | BulkRead
    | FastBulkRead
    | BulkWrite
)


def _u16(value: int, what: str) -> bytes:
    if not 0 <= value <= 0xFFFF:
        raise ValueError(f"{what} must fit 16 bits, not {value}")
    return value.to_bytes(2, "little")


def _ids(ids: Iterable[int]) -> bytes:
    out = tuple(ids)
    for i in out:
        _check_id(i, allow_broadcast=False)
    if len(set(out)) != len(out):
        raise ValueError(f"duplicate IDs in {out}")
    return bytes(out)


def _bulk_read_params(entries: Sequence[BulkReadEntry]) -> bytes:
    _ids(e.id for e in entries)
    return b"".join(bytes((e.id,)) + _u16(e.address, "address") + _u16(e.length, "length") for e in entries)


def command_params(command: Command) -> tuple[Instruction, bytes]:
    """The instruction byte and parameter bytes (unstuffed) for a typed command."""
    match command:
        case Ping():
            return Instruction.PING, b""
        case Read(address, length):
            return Instruction.READ, _u16(address, "address") + _u16(length, "length")
        case Write(address, data):
            return Instruction.WRITE, _u16(address, "address") + bytes(data)
        case RegWrite(address, data):
            return Instruction.REG_WRITE, _u16(address, "address") + bytes(data)
        case Action():
            return Instruction.ACTION, b""
        case FactoryReset(option):
            return Instruction.FACTORY_RESET, bytes((option,))
        case Reboot():
            return Instruction.REBOOT, b""
        case Clear(option, data):
            return Instruction.CLEAR, bytes((option,)) + bytes(data)
        case SyncRead(address, length, ids):
            return Instruction.SYNC_READ, _u16(address, "address") + _u16(length, "length") + _ids(ids)
        case FastSyncRead(address, length, ids):
            return Instruction.FAST_SYNC_READ, _u16(address, "address") + _u16(length, "length") + _ids(ids)
        case SyncWrite(address, length, data):
            parts = [_u16(address, "address"), _u16(length, "length")]
            _ids(data)
            for servo_id, chunk in data.items():
                if len(chunk) != length:
                    raise ValueError(f"SYNC_WRITE data for ID {servo_id} is {len(chunk)} bytes, not {length}")
                parts.append(bytes((servo_id,)) + chunk)
            return Instruction.SYNC_WRITE, b"".join(parts)
        case BulkRead(entries):
            return Instruction.BULK_READ, _bulk_read_params(entries)
        case FastBulkRead(entries):
            return Instruction.FAST_BULK_READ, _bulk_read_params(entries)
        case BulkWrite(entries):
            _ids(e.id for e in entries)
            return Instruction.BULK_WRITE, b"".join(
                bytes((e.id,)) + _u16(e.address, "address") + _u16(len(e.data), "length") + bytes(e.data)
                for e in entries
            )
    raise TypeError(f"not a Dynamixel command: {command!r}")


def encode_instruction(packet_id: int, command: Command) -> bytes:
    instruction, params = command_params(command)
    return encode_packet(packet_id, instruction, params)


def encode_ping(packet_id: int) -> bytes:
    return encode_instruction(packet_id, Ping())


def encode_read(packet_id: int, address: int, length: int) -> bytes:
    return encode_instruction(packet_id, Read(address, length))


def encode_write(packet_id: int, address: int, data: bytes) -> bytes:
    return encode_instruction(packet_id, Write(address, data))


def encode_reg_write(packet_id: int, address: int, data: bytes) -> bytes:
    return encode_instruction(packet_id, RegWrite(address, data))


def encode_action(packet_id: int) -> bytes:
    return encode_instruction(packet_id, Action())


def encode_factory_reset(packet_id: int, option: int = FactoryResetOption.ALL_EXCEPT_ID) -> bytes:
    return encode_instruction(packet_id, FactoryReset(option))


def encode_reboot(packet_id: int) -> bytes:
    return encode_instruction(packet_id, Reboot())


def encode_clear(packet_id: int, option: int = 0x01, data: bytes = CLEAR_MULTI_TURN_KEY) -> bytes:
    return encode_instruction(packet_id, Clear(option, data))


def encode_sync_read(address: int, length: int, ids: Iterable[int]) -> bytes:
    return encode_instruction(BROADCAST_ID, SyncRead(address, length, tuple(ids)))


def encode_fast_sync_read(address: int, length: int, ids: Iterable[int]) -> bytes:
    return encode_instruction(BROADCAST_ID, FastSyncRead(address, length, tuple(ids)))


def encode_sync_write(address: int, length: int, data: Mapping[int, bytes]) -> bytes:
    return encode_instruction(BROADCAST_ID, SyncWrite(address, length, data))


def encode_bulk_read(entries: Iterable[BulkReadEntry]) -> bytes:
    return encode_instruction(BROADCAST_ID, BulkRead(tuple(entries)))


def encode_fast_bulk_read(entries: Iterable[BulkReadEntry]) -> bytes:
    return encode_instruction(BROADCAST_ID, FastBulkRead(tuple(entries)))


def encode_bulk_write(entries: Iterable[BulkWriteEntry]) -> bytes:
    return encode_instruction(BROADCAST_ID, BulkWrite(tuple(entries)))


def _bad(packet: InstructionPacket, reason: str) -> DynamixelError:
    try:
        name = Instruction(packet.instruction).name
    except ValueError:
        name = f"instruction 0x{packet.instruction:02X}"
    return DynamixelError(f"{name}: {reason}", packet.params, packet.id)


def _parse_ids(packet: InstructionPacket, raw: bytes) -> tuple[int, ...]:
    ids = tuple(raw)
    if any(not i <= MAX_ID for i in ids):
        raise _bad(packet, f"invalid servo ID in {ids}")
    if len(set(ids)) != len(ids):
        raise _bad(packet, f"duplicate servo ID in {ids}")
    return ids


def _parse_bulk_read(packet: InstructionPacket) -> tuple[BulkReadEntry, ...]:
    p = packet.params
    if not p or len(p) % 5:
        raise _bad(packet, f"{len(p)} parameter bytes is not a multiple of 5 (ID, address, length)")
    entries = tuple(
        BulkReadEntry(p[i], p[i + 1] | p[i + 2] << 8, p[i + 3] | p[i + 4] << 8) for i in range(0, len(p), 5)
    )
    _parse_ids(packet, bytes(e.id for e in entries))
    return entries


def parse_command(packet: InstructionPacket) -> Command:
    """The typed command in an instruction packet; :class:`DynamixelError` if its parameters are malformed
    or the instruction is unknown (a STATUS packet is not a command either)."""
    p = packet.params
    match packet.instruction:
        case Instruction.PING | Instruction.ACTION | Instruction.REBOOT:
            if p:
                raise _bad(packet, f"takes no parameters, got {len(p)} bytes")
            if packet.instruction == Instruction.PING:
                return Ping()
            return Action() if packet.instruction == Instruction.ACTION else Reboot()
        case Instruction.READ:
            if len(p) != 4:
                raise _bad(packet, f"needs 4 parameter bytes (address, length), got {len(p)}")
            return Read(p[0] | p[1] << 8, p[2] | p[3] << 8)
        case Instruction.WRITE | Instruction.REG_WRITE:
            if len(p) < 2:
                raise _bad(packet, f"needs an address, got {len(p)} parameter bytes")
            cls = Write if packet.instruction == Instruction.WRITE else RegWrite
            return cls(p[0] | p[1] << 8, bytes(p[2:]))
        case Instruction.FACTORY_RESET:
            if len(p) != 1:
                raise _bad(packet, f"needs 1 option byte, got {len(p)}")
            return FactoryReset(p[0])
        case Instruction.CLEAR:
            if not p:
                raise _bad(packet, "needs an option byte")
            return Clear(p[0], bytes(p[1:]))
        case Instruction.SYNC_READ | Instruction.FAST_SYNC_READ:
            if len(p) < 5:
                raise _bad(packet, f"needs address, length and at least one ID, got {len(p)} bytes")
            cls_r = SyncRead if packet.instruction == Instruction.SYNC_READ else FastSyncRead
            return cls_r(p[0] | p[1] << 8, p[2] | p[3] << 8, _parse_ids(packet, p[4:]))
        case Instruction.SYNC_WRITE:
            if len(p) < 4:
                raise _bad(packet, f"needs address and length, got {len(p)} bytes")
            address, length = p[0] | p[1] << 8, p[2] | p[3] << 8
            body = p[4:]
            if length == 0 or not body or len(body) % (1 + length):
                raise _bad(packet, f"{len(body)} data bytes do not split into (ID + {length} bytes) blocks")
            step = 1 + length
            blocks = [body[i : i + step] for i in range(0, len(body), step)]
            _parse_ids(packet, bytes(b[0] for b in blocks))
            return SyncWrite(address, length, {b[0]: bytes(b[1:]) for b in blocks})
        case Instruction.BULK_READ:
            return BulkRead(_parse_bulk_read(packet))
        case Instruction.FAST_BULK_READ:
            return FastBulkRead(_parse_bulk_read(packet))
        case Instruction.BULK_WRITE:
            entries = []
            i = 0
            while i < len(p):
                if len(p) - i < 5:
                    raise _bad(packet, f"truncated entry header at byte {i}")
                length = p[i + 3] | p[i + 4] << 8
                if length == 0 or i + 5 + length > len(p):
                    raise _bad(
                        packet, f"entry at byte {i} declares {length} data bytes, {len(p) - i - 5} remain"
                    )
                entries.append(
                    BulkWriteEntry(p[i], p[i + 1] | p[i + 2] << 8, bytes(p[i + 5 : i + 5 + length]))
                )
                i += 5 + length
            if not entries:
                raise _bad(packet, "no entries")
            _parse_ids(packet, bytes(e.id for e in entries))
            return BulkWrite(tuple(entries))
    raise _bad(packet, "unknown instruction")


# -- replies -----------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class PingReply:
    id: int
    model_number: int
    firmware_version: int


def parse_ping_reply(status: StatusPacket) -> PingReply:
    if len(status.params) != 3:
        raise DynamixelError(
            f"PING reply needs 3 parameter bytes, got {len(status.params)}", status.params, status.id
        )
    p = status.params
    return PingReply(status.id, p[0] | p[1] << 8, p[2])


@dataclass(frozen=True, slots=True)
class FastReadItem:
    """One servo's share of a fast sync/bulk read reply."""

    id: int
    error: int
    data: bytes


def encode_fast_read_status(items: Sequence[FastReadItem]) -> bytes:
    """The single status packet that the servos of a FAST_SYNC_READ / FAST_BULK_READ build together.

    From the broadcast ID, not stuffed. The first servo's ERR is the packet's ERR field; every servo but
    the last appends the running CRC of the whole packet so far, the last one's CRC is the packet CRC.
    """
    if not items:
        raise ValueError("a fast read reply needs at least one servo")
    parts: list[bytes] = []
    for n, item in enumerate(items):
        _check_id(item.id, allow_broadcast=False)
        parts.append((bytes((item.error,)) if n else b"") + bytes((item.id,)) + bytes(item.data))
    length = 2 + sum(len(part) for part in parts) + 2 * (len(items) - 1) + 2  # INST ERR ... CRCs
    packet = bytearray(
        HEADER + bytes((BROADCAST_ID, length & 0xFF, length >> 8, Instruction.STATUS, items[0].error))
    )
    for n, part in enumerate(parts):
        packet += part
        if n < len(parts) - 1:
            packet += crc16(packet).to_bytes(2, "little")
    if len(packet) + 2 > MAX_PACKET_BYTES:
        raise ValueError(f"fast read reply of {len(packet) + 2} bytes exceeds {MAX_PACKET_BYTES}")
    return bytes(packet + crc16(packet).to_bytes(2, "little"))


def parse_fast_read_status(status: StatusPacket, lengths: Sequence[int]) -> tuple[FastReadItem, ...]:
    """Split a fast-read reply into each servo's (ID, ERR, data); ``lengths`` are the data lengths asked for,
    in the order of the request. The intermediate CRCs are checked."""
    if status.id != BROADCAST_ID:
        raise DynamixelError(
            f"a fast read reply comes from the broadcast ID, not {status.id}", status.params, status.id
        )
    p = status.params
    expected = sum(1 + n for n in lengths) + 3 * (len(lengths) - 1)
    if not lengths or len(p) != expected:
        raise DynamixelError(
            f"fast read reply has {len(p)} parameter bytes, {expected} expected for data "
            f"lengths {list(lengths)}",
            p,
            status.id,
        )
    # The intermediate CRCs cover the packet from its header, so rebuild the bytes before the params.
    length = 2 + len(p) + 2
    running = bytearray(
        HEADER + bytes((BROADCAST_ID, length & 0xFF, length >> 8, Instruction.STATUS, status.error))
    )
    items = []
    error = status.error
    i = 0
    for n, size in enumerate(lengths):
        if n:
            error = p[i]
            running.append(p[i])
            i += 1
        servo_id = p[i]
        data = bytes(p[i + 1 : i + 1 + size])
        running += p[i : i + 1 + size]
        i += 1 + size
        if n < len(lengths) - 1:
            got = p[i] | p[i + 1] << 8
            if crc16(running) != got:
                raise DynamixelError(
                    f"fast read reply: CRC after ID {servo_id} does not match", p, servo_id, crc_mismatch=True
                )
            running += p[i : i + 2]
            i += 2
        items.append(FastReadItem(servo_id, error, data))
    return tuple(items)


# -- streaming decoder -------------------------------------------------------------------------------


class DynamixelDecoder:
    """Finds packets in a byte stream: instruction packets (what a servo hears) and status packets (what a
    controller hears).

    ``feed`` returns the packets completed so far and keeps a partial one. Junk before a header, a header
    with an impossible ID or LEN, and a frame whose CRC fails are skipped one byte at a time, so a real
    packet hidden inside a damaged one is still found; every skipped byte is counted in
    ``discarded_bytes`` and the reason kept in a short log (:meth:`take_errors`). The buffer never holds
    more than one maximal packet: ``7 + max_length`` bytes.
    """

    def __init__(self, max_length: int = MAX_PACKET_BYTES - _PREFIX, error_log: int = 32) -> None:
        if not MIN_LENGTH <= max_length <= 0xFFFF:
            raise ValueError(f"max_length must be {MIN_LENGTH}..65535, not {max_length}")
        self.max_length = max_length
        self._buf = bytearray()
        self.discarded_bytes = 0
        self.packet_bytes = 0  # bytes of accepted frames: fed = packet_bytes + discarded_bytes + buffered
        self.crc_errors = 0
        self.bad_headers = 0
        self.packets = 0
        self._errors: collections.deque[DynamixelError] = collections.deque(maxlen=error_log)

    @property
    def buffered(self) -> int:
        return len(self._buf)

    def take_errors(self) -> list[DynamixelError]:
        """What was skipped since the last call (the most recent ``error_log`` entries)."""
        errors = list(self._errors)
        self._errors.clear()
        return errors

    def reset(self) -> int:
        """Drop a partial packet (e.g. after an inter-byte timeout); returns how many bytes were dropped."""
        n = len(self._buf)
        self.discarded_bytes += n
        self._buf.clear()
        return n

    def feed(self, data: bytes | bytearray | memoryview) -> list[Packet]:
        buf = self._buf
        buf += data
        out: list[Packet] = []
        pos = 0
        junk_from = -1  # start of a run of junk bytes, reported once per run
        while True:
            idx = buf.find(HEADER, pos)
            if idx < 0:
                # Keep a tail that may be the start of a header (FF, FF FF, FF FF FD); the rest is junk.
                keep = 0
                for n in (3, 2, 1):
                    if len(buf) - pos >= n and buf[len(buf) - n :] == HEADER[:n]:
                        keep = n
                        break
                end = len(buf) - keep
                if end > pos:
                    self._skip(buf, junk_from if junk_from >= 0 else pos, end, "junk between packets")
                pos = end
                junk_from = -1
                break
            if idx > pos and junk_from < 0:
                junk_from = pos
            pos = idx
            if len(buf) - pos < _PREFIX:
                break
            packet_id = buf[pos + 4]
            length = buf[pos + 5] | buf[pos + 6] << 8
            if not _valid_id(packet_id) or not MIN_LENGTH <= length <= self.max_length:
                self.bad_headers += 1
                if junk_from < 0:
                    junk_from = pos
                pos += 1
                continue
            end = pos + _PREFIX + length
            if end > len(buf):
                break
            frame = bytes(buf[pos:end])
            got = frame[-2] | frame[-1] << 8
            if crc16(frame[:-2]) != got or (frame[_PREFIX] == Instruction.STATUS and length < 4):
                crc_bad = crc16(frame[:-2]) != got
                if junk_from >= 0:
                    self._skip(buf, junk_from, pos, "junk between packets")
                    junk_from = -1
                self.crc_errors += crc_bad
                self._errors.append(
                    DynamixelError(
                        "CRC mismatch" if crc_bad else "status packet without an ERR byte",
                        frame,
                        packet_id,
                        crc_mismatch=crc_bad,
                    )
                )
                self.discarded_bytes += 1
                pos += 1
                continue
            if junk_from >= 0:
                self._skip(buf, junk_from, pos, "junk between packets")
                junk_from = -1
            out.append(_packet_from_frame(frame))
            self.packets += 1
            self.packet_bytes += end - pos
            pos = end
        if junk_from >= 0:
            # A run of junk is pending before a partial header: count it now so the counter is current.
            self._skip(buf, junk_from, pos, "junk between packets")
        del buf[:pos]
        return out

    def _skip(self, buf: bytearray, start: int, end: int, reason: str) -> None:
        self.discarded_bytes += end - start
        self._errors.append(DynamixelError(reason, bytes(buf[start:end])))
