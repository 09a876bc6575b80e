"""A discriminative translation filter: where the learnt target sits inside a window, to the pixel.

After Danelljan, Häger, Shahbaz Khan and Felsberg, "Accurate scale estimation for robust visual tracking"
(BMVC 2014, DSST), its translation filter (the 2-D half of DSST; its scale filter is
``agent.following.scale``):

* Around a centre, the patch of ``1 + padding`` times the target's size is resized to one fixed template
  (the target's part at most ``max_area`` pixels) and described per 4 x 4-pixel cell by ``d`` values:
  the 9 unsigned gradient-orientation bins of ``agent.following.scale`` (each cell normalised by its
  3 x 3 neighbourhood's energy) and the cell's mean grey level (DSST's features are FHOG and grey too).
  The cells, weighted by a 2-D Hann window, are the ``d``-channel 2-D signal ``x``.
* The filter minimises ``|sum_l h^l * x^l - g|^2 + lambda sum_l |h^l|^2`` for ``g`` a Gaussian peaked at
  the patch's centre (sigma ``sigma_factor`` times the target's geometric mean size): in the Fourier
  domain ``H^l = conj(G) X^l / (sum_k conj(X^k) X^k + lambda)``, numerator and denominator each learnt
  online as ``(1 - eta) old + eta new`` (``learning_rate``).
* On a new frame, the response ``y = IDFT(sum_l conj(A^l) Z^l / (B + lambda))`` over the patch ``z``
  around the given centre; its maximum (refined per axis by a parabola through it and its two
  neighbours) is where the learnt target is, relative to that centre.

The paper's values: padding 1, sigma factor 1/16, lambda 0.01, eta 0.025. A pure core: BGR ``uint8``
frames in, an offset in pixels out. The mean shift tracker (``agent.following.meanshift``) uses it to place
the scale filter's ladder on the body rather than on its colour mode, and optionally to report the box
there; it does not track with it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from agent.following.scale import _CELL, _cell_features

__all__ = ["TranslationFilter", "TranslationFilterConfig"]

FloatArray = npt.NDArray[np.float64]
ImageU8 = npt.NDArray[np.uint8]


@dataclass(frozen=True)
class TranslationFilterConfig:
    padding: float = 1.0  # the patch is (1 + padding) times the target's size
    sigma_factor: float = 1.0 / 16.0  # the desired response's sigma, times sqrt(w h)
    regularisation: float = 0.01  # lambda
    learning_rate: float = 0.025  # eta
    max_area: int = 1024  # the target's part of the template, pixels at most

    def __post_init__(self) -> None:
        if not (self.padding > 0.0 and self.sigma_factor > 0.0 and self.regularisation > 0.0):
            raise ValueError("need padding > 0, sigma_factor > 0, regularisation > 0")
        if not 0.0 < self.learning_rate <= 1.0:
            raise ValueError("learning_rate must be in (0, 1]")
        if self.max_area < 4 * _CELL * _CELL:
            raise ValueError(f"max_area must be at least {4 * _CELL * _CELL} pixels")


class TranslationFilter:
    """:meth:`start` on the first frame at the target's box, then per frame :meth:`estimate` (where the
    target is relative to a centre) and :meth:`learn` (at the accepted centre and size). Centres are
    (x, y), sizes (w, h), in pixels. The template's cell grid is fixed at :meth:`start`; later sizes are
    resampled onto it (the patch follows the size, the filter does not)."""

    def __init__(self, config: TranslationFilterConfig | None = None) -> None:
        self.config = config or TranslationFilterConfig()
        self._cells = (3, 3)  # (columns, rows) of the patch's template
        self._g_hat: npt.NDArray[np.complex128] | None = None
        self._window = np.ones((3, 3))
        self._num: npt.NDArray[np.complex128] | None = None
        self._den: FloatArray | None = None
        self._last: FloatArray | None = None  # the last estimate's cells, not windowed
        self._last_patch = (1.0, 1.0)  # ... and its size in frame pixels

    @property
    def started(self) -> bool:
        return self._num is not None

    def start(self, frame: ImageU8, centre: FloatArray, size: FloatArray) -> None:
        """The template from ``size`` and the filter from this frame's patch at ``centre``."""
        cfg = self.config
        w, h = float(size[0]), float(size[1])
        if not (w >= 2.0 and h >= 2.0):
            raise ValueError(f"size {size} is smaller than 2 x 2 pixels")
        shrink = min(1.0, math.sqrt(cfg.max_area / (w * h)))
        cols = max(3, round((1.0 + cfg.padding) * w * shrink / _CELL))
        rows = max(3, round((1.0 + cfg.padding) * h * shrink / _CELL))
        self._cells = (cols, rows)
        # The desired response: a Gaussian at offset (0, 0), stored wrapped (index 0 = no shift), so a
        # response's index is the shift itself (negative ones wrapped to the end).
        sigma = cfg.sigma_factor * math.sqrt(w * h) * shrink / _CELL
        dy = _signed(rows)[:, None]
        dx = _signed(cols)[None, :]
        g = np.exp(-0.5 * (dx * dx + dy * dy) / sigma**2)
        self._g_hat = np.fft.fft2(g)
        self._window = _hann(rows, 0.0)[:, None] * _hann(cols, 0.0)[None, :]
        self._num = None
        self._den = None
        self.learn(frame, centre, size)

    def estimate(self, frame: ImageU8, centre: FloatArray, size: FloatArray) -> tuple[FloatArray, float]:
        """Where the learnt target is relative to ``centre`` (x, y pixels, at most half the patch) in the
        patch around ``centre`` at ``size``, and the response's peak (1 on the frame it was learnt
        from alone, lower as the target's look changes)."""
        if self._num is None or self._den is None:
            raise RuntimeError("TranslationFilter.estimate before start")
        raw = self._features(frame, centre, size)
        self._last = raw
        z_hat = np.fft.fft2(raw * self._window[:, :, None], axes=(0, 1))
        response = np.real(
            np.fft.ifft2(
                np.sum(np.conj(self._num) * z_hat, axis=2) / (self._den + self.config.regularisation)
            )
        )
        rows, cols = response.shape
        i, j = np.unravel_index(int(np.argmax(response)), response.shape)
        peak = float(response[i, j])
        sy = _signed(rows)[i] + _vertex(response[(i - 1) % rows, j], peak, response[(i + 1) % rows, j])
        sx = _signed(cols)[j] + _vertex(response[i, (j - 1) % cols], peak, response[i, (j + 1) % cols])
        pw, ph = self._patch(size)
        self._last_patch = (pw, ph)
        return np.array([sx * pw / cols, sy * ph / rows]), peak

    def learn(self, frame: ImageU8, centre: FloatArray, size: FloatArray) -> None:
        """Blend this frame's patch at ``centre`` (the target's accepted centre) into the filter."""
        if self._g_hat is None:
            raise RuntimeError("TranslationFilter.learn before start")
        x = self._features(frame, centre, size) * self._window[:, :, None]
        self._blend(np.fft.fft2(x, axes=(0, 1)), self._g_hat)

    def learn_last(self, offset: FloatArray) -> None:
        """Blend the last :meth:`estimate`'s patch into the filter, the target at ``offset`` (x, y pixels)
        from its centre: the Hann window and the desired response's peak (by a phase ramp) moved there
        instead of a new patch cut around the target, which halves the filter's cost per frame. The same
        as :meth:`learn` at the patch's centre plus ``offset`` but for the patch's border (what lies past
        it on the far side of the shift is missing, where the window is low)."""
        if self._last is None or self._g_hat is None:
            raise RuntimeError("TranslationFilter.learn_last before estimate")
        cols, rows = self._cells
        pw, ph = self._last_patch
        dx, dy = float(offset[0]) * cols / pw, float(offset[1]) * rows / ph  # in cells
        window = _hann(rows, dy)[:, None] * _hann(cols, dx)[None, :]
        x_hat = np.fft.fft2(self._last * window[:, :, None], axes=(0, 1))
        ky = np.fft.fftfreq(rows)[:, None]
        kx = np.fft.fftfreq(cols)[None, :]
        self._blend(x_hat, self._g_hat * np.exp(-2j * np.pi * (kx * dx + ky * dy)))

    def _blend(self, x_hat: npt.NDArray[np.complex128], g_hat: npt.NDArray[np.complex128]) -> None:
        num = np.conj(g_hat)[:, :, None] * x_hat
        den = np.sum(np.real(x_hat * np.conj(x_hat)), axis=2)
        if self._num is None or self._den is None:
            self._num, self._den = num, den
            return
        eta = self.config.learning_rate
        self._num = (1.0 - eta) * self._num + eta * num
        self._den = (1.0 - eta) * self._den + eta * den

    def _patch(self, size: FloatArray) -> tuple[float, float]:
        pad = 1.0 + self.config.padding
        return pad * float(size[0]), pad * float(size[1])

    def _features(self, frame: ImageU8, centre: FloatArray, size: FloatArray) -> FloatArray:
        """(rows, cols, 10) cells of the patch around ``centre``: 9 orientation bins and the mean grey
        level in [-0.5, 0.5] (not windowed)."""
        import cv2

        cols, rows = self._cells
        pw, ph = self._patch(size)
        tw, th = cols * _CELL, rows * _CELL
        # One affine sampling of the patch (bilinear, sub-pixel, the border replicated past the frame's
        # edge) at twice the template's resolution, then one 2 x 2 area average onto it: the cost is the
        # template's, not the patch's (a 200 x 220 px person's 400 x 440 px patch cost 0.7 ms to crop and
        # shrink; this 0.1 ms).
        sx, sy = pw / (2 * tw), ph / (2 * th)
        m = np.array(
            [
                [sx, 0.0, float(centre[0]) - (2 * tw - 1) / 2.0 * sx],
                [0.0, sy, float(centre[1]) - (2 * th - 1) / 2.0 * sy],
            ]
        )
        fine = cv2.warpAffine(
            frame,
            m,
            (2 * tw, 2 * th),
            flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
            borderMode=cv2.BORDER_REPLICATE,
        )
        patch = cv2.resize(fine, (tw, th), interpolation=cv2.INTER_AREA)
        pixels = np.asarray(patch, dtype=np.float32)[None]
        hog = _cell_features(pixels).reshape(rows, cols, -1)
        grey = pixels[0, :, :, 0] * 0.114 + pixels[0, :, :, 1] * 0.587 + pixels[0, :, :, 2] * 0.299
        mean = grey.reshape(rows, _CELL, cols, _CELL).mean(axis=(1, 3)) / 255.0 - 0.5
        return np.concatenate([hog, mean[:, :, None].astype(np.float64)], axis=2)


def _signed(n: int) -> npt.NDArray[np.intp]:
    """0, 1, ..., then the negative shifts: the offset each index of an ``n``-long DFT stands for."""
    d = np.arange(n)
    d[d > n // 2] -= n
    return d


def _hann(n: int, shift: float) -> FloatArray:
    """``n`` samples of a Hann window ``n + 1`` samples long, centred ``shift`` samples past the middle
    (``numpy.hanning(n + 2)[1:-1]`` for no shift; zero past its ends)."""
    k = np.clip(np.arange(1, n + 1, dtype=np.float64) - shift, 0.0, n + 1.0)
    return 0.5 - 0.5 * np.cos(2.0 * np.pi * k / (n + 1.0))


def _vertex(left: float, mid: float, right: float) -> float:
    """The sub-cell offset of the peak through three samples: the vertex of the parabola through their
    logarithms (exact for a Gaussian peak, which the desired response is; a parabola through the values
    themselves locks onto the cells, measured 1.1-1.5 px short of a 3 px shift on 8 px cells), or through
    the values if a neighbour is not positive; 0 if ``mid`` is not a maximum."""
    if left > 0.0 and right > 0.0 and mid > 0.0:
        left, mid, right = math.log(left), math.log(mid), math.log(right)
    curvature = left - 2.0 * mid + right
    if curvature >= 0.0:
        return 0.0
    return float(np.clip(0.5 * (left - right) / curvature, -0.5, 0.5))
