"""Consistent Overhead Byte Stuffing (Cheshire & Baker, IEEE/ACM Trans. Networking 7(2), 1999).

COBS rewrites a block of bytes so that it contains no 0x00, which frees 0x00 to mark the end of a frame on
a serial line: a receiver that loses sync only has to wait for the next 0x00. The encoding splits the data
at each zero; every piece becomes a *code byte* (piece length + 1) followed by the piece, and a piece of 254
non-zero bytes is written as code 0xFF with no zero after it. The cost is one byte, plus one per 254 bytes
of data without a zero::

    00           -> 01 01            11 22 00 33 -> 03 11 22 02 33
    11 22 33 44  -> 05 11 22 33 44   01 .. FE    -> FF 01 .. FE

:func:`cobs_encode` writes the canonical form (the vectors above and in ``../shared/reference/devices.md``
section 6 are tests). :func:`cobs_decode` takes one encoded frame *without* its 0x00 delimiter and raises
:class:`CobsError` (with the bytes) when a code byte points past the end or a 0x00 appears inside. Like
most decoders (and the C reference decoder in ``firmware_protocol/c/``) it also accepts the one
non-canonical form some encoders write, an extra ``01`` after a final 0xFF block.
"""

from __future__ import annotations

from firmware_protocol.errors import ProtocolError

__all__ = ["CobsError", "cobs_decode", "cobs_encode", "max_encoded_length"]

_BLOCK = 254  # non-zero data bytes one code byte can carry


class CobsError(ProtocolError):
    """Bytes that are not a valid COBS encoding."""


def max_encoded_length(length: int) -> int:
    """A bound on the COBS encoding of ``length`` bytes (without the 0x00 delimiter); exact below 254."""
    if length < 0:
        raise ValueError(f"length must be >= 0, not {length}")
    return length + length // _BLOCK + 1


def cobs_encode(data: bytes | bytearray | memoryview) -> bytes:
    """The canonical COBS encoding of ``data`` (no 0x00 in it; append the delimiter yourself)."""
    out = bytearray()
    pieces = bytes(data).split(b"\x00")
    last = len(pieces) - 1
    for index, piece in enumerate(pieces):
        start = 0
        # Full 254-byte blocks: code 0xFF, no zero implied after them.
        while len(piece) - start >= _BLOCK:
            out.append(0xFF)
            out += piece[start : start + _BLOCK]
            start += _BLOCK
        rest = len(piece) - start
        # After full blocks, the final piece (no real zero follows it) needs no empty trailing block.
        if rest or start == 0 or index != last:
            out.append(rest + 1)
            out += piece[start:]
    return bytes(out)


def cobs_decode(encoded: bytes | bytearray | memoryview) -> bytes:
    """Decode one COBS frame given without its delimiter; :class:`CobsError` if it is not valid COBS."""
    enc = bytes(encoded)
    if not enc:
        raise CobsError("empty COBS frame (even empty data encodes to 01)")
    zero = enc.find(0)
    if zero >= 0:
        raise CobsError(f"0x00 inside a COBS frame at offset {zero}", enc)
    out = bytearray()
    i, n = 0, len(enc)
    while i < n:
        code = enc[i]
        end = i + code
        if end > n:
            raise CobsError(f"COBS code byte {code:02X} at offset {i} points past the end ({n} bytes)", enc)
        out += enc[i + 1 : end]
        i = end
        if code != 0xFF and i < n:
            out.append(0)
    return bytes(out)
