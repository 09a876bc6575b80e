"""The link layer every frame on the controller's serial line shares: ``COBS(payload || CRC) || 00``.

:class:`FrameSplitter` cuts a byte stream at each 0x00 into candidate frames, undoes COBS and checks the
CRC-16/CCITT-FALSE (sent little-endian after the payload), so a message codec only ever sees a checked
payload. It keeps the receive rules of ``docs/wire-format.md``: an empty candidate is idle fill; a
candidate longer than the bound is counted once in ``overflows`` and skipped to the next 0x00; every
rejected candidate's bytes, its 0x00 included, go to ``discarded_bytes``; a bad candidate never costs the
next one. Pure and sans-I/O: bytes in, payloads (or errors) out.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

from firmware_protocol.cobs import CobsError, cobs_decode, cobs_encode, max_encoded_length
from firmware_protocol.crc import crc16_ccitt_false
from firmware_protocol.errors import ProtocolError

__all__ = ["CRC_LENGTH", "Candidate", "FrameSplitter", "LinkError", "encode_link_frame"]

CRC_LENGTH = 2


class LinkError(ProtocolError):
    """A candidate frame that fails the link layer.

    ``kind`` is ``cobs``, ``length``, ``crc`` or ``overflow``.
    """

    def __init__(self, kind: str, reason: str, data: bytes = b"") -> None:
        super().__init__(reason, data)
        self.kind = kind


@dataclass(frozen=True, slots=True)
class Candidate:
    """What one 0x00 ended: a checked ``payload``, or the ``error`` that rejected it (and its raw size)."""

    payload: bytes | None
    error: LinkError | None
    raw_length: int


def encode_link_frame(payload: bytes) -> bytes:
    """``COBS(payload || CRC-LE) || 00``: the bytes to write for one payload."""
    return cobs_encode(payload + crc16_ccitt_false(payload).to_bytes(CRC_LENGTH, "little")) + b"\x00"


def check_link_frame(body: bytes, min_payload: int, max_payload: int) -> bytes:
    """The payload of one stuffed frame given without its 0x00; :class:`LinkError` if it fails a check."""
    try:
        decoded = cobs_decode(body)
    except CobsError as exc:
        raise LinkError("cobs", exc.reason, body) from exc
    if not min_payload + CRC_LENGTH <= len(decoded) <= max_payload + CRC_LENGTH:
        raise LinkError(
            "length",
            f"frame is {len(decoded)} bytes after COBS, "
            f"not {min_payload + CRC_LENGTH}..{max_payload + CRC_LENGTH}",
            decoded,
        )
    payload, sent = decoded[:-CRC_LENGTH], int.from_bytes(decoded[-CRC_LENGTH:], "little")
    computed = crc16_ccitt_false(payload)
    if sent != computed:
        raise LinkError("crc", f"frame CRC {sent:04X} != computed {computed:04X}", decoded)
    return payload


class FrameSplitter:
    """Cuts a stream into checked payloads of ``min_payload..max_payload`` bytes, bounding its buffer.

    An overflow is counted in ``overflows`` as soon as the bound is passed; the candidate it spoils is
    still handed over (with its error) at the 0x00 that ends it, so that its bytes can be counted then.
    """

    def __init__(self, min_payload: int, max_payload: int) -> None:
        if not 1 <= min_payload <= max_payload:
            raise ValueError(f"payload bounds {min_payload}..{max_payload} are not 1 <= min <= max")
        self.min_payload = min_payload
        self.max_payload = max_payload
        self.max_encoded = max_encoded_length(max_payload + CRC_LENGTH)
        self._buf = bytearray()
        self._raw = 0  # bytes since the last delimiter, also those not kept after an overflow
        self._overflow: LinkError | None = None
        # Counted when it happens, as the C decoder does, not when the 0x00 that ends the skip arrives.
        self.overflows = 0

    @property
    def pending(self) -> int:
        """Bytes received since the last 0x00."""
        return self._raw

    def reset(self) -> None:
        """Forget a partial frame (e.g. after reopening the port)."""
        self._buf.clear()
        self._raw = 0
        self._overflow = None

    def feed(self, data: bytes | bytearray | memoryview) -> Iterator[Candidate]:
        """Every candidate the 0x00 bytes in ``data`` complete, in order; the rest waits for more bytes."""
        data = bytes(data)
        start = 0
        while True:
            end = data.find(0, start)
            self._take(data[start:] if end < 0 else data[start:end])
            if end < 0:
                return
            candidate = self._end_of_frame()
            if candidate is not None:
                yield candidate
            start = end + 1

    def _take(self, chunk: bytes) -> None:
        if not chunk:
            return
        self._raw += len(chunk)
        if self._overflow is not None:
            return
        if len(self._buf) + len(chunk) > self.max_encoded:
            self._overflow = LinkError(
                "overflow",
                f"no 0x00 within {self.max_encoded} bytes: skipping to the next one",
                bytes(self._buf + chunk[: self.max_encoded + 1 - len(self._buf)]),
            )
            self.overflows += 1
            self._buf.clear()
            return
        self._buf += chunk

    def _end_of_frame(self) -> Candidate | None:
        raw, overflow, body = self._raw, self._overflow, bytes(self._buf)
        self.reset()
        if raw == 0:
            return None
        if overflow is not None:
            return Candidate(None, overflow, raw)
        try:
            return Candidate(check_link_frame(body, self.min_payload, self.max_payload), None, raw)
        except LinkError as exc:
            return Candidate(None, exc, raw)
