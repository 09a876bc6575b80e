"""Checks on the product's pictures: size, and the legend samples that :mod:`agent.figure` draws."""

from __future__ import annotations

import cv2
import numpy as np
import numpy.typing as npt

from agent.figure import SWATCH_PX, Colour


def has_swatch(img: npt.NDArray[np.uint8], colour: Colour) -> bool:
    """Whether ``img`` holds a legend sample of exactly ``colour``: a solid block at least as tall as
    :data:`agent.figure.SWATCH_PX` (paths are thinner, anti-aliased, their start rings hollow)."""
    exact = np.all(img == np.array(colour, dtype=np.uint8), axis=2).astype(np.uint8)
    side = SWATCH_PX[1]
    return bool(cv2.erode(exact, np.ones((side, side), np.uint8)).any())


def has_colour(img: npt.NDArray[np.uint8], colour: Colour, at_least: int = 20) -> bool:
    """Whether at least ``at_least`` pixels are exactly ``colour`` (a path or points drawn in it)."""
    return int(np.all(img == np.array(colour, dtype=np.uint8), axis=2).sum()) >= at_least
