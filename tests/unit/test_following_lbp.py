"""The LBP operator against a per-pixel reference, and the riu2 / u2 label tables."""

from __future__ import annotations

import numpy as np
import pytest

from agent.following.lbp import NEIGHBOURS, RIU2_LUT, U2_LUT, lbp_codes, riu2_labels, u2_labels


def _reference(gray: np.ndarray, threshold: int) -> np.ndarray:
    h, w = gray.shape
    out = np.zeros((h, w), dtype=np.uint8)
    for r in range(h):
        for c in range(w):
            code = 0
            for bit, (dr, dc) in enumerate(NEIGHBOURS):
                rr, cc = min(max(r + dr, 0), h - 1), min(max(c + dc, 0), w - 1)
                if int(gray[rr, cc]) > int(gray[r, c]) + threshold:
                    code |= 1 << bit
            out[r, c] = code
    return out


@pytest.mark.parametrize("threshold", [0, 3])
def test_codes_match_the_per_pixel_definition(threshold: int) -> None:
    gray = np.random.default_rng(1).integers(0, 256, size=(17, 23), dtype=np.uint8)
    np.testing.assert_array_equal(lbp_codes(gray, threshold), _reference(gray, threshold))


def test_label_tables() -> None:
    # riu2: 0..8 for the uniform codes by their number of ones, 9 for the rest; 58 uniform codes.
    assert RIU2_LUT[0] == 0 and RIU2_LUT[255] == 8
    assert RIU2_LUT[0b00000111] == 3 and RIU2_LUT[0b11100000] == 3 and RIU2_LUT[0b10000011] == 3
    assert RIU2_LUT[0b00000101] == 9 and RIU2_LUT[0b01010101] == 9
    assert int(np.sum(RIU2_LUT < 9)) == 58
    # u2: each uniform code its own label, so the two rotations of one edge differ; the rest share 58.
    assert U2_LUT[0b00000111] != U2_LUT[0b01110000]
    assert len(set(U2_LUT[RIU2_LUT < 9].tolist())) == 58 and set(U2_LUT[RIU2_LUT == 9].tolist()) == {58}


def test_flat_and_striped_patches() -> None:
    flat = np.full((8, 8), 100, dtype=np.uint8)
    flat_noisy = flat + np.random.default_rng(0).integers(0, 3, size=flat.shape, dtype=np.uint8)
    # A margin of 3 grey levels keeps sensor noise from inventing texture on plain cloth.
    assert np.all(riu2_labels(flat_noisy, threshold=3) == 0)
    # Vertical and horizontal stripes: the same riu2 labels, different u2 labels.
    vertical = np.tile(np.array([0, 0, 200, 200], dtype=np.uint8), (8, 2))
    horizontal = vertical.T.copy()
    assert np.array_equal(
        np.bincount(riu2_labels(vertical).ravel(), minlength=10),
        np.bincount(riu2_labels(horizontal).ravel(), minlength=10),
    )
    assert not np.array_equal(
        np.bincount(u2_labels(vertical).ravel(), minlength=59),
        np.bincount(u2_labels(horizontal).ravel(), minlength=59),
    )
    with pytest.raises(ValueError):
        lbp_codes(np.zeros((4, 4, 3), dtype=np.uint8))
