"""The VLP detection and decoding on real rolling-shutter photographs (../shared/data/vlp; skipped without):

* MindVision MV-UB300 frames of the reference robot system (R-C-Group/VLC-ROS): every LED is found, none is
  taken for a border blob, and on the six frames of a still camera each LED's outline centre repeats to a
  few tenths of a pixel although its OOK stripes change from frame to frame;
* ``pos_20_-20_rot_ccw45_800x600.jpg``: the three PWM LEDs' stripe periods come out near 6, 8 and 13 px;
* the Luxapose Lumia 1020 photos (lab11/vlc-localization): with t_row = 1/47540 s, the five LEDs' frequencies
  (2.0 to 4.0 kHz in 0.5 kHz steps) come out within 3 %, from the stripe runs and from the FFT.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import numpy.typing as npt
import pytest

from agent.vlp.decode import DecoderConfig, StripeDecoder
from agent.vlp.detect import DetectorConfig, background_level, find_blobs

ImageU8 = npt.NDArray[np.uint8]
LUMIA_T_ROW_S = 1.0 / 47540.0  # lab11/vlc-localization lumia_1020_camera.py: rolling_shutter_r
LUXAPOSE_HZ = (2000.0, 2500.0, 3000.0, 3500.0, 4000.0)


def grey(path: Path) -> ImageU8:
    image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    assert image is not None, path
    return np.asarray(image, dtype=np.uint8)


@pytest.mark.parametrize(
    ("pattern", "size", "min_diameter_px", "radius_px"),
    [
        ("frame000[0-5].jpg", (1280, 960), 25.0, 27.0),
        ("frame001[0-5].jpg", (2048, 1536), 40.0, 43.0),
        ("pos_20_-20_rot_ccw45_800x600.jpg", (800, 600), 30.0, 33.5),
    ],
)
def test_every_led_is_found_in_the_mv_ub300_frames(
    shared_data: Path, pattern: str, size: tuple[int, int], min_diameter_px: float, radius_px: float
) -> None:
    paths = sorted((shared_data / "vlp" / "scut-mv-ub300").glob(pattern))
    assert paths
    centres = []
    for path in paths:
        image = grey(path)
        assert image.shape == (size[1], size[0])
        blobs = find_blobs(image, DetectorConfig(min_diameter_px=min_diameter_px))
        # Three LEDs in each frame (checked by eye), all clear of the border, all the reference's disk size.
        assert len(blobs) == 3, path.name
        assert not any(b.at_border for b in blobs)
        for b in blobs:
            assert b.radius_px == pytest.approx(radius_px, rel=0.1)
            assert b.outline_rms_px < 0.6
        centres.append(sorted(b.centre_px for b in blobs))
    if len(centres) > 1:
        # A still camera: each LED's centre repeats although its data stripes differ in every frame.
        spread = np.array(centres).std(axis=0)
        assert spread.max() < 0.15


def test_stripe_periods_of_the_pwm_leds(shared_data: Path) -> None:
    image = grey(shared_data / "vlp" / "scut-mv-ub300" / "pos_20_-20_rot_ccw45_800x600.jpg")
    background, _ = background_level(image)
    decoder = StripeDecoder(DecoderConfig())
    blobs = find_blobs(image, DetectorConfig(min_diameter_px=30.0))
    assert len(blobs) == 3
    # t_row_eff does not matter for the period in pixels; 1 s makes frequency_hz = 1 / period.
    periods = sorted(
        decoder.features(image, b.centre_px, b.radius_px, background, 1.0).period_px for b in blobs
    )
    for got, expected in zip(periods, (6.0, 8.0, 13.0), strict=True):
        assert got == pytest.approx(expected, rel=0.10)
    for b in blobs:
        features = decoder.features(image, b.centre_px, b.radius_px, background, 1.0)
        assert features.fft_agrees is True
        assert 0.35 < features.duty < 0.65


@pytest.mark.parametrize("name", ["samples__x_0_y_1.27.jpg", "samples__small_blob.jpg"])
def test_luxapose_frequencies(shared_data: Path, name: str) -> None:
    image = grey(shared_data / "vlp" / "luxapose" / name)
    blobs = find_blobs(image, DetectorConfig(min_diameter_px=60.0))
    assert len(blobs) == 5
    # Bare bulbs: the stripes glow far beyond the saturated core the outline fit finds. The profile takes
    # +-80 rows around each centre and a band of +-8 columns (a "radius" of 80 px, the whole band in rows).
    decoder = StripeDecoder(DecoderConfig(row_span=1.0, band_fraction=0.1, min_swing_global=0.05))
    found = []
    for blob in blobs:
        features = decoder.features(image, blob.centre_px, 80.0, 0.0, LUMIA_T_ROW_S)
        fft_hz = 1.0 / (features.fft_period_px * LUMIA_T_ROW_S)
        nearest = min(LUXAPOSE_HZ, key=lambda f: abs(f - features.frequency_hz))
        assert features.frequency_hz == pytest.approx(nearest, rel=0.03), blob.centre_px
        assert fft_hz == pytest.approx(nearest, rel=0.03), blob.centre_px
        assert features.fft_agrees is True
        found.append(nearest)
    # Five LEDs, five different frequencies: each of the rig's LEDs once.
    assert sorted(found) == list(LUXAPOSE_HZ)
