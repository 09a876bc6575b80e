"""The pictures for people: the shared drawing helpers (agent.figure), the map picture (agent.slam.render)
and the calibration report's scatter plot (calibration.plot)."""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np
import pytest

from agent import figure
from agent.slam.render import OCCUPIED_VALUE, UNKNOWN_VALUE, MapPath, map_picture, occupancy_image
from calibration import plot
from tests.figures import has_colour, has_swatch


def _room() -> Any:
    """A 3 m x 2 m room at 5 cm: 60 x 40 cells, much smaller than a picture a person can read."""
    log_odds = np.zeros((40, 60), dtype=np.float32)
    log_odds[5:35, 10:50] = -2.0
    log_odds[5, 10:50] = 3.0
    log_odds[34, 10:50] = 3.0
    return occupancy_image(log_odds, (-1.5, 2.25), 0.05)


@pytest.mark.parametrize(
    ("lo", "hi", "ticks"),
    [
        (0.0, 1.0, [0.0, 0.2, 0.4, 0.6, 0.8, 1.0]),
        (-0.56, 0.57, [-0.4, -0.2, 0.0, 0.2, 0.4]),
        (-11.3, 11.1, [-10.0, -5.0, 0.0, 5.0, 10.0]),
        (1500.0, 4500.0, [1500.0, 2000.0, 2500.0, 3000.0, 3500.0, 4000.0, 4500.0]),
    ],
)
def test_ticks_are_round_values_inside_the_range(lo: float, hi: float, ticks: list[float]) -> None:
    assert figure.nice_ticks(lo, hi) == pytest.approx(ticks)


@pytest.mark.parametrize(("px_per_m", "metres"), [(20.0, 5.0), (47.0, 2.0), (100.0, 1.0), (700.0, 0.2)])
def test_scale_bar_is_a_round_length_no_longer_than_asked(px_per_m: float, metres: float) -> None:
    img = np.full((60, 400, 3), 255, np.uint8)
    length = figure.scale_bar(img, px_per_m, (10, 50), target_px=160)
    assert length == round(metres * px_per_m) <= 160
    # The bar is drawn where asked: black at its left end, its right half outlined.
    assert (img[45, 10] == 0).all() and (img[45, 10 + length] == 0).all()


def test_legend_shows_each_colour_as_a_solid_sample() -> None:
    img = np.full((200, 400, 3), 255, np.uint8)
    entries = [
        figure.Entry("truth", figure.TRUTH),
        figure.Entry("fix", figure.VLP_FIX, figure.Mark.DOT),
        figure.Entry("known point", figure.LED, figure.Mark.CROSS),
    ]
    figure.legend(img, entries, (10, 10))
    w, h = figure.legend_size(entries)
    assert all(has_swatch(img, e.colour) for e in entries)
    assert not has_swatch(img, figure.SLAM)
    assert (img[10, 10 : 10 + w] == 0).all() and (img[10 : 10 + h, 10] == 0).all()  # framed


def test_palette_colours_are_distinct() -> None:
    colours = [
        figure.TRUTH,
        figure.FUSED,
        figure.SLAM,
        figure.ODOMETRY,
        figure.VLP_FIX,
        figure.UNCALIBRATED,
        figure.LED,
    ]
    assert len(set(colours)) == len(colours)
    assert figure.TRUTH_WIDTH_PX > figure.FUSED_WIDTH_PX > figure.ESTIMATE_WIDTH_PX


def test_map_picture_is_large_with_paths_legend_and_axes() -> None:
    image = _room()
    line = np.array([[-0.5, 2.8], [0.0, 3.0], [0.8, 3.2], [1.0, 3.0]])
    paths = [
        MapPath("truth", line, figure.TRUTH, figure.TRUTH_WIDTH_PX),
        MapPath("SLAM estimate", line.copy(), figure.SLAM),  # on the truth exactly
    ]
    picture = map_picture(image, paths, "map.png: test room")
    height, width, _ = picture.shape
    assert width >= 800 and height >= 14 * 40  # 60 x 40 cells enlarged 14 times, plus axes and legend
    for colour in (figure.TRUTH, figure.SLAM, (OCCUPIED_VALUE,) * 3, (UNKNOWN_VALUE,) * 3):
        assert has_swatch(picture, colour), colour
    # The map area (left of the legend panel): the estimate is on top, and the thicker truth still shows
    # on both sides of it.
    map_area = picture[66 : 66 + 14 * 40, 80 : 80 + 14 * 60]
    assert has_colour(map_area, figure.SLAM, 100)
    assert has_colour(map_area, figure.TRUTH, 200)
    # The cells are enlarged whole (nearest neighbour): a wall row is 14 pixels of black.
    wall_row = 66 + 14 * (39 - 5) + 7
    assert (picture[wall_row, 80 + 14 * 10 + 2 : 80 + 14 * 50 - 2] == 0).all()


def test_map_picture_names_a_path_only_when_there_is_one() -> None:
    picture = map_picture(_room(), [MapPath("SLAM estimate", np.zeros((0, 2)), figure.SLAM)])
    assert not has_swatch(picture, figure.SLAM)
    assert has_swatch(picture, (OCCUPIED_VALUE,) * 3)


def test_a_large_map_is_not_enlarged() -> None:
    log_odds = np.full((500, 900), -2.0, dtype=np.float32)
    picture = map_picture(occupancy_image(log_odds, (0.0, 0.0), 0.05))
    assert picture.shape[1] < 900 + 600 and picture.shape[0] < 500 + 200


def test_calibration_scatter_has_ticks_a_legend_and_point_labels(monkeypatch: pytest.MonkeyPatch) -> None:
    drawn: list[tuple[str, ...]] = []
    real_draw = figure.Axes.draw

    def spy(self: figure.Axes, img: Any, *labels: str, **kw: Any) -> None:
        drawn.append(labels)
        real_draw(self, img, *labels, **kw)

    monkeypatch.setattr(figure.Axes, "draw", spy)
    where = np.array([[-0.46, 0.5], [-0.46, -0.42], [0.46, 0.49], [0.48, -0.43]])
    kwargs: dict[str, Any] = {"title": "LED map", "axis_labels": ("x (m)", "y (m)")}
    bare = plot.scatter([plot.Series(where, plot.ORANGE, "LED", 6)], **kwargs)
    named = plot.scatter(
        [plot.Series(where, plot.ORANGE, "LED", 6, labels=["L1", "L2", "L3", "L4"])], **kwargs
    )
    assert drawn == [("x (m)", "y (m)")] * 2
    assert bare.shape[1] >= 640 and has_swatch(named, figure.LED)
    # Each id is written beside its LED: the pictures differ just up and right of every LED's dot.
    amber = np.all(bare == np.array(figure.LED, np.uint8), axis=2).astype(np.uint8)
    amber[bare.shape[0] - 60 :] = 0  # not the legend's sample
    count, _, _, centroids = cv2.connectedComponentsWithStats(amber)
    assert count - 1 == 4
    changed = np.any(bare != named, axis=2)
    for u, v in centroids[1:].astype(int):
        assert changed[v - 30 : v, u : u + 40].sum() > 10, (u, v)


def test_bar_chart_values_on_a_round_scale() -> None:
    img = plot.bar_chart(
        [0.16, 0.6, 0.12], title="rms per view", ylabel="rms (px)", xlabel="view", threshold=0.5
    )
    assert img.shape == (400, 640, 3)
    assert has_colour(img, plot.RED, 50) and has_colour(img, plot.BLUE, 50)
