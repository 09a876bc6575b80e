"""COBS: the vectors of ``../shared/reference/devices.md`` section 6 (cross-checked there with PyPI ``cobs``),
round trips, and malformed input raising :class:`CobsError` with the bytes."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from firmware_protocol.cobs import CobsError, cobs_decode, cobs_encode, max_encoded_length
from firmware_protocol.errors import ProtocolError


def h(text: str) -> bytes:
    return bytes.fromhex(text.replace(" ", ""))


RUN_01_FE = bytes(range(1, 0xFF))  # 254 non-zero bytes

VECTORS = [
    (b"", h("01")),
    (h("00"), h("01 01")),
    (h("00 00"), h("01 01 01")),
    (h("00 11 00"), h("01 02 11 01")),
    (h("11 22 00 33"), h("03 11 22 02 33")),
    (h("11 22 33 44"), h("05 11 22 33 44")),
    (h("11 00 00 00"), h("02 11 01 01 01")),
    (RUN_01_FE, b"\xff" + RUN_01_FE),
    (b"\x00" + RUN_01_FE, b"\x01\xff" + RUN_01_FE),
    (bytes(range(1, 0x100)), b"\xff" + RUN_01_FE + h("02 ff")),
    # devices.md's example frame: payload 01 02 00 03 with its CRC-16/CCITT-FALSE (LE) appended.
    (h("01 02 00 03 77 ac"), h("03 01 02 04 03 77 ac")),
]


@pytest.mark.parametrize(("data", "encoded"), VECTORS, ids=lambda v: v.hex()[:16])
def test_vectors_encode_and_decode(data: bytes, encoded: bytes) -> None:
    assert cobs_encode(data) == encoded
    assert cobs_decode(encoded) == data


def test_long_runs_and_zeros_around_the_254_byte_boundary() -> None:
    for n in (253, 254, 255, 508, 509):
        data = bytes((i % 255) + 1 for i in range(n))
        for variant in (data, data + b"\x00", b"\x00" + data, data + b"\x00" + data):
            enc = cobs_encode(variant)
            assert 0 not in enc
            assert cobs_decode(enc) == variant
            assert len(enc) <= max_encoded_length(len(variant))
    # A 254-byte run followed by a real zero needs the explicit empty block after the FF block.
    assert cobs_encode(RUN_01_FE + b"\x00") == b"\xff" + RUN_01_FE + h("01 01")


def test_accepts_the_non_canonical_trailing_empty_block() -> None:
    # Some encoders write FF <254 bytes> 01 for a 254-byte run at the end; it means the same data.
    assert cobs_decode(b"\xff" + RUN_01_FE + b"\x01") == RUN_01_FE


def test_max_encoded_length() -> None:
    assert [max_encoded_length(n) for n in (0, 1, 32, 253, 254, 255, 508)] == [1, 2, 33, 254, 256, 257, 511]
    with pytest.raises(ValueError):
        max_encoded_length(-1)


@pytest.mark.parametrize(
    ("encoded", "reason"),
    [
        (b"", "empty"),
        (h("05 11 22"), "past the end"),
        (h("03 11 22 04 33"), "past the end"),
        (h("02 11 00 01"), "0x00 inside"),
        (h("00"), "0x00 inside"),
    ],
)
def test_malformed_input_raises_cobs_error_with_the_bytes(encoded: bytes, reason: str) -> None:
    with pytest.raises(CobsError) as info:
        cobs_decode(encoded)
    assert reason in info.value.reason
    assert isinstance(info.value, ProtocolError)
    assert info.value.data == encoded


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=700))
def test_round_trip_and_no_zero_on_the_wire(data: bytes) -> None:
    enc = cobs_encode(data)
    assert 0 not in enc
    assert len(data) < len(enc) <= max_encoded_length(len(data))
    assert cobs_decode(enc) == data


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=300))
def test_any_input_decodes_or_raises_cobs_error(data: bytes) -> None:
    try:
        decoded = cobs_decode(data)
    except CobsError:
        return
    # What decodes has no more bytes than went in, less the first code byte.
    assert len(decoded) <= len(data) - 1
