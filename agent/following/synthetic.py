"""A procedural tracking sequence with exact ground truth: a textured target walking across a mottled
background while a passer-by of the same colours but another texture crosses in front of it.

This is the case the seed paper's multi-feature tracker is for (``rtm-assistance-robot-system.txt`` §5.2:
"the single feature cannot reliably distinguish target between other people"), and the one
``reference/eco.md`` §2.4-§2.5 recommends generating: colour alone cannot tell the two apart (the
passer-by's colour histogram is the target's), LBP texture can (broad horizontal stripes against a fine
check). Used by the tests and by ``benchmarks/tracker_speed.py``; seeded, no I/O.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

__all__ = ["CrossingScene", "crossing_sequence"]

ImageU8 = npt.NDArray[np.uint8]
FloatArray = npt.NDArray[np.float64]

RED = np.array([40, 40, 200], dtype=np.float64)  # BGR
BLUE = np.array([190, 70, 30], dtype=np.float64)


@dataclass(frozen=True)
class CrossingScene:
    width_px: int = 320
    height_px: int = 240
    frames: int = 60
    target_size_px: tuple[int, int] = (40, 100)  # w, h
    target_start_px: tuple[float, float] = (110.0, 120.0)  # centre x, y
    target_speed_px: float = 1.0  # per frame, to the right
    passer_speed_px: float = -1.5  # per frame: right to left, in front of the target
    passer_scale: float = 1.4  # the passer-by is larger, so it hides the target whole for a while
    stripe_px: int = 8  # the target's horizontal stripes
    check_px: int = 2  # the passer-by's check
    noise_grey: float = 3.0  # sensor noise (standard deviation)
    passer: bool = True  # False: the target alone
    seed: int = 0


def _person_mask(w: int, h: int) -> npt.NDArray[np.bool_]:
    gy, gx = np.mgrid[0:h, 0:w]
    u = (gx + 0.5 - w / 2.0) / (w / 2.0)
    v = (gy + 0.5 - h / 2.0) / (h / 2.0)
    return np.asarray(u * u + v * v < 1.0)


def crossing_sequence(scene: CrossingScene | None = None) -> Iterator[tuple[ImageU8, FloatArray]]:
    """Frames (BGR uint8) with the target's true box (x, y, w, h, 0-based) in each."""
    scene = scene or CrossingScene()
    rng = np.random.default_rng(scene.seed)
    height, width = scene.height_px, scene.width_px
    # Mottled grey-green background: coarse noise blown up, so it has texture of its own.
    coarse = rng.uniform(60, 140, size=(height // 8 + 2, width // 8 + 2, 3))
    background = np.kron(coarse, np.ones((8, 8, 1)))[:height, :width] * np.array([0.9, 1.0, 0.8])

    tw, th = scene.target_size_px
    target_mask = _person_mask(tw, th)
    rows = np.arange(th)[:, None]
    stripes = ((rows // scene.stripe_px) % 2 == 0)[..., None]
    target_skin = np.where(stripes, RED, BLUE) * np.ones((th, tw, 1))

    pw, ph = round(tw * scene.passer_scale), round(th * scene.passer_scale)
    passer_mask = _person_mask(pw, ph)
    cy, cx = np.mgrid[0:ph, 0:pw]
    check = ((cy // scene.check_px + cx // scene.check_px) % 2 == 0)[..., None]
    passer_skin = np.where(check, RED, BLUE) * np.ones((ph, pw, 1))

    tx, ty = scene.target_start_px
    # The passer-by starts right of the target and meets it half-way through.
    meet = scene.frames / 2.0
    px0 = tx + scene.target_speed_px * meet - scene.passer_speed_px * meet
    for i in range(scene.frames):
        frame = background.copy()
        centre_t = (tx + scene.target_speed_px * i, ty)
        _paste(frame, target_skin, target_mask, centre_t)
        if scene.passer:
            centre_p = (px0 + scene.passer_speed_px * i, ty + 2.0)
            _paste(frame, passer_skin, passer_mask, centre_p)
        frame += rng.normal(0.0, scene.noise_grey, size=frame.shape)
        image = np.clip(frame, 0, 255).astype(np.uint8)
        box = np.array([centre_t[0] - tw / 2.0, centre_t[1] - th / 2.0, float(tw), float(th)])
        yield image, box


def _paste(
    frame: FloatArray, skin: FloatArray, mask: npt.NDArray[np.bool_], centre: tuple[float, float]
) -> None:
    h, w = mask.shape
    x0, y0 = round(centre[0] - w / 2.0), round(centre[1] - h / 2.0)
    fx0, fy0 = max(0, x0), max(0, y0)
    fx1, fy1 = min(frame.shape[1], x0 + w), min(frame.shape[0], y0 + h)
    if fx1 <= fx0 or fy1 <= fy0:
        return
    sub = mask[fy0 - y0 : fy1 - y0, fx0 - x0 : fx1 - x0]
    region = frame[fy0:fy1, fx0:fx1]
    region[sub] = skin[fy0 - y0 : fy1 - y0, fx0 - x0 : fx1 - x0][sub]
