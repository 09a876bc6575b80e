"""LED detection: circle fits, blobs in rendered frames, the outline centre against the renderer's truth,
border rejection, row-gap bridging, and frames with nothing to find."""

from __future__ import annotations

import dataclasses
import itertools
import math

import numpy as np
import pytest

from agent.vlp.detect import (
    DetectorConfig,
    _edge_rows,
    _kasa_many,
    background_level,
    close_rows,
    find_blobs,
    fit_circle,
    measure_blob,
    measure_tracked,
    measure_tracked_many,
    refine_circle,
    search_bands,
)
from drivers.sim.render import LedCover, RollingShutterRenderer
from drivers.sim.world import CameraModel, Led, Mount, Pose2D

MOUNT = Mount(0.0, 0.0, 0.2)
# Environment 1's LEDs (examples/worlds/env1.toml): ~32 px disks at 800x600, 1.5-4.5 kHz stripes.
ENV1 = (
    Led("L1", -0.465, 0.495, 1.5, frequency_hz=1500.0, duty=0.3),
    Led("L2", -0.460, -0.420, 1.5, frequency_hz=2500.0, duty=0.6),
    Led("L3", 0.460, 0.490, 1.5, frequency_hz=3500.0, duty=0.4),
    Led("L4", 0.480, -0.425, 1.5, frequency_hz=4500.0, duty=0.5),
)
# Bridge the longest dark stripe of these signatures: (1 - 0.3) / (1500 Hz * 82 us) = 5.7 rows, plus 2.
CONFIG = DetectorConfig(min_diameter_px=16.0, bridge_px=8.0)


def still(x: float, y: float, yaw: float):  # type: ignore[no-untyped-def]
    return lambda t: Pose2D(x, y, yaw)


def test_kasa_fit_is_exact_on_points_of_a_circle() -> None:
    a = np.linspace(0.0, 2.0 * math.pi, 40, endpoint=False)
    cx, cy, r = fit_circle(12.3 + 7.5 * np.cos(a), -4.1 + 7.5 * np.sin(a))
    assert (cx, cy, r) == pytest.approx((12.3, -4.1, 7.5), abs=1e-9)


def test_robust_refinement_drops_points_on_a_cover_edge() -> None:
    # The right half of a circle of radius 10 at (50, 40), and a vertical cover edge at x = 50 cutting it:
    # the points on the edge are not on the rim and must not pull the centre.
    rng = np.random.default_rng(1)
    a = np.linspace(-1.3, 1.3, 30)
    rim_x, rim_y = 50 + 10 * np.cos(a), 40 + 10 * np.sin(a)
    edge_y = np.linspace(31, 49, 15)
    x = np.concatenate((rim_x, np.full(15, 50.0))) + rng.normal(0, 0.05, 45)
    y = np.concatenate((rim_y, edge_y)) + rng.normal(0, 0.05, 45)
    naive = fit_circle(x, y)
    assert math.dist(naive[:2], (50, 40)) > 2.0
    cx, cy, r, rms, inliers = refine_circle(x, y, (48.0, 41.0), 10.0, fixed_radius=True)
    assert (cx, cy) == pytest.approx((50.0, 40.0), abs=0.1)
    assert r == 10.0
    assert inliers == pytest.approx(30 / 45, abs=0.05)
    assert rms < 0.2


def test_background_level_ignores_the_few_bright_pixels() -> None:
    rng = np.random.default_rng(2)
    image = np.clip(np.rint(rng.normal(16.0, 1.5, (600, 800))), 0, 255).astype(np.uint8)
    image[100:140, 200:240] = 230
    median, sigma = background_level(image)
    assert median == pytest.approx(16.0, abs=1.0)
    assert sigma == pytest.approx(1.5, abs=0.6)


def test_every_led_in_view_is_found_with_its_centre_from_the_outline() -> None:
    renderer = RollingShutterRenderer(CameraModel(), ENV1, MOUNT, seed=3)
    rng = np.random.default_rng(4)
    errors = []
    for k in range(30):
        pose = still(*rng.uniform(-0.3, 0.3, 2), float(rng.uniform(-math.pi, math.pi)))
        frame = renderer.render(pose, 10.0 + 0.05 * k + float(rng.uniform(0, 0.01)))
        blobs = find_blobs(frame.image, CONFIG)
        for truth in frame.truth.leds:
            u, v = truth.centre_px
            inside = 40 < u < 760 and 40 < v < 560
            matches = [b for b in blobs if math.dist(b.centre_px, truth.centre_px) < 3.0]
            if inside:
                assert len(matches) == 1, f"frame {k}: LED {truth.id} at {truth.centre_px} not found once"
                blob = matches[0]
                assert not blob.at_border
                assert blob.radius_px == pytest.approx(truth.radius_px, abs=0.5)
                errors.append(np.subtract(blob.centre_px, truth.centre_px))
    err = np.array(errors)
    assert len(err) > 60
    # The stripes cut the disk differently in every frame; the outline centre must not follow them: no bias
    # and a small scatter (1 px is 2.7 mm on the LED plane).
    assert np.abs(err.mean(axis=0)).max() < 0.05
    assert err.std(axis=0).max() < 0.15
    assert np.abs(err).max() < 0.5


def test_a_search_spread_over_bands_finds_each_led_once_as_the_whole_search() -> None:
    # Bands overlapping by a disk (32 px here), a bridged stripe gap (8 px) either side and padding: an LED on
    # a band edge lies whole in the next band and is found there, measured in the whole image as by the
    # whole search.
    renderer = RollingShutterRenderer(CameraModel(), ENV1, MOUNT, seed=3)
    rng = np.random.default_rng(5)
    bands = search_bands(600, 4, 70)
    assert bands[0][0] == 0 and bands[-1][1] == 600
    assert all(a[1] - b[0] >= 70 for a, b in itertools.pairwise(bands))
    on_an_edge = 0
    for k in range(12):
        pose = still(*rng.uniform(-0.3, 0.3, 2), float(rng.uniform(-math.pi, math.pi)))
        frame = renderer.render(pose, 10.0 + 0.05 * k)
        whole = find_blobs(frame.image, CONFIG)
        parts = [b for rows in bands for b in find_blobs(frame.image, CONFIG, rows=rows)]
        for blob in whole:
            same = [b for b in parts if math.dist(b.centre_px, blob.centre_px) < 1.0]
            assert len(same) in (1, 2), f"frame {k}: {blob.centre_px} found {len(same)} times"
            for b in same:
                # The band's own background estimate and coarse grid may move the fit by a hair.
                assert math.dist(b.centre_px, blob.centre_px) < 0.1
                assert b.radius_px == pytest.approx(blob.radius_px, abs=0.2)
                assert b.at_border == blob.at_border
            on_an_edge += any(y0 < blob.centre_px[1] < y0 + 20 for y0, _ in bands[1:])
        assert len({(round(b.centre_px[0]), round(b.centre_px[1])) for b in parts}) == len(whole)
    assert on_an_edge > 0


def test_the_box_centre_of_the_stripes_would_be_biased() -> None:
    """What the outline fit avoids: the reference's bounding-box centre moves with the stripe phase."""
    renderer = RollingShutterRenderer(CameraModel(), ENV1[:1], MOUNT, seed=5)
    rng = np.random.default_rng(6)
    box_err, fit_err = [], []
    for k in range(40):
        frame = renderer.render(still(-0.4, 0.45, 0.0), 20.0 + 0.05 * k + float(rng.uniform(0, 0.01)))
        (truth,) = frame.truth.leds
        (blob,) = find_blobs(frame.image, CONFIG)
        _, y0, _, y1 = blob.box
        box_err.append(abs(0.5 * (y0 + y1 - 1) - truth.centre_px[1]))
        fit_err.append(abs(blob.centre_px[1] - truth.centre_px[1]))
    assert max(box_err) > 1.0
    assert max(fit_err) < 0.4


def test_blobs_touching_the_border_are_flagged() -> None:
    renderer = RollingShutterRenderer(CameraModel(), ENV1[:1], MOUNT, seed=7)
    # L1 at x = -0.465: a camera at x = 0.58 (yaw 0) puts it 0.8 * 488 px left of the centre: at the left
    # border.
    frame = renderer.render(still(0.545, 0.495, 0.0), 3.0)
    (truth,) = frame.truth.leds
    assert truth.centre_px[0] < 30
    blobs = find_blobs(frame.image, CONFIG)
    assert blobs and all(b.at_border for b in blobs)


def test_long_dark_stripes_are_bridged_into_one_blob() -> None:
    # 1 kHz at duty 0.3: 12 px dark stripes at 800x600; without the bridging each bright bar is its own blob.
    led = dataclasses.replace(ENV1[0], x_m=0.0, y_m=0.0, frequency_hz=1000.0, duty=0.3, diameter_m=0.15)
    frame = RollingShutterRenderer(CameraModel(), [led], MOUNT, seed=8).render(still(0, 0, 0), 4.0)
    diameter = 2.0 * frame.truth.leds[0].radius_px
    (bridged,) = find_blobs(frame.image, DetectorConfig(min_diameter_px=16.0, bridge_px=14.0))
    assert bridged.radius_px == pytest.approx(0.5 * diameter, abs=0.5)
    # The bridged component spans the disk from its first to its last bright bar.
    assert bridged.box[3] - bridged.box[1] > 0.6 * diameter
    unbridged = measure_blob(
        frame.image, (350, 250, 450, 350), 16.0, 1.5, DetectorConfig(min_diameter_px=6.0, bridge_px=3.0)
    )
    assert unbridged is not None
    assert unbridged.box[3] - unbridged.box[1] < 0.25 * diameter


def test_a_half_covered_led_measured_with_its_known_radius() -> None:
    # L2 (2.5 kHz, duty 0.6) half covered; the tracker knows its radius and roughly (1 px) where it is.
    renderer = RollingShutterRenderer(CameraModel(), ENV1[1:2], MOUNT, seed=9)
    frame = renderer.render(still(-0.4, -0.4, 0.3), 5.0, covers=[LedCover(0, 0.0, 0.5)])
    (truth,) = frame.truth.leds
    u, v = truth.centre_px
    r = truth.radius_px
    box = (int(u - r - 6), int(v - r - 6), int(u + r + 7), int(v + r + 7))
    free = measure_blob(frame.image, box, 16.0, 1.5, CONFIG)
    known = measure_blob(frame.image, box, 16.0, 1.5, CONFIG, radius_hint=r, centre_hint=(u + 0.8, v - 0.6))
    assert free is not None and known is not None
    # A free circle through the half disk's outline is far off; the known radius puts it back.
    assert math.dist(free.centre_px, truth.centre_px) > 2.0
    assert math.dist(known.centre_px, truth.centre_px) < 0.4
    assert known.inlier_fraction < 0.8


@pytest.mark.parametrize(
    "image",
    [
        np.zeros((600, 800), np.uint8),
        np.full((600, 800), 255, np.uint8),
        np.clip(np.random.default_rng(0).normal(16, 1.5, (600, 800)), 0, 255).astype(np.uint8),
        np.zeros((2, 3), np.uint8),
    ],
    ids=["black", "saturated", "noise", "tiny"],
)
def test_nothing_is_found_in_frames_without_leds(image: np.ndarray) -> None:  # type: ignore[type-arg]
    assert find_blobs(image, CONFIG) == []


def test_edge_rows_of_several_windows_are_those_of_each() -> None:
    """_edge_rows stacks windows of different sizes (zero-padded): each window's edges come out bit for bit
    as when it is alone."""
    renderer = RollingShutterRenderer(CameraModel(), ENV1, MOUNT, seed=12)
    rng = np.random.default_rng(13)
    for k in range(8):
        pose = still(*rng.uniform(-0.3, 0.3, 2), float(rng.uniform(-math.pi, math.pi)))
        image = renderer.render(pose, 30.0 + 0.05 * k).image
        blobs = [b for b in find_blobs(image, CONFIG) if not b.at_border]
        subs = []
        for j, b in enumerate(blobs):
            x0, y0, x1, y1 = b.box
            # Windows of several widths and heights, one too small to have edges.
            subs.append(image[y0 : y1 + j % 2, max(x0 - 3 - j, 0) : x1 + 3])
        subs.append(image[10:12, 10:40])
        backgrounds = [16.0] * len(subs)
        peaks = [float(s.max()) for s in subs]
        rows = _edge_rows(subs, backgrounds, peaks)
        for j, (sub, peak) in enumerate(zip(subs, peaks, strict=True)):
            alone = _edge_rows([sub], [16.0], [peak]).points(0, (7, 9))
            together = rows.points(j, (7, 9))
            np.testing.assert_array_equal(together[0], alone[0])
            np.testing.assert_array_equal(together[1], alone[1])


def test_batched_circle_fits_are_fit_circle() -> None:
    rng = np.random.default_rng(14)
    subs, truths = [], []
    for _ in range(5):
        image = np.full((60, 60), 16, np.uint8)
        cx, cy, r = rng.uniform(25, 35), rng.uniform(25, 35), rng.uniform(10, 18)
        yy, xx = np.mgrid[0:60, 0:60]
        image[np.hypot(xx - cx, yy - cy) <= r] = 200
        subs.append(image)
        truths.append((cx, cy, r))
    rows = _edge_rows(subs, [16.0] * 5, [200.0] * 5)
    which = [0, 2, 3, 4]
    for j, (cx, cy, r, rms, worst) in zip(which, _kasa_many(rows, which), strict=True):
        x, y = rows.points(j, (0, 0))
        assert (cx, cy, r) == pytest.approx(fit_circle(x, y), abs=1e-9)
        resid = np.hypot(x - cx, y - cy) - r
        assert rms == pytest.approx(math.sqrt(float(np.mean(resid**2))), abs=1e-9)
        assert worst == pytest.approx(float(np.abs(resid).max()), abs=1e-9)
        assert (cx, cy, r) == pytest.approx(truths[j], abs=0.3)


def test_measuring_tracked_leds_together_is_measuring_each() -> None:
    renderer = RollingShutterRenderer(CameraModel(), ENV1, MOUNT, seed=15)
    rng = np.random.default_rng(16)
    kernel = np.ones((CONFIG.bridge, 1), np.uint8)
    for k in range(6):
        pose = still(*rng.uniform(-0.3, 0.3, 2), float(rng.uniform(-math.pi, math.pi)))
        image = renderer.render(pose, 40.0 + 0.05 * k).image
        leds = []
        for b in find_blobs(image, CONFIG):
            u, v = b.centre_px
            x0, y0 = max(int(u - 30), 0), max(int(v - 30), 0)
            closed = close_rows(image[y0 : int(v + 30), x0 : int(u + 30)], kernel)
            leds.append((closed, (u + 0.3, v - 0.2), b.radius_px, 16.0))
        together = measure_tracked_many(image, leds, CONFIG)
        for (closed, centre, radius, background), blob in zip(leds, together, strict=True):
            alone = measure_tracked(image, closed, centre, radius, background, CONFIG)
            assert (blob is None) == (alone is None)
            if blob is not None and alone is not None:
                assert blob.centre_px == pytest.approx(alone.centre_px, abs=1e-9)
                assert blob.radius_px == pytest.approx(alone.radius_px, abs=1e-9)
                assert (
                    dataclasses.replace(
                        blob,
                        centre_px=alone.centre_px,
                        radius_px=alone.radius_px,
                        outline_rms_px=alone.outline_rms_px,
                    )
                    == alone
                )
                assert blob.outline_rms_px == pytest.approx(alone.outline_rms_px, abs=1e-9)
