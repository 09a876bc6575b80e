"""A discriminative scale-space filter: the target's size by a search over a ladder of scales.

After Danelljan, Häger, Shahbaz Khan and Felsberg, "Accurate scale estimation for robust visual tracking"
(BMVC 2014, DSST), its scale filter alone (the mean shift finds the centre):

* At the target's centre, ``S`` patches of the target's size times ``a^n``, ``n = -(S-1)/2 .. (S-1)/2``
  (``scales``, ``step``), are each resized to one fixed template (at most ``max_area`` pixels, the target's
  aspect) and described by a feature vector ``x_n`` of ``d`` values: per 4 x 4-pixel cell a histogram of
  gradient orientations (9 unsigned bins, each cell normalised by its 3 x 3 neighbourhood's energy) and
  the cell's mean B, G, R. The ``S`` vectors, weighted by a Hann window over the scales, are the
  ``d``-channel 1-D signal ``x`` (scales x d).
* The filter ``h`` minimises ``|sum_l h^l * x^l - g|^2 + lambda sum_l |h^l|^2`` for ``g`` a Gaussian over
  the scales peaked at ``n = 0`` (sigma ``sigma_factor * S / sqrt(33)`` scales): in the Fourier domain
  ``H^l = conj(G) X^l / (sum_k conj(X^k) X^k + lambda)``. Numerator and denominator are learnt online,
  each ``(1 - eta) old + eta new`` (``learning_rate``).
* On a new frame the response ``y = IDFT(sum_l conj(A^l) Z^l / (B + lambda))`` over the scales of the
  new frame's ladder ``z``; its maximum (refined by a parabola through it and its two neighbours) is the
  scale change.

The paper's values: 33 scales, a = 1.02, sigma factor 1/4, lambda 0.01, eta 0.025, 512-pixel template;
its features are FHOG (31 per cell), here a 12-value cell of the same kind (orientation histogram and
colour). A pure core: BGR ``uint8`` frames in, a scale factor out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

__all__ = ["ScaleFilter", "ScaleFilterConfig"]

FloatArray = npt.NDArray[np.float64]
ImageU8 = npt.NDArray[np.uint8]

_CELL = 4
_ORIENTATIONS = 9


@dataclass(frozen=True)
class ScaleFilterConfig:
    scales: int = 33  # S, the ladder's rungs (odd: one at the current size)
    step: float = 1.02  # a, the ratio of neighbouring rungs
    sigma_factor: float = 0.25  # the desired response's sigma, times S / sqrt(33) rungs
    regularisation: float = 0.01  # lambda
    learning_rate: float = 0.025  # eta
    max_area: int = 512  # the template's area cap, pixels

    def __post_init__(self) -> None:
        if self.scales < 3 or self.scales % 2 == 0:
            raise ValueError("scales must be odd and at least 3")
        if not (self.step > 1.0 and self.sigma_factor > 0.0 and self.regularisation > 0.0):
            raise ValueError("need step > 1, sigma_factor > 0, regularisation > 0")
        if not 0.0 < self.learning_rate <= 1.0:
            raise ValueError("learning_rate must be in (0, 1]")
        if self.max_area < 4 * _CELL * _CELL:
            raise ValueError(f"max_area must be at least {4 * _CELL * _CELL} pixels")


class ScaleFilter:
    """:meth:`start` on the first frame, then per frame :meth:`estimate` (the scale change at the new
    centre) and :meth:`learn` (at the accepted centre and size). Sizes are (w, h) in pixels; the filter
    holds no size of its own, only what the target looks like across the ladder."""

    def __init__(self, config: ScaleFilterConfig | None = None) -> None:
        self.config = config or ScaleFilterConfig()
        cfg = self.config
        s = cfg.scales
        self._exponents = np.arange(s, dtype=np.float64) - (s - 1) // 2
        self.factors: FloatArray = cfg.step**self._exponents
        sigma = cfg.sigma_factor * s / math.sqrt(33.0)
        # The desired response peaks at index (S-1)/2, the rung n = 0; correlating a ladder with itself
        # gives it back unshifted, so the response's index i is rung i too.
        g = np.exp(-0.5 * self._exponents**2 / sigma**2)
        self._g_hat = np.fft.fft(g)
        self._window = np.hanning(s + 2)[1:-1]  # no zero weight at either end
        self._template = (8, 8)
        self._num: npt.NDArray[np.complex128] | None = None
        self._den: FloatArray | None = None

    @property
    def started(self) -> bool:
        return self._num is not None

    def start(self, frame: ImageU8, centre: FloatArray, size: FloatArray) -> None:
        """The template's shape from ``size`` (the target's aspect, area at most ``max_area``) and the
        filter from this frame's ladder."""
        w, h = float(size[0]), float(size[1])
        if not (w >= 2.0 and h >= 2.0):
            raise ValueError(f"size {size} is smaller than 2 x 2 pixels")
        shrink = min(1.0, math.sqrt(self.config.max_area / (w * h)))
        tw = max(2, round(w * shrink / _CELL)) * _CELL
        th = max(2, round(h * shrink / _CELL)) * _CELL
        self._template = (tw, th)
        self._num = None
        self._den = None
        self.learn(frame, centre, size)

    def estimate(self, frame: ImageU8, centre: FloatArray, size: FloatArray) -> tuple[float, float]:
        """The scale change (multiply ``size`` by it) and the response's peak value, from the ladder
        around ``centre`` at ``size``."""
        if self._num is None or self._den is None:
            raise RuntimeError("ScaleFilter.estimate before start")
        z_hat = np.fft.fft(self._ladder(frame, centre, size), axis=0)
        response = np.real(
            np.fft.ifft(np.sum(np.conj(self._num) * z_hat, axis=1) / (self._den + self.config.regularisation))
        )
        i = int(np.argmax(response))
        offset = 0.0
        if 0 < i < len(response) - 1:
            left, mid, right = response[i - 1], response[i], response[i + 1]
            curvature = left - 2.0 * mid + right
            if curvature < 0.0:
                offset = float(np.clip(0.5 * (left - right) / curvature, -0.5, 0.5))
        exponent = float(self._exponents[i]) + offset
        return float(self.config.step**exponent), float(response[i])

    def learn(self, frame: ImageU8, centre: FloatArray, size: FloatArray) -> None:
        """Blend this frame's ladder at ``size`` (the accepted size) into the filter."""
        x_hat = np.fft.fft(self._ladder(frame, centre, size), axis=0)
        num = np.conj(self._g_hat)[:, None] * x_hat
        den = np.sum(np.real(x_hat * np.conj(x_hat)), axis=1)
        if self._num is None or self._den is None:
            self._num, self._den = num, den
            return
        eta = self.config.learning_rate
        self._num = (1.0 - eta) * self._num + eta * num
        self._den = (1.0 - eta) * self._den + eta * den

    def _ladder(self, frame: ImageU8, centre: FloatArray, size: FloatArray) -> FloatArray:
        """(S, d) features of the patches ``size * a^n`` around ``centre``, Hann-weighted over n."""
        import cv2

        tw, th = self._template
        w, h = float(size[0]), float(size[1])
        # One crop around the largest rung (sub-pixel, the border replicated past the frame's edge),
        # shrunk once so that the size maps to about the template; each rung is then sampled from it
        # by one remap (bilinear, at most a^((S-1)/2) pixels apart).
        big = float(self.factors[-1])
        lw, lh = max(2, math.ceil(w * big) + 2), max(2, math.ceil(h * big) + 2)
        region = cv2.getRectSubPix(frame, (lw, lh), (float(centre[0]), float(centre[1])))
        sw = max(2, round(lw * tw / w))
        sh = max(2, round(lh * th / h))
        shrinking = sw < lw and sh < lh
        small = cv2.resize(region, (sw, sh), interpolation=cv2.INTER_AREA if shrinking else cv2.INTER_LINEAR)
        ux = (np.arange(tw, dtype=np.float32) - (tw - 1) / 2.0) * np.float32(w / tw * sw / lw)
        uy = (np.arange(th, dtype=np.float32) - (th - 1) / 2.0) * np.float32(h / th * sh / lh)
        f = self.factors.astype(np.float32)
        map_x = np.broadcast_to(f[:, None, None] * ux[None, None, :], (len(f), th, tw)) + np.float32(
            (sw - 1) / 2.0
        )
        map_y = np.broadcast_to(f[:, None, None] * uy[None, :, None], (len(f), th, tw)) + np.float32(
            (sh - 1) / 2.0
        )
        sampled = cv2.remap(
            small,
            np.ascontiguousarray(map_x.reshape(-1, tw)),
            np.ascontiguousarray(map_y.reshape(-1, tw)),
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REPLICATE,
        )
        patches = np.asarray(sampled, dtype=np.float32).reshape(len(f), th, tw, 3)
        feats = _cell_features(patches)
        return feats * self._window[:, None]


def _cell_features(patches: npt.NDArray[np.float32]) -> FloatArray:
    """(S, H, W, 3) BGR patches -> (S, d): per 4 x 4 cell, 9 unsigned orientation bins of the gradient
    magnitude (normalised by the 3 x 3 cells' energy around it, clipped at 0.2 as in HOG) and the mean
    B, G, R in [-0.5, 0.5]."""
    s, h, w, _ = patches.shape
    grey = patches[..., 0] * 0.114 + patches[..., 1] * 0.587 + patches[..., 2] * 0.299
    gx = np.zeros_like(grey)
    gy = np.zeros_like(grey)
    gx[:, :, 1:-1] = grey[:, :, 2:] - grey[:, :, :-2]
    gy[:, 1:-1, :] = grey[:, 2:, :] - grey[:, :-2, :]
    magnitude = np.sqrt(gx * gx + gy * gy)
    angle = np.arctan2(gy, gx) % np.pi
    bins = np.minimum((angle * (_ORIENTATIONS / np.pi)).astype(np.intp), _ORIENTATIONS - 1)
    ch, cw = h // _CELL, w // _CELL
    # Each pixel's cell index, then one bincount over (scale, cell, orientation).
    rows = np.arange(h) // _CELL
    cols = np.arange(w) // _CELL
    cell = rows[:, None] * cw + cols[None, :]
    index = (np.arange(s)[:, None, None] * (ch * cw) + cell[None]) * _ORIENTATIONS + bins
    hist = np.bincount(index.ravel(), weights=magnitude.ravel(), minlength=s * ch * cw * _ORIENTATIONS)
    hist = hist.reshape(s, ch, cw, _ORIENTATIONS)
    energy = np.sum(hist * hist, axis=3)
    padded = np.pad(energy, ((0, 0), (1, 1), (1, 1)))
    local = sum(padded[:, dy : dy + ch, dx : dx + cw] for dy in range(3) for dx in range(3))
    hist = np.minimum(hist / (np.sqrt(local)[..., None] + 1e-3 * _CELL * _CELL * 255.0), 0.2)
    return hist.reshape(s, -1).astype(np.float64)
