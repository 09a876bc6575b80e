"""SCIP 2.0, the protocol of Hokuyo URG laser scanners: a sans-I/O codec (bytes in, frozen dataclasses out).

Source: Hokuyo "Communication Protocol Specification For SCIP2.0", doc C-42-03320B (cited below as
"spec p.N"), cross-checked against urg_c ``urg_sensor.c`` and five real URG-04LX captures
(``../shared/data/urg``). The facts the code relies on:

* Host -> sensor: ``command [parameters] [;tag] LF``. The tag is up to 16 characters of letters, digits,
  blank and ``._+@`` (spec p.9) and comes back in the echo, so a reply can be matched to its request.
* Sensor -> host: the echo line, a status line (2 characters + checksum), then, depending on the command,
  a 4-character timestamp line, data blocks of at most 64 characters + checksum each, or ``KEY:value;sum``
  parameter lines; always terminated by an empty line (the reply ends with LF LF).
* Checksum of a line = ``(sum(body) & 0x3F) + 0x30``. On VV/PP/II parameter lines the URG-04LX sums the
  text *without* the ``;`` before the checksum character (real capture A), later models include it; urg_c
  accepts both, and so does this decoder.
* Values are 6 bits per character, offset 0x30, most significant first: 2 characters (GS/MS), 3 (GD/MD)
  or 4 (timestamps, a 24-bit millisecond counter). Data values are concatenated *before* being cut into
  64-character blocks, so a value can straddle two blocks: blocks are joined before decoding.
* MD/MS: the acknowledgement is the echo + ``00`` + LF LF; each scan is then sent with status ``99`` and
  the echo carries the number of remaining scans in place of the requested number (spec p.11).
* In SCIP 1.1 mode the sensor answers with a 1-character status and no checksum; the reply to
  ``SCIP2.0`` that switches the mode is ``SCIP2.0 LF 0 LF LF`` (spec p.3). A URG-04LX-UG01 that is
  already in SCIP 2.0 answers ``SCIP2.0`` with ``0E`` (capture B's log).

The decoder resynchronises on junk: a reply that does not parse is dropped up to the next place that looks
like the start of a reply (a known command's echo followed by a status line with a valid checksum), the
dropped bytes are counted and kept in a :class:`ScipError`, and decoding carries on.
"""

from __future__ import annotations

import enum
import re
from collections import deque
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType

from firmware_protocol.errors import ProtocolError

__all__ = [
    "BLOCK_CHARS",
    "TAG_MAX_CHARS",
    "TIMESTAMP_MODULUS",
    "ScipDecoder",
    "ScipError",
    "ScipReply",
    "ScipStatus",
    "StatusKind",
    "checksum",
    "decode_value",
    "decode_values",
    "encode_bm",
    "encode_command",
    "encode_data_blocks",
    "encode_gd",
    "encode_gs",
    "encode_ii",
    "encode_line",
    "encode_md",
    "encode_ms",
    "encode_param_line",
    "encode_pp",
    "encode_qt",
    "encode_reply",
    "encode_rs",
    "encode_scip1_reply",
    "encode_scip2",
    "encode_ss",
    "encode_tm",
    "encode_value",
    "encode_values",
    "encode_vv",
    "expected_value_count",
    "parse_reply",
    "scan_reply_size",
    "status_meaning",
]

BLOCK_CHARS = 64
"""Data characters per block line (spec p.11, 13)."""
TIMESTAMP_MODULUS = 1 << 24
"""The sensor's millisecond counter is 24 bits wide: it wraps every 16 777 216 ms (about 4.66 h)."""
TAG_MAX_CHARS = 16

_TAG_RE = re.compile(r"[A-Za-z0-9 ._+@]{0,16}")
_ECHO_MAX_CHARS = 64  # longest legal echo: "MD" + 13 digits + ";" + 16 tag characters = 32; room for others
_MIN_CODE, _MAX_CODE = 0x30, 0x6F  # one 6-bit character: 0x30 + (0..63)

# Data commands: characters per value, length of the command body (code + parameters), streaming or not.
_DATA_COMMANDS: dict[str, tuple[int, int, bool]] = {
    "GD": (3, 12, False),
    "GS": (2, 12, False),
    "MD": (3, 15, True),
    "MS": (2, 15, True),
}
_PARAM_COMMANDS = frozenset({"VV", "PP", "II"})

# What the start of a reply looks like, used only to resynchronise after junk: the echo of a command this
# codec knows, then a status line. Generic echoes (unknown commands) are accepted where a reply is expected,
# but are not trusted as resync points because junk can look like them.
_KNOWN_ECHO = (
    rb"(?:G[DS]\d{10}|M[DS]\d{13}|VV|PP|II|BM|QT|RS|TM[012]|SS\d{6}|SCIP2\.0)(?:;[A-Za-z0-9 ._+@]{0,16})?"
)
_KNOWN_ECHO_RE = re.compile(_KNOWN_ECHO)
_REPLY_START_RE = re.compile(_KNOWN_ECHO + rb"\n(?:([0-9A-Z]{2})([\x30-\x6f])|[0-9A-Z])\n")
_GENERIC_COMMAND_RE = re.compile(r"[A-Z]{2}")


class ScipError(ProtocolError):
    """Bytes that are not SCIP 2.0. ``data`` holds the offending frame or the discarded junk."""


# -- 6-bit character encoding ----------------------------------------------------------------------------


def checksum(body: bytes | bytearray | memoryview) -> int:
    """The SCIP line checksum character (as an int): ``(sum(body) & 0x3F) + 0x30``."""
    return (sum(body) & 0x3F) + 0x30


def encode_value(value: int, nchars: int) -> bytes:
    """``value`` in ``nchars`` 6-bit characters (spec p.6-8: 1234 -> b"CB", 5432 -> b"1Dh")."""
    if not 1 <= nchars <= 4:
        raise ValueError(f"SCIP encodes values in 1 to 4 characters, not {nchars}")
    if not 0 <= value < 1 << (6 * nchars):
        raise ValueError(f"{value} does not fit in {nchars} SCIP characters")
    return bytes(0x30 + ((value >> (6 * i)) & 0x3F) for i in range(nchars - 1, -1, -1))


def encode_values(values: Iterable[int], nchars: int) -> bytes:
    """Concatenated encoding of ``values`` (the payload before it is cut into blocks)."""
    return b"".join(encode_value(v, nchars) for v in values)


def decode_value(chars: bytes | bytearray | memoryview) -> int:
    """Decode one value of 1 to 4 characters; raises :class:`ScipError` on a character out of 0x30..0x6F."""
    value = 0
    for c in bytes(chars):
        if not _MIN_CODE <= c <= _MAX_CODE:
            raise ScipError(f"byte 0x{c:02x} is not a SCIP 6-bit character", bytes(chars))
        value = (value << 6) | (c - 0x30)
    return value


def decode_values(payload: bytes | bytearray | memoryview, nchars: int) -> tuple[int, ...]:
    """Decode a joined data payload of ``nchars``-character values."""
    data = bytes(payload)
    if nchars not in (2, 3, 4):
        raise ValueError(f"SCIP data values have 2, 3 or 4 characters, not {nchars}")
    if len(data) % nchars:
        raise ScipError(f"data length {len(data)} is not a multiple of {nchars}", data)
    if data and (min(data) < _MIN_CODE or max(data) > _MAX_CODE):
        raise ScipError("data holds a byte outside the SCIP 6-bit characters", data)
    # Integer arithmetic on the whole payload: one 6-bit digit per character, most significant first.
    if nchars == 3:
        it = iter(data)
        return tuple(
            ((a - 48) << 12) | ((b - 48) << 6) | (c - 48) for a, b, c in zip(it, it, it, strict=True)
        )
    if nchars == 2:
        it = iter(data)
        return tuple(((a - 48) << 6) | (b - 48) for a, b in zip(it, it, strict=True))
    return tuple(decode_value(data[i : i + nchars]) for i in range(0, len(data), nchars))


def expected_value_count(first_step: int, last_step: int, cluster: int) -> int:
    """How many values a GD/MD request for ``first_step..last_step`` grouped by ``cluster`` returns.

    Cluster 0 means 1 (spec p.10); a last group shorter than ``cluster`` still yields one value.
    """
    cluster = max(cluster, 1)
    return (last_step - first_step + cluster) // cluster


def scan_reply_size(echo_chars: int, value_count: int, nchars: int) -> int:
    """Bytes on the wire of one scan reply (GD/GS, or an MD/MS scan) whose echo is ``echo_chars`` long and
    which carries ``value_count`` values of ``nchars`` characters: what a link's byte rate must carry.

    Echo + LF, status line (2 + sum + LF), timestamp line (4 + sum + LF), each data block of up to 64
    characters + sum + LF, and the final LF. A full URG-04LX ``GD0044072501`` is 2134 bytes.
    """
    payload = value_count * nchars
    blocks = -(-payload // BLOCK_CHARS)
    return (echo_chars + 1) + 4 + 6 + payload + 2 * blocks + 1


# -- commands, host -> sensor ----------------------------------------------------------------------------


def encode_command(body: str, tag: str = "") -> bytes:
    """``body[;tag] LF``. Raises ``ValueError`` for a tag the sensor would refuse (status 0G or 0H)."""
    if not body.isascii() or not body.isprintable() or ";" in body:
        raise ValueError(f"not a SCIP command body: {body!r}")
    if tag:
        if _TAG_RE.fullmatch(tag) is None:
            raise ValueError(f"SCIP tags are up to {TAG_MAX_CHARS} of [A-Za-z0-9 ._+@], not {tag!r}")
        return f"{body};{tag}\n".encode("ascii")
    return f"{body}\n".encode("ascii")


def encode_qt(tag: str = "") -> bytes:
    """QT: laser off, ends MD/MS streaming."""
    return encode_command("QT", tag)


def encode_scip2() -> bytes:
    """``SCIP2.0``: switch a SCIP 1.1 sensor to SCIP 2.0 (no tag: a SCIP 1.1 sensor would not parse it)."""
    return b"SCIP2.0\n"


def encode_vv(tag: str = "") -> bytes:
    return encode_command("VV", tag)


def encode_pp(tag: str = "") -> bytes:
    return encode_command("PP", tag)


def encode_ii(tag: str = "") -> bytes:
    return encode_command("II", tag)


def encode_bm(tag: str = "") -> bytes:
    return encode_command("BM", tag)


def encode_rs(tag: str = "") -> bytes:
    return encode_command("RS", tag)


def encode_tm(mode: int, tag: str = "") -> bytes:
    """TM0 enter time-adjust mode, TM1 read the sensor's clock, TM2 leave the mode (spec p.15)."""
    if mode not in (0, 1, 2):
        raise ValueError(f"TM control code is 0, 1 or 2, not {mode}")
    return encode_command(f"TM{mode}", tag)


def encode_ss(bitrate: int, tag: str = "") -> bytes:
    """SS: RS-232 bit rate, 6 digits (spec p.16); accepted but without effect over USB."""
    if not 0 <= bitrate <= 999_999:
        raise ValueError(f"bit rate {bitrate} does not fit in 6 digits")
    return encode_command(f"SS{bitrate:06d}", tag)


def _steps(code: str, first_step: int, last_step: int, cluster: int) -> str:
    if not (0 <= first_step <= 9999 and 0 <= last_step <= 9999 and 0 <= cluster <= 99):
        raise ValueError(
            f"{code}: steps are 4 digits and cluster 2 digits ({first_step}, {last_step}, {cluster})"
        )
    return f"{code}{first_step:04d}{last_step:04d}{cluster:02d}"


def encode_gd(first_step: int, last_step: int, cluster: int = 1, tag: str = "") -> bytes:
    """GD: one scan, 3-character values (up to 262 143 mm)."""
    return encode_command(_steps("GD", first_step, last_step, cluster), tag)


def encode_gs(first_step: int, last_step: int, cluster: int = 1, tag: str = "") -> bytes:
    """GS: one scan, 2-character values (up to 4095 mm)."""
    return encode_command(_steps("GS", first_step, last_step, cluster), tag)


def _stream(code: str, first_step: int, last_step: int, cluster: int, interval: int, scans: int) -> str:
    if not (0 <= interval <= 9 and 0 <= scans <= 99):
        raise ValueError(f"{code}: interval is 1 digit and scan count 2 digits ({interval}, {scans})")
    return f"{_steps(code, first_step, last_step, cluster)}{interval:d}{scans:02d}"


def encode_md(
    first_step: int, last_step: int, cluster: int = 1, interval: int = 0, scans: int = 0, tag: str = ""
) -> bytes:
    """MD: stream scans with 3-character values; ``interval`` scans skipped between sends, ``scans`` = 0
    streams until QT."""
    return encode_command(_stream("MD", first_step, last_step, cluster, interval, scans), tag)


def encode_ms(
    first_step: int, last_step: int, cluster: int = 1, interval: int = 0, scans: int = 0, tag: str = ""
) -> bytes:
    """MS: as MD with 2-character values."""
    return encode_command(_stream("MS", first_step, last_step, cluster, interval, scans), tag)


# -- replies, sensor -> host (what a fake sensor sends) --------------------------------------------------


def encode_line(body: bytes) -> bytes:
    """``body`` + checksum + LF (status, timestamp and data lines: the sum covers the whole body, which may
    itself end with ``;``, a legal 6-bit character)."""
    return body + bytes((checksum(body),)) + b"\n"


def encode_param_line(key: str, value: str, *, sum_includes_semicolon: bool = False) -> bytes:
    """``KEY:value;`` + checksum + LF. The URG-04LX leaves the ``;`` out of the sum (real capture A);
    later models include it (``sum_includes_semicolon=True``)."""
    text = f"{key}:{value}".encode("ascii")
    summed = text + b";" if sum_includes_semicolon else text
    return text + b";" + bytes((checksum(summed),)) + b"\n"


def encode_data_blocks(payload: bytes) -> bytes:
    """Cut a joined payload into 64-character block lines, each with its checksum (no final empty line)."""
    return b"".join(encode_line(payload[i : i + BLOCK_CHARS]) for i in range(0, len(payload), BLOCK_CHARS))


def encode_reply(
    echo: bytes,
    status: str,
    *,
    timestamp_ms: int | None = None,
    payload: bytes = b"",
    params: Iterable[tuple[str, str]] = (),
    sum_includes_semicolon: bool = False,
) -> bytes:
    """A whole SCIP 2.0 reply: echo, status, optional timestamp, data blocks or parameter lines, LF LF."""
    if len(status) != 2 or not status.isascii():
        raise ValueError(f"SCIP 2.0 status is 2 ASCII characters, not {status!r}")
    out = bytearray(echo)
    out += b"\n"
    out += encode_line(status.encode("ascii"))
    if timestamp_ms is not None:
        out += encode_line(encode_value(timestamp_ms % TIMESTAMP_MODULUS, 4))
    out += encode_data_blocks(payload)
    for key, value in params:
        out += encode_param_line(key, value, sum_includes_semicolon=sum_includes_semicolon)
    out += b"\n"
    return bytes(out)


def encode_scip1_reply(echo: bytes, status: str) -> bytes:
    """A SCIP 1.1-style reply: 1-character status, no checksum (what ``SCIP2.0`` gets from a 1.1 sensor)."""
    if len(status) != 1:
        raise ValueError(f"SCIP 1.1 status is 1 character, not {status!r}")
    return echo + b"\n" + status.encode("ascii") + b"\n\n"


# -- status codes ----------------------------------------------------------------------------------------


class StatusKind(enum.Enum):
    OK = "ok"
    STREAMING = "streaming"  # MD/MS scan data follows (99)
    PARAMETER_ERROR = "parameter error"  # the command's parameters were refused
    COMMAND_ERROR = "command error"  # 0A..0I: undefined, incomplete or unprocessable command
    LASER_OFF = "laser off"  # GD/GS 10: send BM first
    ALREADY_SET = "already set"  # BM 02, TM 02/03, SS 03, SCIP2.0 0E: nothing to do
    WRONG_STATE = "wrong state"  # TM1 while not in time-adjust mode
    UNSUPPORTED = "unsupported"  # the model does not have this feature
    HARDWARE_FAULT = "hardware fault"  # laser or motor trouble (BM 01, 21..49, 50..98)
    RESUMED = "resumed"  # MD/MS 98: measurement resumed after a fault
    SCIP1 = "SCIP 1.1 reply"  # 1-character status: the sensor is not in SCIP 2.0 mode
    UNKNOWN = "unknown"


@dataclass(frozen=True, slots=True)
class ScipStatus:
    """The meaning of a status code for one command."""

    code: str
    kind: StatusKind
    text: str

    @property
    def is_error(self) -> bool:
        return self.kind not in (
            StatusKind.OK,
            StatusKind.STREAMING,
            StatusKind.ALREADY_SET,
            StatusKind.RESUMED,
        )


_P, _C = StatusKind.PARAMETER_ERROR, StatusKind.COMMAND_ERROR
# Spec p.23, "Response to Invalid Commands": the same codes for every command.
_COMMON_STATUS: dict[str, tuple[StatusKind, str]] = {
    "0A": (_C, "unable to create transmission data or reply internally"),
    "0B": (_C, "buffer shortage, or a command repeated that is already being processed"),
    "0C": (_C, "command with insufficient parameters (1)"),
    "0D": (_C, "undefined command (1)"),
    "0E": (_C, "undefined command (2)"),
    "0F": (_C, "command with insufficient parameters (2)"),
    "0G": (_C, "tag longer than 16 characters"),
    "0H": (_C, "tag has invalid characters"),
    "0I": (_C, "sensor is in firmware update mode"),
}
_STEP_STATUS: dict[str, tuple[StatusKind, str]] = {
    "01": (_P, "starting step is not numeric"),
    "02": (_P, "end step is not numeric"),
    "03": (_P, "cluster count is not numeric"),
    "04": (_P, "end step is out of range"),
    "05": (_P, "end step is smaller than starting step"),
}
_GET_STATUS = {**_STEP_STATUS, "10": (StatusKind.LASER_OFF, "laser is off (send BM first)")}
_STREAM_STATUS = {
    **_STEP_STATUS,
    "06": (_P, "scan interval is not numeric"),
    "07": (_P, "number of scans is not numeric"),
    "98": (StatusKind.RESUMED, "measurement resumed after the laser was confirmed normal"),
    "99": (StatusKind.STREAMING, "scan data"),
}
# Per command, from spec p.11 (MD/MS), 13 (GD/GS), 14 (BM), 15 (TM), 16 (SS), 3 (SCIP2.0).
_COMMAND_STATUS: dict[str, dict[str, tuple[StatusKind, str]]] = {
    "GD": _GET_STATUS,
    "GS": _GET_STATUS,
    "MD": _STREAM_STATUS,
    "MS": _STREAM_STATUS,
    "BM": {
        "01": (StatusKind.HARDWARE_FAULT, "cannot switch the laser on (laser malfunction)"),
        "02": (StatusKind.ALREADY_SET, "laser is already on"),
    },
    "TM": {
        "01": (_P, "invalid control code"),
        "02": (StatusKind.ALREADY_SET, "time-adjust mode is already on"),
        "03": (StatusKind.ALREADY_SET, "time-adjust mode is already off"),
        "04": (StatusKind.WRONG_STATE, "time requested while time-adjust mode is off"),
    },
    "SS": {
        "01": (_P, "bit rate is not numeric"),
        "02": (_P, "invalid bit rate"),
        "03": (StatusKind.ALREADY_SET, "sensor already runs at this bit rate"),
        "04": (StatusKind.UNSUPPORTED, "bit rate not supported by this model"),
    },
    "SCIP2.0": {
        "0": (StatusKind.OK, "switched to SCIP 2.0"),
        # The URG-04LX-UG01 treats SCIP2.0 as an undefined command once it is in SCIP 2.0 mode.
        "0E": (StatusKind.ALREADY_SET, "already in SCIP 2.0 mode"),
    },
}


def status_meaning(command: str, status: str) -> ScipStatus:
    """What ``status`` means in reply to ``command`` ("GD", "MD", "BM", "TM", "SCIP2.0", ...)."""
    table = _COMMAND_STATUS.get(command, {})
    if status in table:
        kind, text = table[status]
        return ScipStatus(status, kind, text)
    if status == "00":
        return ScipStatus(status, StatusKind.OK, "ok")
    if len(status) == 1:
        return ScipStatus(status, StatusKind.SCIP1, "sensor answered in SCIP 1.1; send SCIP2.0")
    if status in _COMMON_STATUS:
        kind, text = _COMMON_STATUS[status]
        return ScipStatus(status, kind, text)
    if status.isdigit():
        n = int(status)
        if command in ("MD", "MS") and 21 <= n <= 49:
            return ScipStatus(status, StatusKind.HARDWARE_FAULT, "processing stopped to verify an error")
        if command in ("MD", "MS", "GD", "GS") and 50 <= n <= 98:
            return ScipStatus(status, StatusKind.HARDWARE_FAULT, "hardware trouble (laser, motor)")
    return ScipStatus(status, StatusKind.UNKNOWN, f"status {status!r} undocumented for {command}")


# -- replies ---------------------------------------------------------------------------------------------


def _no_params() -> Mapping[str, str]:
    return MappingProxyType({})


@dataclass(frozen=True, slots=True)
class ScipReply:
    """One reply from the sensor.

    ``echo`` is the echo line as received (command, parameters, ``;tag``). For MD/MS scans
    (``status == "99"``) the echo carries the remaining-scan count, also in ``remaining_scans``.
    ``timestamp_ms`` is the sensor's raw 24-bit clock for data replies and TM1. ``data`` is the joined
    payload (block checksums removed) and ``values`` its decoding; ``params`` holds VV/PP/II lines.
    """

    echo: str
    command: str
    status: str
    tag: str = ""
    timestamp_ms: int | None = None
    data: bytes = b""
    values: tuple[int, ...] = field(default=(), repr=False)
    params: Mapping[str, str] = field(default_factory=_no_params, hash=False)
    first_step: int | None = None
    last_step: int | None = None
    cluster: int | None = None
    remaining_scans: int | None = None
    scip1: bool = False
    raw: bytes = field(default=b"", repr=False, compare=False)

    @property
    def meaning(self) -> ScipStatus:
        return status_meaning(self.command, self.status)

    @property
    def body(self) -> str:
        """The echo without its tag."""
        return self.echo.partition(";")[0]

    @property
    def is_scan(self) -> bool:
        """True for a reply that carries range data (GD/GS with 00, MD/MS with 99)."""
        return self.timestamp_ms is not None and self.command in _DATA_COMMANDS


def _command_of(body: str) -> str:
    return "SCIP2.0" if body == "SCIP2.0" else body[:2]


def _check_line(line: bytes, what: str) -> bytes:
    """Verify a line's trailing checksum character; return the body."""
    if len(line) < 2:
        raise ScipError(f"{what} line too short", line)
    body, got = line[:-1], line[-1]
    if checksum(body) != got:
        raise ScipError(
            f"{what} line checksum mismatch (got {chr(got)!r}, want {chr(checksum(body))!r})", line
        )
    return body


def _parse_timestamp(line: bytes) -> int:
    body = _check_line(line, "timestamp")
    if len(body) != 4:
        raise ScipError(f"timestamp has {len(body)} characters, not 4", line)
    return decode_value(body)


def _join_blocks(lines: list[bytes]) -> bytes:
    if not lines:
        raise ScipError("data reply without data blocks")
    parts = []
    for i, line in enumerate(lines):
        body = _check_line(line, "data")
        if not body or len(body) > BLOCK_CHARS or (i < len(lines) - 1 and len(body) != BLOCK_CHARS):
            raise ScipError(f"data block {i} has {len(body)} characters", line)
        parts.append(body)
    return b"".join(parts)


def _parse_params(lines: list[bytes]) -> Mapping[str, str]:
    params: dict[str, str] = {}
    for line in lines:
        # KEY:value;C. The sum covers "KEY:value" on the URG-04LX, "KEY:value;" on later models.
        if len(line) < 3 or line[-2:-1] != b";":
            raise ScipError("parameter line does not end with ';' + checksum", line)
        got = line[-1]
        if got != checksum(line[:-2]) and got != checksum(line[:-1]):
            raise ScipError("parameter line checksum mismatch", line)
        text = line[:-2]
        if not text.isascii() or b":" not in text:
            raise ScipError("parameter line is not KEY:value", line)
        key, _, value = text.decode("ascii").partition(":")
        params[key] = value
    return MappingProxyType(params)


def _step_params(body: str, length: int) -> tuple[int, int, int, int, int] | None:
    """first, last, cluster, interval, count from a GD/MD body, or None when they are not all digits."""
    if len(body) != length or not body[2:].isdigit():
        return None
    first, last, cluster = int(body[2:6]), int(body[6:10]), int(body[10:12])
    if length == 15:
        return first, last, cluster, int(body[12]), int(body[13:15])
    return first, last, cluster, 0, 0


def parse_reply(frame: bytes) -> ScipReply:
    """Parse one whole reply (ending with LF LF). Raises :class:`ScipError` on anything malformed."""
    frame = bytes(frame)
    if not frame.endswith(b"\n\n"):
        raise ScipError("reply does not end with LF LF", frame)
    lines = frame[:-2].split(b"\n")
    echo_b = lines[0]
    if not echo_b or len(echo_b) > _ECHO_MAX_CHARS or min(echo_b) < 0x20 or max(echo_b) > 0x7E:
        raise ScipError("echo line is not printable ASCII of a plausible length", frame)
    echo = echo_b.decode("ascii")
    body, _, tag = echo.partition(";")
    command = _command_of(body)
    if command != "SCIP2.0" and _GENERIC_COMMAND_RE.fullmatch(command) is None:
        raise ScipError(f"echo does not start with a command code: {echo!r}", frame)
    if len(lines) < 2:
        raise ScipError("reply without status line", frame)
    status_line = lines[1]
    rest = lines[2:]
    if len(status_line) == 1:
        # SCIP 1.1 answers with one status character and no checksum (urg_c treats it the same way).
        if rest or not chr(status_line[0]).isalnum():
            raise ScipError("malformed SCIP 1.1 reply", frame)
        return ScipReply(echo, command, chr(status_line[0]), tag, scip1=True, raw=frame)
    if len(status_line) != 3:
        raise ScipError(f"status line has {len(status_line)} bytes, not 3", frame)
    status_b = _check_line(status_line, "status")
    if not status_b.isalnum():
        raise ScipError("status is not alphanumeric", frame)
    status = status_b.decode("ascii")

    if command in _DATA_COMMANDS:
        return _parse_data_reply(frame, echo, body, tag, command, status, rest)
    if command == "TM" and body == "TM1" and status == "00":
        if len(rest) != 1:
            raise ScipError("TM1 reply needs exactly one time line", frame)
        return ScipReply(echo, command, status, tag, timestamp_ms=_parse_timestamp(rest[0]), raw=frame)
    if command in _PARAM_COMMANDS and status == "00":
        return ScipReply(echo, command, status, tag, params=_parse_params(rest), raw=frame)
    if rest:
        raise ScipError(f"unexpected lines after status {status} of {command}", frame)
    return ScipReply(echo, command, status, tag, raw=frame)


def _parse_data_reply(
    frame: bytes, echo: str, body: str, tag: str, command: str, status: str, rest: list[bytes]
) -> ScipReply:
    nchars, length, streaming = _DATA_COMMANDS[command]
    steps = _step_params(body, length)
    first = last = cluster = remaining = None
    if steps is not None:
        first, last, cluster = steps[0], steps[1], steps[2]
        remaining = steps[4] if streaming else None
    carries_data = status == ("99" if streaming else "00")
    if not carries_data:
        if rest:
            raise ScipError(f"{command} status {status} followed by data", frame)
        return ScipReply(
            echo,
            command,
            status,
            tag,
            first_step=first,
            last_step=last,
            cluster=cluster,
            remaining_scans=remaining,
            raw=frame,
        )
    if steps is None or first is None or last is None or cluster is None:
        raise ScipError(f"{command} data reply with malformed echo {echo!r}", frame)
    if last < first:
        raise ScipError(f"{command} data reply for an empty step range", frame)
    if len(rest) < 2:
        raise ScipError(f"{command} data reply without timestamp and data", frame)
    timestamp = _parse_timestamp(rest[0])
    payload = _join_blocks(rest[1:])
    values = decode_values(payload, nchars)
    want = expected_value_count(first, last, cluster)
    if len(values) != want:
        raise ScipError(f"{command} reply has {len(values)} values, the echo asks for {want}", frame)
    return ScipReply(
        echo,
        command,
        status,
        tag,
        timestamp_ms=timestamp,
        data=payload,
        values=values,
        first_step=first,
        last_step=last,
        cluster=cluster,
        remaining_scans=remaining,
        raw=frame,
    )


class ScipDecoder:
    """Streaming SCIP reply decoder: ``feed(bytes) -> list[ScipReply]``; partial input is kept.

    Malformed replies and junk are dropped up to the next plausible reply start; the drop is counted in
    ``discarded_bytes`` / ``bad_frames`` and the reason kept as a :class:`ScipError` for
    :meth:`take_errors` (the last ``max_errors`` of them). Bytes without a reply end are kept up to
    ``max_buffer``; beyond that the oldest are dropped the same way. ``feed`` itself never raises on bad
    input, so one bad frame cannot hide the good ones that came with it.
    """

    # What must be kept at the end of an overflowing buffer in case it is a reply still arriving: a known
    # reply is found by its start (echo + status, at most 38 bytes), but a whole reply to an unknown command
    # (64-character echo + LF + status line + LF LF = 70 bytes) is only recognised once complete.
    _TAIL_KEEP = 72

    def __init__(self, max_buffer: int = 8192, max_errors: int = 32) -> None:
        if max_buffer < 4096:
            raise ValueError("max_buffer must hold a whole scan reply (about 2.5 kB)")
        self.max_buffer = max_buffer
        self._buf = bytearray()
        self._errors: deque[ScipError] = deque(maxlen=max_errors)
        self.replies = 0
        self.bad_frames = 0
        self.discarded_bytes = 0

    @property
    def buffered(self) -> int:
        """Bytes held waiting for the rest of a reply."""
        return len(self._buf)

    def reset(self) -> None:
        """Forget buffered bytes (after the port was flushed or reopened); counters are kept."""
        self._buf.clear()

    def take_errors(self) -> list[ScipError]:
        """The errors recorded since the last call, oldest first."""
        errors = list(self._errors)
        self._errors.clear()
        return errors

    def feed(self, data: bytes | bytearray | memoryview) -> list[ScipReply]:
        buf = self._buf
        buf += data
        out: list[ScipReply] = []
        pos = 0
        while True:
            end = buf.find(b"\n\n", pos)
            if end < 0:
                break
            frame_end = end + 2
            try:
                reply = parse_reply(bytes(buf[pos:frame_end]))
                if _KNOWN_ECHO_RE.fullmatch(reply.echo.encode("ascii")) is None:
                    # A generic echo may be junk glued to the front of a real reply: prefer the real one.
                    inner = self._reply_start(pos + 1, pos + len(reply.echo))
                    if inner >= 0:
                        raise ScipError("junk before a reply", bytes(buf[pos:inner]))
            except ScipError as exc:
                nxt = self._reply_start(pos + 1, frame_end)
                cut = nxt if nxt >= 0 else frame_end
                self._discard(pos, cut, exc.reason)
                pos = cut
                continue
            out.append(reply)
            self.replies += 1
            pos = frame_end
        while len(buf) - pos > self.max_buffer:
            # No reply ends within the bound: drop up to the next plausible reply start (again, if even that
            # leaves too much), or all but a tail that may be the start of a reply still arriving.
            nxt = self._reply_start(pos + 1, len(buf))
            cut = nxt if nxt >= 0 else len(buf) - self._TAIL_KEEP
            self._discard(pos, cut, f"no reply end within {self.max_buffer} bytes")
            pos = cut
        del buf[:pos]
        return out

    def _reply_start(self, start: int, stop: int) -> int:
        """Offset of the first plausible reply start in ``[start, stop)`` (status checksum checked), or -1."""
        # search() from one past each rejected candidate rather than finditer(): a candidate whose status
        # checksum fails must not hide a real reply that starts inside it.
        i = start
        while (m := _REPLY_START_RE.search(self._buf, i)) is not None and m.start() < stop:
            status, got = m.group(1), m.group(2)
            if status is None or checksum(status) == got[0]:
                return m.start()
            i = m.start() + 1
        return -1

    def _discard(self, start: int, stop: int, reason: str) -> None:
        dropped = bytes(self._buf[start:stop])
        self.bad_frames += 1
        self.discarded_bytes += len(dropped)
        self._errors.append(ScipError(f"discarded {len(dropped)} bytes: {reason}", dropped))
