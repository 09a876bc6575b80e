"""Reading an LED's identity from its rolling-shutter stripes.

The chain (``reference/vlp.md`` §1.4, the reference paper's Fig. 1(b)):

1. **Profile.** Row i of a rolling-shutter image integrates the LED over [t0 + i t_row, + T_exp], so the
   LED's waveform shows up down the rows. The profile is the mean of each row across a central band of the
   disk (away from the blurred rim), or, as in the paper, the single middle column of the ROI
   (``mode="middle_column"``).
2. **Cubic spline interpolation** (scipy, x ~3.9: 28 samples -> 109 in the paper). A natural-knot spline is
   linear in the data, so its operator is built once per profile length and applied as a matrix product.
3. **LEXW** (local extremum window thresholding, the group's ``LEDMeanRowThreshold``): local extrema of the
   (lightly smoothed) profile bound windows; a window that swings most of the way to the dark level is an
   edge and is cut at the middle of its own min and max (a min at the background is first replaced by the
   background compensation); ripples inside a stripe, and the two end windows (cut by the disk outline, not
   by an extremum), take the level of the preceding edge window.
4. **Runs and edges.** Transitions of the binary profile, interpolated to a fraction of a sample, give edges
   (rising: dark -> bright going down the image) and run lengths. Interior runs only (the first and last are
   cut by the disk outline): the period P is the span of the complete periods (first to last edge of one
   kind) over their number, i.e. mean(bright + dark) over complete periods; duty D = mean(bright) / P;
   frequency f = 1 / (P t_row_eff) with t_row_eff = t_row * sensor rows per output row.
5. **FFT cross-check** of the period: the strongest frequency of the windowed profile, mean removed (and,
   for long profiles, its slow envelope divided out).
6. **Classification** against the LED map's signatures (f_k, D_k): each predicts edges every
   P_k = 1 / (f_k t_row_eff) rows, falling edges D_k P_k after rising ones, at an unknown phase. The phase is
   the circular mean of the edges' phases; each edge's distance to its predicted place (capped), and each
   predicted edge inside the profile that was not seen, add to chi^2 with the edge noise sigma. Log-likelihood
   -chi^2/2 per signature; the posterior over signatures (uniform prior) gives the id and its confidence.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np
import numpy.typing as npt
from scipy.interpolate import CubicSpline

from agent.vlp.model import CameraIntrinsics, Signature

FloatArray = npt.NDArray[np.float64]
ImageU8 = npt.NDArray[np.uint8]

__all__ = [
    "Classification",
    "DecoderConfig",
    "LedRequest",
    "RowTiming",
    "SpectralPeriod",
    "SplineInterpolator",
    "StripeDecoder",
    "StripeFeatures",
    "classify",
    "classify_many",
    "fft_period",
    "fit_period",
    "lexw_threshold",
    "match_signatures",
    "normalised_profile",
    "signature_table",
    "stripe_edges",
    "stripe_profile",
]

MODES = ("row_mean", "middle_column")
PERIOD_FITS = ("never", "ambiguous", "always")

# One LED to decode: (centre_px, radius_px, background_dn, fft_check), as the arguments of
# StripeDecoder.features.
LedRequest = tuple[tuple[float, float], float, float, bool]


@dataclass(frozen=True, slots=True)
class DecoderConfig:
    """``row_span`` / ``band_fraction``: the profile takes rows |v - v0| <= row_span R and, in each, the
    columns |u - u0| <= band_fraction R (0.27 = the inner 70 % of the chord at 0.92 R, inside the disk and
    away from its blurred rim). ``interpolation``: spline upsampling factor (paper: 3.9).
    ``smooth_samples``: box filter over the
    interpolated profile before looking for extrema (the reference used 15 on 2048-row images; a sample is
    1/3.9 of a row here). ``min_swing_dn`` / ``min_swing_fraction``: a window is a stripe edge, thresholded on
    its own, when its swing exceeds max(min_swing_dn, min_swing_fraction x its top above the background,
    min_swing_global x the profile's range above the background): a real edge falls (nearly) to the dark
    level whatever the lamp's fall-off, a ripple or the noise on the dark level does not (the reference used
    a fixed 30 DN).
    ``dark_margin_dn`` / ``dark_compensation_dn``: a window minimum within the margin of the background is
    replaced by background + compensation (reference: below 20 DN -> 40 DN for its camera; 0 here, for a
    linear sensor). ``edge_sigma_px``: edge position noise for the classifier; ``edge_cap_px``: a worse
    misfit counts as this much. ``min_confidence``: below it, a frame's id is left undecided.

    The sub-row fit (:func:`fit_period`, :func:`match_signatures`): ``period_fit`` says when it runs:
    ``"never"`` (the edges alone), ``"ambiguous"`` (the close signatures compared by the fit, for an LED
    whose measured period lies within ``ambiguous_fraction`` of two or more signatures' periods, with
    duties within ``ambiguous_duty`` of its measured duty: the only case where the edges' resolution is
    not enough, as they are within 4 % even on a 19-row blob; the period itself stays the edges'),
    ``"always"`` (also every LED's period fitted: the row-time calibration, the benchmark).
    ``fit_noise_floor``: the least noise assumed on the normalised profile (a fraction of the stripe's
    height) when the fit's residual is smaller; ``fit_min_confidence``: the posterior a frame needs for the
    fit to name one of close signatures (their frames vote all the same). ``fit_min_periods``: the fitted
    period replaces the edges' only on a profile this many periods long (on shorter ones the edges measure
    it as well or better; the signatures are still compared by the fit).
    Refusals (a :class:`Classification` with ``id`` None and a ``reason``, no vote): a profile with less
    than ``min_contrast_dn`` between its brightest and darkest rows (``low-contrast``); one shorter than
    ``min_profile_periods`` periods of the best signature (``blob-too-short``); a best signature whose
    shorter stripe (bright or dark) lasts less than ``min_stripe_rows`` output rows, which the
    nearest-neighbour resize can drop whole (``stripe-too-short``); a best signature whose period (more
    than ``max_period_mismatch`` relative) or duty (more than ``max_duty_mismatch``) the profile's own
    measurement contradicts, on a profile of two of its periods or more (``poor-fit``: an LED whose short
    stripes were dropped, read as another)."""

    mode: str = "row_mean"
    interpolation: float = 3.9
    row_span: float = 0.92
    band_fraction: float = 0.27
    smooth_samples: int = 3
    min_swing_dn: float = 4.0
    min_swing_fraction: float = 0.5
    min_swing_global: float = 0.2
    dark_margin_dn: float = 4.0
    dark_compensation_dn: float = 0.0
    edge_sigma_px: float = 0.3
    edge_cap_px: float = 1.2
    end_margin_px: float = 0.8
    min_confidence: float = 0.6
    max_misfit_per_edge: float = 3.0
    period_fit: str = "ambiguous"
    ambiguous_fraction: float = 0.12
    ambiguous_duty: float = 0.15
    fit_noise_floor: float = 0.06
    fit_min_periods: float = 4.5
    fit_min_confidence: float = 0.9
    min_contrast_dn: float = 10.0
    min_stripe_rows: float = 1.0
    max_fit_rms: float = 0.2
    min_profile_periods: float = 1.0
    max_period_mismatch: float = 0.1
    max_duty_mismatch: float = 0.2

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got {self.mode!r}")
        if self.period_fit not in PERIOD_FITS:
            raise ValueError(f"period_fit must be one of {PERIOD_FITS}, got {self.period_fit!r}")
        if not self.interpolation >= 1.0:
            raise ValueError(f"interpolation must be >= 1, got {self.interpolation}")


@dataclass(frozen=True, slots=True)
class StripeFeatures:
    """What the stripes of one LED say, in output rows (``first_row`` is the profile's first image row).

    ``period_px``, ``frequency_hz`` and ``duty`` are NaN when the profile holds no complete period;
    ``fft_period_px`` is NaN when it is too short for the FFT to mean anything, and ``fft_agrees`` is then
    None."""

    first_row: int
    length_px: int
    edges_px: tuple[float, ...]
    rising: tuple[bool, ...]
    bright_runs_px: tuple[float, ...]
    dark_runs_px: tuple[float, ...]
    period_px: float
    frequency_hz: float
    duty: float
    fft_period_px: float
    fft_agrees: bool | None
    contrast_dn: float


@dataclass(frozen=True, slots=True)
class Classification:
    """The id this frame's stripes give (``None``: undecided), its posterior probability, and the
    log-likelihood of every signature (in the order given to :func:`classify`). ``reason``: why there is
    no id, a code and its detail (``"unresolved: A (2000 Hz) and B (2050 Hz) ..."``, ``"low-contrast: ..."``,
    ``"too-few-stripes: ..."``, ``"blob-too-short: ..."``, ``"stripe-too-short: ..."``, ``"poor-fit: ..."``);
    None when there is an id. A refusal for what the frame cannot show (contrast, length, a stripe shorter
    than a row) carries no log-likelihoods, so it does not vote."""

    id: str | None
    confidence: float
    log_likelihood: tuple[float, ...]
    reason: str | None = None


class SplineInterpolator:
    """Cubic spline upsampling of profiles by ``factor``: n samples -> round(n * factor) over the same span.

    The spline (scipy ``CubicSpline``, not-a-knot ends) is linear in the data, so the operator M (a
    round(n f) x n matrix) is built once per length n and kept; interpolation is then M @ y. With
    ``smooth_samples`` > 1 the box filter LEXW applies before finding extrema is folded into M.
    """

    def __init__(self, factor: float, smooth_samples: int = 1) -> None:
        self.factor = factor
        self.smooth_samples = smooth_samples
        self._operators: dict[int, FloatArray] = {}

    def operator(self, n: int) -> FloatArray:
        """The (round(n f) x n) matrix of spline interpolation, followed by the box smoothing when asked
        (both are linear, so they fold into one matrix)."""
        op = self._operators.get(n)
        if op is None:
            x = np.arange(n, dtype=np.float64)
            n_out = max(round(n * self.factor), n)
            x_new = np.linspace(0.0, n - 1.0, n_out)
            op = np.asarray(CubicSpline(x, np.eye(n), axis=0)(x_new), dtype=np.float64)
            if self.smooth_samples > 1:
                op = np.apply_along_axis(box_smooth, 0, op, self.smooth_samples)
            self._operators[n] = op
        return op

    def __call__(self, profile: FloatArray) -> tuple[FloatArray, float]:
        """The upsampled profile and its sample spacing in original samples ((n - 1) / (n_out - 1))."""
        n = profile.size
        if n < 4:
            return profile.astype(np.float64), 1.0
        op = self.operator(n)
        return op @ profile, (n - 1.0) / (op.shape[0] - 1.0)


def stripe_profile(
    image: ImageU8,
    centre_px: tuple[float, float],
    radius_px: float,
    config: DecoderConfig,
) -> tuple[FloatArray, int]:
    """The stripe profile across the LED disk: (values, image row of the first value).

    Rows |v - v0| <= row_span R. ``row_mean``: each row's mean over a central band of columns
    |u - u0| <= band_fraction R, so every row averages the same columns, all inside the disk and away from
    its blurred rim. ``middle_column``: the single column nearest u0, as in the paper.
    """
    height, width = image.shape
    u0, v0 = centre_px
    reach = config.row_span * radius_px
    top = max(math.ceil(v0 - reach), 0)
    bottom = min(math.floor(v0 + reach), height - 1)
    if bottom - top < 2:
        return np.empty(0), top
    col = min(max(round(u0), 0), width - 1)
    if config.mode == "middle_column":
        return image[top : bottom + 1, col].astype(np.float64), top
    half = config.band_fraction * radius_px
    c0 = max(math.floor(u0 - half + 0.5), 0)
    c1 = min(max(math.floor(u0 + half + 0.5), c0), width - 1)
    band = image[top : bottom + 1, c0 : c1 + 1]
    profile: FloatArray = np.add.reduce(band, axis=1, dtype=np.float64) * (1.0 / band.shape[1])
    return profile, top


def box_smooth(samples: FloatArray, width: int) -> FloatArray:
    """Moving average over ``width`` samples, the ends padded with the end values (``width`` <= 1: none)."""
    if width <= 1 or samples.size <= width:
        return samples
    padded = np.pad(samples, (width // 2, width - 1 - width // 2), mode="edge")
    smooth: FloatArray = np.convolve(padded, np.full(width, 1.0 / width), mode="valid")
    return smooth


def lexw_threshold(
    samples: FloatArray, background_dn: float, config: DecoderConfig, *, smoothed: bool = False
) -> tuple[npt.NDArray[np.bool_], FloatArray]:
    """LEXW: the binary profile and the threshold used at every sample (see the module docstring).
    ``smoothed``: the samples already went through the ``smooth_samples`` box filter."""
    n = samples.size
    smooth = samples if smoothed else box_smooth(samples, config.smooth_samples)
    if n < 2:
        level = 0.5 * (max(float(smooth.min()), background_dn) + float(smooth.max())) if n else 0.0
        thresholds = np.full(n, level)
        return samples > thresholds, thresholds
    # Local extrema: where the sign of the first difference changes (XOR of the binarised difference with
    # its shift), plus both ends.
    rising = smooth[1:] > smooth[:-1]
    turn = np.empty(n, dtype=np.bool_)
    turn[0] = turn[-1] = True
    np.not_equal(rising[1:], rising[:-1], out=turn[1:-1])
    ext = turn.nonzero()[0]
    values = smooth[ext]
    # The profile's extremes are among its local extrema and ends.
    lo_all, hi_all = float(values.min()), float(values.max())
    a, b = values[:-1], values[1:]
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    lo = np.where(lo < background_dn + config.dark_margin_dn, background_dn + config.dark_compensation_dn, lo)
    # A window is a stripe edge when it swings most of the way down to the dark level: by more than
    # min_swing_fraction (hi - background), and by more than min_swing_dn and min_swing_global of the
    # profile's whole range (noise near the background is no edge either). Smaller swings are ripples inside
    # a stripe (noise, the lamp's structure); they take the level of the preceding edge window, as do the
    # two end windows, which end at the profile's ends rather than at extrema (a ramp there is the disk's
    # fall-off inside a stripe cut by the outline, not an edge).
    floor = max(config.min_swing_dn, config.min_swing_global * (hi_all - background_dn))
    edge = hi - lo > np.maximum(floor, config.min_swing_fraction * (hi - background_dn))
    if edge.size >= 2:
        edge[0] = edge[-1] = False
    good = edge.nonzero()[0]
    if good.size == 0:
        global_level = 0.5 * (max(lo_all, background_dn) + hi_all)
        window_level = np.full(edge.size, global_level)
    else:
        # Each non-edge window takes the level of the edge window before it (the first ones: the first):
        # the k-th edge window's level for every window after k edge windows (counted inclusively).
        levels = 0.5 * (lo[good] + hi[good])
        count = edge.cumsum()
        count[count == 0] = 1
        window_level = levels[count - 1]
    lengths = ext[1:] - ext[:-1]
    lengths[-1] += 1
    thresholds = window_level.repeat(lengths)
    return samples > thresholds, thresholds


def stripe_edges(
    samples: FloatArray, binary: npt.NDArray[np.bool_], thresholds: FloatArray, step: float
) -> tuple[FloatArray, npt.NDArray[np.bool_]]:
    """Edge positions (in original samples, fractional) and whether each is rising (dark -> bright)."""
    change = (binary[1:] != binary[:-1]).nonzero()[0]
    if change.size == 0:
        return np.empty(0), np.empty(0, dtype=np.bool_)
    after = change + 1
    s0 = samples[change]
    rise = samples[after] - s0
    rise[rise == 0.0] = 1.0
    frac = (thresholds[change] - s0) / rise
    positions: FloatArray = (change + np.minimum(np.maximum(frac, 0.0), 1.0)) * step
    return positions, binary[after]


def fft_period(profile: FloatArray, min_period: float = 2.0, window: FloatArray | None = None) -> float:
    """Period (in samples) of the strongest frequency of the mean-removed, Hann-windowed profile: the
    zero-padded FFT's peak, refined by parabolic interpolation; NaN for profiles shorter than 8 samples.
    (:class:`SpectralPeriod` gives the same numbers faster for repeated lengths.)"""
    n = profile.size
    if n < 8:
        return math.nan
    y = (profile - profile.mean()) * (np.hanning(n) if window is None else window)
    n_fft = _fft_size(n)
    spectrum = np.abs(np.fft.rfft(y, n_fft))
    k_lo, k_hi = _fft_band(n, n_fft, min_period, spectrum.size)
    if k_hi <= k_lo:
        return math.nan
    return _peak_period(spectrum, k_lo, k_hi, n_fft)


def _fft_size(n: int) -> int:
    """Zero padding to the power of two >= 4 n (at least 64): the parabolic peak interpolation does the
    rest."""
    return max(64, 1 << math.ceil(math.log2(4 * n)))


def _fft_band(n: int, n_fft: int, min_period: float, size: int) -> tuple[int, int]:
    """Bins from one period over the whole profile to ``min_period`` samples."""
    return max(math.ceil(n_fft / n), 1), min(int(n_fft / min_period), size - 2)


def _peak_period(spectrum: FloatArray, k_lo: int, k_hi: int, n_fft: int) -> float:
    k = k_lo + int(np.argmax(spectrum[k_lo : k_hi + 1]))
    a, b, c = float(spectrum[k - 1]), float(spectrum[k]), float(spectrum[k + 1])
    denom = a - 2.0 * b + c
    shift = 0.5 * (a - c) / denom if denom != 0 else 0.0
    return n_fft / (k + shift)


class SpectralPeriod:
    """The FFT cross-check for short profiles: the same zero-padded spectrum as :func:`fft_period`, but
    only its searched band (plus one bin each side for the peak interpolation), as products with cached
    DFT matrices C_kj = w_j cos(2 pi k j / n_fft), S_kj = w_j sin(...) (w: Hann window; the mean is removed
    through the matrices' row sums). For 15-80 samples two small real matrix products cost less than an FFT
    call, and stay on one core."""

    def __init__(self, min_period: float = 2.0) -> None:
        self.min_period = min_period
        self._mats: dict[int, tuple[FloatArray, FloatArray, int, int, int]] = {}

    def __call__(self, profile: FloatArray) -> float:
        n = profile.size
        if n < 8:
            return math.nan
        entry = self._mats.get(n)
        if entry is None:
            n_fft = _fft_size(n)
            k_lo, k_hi = _fft_band(n, n_fft, self.min_period, n_fft // 2 + 1)
            k = np.arange(k_lo - 1, k_hi + 2, dtype=np.float64)[:, None]
            j = np.arange(n, dtype=np.float64)[None, :]
            window = np.hanning(n)[None, :]
            cos = window * np.cos(2.0 * math.pi * k * j / n_fft)
            sin = window * np.sin(2.0 * math.pi * k * j / n_fft)
            # Removing the mean first is the same as subtracting each row's sum times the mean.
            cos = np.ascontiguousarray(cos - cos.sum(axis=1, keepdims=True) / n)
            sin = np.ascontiguousarray(sin - sin.sum(axis=1, keepdims=True) / n)
            entry = (cos, sin, k_lo, k_hi, n_fft)
            self._mats[n] = entry
        cos, sin, k_lo, k_hi, n_fft = entry
        if k_hi <= k_lo:
            return math.nan
        band = np.hypot(cos @ profile, sin @ profile)
        # band[i] is bin k_lo - 1 + i.
        i = 1 + int(band[1:-1].argmax())
        a, b, c = float(band[i - 1]), float(band[i]), float(band[i + 1])
        denom = a - 2.0 * b + c
        shift = 0.5 * (a - c) / denom if denom != 0 else 0.0
        return n_fft / (k_lo - 1 + i + shift)


def signature_table(signatures: tuple[Signature, ...], t_row_eff_s: float) -> tuple[FloatArray, FloatArray]:
    """(P_k in output rows, D_k) of every signature: P = 1 / (f t_row_eff)."""
    period = np.array([1.0 / (s.frequency_hz * t_row_eff_s) for s in signatures], dtype=np.float64)
    duty = np.array([s.duty for s in signatures], dtype=np.float64)
    return period, duty


def classify(
    edges_px: FloatArray,
    rising: npt.NDArray[np.bool_],
    span_px: tuple[float, float],
    signatures: tuple[Signature, ...],
    t_row_eff_s: float,
    config: DecoderConfig,
    table: tuple[FloatArray, FloatArray] | None = None,
) -> Classification:
    """Posterior over the map's signatures from the edges (see the module docstring, step 6).
    ``table`` is :func:`signature_table` of the same signatures, when the caller keeps it.

    All signatures at once: (K signatures) x (n edges) arrays. For signature k, P_k = 1 / (f_k t_row_eff);
    edge j's phase is (e_j - [falling] D_k P_k) / P_k; phi_k is their circular mean; the misfit of edge j is
    its phase distance to phi_k times P_k, capped at ``edge_cap_px``. Predicted edges inside the span that
    no observed edge matches count as capped misfits too (that is what separates P from P/2).
    """
    k_sig = len(signatures)
    if k_sig == 0:
        return Classification(None, 0.0, (), "no signatures to compare with")
    if table is None:
        table = signature_table(signatures, t_row_eff_s)
    period, duty = table
    inv_p = 1.0 / period
    lo, hi = span_px[0] + config.end_margin_px, span_px[1] - config.end_margin_px
    cap = config.edge_cap_px
    n_edges = edges_px.size
    if n_edges:
        # Phase in cycles of every edge under every signature; falling edges moved back by D (cycles).
        phase = edges_px[None, :] * inv_p[:, None] - np.where(rising, 0.0, duty[:, None])
        angle = (2.0 * math.pi) * phase
        phi = np.arctan2(np.sin(angle).sum(axis=1), np.cos(angle).sum(axis=1)) * (0.5 / math.pi)
        resid = (np.mod(phase - phi[:, None] + 0.5, 1.0) - 0.5) * period[:, None]
        sq = resid * resid
        misfit = np.minimum(sq, cap * cap).sum(axis=1)
        inside = (edges_px >= lo - cap) & (edges_px <= hi + cap)
        matched = (sq <= cap * cap) & inside
        matched_r = (matched & rising).sum(axis=1)
        matched_f = matched.sum(axis=1) - matched_r
    else:
        phi = np.zeros(k_sig)
        misfit = np.zeros(k_sig)
        matched_r = matched_f = np.zeros(k_sig, dtype=np.intp)
    # Predicted rising edges at (j + phi) P in [lo, hi]: j from ceil(lo/P - phi) to floor(hi/P - phi);
    # falling ones D P later.
    lo_c, hi_c = lo * inv_p - phi, hi * inv_p - phi
    pred_r = np.floor(hi_c) - np.ceil(lo_c) + 1.0
    pred_f = np.floor(hi_c - duty) - np.ceil(lo_c - duty) + 1.0
    missing = np.maximum(pred_r - matched_r, 0.0) + np.maximum(pred_f - matched_f, 0.0)
    chi2 = (misfit + missing * (cap * cap)) * (1.0 / config.edge_sigma_px**2)
    loglik = -0.5 * chi2
    best = int(loglik.argmax())
    confidence = 1.0 / float(np.exp(loglik - loglik[best]).sum())
    misfit_ok = n_edges >= 2 and float(chi2[best]) <= config.max_misfit_per_edge**2 * n_edges
    ll = loglik.tolist()
    chosen = signatures[best].id if (confidence >= config.min_confidence and misfit_ok) else None
    reason = None if chosen else _undecided(n_edges, float(chi2[best]), confidence, ll, signatures, config)
    return Classification(chosen, confidence if misfit_ok else 0.0, tuple(ll), reason)


def _undecided(
    n_edges: int,
    chi2_best: float,
    confidence: float,
    loglik: list[float],
    signatures: tuple[Signature, ...],
    config: DecoderConfig,
) -> str:
    """Why a frame's edges name no signature."""
    if n_edges < 2:
        return f"too-few-stripes: {n_edges} edge{'s' if n_edges != 1 else ''}, 2 needed"
    if chi2_best > config.max_misfit_per_edge**2 * n_edges:
        return f"poor-fit: chi2 {chi2_best:.0f} over {n_edges} edges fits no signature"
    order = sorted(range(len(loglik)), key=lambda k: -loglik[k])
    a = signatures[order[0]]
    if len(order) < 2:
        return f"unresolved: {a.id} at posterior {confidence:.2f}"
    b = signatures[order[1]]
    return (
        f"unresolved: {a.id} ({a.frequency_hz:.0f} Hz, duty {a.duty:.2f}) and {b.id} "
        f"({b.frequency_hz:.0f} Hz, duty {b.duty:.2f}) fit alike (posterior {confidence:.2f})"
    )


def classify_many(
    edges_px: list[FloatArray],
    rising: list[npt.NDArray[np.bool_]],
    spans_px: list[tuple[float, float]],
    signatures: tuple[Signature, ...],
    t_row_eff_s: float,
    config: DecoderConfig,
    table: tuple[FloatArray, FloatArray] | None = None,
) -> list[Classification]:
    """:func:`classify` for several LEDs at once (the same arithmetic on all their edges together: segment
    sums by ``np.add.reduceat``), which costs about what one LED costs alone. LEDs without edges go through
    :func:`classify` one by one."""
    out: list[Classification | None] = [None] * len(edges_px)
    batch = [i for i, e in enumerate(edges_px) if e.size > 0]
    for i in range(len(edges_px)):
        if edges_px[i].size == 0:
            out[i] = classify(edges_px[i], rising[i], spans_px[i], signatures, t_row_eff_s, config, table)
    if batch and signatures:
        if table is None:
            table = signature_table(signatures, t_row_eff_s)
        results = _classify_batch(
            np.concatenate([edges_px[i] for i in batch]),
            np.concatenate([rising[i] for i in batch]),
            [edges_px[i].size for i in batch],
            [spans_px[i] for i in batch],
            signatures,
            config,
            table,
        )
        for i, result in zip(batch, results, strict=True):
            out[i] = result
    return [c if c is not None else Classification(None, 0.0, ()) for c in out]


_CONSTANTS: list[tuple[FloatArray, FloatArray, tuple[FloatArray, FloatArray]]] = []


def _signature_constants(period: FloatArray, duty: FloatArray) -> tuple[FloatArray, FloatArray]:
    """1 / P_k and the phase shift of each edge kind, (0, D_k) as a (2, K, 1) array, of a signature table;
    the last table's are kept (a decoder keeps its table between frames)."""
    if _CONSTANTS and _CONSTANTS[0][0] is period and _CONSTANTS[0][1] is duty:
        return _CONSTANTS[0][2]
    constants = (1.0 / period, np.multiply.outer((0.0, 1.0), duty)[:, :, None])
    _CONSTANTS[:] = [(period, duty, constants)]
    return constants


def _classify_batch(
    edges_px: FloatArray,
    rising: npt.NDArray[np.bool_],
    counts: list[int],
    spans_px: list[tuple[float, float]],
    signatures: tuple[Signature, ...],
    config: DecoderConfig,
    table: tuple[FloatArray, FloatArray],
    *,
    within_spans: bool = False,
) -> list[Classification]:
    """The classification of LEDs that all have edges (``counts[i]`` >= 1 of them, laid end to end in
    ``edges_px``), as :func:`classify` (module docstring, step 6), on (K signatures) x (all edges) arrays
    with per-LED segment sums. ``within_spans``: every edge is known to lie in its LED's span (the
    decoder's own edges do), so when the cap reaches past the end margins no edge can be outside.

    Per edge e under signature k the phase in cycles is e / P_k - [falling] D_k (D_k times 0 or 1, so a
    rising edge's phase is exactly e / P_k). Per LED and signature the predicted rising edges in [lo, hi]
    are floor(hi / P - phi) - ceil(lo / P - phi) + 1, and the falling ones the same with phi + D: both
    kinds are one (2, K, LEDs) array, as are the matched counts.
    """
    period, duty = table
    inv_p, kind_shift = _signature_constants(period, duty)
    cap = config.edge_cap_px
    cap2 = cap * cap
    starts = [0] * len(counts)
    for j in range(1, len(counts)):
        starts[j] = starts[j - 1] + counts[j - 1]
    # Per LED [lo, hi]: the span less the end margins; per edge, its LED's, widened by the cap (an edge just
    # outside still matches).
    span = np.array(
        [[s0 + config.end_margin_px for s0, _ in spans_px], [s1 - config.end_margin_px for _, s1 in spans_px]]
    )
    # The decoder's edges are within [0, length - 1] up to rounding (hence the 1e-6 px of slack).
    if within_spans and cap >= config.end_margin_px + 1e-6:
        inside: npt.NDArray[np.bool_] | bool = True
    else:
        lo_e, hi_e = span.repeat(counts, axis=1)
        inside = (edges_px >= lo_e - cap) & (edges_px <= hi_e + cap)
    kinds = np.array([rising, ~rising])
    phase = np.multiply.outer(inv_p, edges_px)
    phase -= np.multiply.outer(duty, kinds[1])
    angle = (2.0 * math.pi) * phase
    sums = np.add.reduceat(np.array([np.sin(angle), np.cos(angle)]), starts, axis=2)
    phi = np.arctan2(sums[0], sums[1]) * (0.5 / math.pi)
    resid = (np.mod(phase - phi.repeat(counts, axis=1) + 0.5, 1.0) - 0.5) * period[:, None]
    sq = resid * resid
    misfit = np.add.reduceat(np.minimum(sq, cap2), starts, axis=1)
    matched = (sq <= cap2) & inside
    # Matched edges of each kind per LED, (2, K, LEDs), rising first.
    matched_kinds = np.add.reduceat(matched[None, :, :] & kinds[:, None, :], starts, axis=2)
    # The span's ends in cycles after the phase, (2 ends, K, LEDs), then per kind (the falling edges shifted
    # by D): (2 ends, 2 kinds, K, LEDs).
    ends = (span[:, None, :] * inv_p[:, None] - phi)[:, None] - kind_shift
    predicted = np.floor(ends[1]) - np.ceil(ends[0]) + 1.0
    missing = np.maximum(predicted - matched_kinds, 0.0).sum(axis=0)
    chi2 = (misfit + missing * cap2) * (1.0 / config.edge_sigma_px**2)
    loglik = (-0.5 * chi2).T.tolist()
    out = []
    limit = config.max_misfit_per_edge**2
    for n_edges, ll, c2 in zip(counts, loglik, chi2.T.tolist(), strict=True):
        best = ll.index(max(ll))
        top = ll[best]
        confidence = 1.0 / math.fsum([math.exp(v - top) for v in ll])
        ok = n_edges >= 2 and c2[best] <= limit * n_edges
        chosen = signatures[best].id if (confidence >= config.min_confidence and ok) else None
        reason = None if chosen else _undecided(n_edges, c2[best], confidence, ll, signatures, config)
        out.append(Classification(chosen, confidence if ok else 0.0, tuple(ll), reason))
    return out


class _EdgeBatch(NamedTuple):
    """The edges of several profiles found together: flat arrays in profile order, with ``bounds[i]`` to
    ``bounds[i + 1]`` the edges of profile i (positions in its own samples, fractional)."""

    positions: FloatArray
    rising: npt.NDArray[np.bool_]
    bounds: list[int]


def _lexw_edges_batch(
    samples: list[FloatArray], backgrounds: list[float], steps: list[float], config: DecoderConfig
) -> _EdgeBatch:
    """:func:`lexw_threshold` (on already smoothed samples) and :func:`stripe_edges` of several profiles
    (each of 2 samples or more) at once: the profiles are laid end to end and every array operation runs
    once for all of them. The arithmetic per sample, window and edge is that of the single-profile
    functions; what the concatenation adds is kept out explicitly:

    - each profile's first and last sample are extrema (as the ends of a single profile are);
    - the "window" from one profile's last extremum to the next one's first is a seam, never an edge, and
      its one sample (the profile's last) takes the level of the profile's last window, as the single
      version's last window covers the last sample;
    - a window takes the level of the edge window before it *within its profile* (the first edge window's
      for those before it; the profile's global level when it has none);
    - the binary change across a seam is no edge.
    """
    count = len(samples)
    flat = samples[0] if count == 1 else np.concatenate(samples)
    total = flat.size
    starts = [0] * count
    for i in range(1, count):
        starts[i] = starts[i - 1] + samples[i - 1].size
    ends = [s + p.size - 1 for s, p in zip(starts, samples, strict=True)]
    # Local extrema: where the sign of the first difference changes, plus every profile's two ends.
    rising = flat[1:] > flat[:-1]
    turn = np.empty(total, dtype=np.bool_)
    np.not_equal(rising[1:], rising[:-1], out=turn[1:-1])
    turn[starts + ends] = True
    ext = turn.nonzero()[0]
    values = flat[ext]
    # Extremum index where each profile's extrema start; window j runs from extremum j to j + 1.
    first_ext = ext.searchsorted(starts).tolist()
    hi_all = np.maximum.reduceat(values, first_ext).tolist()
    n_ext = [b - a for a, b in itertools.pairwise([*first_ext, ext.size])]
    # Windows per profile: its own (n_ext - 1) plus the seam after it (none after the last profile).
    n_win = list(n_ext)
    n_win[-1] -= 1
    per_profile = []
    for bg, top in zip(backgrounds, hi_all, strict=True):
        per_profile.append(
            (
                bg,
                bg + config.dark_margin_dn,
                bg + config.dark_compensation_dn,
                max(config.min_swing_dn, config.min_swing_global * (top - bg)),
            )
        )
    bg_w, dark_w, comp_w, floor_w = np.array(per_profile).T.repeat(n_win, axis=1)
    a, b = values[:-1], values[1:]
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    lo = np.where(lo < dark_w, comp_w, lo)
    # A window is a stripe edge when it swings most of the way down to the dark level (see
    # lexw_threshold); the first and last window of a profile with two or more are not, nor are seams.
    edge = hi - lo > np.maximum(floor_w, config.min_swing_fraction * (hi - bg_w))
    never = []
    for i in range(count):
        own = n_ext[i] - 1
        if own >= 2:
            never += [first_ext[i], first_ext[i] + own - 1]
        if i < count - 1:
            never.append(first_ext[i] + own)
    if never:
        edge[never] = False
    good = edge.nonzero()[0]
    # Window levels: the edge windows' own. Edge windows up to and including each window; a window takes
    # the last of them in its profile, or the profile's first when none precedes it.
    table = 0.5 * (lo[good] + hi[good])
    seen = edge.cumsum()
    before = [0, *seen[[first_ext[i] - 1 for i in range(1, count)]].tolist()]
    after = [*before[1:], good.size]
    source = np.maximum(seen - 1, np.array(before).repeat(n_win))
    bare = [i for i in range(count) if after[i] == before[i]]
    if bare:
        # Profiles without an edge window: their global level, appended to the table.
        lo_all = np.minimum.reduceat(values, first_ext).tolist()
        levels = [0.5 * (max(lo_all[i], backgrounds[i]) + hi_all[i]) for i in bare]
        table = np.concatenate((table, levels))
        for k, i in enumerate(bare):
            w0 = first_ext[i]
            source[w0 : w0 + n_win[i]] = good.size + k
    lengths = ext[1:] - ext[:-1]
    lengths[-1] += 1
    thresholds = table[source].repeat(lengths)
    binary = flat > thresholds
    # Transitions of the binary profiles (not across a seam), interpolated between samples.
    change_mask = binary[1:] != binary[:-1]
    if count > 1:
        change_mask[ends[:-1]] = False
    change = change_mask.nonzero()[0]
    bounds = change.searchsorted([*starts, total]).tolist()
    if change.size == 0:
        return _EdgeBatch(np.empty(0), np.empty(0, dtype=np.bool_), bounds)
    n_changes = [b1 - b0 for b0, b1 in itertools.pairwise(bounds)]
    offset = np.array(starts).repeat(n_changes)
    step = np.array(steps).repeat(n_changes)
    after_c = change + 1
    s0 = flat[change]
    rise = flat[after_c] - s0
    rise[rise == 0.0] = 1.0
    frac = (thresholds[change] - s0) / rise
    positions: FloatArray = ((change - offset) + np.minimum(np.maximum(frac, 0.0), 1.0)) * step
    return _EdgeBatch(positions, binary[after_c], bounds)


@dataclass(frozen=True)
class RowTiming:
    """When each output row was exposed, in output rows: ``clock_rows[v]`` = (the sensor row that output row
    v shows) / (sensor rows per output row), so that a stripe period of P = 1 / (f t_row_eff) rows holds
    exactly in this clock, and ``exposure_rows`` = T_exp / t_row_eff. A frame resized with nearest
    neighbour shows sensor rows 0, 2, 5, 7, 10, ... (2.56 apart on average at 1536 -> 600): row v's time is
    off the uniform a v by up to half a sensor row, which the clock removes."""

    clock_rows: FloatArray
    exposure_rows: float

    @classmethod
    def uniform(cls, height_px: int, exposure_rows: float) -> RowTiming:
        return cls(np.arange(height_px, dtype=np.float64), exposure_rows)

    @classmethod
    def of(cls, intrinsics: CameraIntrinsics) -> RowTiming:
        """The timing of the camera's frames (OpenCV ``resizeNN``'s row selection, as
        :meth:`CameraIntrinsics.from_sensor` models it)."""
        h, sensor = intrinsics.height_px, intrinsics.sensor_height_px
        exposure = intrinsics.exposure_s / intrinsics.t_row_eff_s
        if sensor <= 0 or sensor == h:
            return cls.uniform(h, exposure)
        ifx = 1.0 / (h / sensor)
        rows = np.minimum(np.floor(np.arange(h, dtype=np.float64) * ifx), sensor - 1)
        return cls(rows / intrinsics.sensor_rows_per_row, exposure)

    def clock(self, first_row: int, n: int) -> FloatArray:
        """The clock of ``n`` rows from ``first_row`` (rows past the table's end continue it uniformly)."""
        table = self.clock_rows
        if first_row + n <= table.size:
            out: FloatArray = table[first_row : first_row + n]
            return out
        return np.arange(first_row, first_row + n, dtype=np.float64)


def normalised_profile(profile: FloatArray, background_dn: float) -> FloatArray | None:
    """The profile as the fraction of the LED's light each row caught: (y - background) / (envelope -
    background), the envelope a parabola fitted to the bright rows (above the middle of the profile's range:
    the lamp's fall-off across the disk). None when too few rows are bright to fit it."""
    n = profile.size
    lo, hi = max(float(profile.min()), background_dn), float(profile.max())
    if n < 6 or hi - lo <= 0.0:
        return None
    x = np.linspace(-1.0, 1.0, n)
    bright = profile > lo + 0.6 * (hi - lo)
    if int(bright.sum()) < 3:
        return None
    xb, yb = x[bright], profile[bright]
    if np.ptp(xb) < 0.5:
        envelope = np.full(n, float(np.median(yb)))
    else:
        coef = np.polyfit(xb, yb, 2 if xb.size >= 5 else 1)
        envelope = np.polyval(coef, x)
    height = np.maximum(envelope - background_dn, 0.25 * (hi - background_dn))
    z: FloatArray = (profile - background_dn) / height
    return z


def _pwm_fractions(
    clock: FloatArray, period: FloatArray, phase: FloatArray, duty: FloatArray, exposure: float
) -> FloatArray:
    """(G, n): the share of each row's exposure the LED was on, for G (period, phase, duty) candidates:
    the box filter of the square wave in closed form (the renderer's ``pwm_exposure_fraction``); the wave is
    on while frac(c / P + phase) < D, c the row's clock at the start of its exposure."""
    w = max(exposure, 1e-3)
    ua = clock[None, :] / period[:, None] + phase[:, None]
    ub = ua + (w / period)[:, None]
    fa, fb = np.floor(ua), np.floor(ub)
    d = duty[:, None]
    on = (fb - fa) * d + np.minimum(ub - fb, d) - np.minimum(ua - fa, d)
    out: FloatArray = on * (period / w)[:, None]
    return out


def _fit_costs(
    z: FloatArray, clock: FloatArray, period: FloatArray, phase: FloatArray, duty: FloatArray, exposure: float
) -> FloatArray:
    r = z[None, :] - _pwm_fractions(clock, period, phase, duty, exposure)
    out: FloatArray = np.einsum("gn,gn->g", r, r)
    return out


_PHASES = 32


def _best_phase(
    z: FloatArray, clock: FloatArray, period: FloatArray, duty: FloatArray, exposure: float
) -> tuple[FloatArray, FloatArray]:
    """Per (period, duty) candidate, the least squared misfit over the phase and the phase: a grid of 32
    phases, then two finer grids around the best."""
    k = period.size
    grid = np.arange(_PHASES, dtype=np.float64) / _PHASES
    p = np.repeat(period, _PHASES)
    d = np.repeat(duty, _PHASES)
    cost = _fit_costs(z, clock, p, np.tile(grid, k), d, exposure).reshape(k, _PHASES)
    best = grid[cost.argmin(axis=1)]
    step = 1.0 / _PHASES
    offsets = np.linspace(-1.0, 1.0, 7)
    for _ in range(2):
        step /= 3.0
        phases = (best[:, None] + 3.0 * step * offsets[None, :]).ravel()
        c2 = _fit_costs(z, clock, np.repeat(period, 7), phases, np.repeat(duty, 7), exposure).reshape(k, 7)
        best = phases.reshape(k, 7)[np.arange(k), c2.argmin(axis=1)]
        cost = c2
    return cost.min(axis=1), best


def match_signatures(
    z: FloatArray, clock: FloatArray, periods: FloatArray, duties: FloatArray, exposure_rows: float
) -> FloatArray:
    """Least squared misfit of the normalised profile ``z`` (rows at ``clock``) to each signature's
    rendered stripes (its period and duty, the phase fitted): the sub-row test of close signatures, which
    uses every row (also those caught half-way through an edge), not only the edges' crossings."""
    costs, _ = _best_phase(z, clock, periods, duties, exposure_rows)
    return costs


def fit_period(
    z: FloatArray,
    clock: FloatArray,
    period0: float,
    duty: float,
    exposure_rows: float,
    half_range: float | None = None,
) -> tuple[float, float, float]:
    """The stripe period below the output row: the period (and phase) whose rendered stripes fit the
    normalised profile ``z`` best, searched within ``half_range`` (default 8 %) of ``period0`` (the edges'
    estimate) on a grid of 17 periods, then on two finer grids. Returns (period, its resolution, the
    residual's rms): the resolution is half the width of the periods whose misfit stays within 4 noise
    variances of the best (where they cannot be told apart from it)."""
    n = z.size
    h = 0.08 * period0 if half_range is None else half_range
    periods = np.linspace(period0 - h, period0 + h, 17)
    duties = np.full(periods.size, duty)
    costs, _ = _best_phase(z, clock, periods, duties, exposure_rows)
    i = int(costs.argmin())
    best_p, best_c = float(periods[i]), float(costs[i])
    step = float(periods[1] - periods[0])
    for _ in range(2):
        step /= 3.0
        fine = best_p + step * np.linspace(-3.0, 3.0, 7)
        c2, _ = _best_phase(z, clock, fine, np.full(7, duty), exposure_rows)
        j = int(c2.argmin())
        if float(c2[j]) <= best_c:
            best_p, best_c = float(fine[j]), float(c2[j])
    noise = max(best_c / max(n - 4, 1), 0.0)
    level = best_c + 4.0 * noise
    within = periods[costs <= level]
    resolution = 0.5 * float(within.max() - within.min()) if within.size else 0.0
    resolution = max(resolution, 0.5 * float(periods[1] - periods[0]))
    return best_p, resolution, math.sqrt(noise)


class StripeDecoder:
    """Profile -> spline -> LEXW -> edges, runs, period, frequency, duty, FFT check -> classification.

    Keeps the spline operators between frames (hence a class); otherwise stateless. Several LEDs of one
    frame are decoded together (:meth:`decode_many`): their profiles go through LEXW, the edge search and
    the classification as one batch of array operations, which costs little more than one LED.
    """

    def __init__(self, config: DecoderConfig = DecoderConfig(), timing: RowTiming | None = None) -> None:
        self.config = config
        self.timing = timing
        self._spline = SplineInterpolator(config.interpolation, config.smooth_samples)
        self._spectral = SpectralPeriod()
        self._table_key: tuple[tuple[Signature, ...], float] | None = None
        self._table: tuple[FloatArray, FloatArray] | None = None

    def features(
        self,
        image: ImageU8,
        centre_px: tuple[float, float],
        radius_px: float,
        background_dn: float,
        t_row_eff_s: float,
        *,
        fft_check: bool = True,
    ) -> StripeFeatures:
        """The stripe features of the LED at ``centre_px`` (steps 1-5 of the module docstring). Without
        ``fft_check`` the FFT cross-check is skipped (``fft_period_px`` NaN, ``fft_agrees`` None): a tracker
        runs it on every few frames of a settled LED."""
        return self.features_many(image, [(centre_px, radius_px, background_dn, fft_check)], t_row_eff_s)[0]

    def features_many(
        self, image: ImageU8, leds: list[LedRequest], t_row_eff_s: float
    ) -> list[StripeFeatures]:
        """:meth:`features` of several LEDs of one frame, each given as (centre_px, radius_px,
        background_dn, fft_check)."""
        features, _, _, profiles = self._features(image, leds, t_row_eff_s)
        if self.config.period_fit == "always":
            features = [
                self._fitted(f, p, first, led[2], t_row_eff_s)[0]
                for f, (p, first), led in zip(features, profiles, leds, strict=True)
            ]
        return features

    def decode_many(
        self,
        image: ImageU8,
        leds: list[LedRequest],
        signatures: tuple[Signature, ...],
        t_row_eff_s: float,
    ) -> list[tuple[StripeFeatures, Classification]]:
        """:meth:`features_many` and :meth:`classify_many` in one go (the edges stay in the batch's arrays
        between the two)."""
        features, batch, members, profiles = self._features(image, leds, t_row_eff_s)
        table = self._signature_table(signatures, t_row_eff_s)
        classes: list[Classification | None] = [None] * len(leds)
        if batch is not None and signatures:
            counts = [batch.bounds[j + 1] - batch.bounds[j] for j in range(len(members))]
            with_edges = [j for j, c in enumerate(counts) if c > 0]
            if with_edges:
                keep = [k for j in with_edges for k in range(batch.bounds[j], batch.bounds[j + 1])]
                everything = len(keep) == batch.positions.size
                positions = batch.positions if everything else batch.positions[keep]
                rising = batch.rising if everything else batch.rising[keep]
                used = [counts[j] for j in with_edges]
                # The edges as the features hold them (image rows) and back, as classify_many sees them.
                rows = np.array([features[members[j]].first_row for j in with_edges]).repeat(used)
                results = _classify_batch(
                    (positions + rows) - rows,
                    rising,
                    used,
                    [(0.0, float(features[members[j]].length_px - 1)) for j in with_edges],
                    signatures,
                    self.config,
                    table,
                    within_spans=True,
                )
                for j, result in zip(with_edges, results, strict=True):
                    classes[members[j]] = result
        out = []
        for f, c in zip(features, classes, strict=True):
            if c is None:
                c = classify(
                    np.empty(0),
                    np.empty(0, dtype=np.bool_),
                    (0.0, float(f.length_px - 1)),
                    signatures,
                    t_row_eff_s,
                    self.config,
                    table,
                )
            out.append((f, c))
        return [
            self._checked(f, c, profile, first, led[2], signatures, t_row_eff_s, table)
            for (f, c), (profile, first), led in zip(out, profiles, leds, strict=True)
        ]

    def _clock(self, first_row: int, n: int, t_row_eff_s: float) -> tuple[FloatArray, float]:
        """The rows' clock and the exposure in rows (uniform rows and a 20 us exposure without a timing)."""
        if self.timing is not None:
            return self.timing.clock(first_row, n), self.timing.exposure_rows
        return np.arange(first_row, first_row + n, dtype=np.float64), 20e-6 / t_row_eff_s

    def _fitted(
        self,
        f: StripeFeatures,
        profile: FloatArray,
        first_row: int,
        background_dn: float,
        t_row_eff_s: float,
        refine: bool = True,
    ) -> tuple[StripeFeatures, FloatArray | None, FloatArray]:
        """The features with the period fitted below the output row (:func:`fit_period`; only with
        ``refine``), the normalised profile (None when it cannot be normalised) and its clock."""
        clock, exposure = self._clock(first_row, profile.size, t_row_eff_s)
        z = normalised_profile(profile, background_dn) if math.isfinite(f.period_px) else None
        if z is None or not refine:
            return f, z, clock
        if f.length_px < self.config.fit_min_periods * f.period_px:
            # Few periods across the blob: the fit has too few edges to beat the edges' own estimate
            # (benchmarks/vlp_decode.py), so the period stays theirs.
            return f, z, clock
        duty = f.duty if math.isfinite(f.duty) else 0.5
        period, _, _ = fit_period(z, clock, f.period_px, duty, exposure)
        return dataclasses.replace(f, period_px=period, frequency_hz=1.0 / (period * t_row_eff_s)), z, clock

    def _checked(
        self,
        f: StripeFeatures,
        c: Classification,
        profile: FloatArray,
        first_row: int,
        background_dn: float,
        signatures: tuple[Signature, ...],
        t_row_eff_s: float,
        table: tuple[FloatArray, FloatArray],
    ) -> tuple[StripeFeatures, Classification]:
        """What the edges said, checked against what the frame can show and, for close signatures, decided
        by the sub-row fit (see :class:`DecoderConfig`)."""
        cfg = self.config
        if f.length_px and f.contrast_dn < cfg.min_contrast_dn:
            return f, Classification(
                None,
                0.0,
                (),
                f"low-contrast: {f.contrast_dn:.0f} DN between the brightest and darkest rows, "
                f"{cfg.min_contrast_dn:.0f} needed",
            )
        if not signatures or not c.log_likelihood:
            return f, c
        period, duty = table
        ll = list(c.log_likelihood)
        if cfg.period_fit != "never" and math.isfinite(f.period_px) and f.length_px >= 6:
            # Close: the period within ambiguous_fraction and the duty within ambiguous_duty of the
            # measured ones (a larger duty difference the edge template sees at once).
            measured_duty = f.duty if math.isfinite(f.duty) else math.nan
            close = [
                k
                for k in range(len(signatures))
                if abs(period[k] - f.period_px) <= cfg.ambiguous_fraction * period[k]
                and not abs(duty[k] - measured_duty) > cfg.ambiguous_duty
            ]
            if len(close) >= 2 or cfg.period_fit == "always":
                # The period itself is refined only when asked for ("always"): the ids need only the
                # signatures' fits.
                refine = cfg.period_fit == "always"
                f, z, clock = self._fitted(f, profile, first_row, background_dn, t_row_eff_s, refine)
                if z is not None and len(close) >= 2 and not (c.reason or "").startswith("poor-fit"):
                    exposure = self.timing.exposure_rows if self.timing is not None else 20e-6 / t_row_eff_s
                    costs = match_signatures(z, clock, period[close], duty[close], exposure)
                    noise = max(float(costs.min()) / max(z.size - 3, 1), cfg.fit_noise_floor**2)
                    fitted = (-0.5 / noise) * costs
                    base = max(ll[k] for k in close)
                    top = float(fitted.max())
                    for k, v in zip(close, fitted.tolist(), strict=True):
                        ll[k] = base + v - top
                    best = ll.index(max(ll))
                    confidence = 1.0 / math.fsum(math.exp(v - ll[best]) for v in ll)
                    chosen = signatures[best].id if confidence >= cfg.fit_min_confidence else None
                    reason = None if chosen else _undecided(2, 0.0, confidence, ll, signatures, cfg)
                    c = Classification(chosen, confidence, tuple(ll), reason)
        if c.id is None:
            return f, c
        best = ll.index(max(ll))
        p_best, d_best = float(period[best]), float(duty[best])
        stripe = min(d_best, 1.0 - d_best) * p_best
        sig = signatures[best]
        if stripe < cfg.min_stripe_rows:
            # The edges cannot see such stripes reliably (the resize keeps some, drops others), but every
            # row caught part of the light: the sub-row fit against every signature's rendered stripes
            # (the square wave box-filtered at each row's true time) decides, when it can.
            fitted_c = self._short_stripes(
                f, profile, first_row, background_dn, signatures, t_row_eff_s, table
            )
            if isinstance(fitted_c, Classification):
                return f, fitted_c
            kind = "bright" if d_best <= 0.5 else "dark"
            return f, Classification(
                None,
                0.0,
                (),
                f"stripe-too-short: {sig.id}'s {kind} stripe lasts {stripe:.2f} rows, under "
                f"{cfg.min_stripe_rows:g}: the resize can drop it, and the sub-row fit cannot tell "
                f"({fitted_c})",
            )
        if (
            math.isfinite(f.period_px)
            and math.isfinite(f.duty)
            and f.length_px >= 2.0 * p_best
            and (
                abs(f.period_px / p_best - 1.0) > cfg.max_period_mismatch
                or abs(f.duty - d_best) > cfg.max_duty_mismatch
            )
        ):
            # The edge template can fit a pattern that is not this signature's (an LED whose short stripes
            # the resize dropped, read as another): its period and duty must be the signature's too.
            return f, Classification(
                None,
                0.0,
                (),
                f"poor-fit: period {f.period_px:.2f} rows and duty {f.duty:.2f} measured, {sig.id}'s "
                f"{p_best:.2f} and {d_best:.2f}",
            )
        if f.length_px < cfg.min_profile_periods * p_best:
            return f, Classification(
                None,
                0.0,
                (),
                f"blob-too-short: {f.length_px} rows hold {f.length_px / p_best:.1f} periods of {sig.id} "
                f"({p_best:.1f} rows), {cfg.min_profile_periods:g} needed",
            )
        return f, c

    def _short_stripes(
        self,
        f: StripeFeatures,
        profile: FloatArray,
        first_row: int,
        background_dn: float,
        signatures: tuple[Signature, ...],
        t_row_eff_s: float,
        table: tuple[FloatArray, FloatArray],
    ) -> Classification | str:
        """An LED whose best signature draws a stripe under ``min_stripe_rows``, named by the sub-row fit
        against every signature (:func:`match_signatures`; log-likelihood -misfit / 2 s^2, s^2 the best
        fit's residual per row, at least ``fit_noise_floor``^2), or why not: the fit is off (``period_fit
        = "never"``), the profile is shorter than ``fit_min_periods`` of the signature's period, the best fit
        leaves a residual over ``max_fit_rms`` per row (the profile is not any signature's), or the
        posterior of the best is under ``fit_min_confidence``."""
        cfg = self.config
        if cfg.period_fit == "never":
            return "the sub-row fit is off"
        period, duty = table
        clock, exposure = self._clock(first_row, profile.size, t_row_eff_s)
        z = normalised_profile(profile, background_dn)
        if z is None:
            return "the profile cannot be normalised"
        if profile.size < cfg.fit_min_periods * float(period.max()):
            return f"{profile.size} rows, under {cfg.fit_min_periods:g} periods"
        costs = match_signatures(z, clock, period, duty, exposure)
        k = int(costs.argmin())
        rms = math.sqrt(float(costs[k]) / z.size)
        if rms > cfg.max_fit_rms:
            return f"best fit {signatures[k].id} leaves {rms:.2f} per row, over {cfg.max_fit_rms:g}"
        noise = max(float(costs[k]) / max(z.size - 3, 1), cfg.fit_noise_floor**2)
        ll = ((-0.5 / noise) * (costs - costs[k])).tolist()
        confidence = 1.0 / math.fsum(math.exp(v) for v in ll)
        if confidence < cfg.fit_min_confidence:
            return f"{signatures[k].id} at posterior {confidence:.2f}"
        return Classification(signatures[k].id, confidence, tuple(ll))

    def _features(
        self, image: ImageU8, leds: list[LedRequest], t_row_eff_s: float
    ) -> tuple[list[StripeFeatures], _EdgeBatch | None, list[int], list[tuple[FloatArray, int]]]:
        """The features of every LED, the edge batch of those with a profile long enough to decode, and
        which LEDs those are (in batch order)."""
        cfg = self.config
        nan = math.nan
        profiles: list[tuple[FloatArray, int]] = []
        members: list[int] = []
        samples: list[FloatArray] = []
        steps: list[float] = []
        backgrounds: list[float] = []
        for i, (centre_px, radius_px, background_dn, _) in enumerate(leds):
            profile, first_row = stripe_profile(image, centre_px, radius_px, cfg)
            profiles.append((profile, first_row))
            if profile.size >= 4:
                up, step = self._spline(profile)
                members.append(i)
                samples.append(up)
                steps.append(step)
                backgrounds.append(background_dn)
        batch = _lexw_edges_batch(samples, backgrounds, steps, cfg) if members else None
        out = [
            StripeFeatures(first_row, profile.size, (), (), (), (), nan, nan, nan, nan, None, 0.0)
            for profile, first_row in profiles
        ]
        if batch is not None:
            positions = batch.positions.tolist()
            rising = batch.rising.tolist()
            for j, i in enumerate(members):
                b0, b1 = batch.bounds[j], batch.bounds[j + 1]
                profile, first_row = profiles[i]
                out[i] = self._summarise(
                    profile, first_row, positions[b0:b1], rising[b0:b1], t_row_eff_s, leds[i][3]
                )
        return out, batch, members, profiles

    def _summarise(
        self,
        profile: FloatArray,
        first_row: int,
        at: list[float],
        rising: list[bool],
        t_row_eff_s: float,
        fft_check: bool,
    ) -> StripeFeatures:
        """Runs, period, duty, frequency and the FFT check of one profile from its edges (``at``: in the
        profile's samples)."""
        nan = math.nan
        lowest, highest, _, _ = cv2.minMaxLoc(profile)
        contrast = float(highest - lowest)
        edges = [e + first_row for e in at]
        # Interior runs: between consecutive edges; the runs before the first and after the last edge are
        # cut by the disk outline and say nothing about the period. (A dozen edges: plain floats.)
        bright: list[float] = []
        dark: list[float] = []
        for k in range(len(at) - 1):
            (bright if rising[k] else dark).append(at[k + 1] - at[k])
        # Period: the complete periods the runs make up, counted between edges of the same kind (from the
        # first to the last rising edge, and likewise falling): sum of spans / number of periods. This is
        # the mean of (bright + dark) over complete periods, each period counted once.
        span, periods = 0.0, 0
        for kind in (True, False):
            same = [k for k, r in enumerate(rising) if r is kind]
            if len(same) >= 2:
                span += at[same[-1]] - at[same[0]]
                periods += len(same) - 1
        if periods and bright:
            period = span / periods
            duty = min(sum(bright) / len(bright) / period, 1.0)
            frequency = 1.0 / (period * t_row_eff_s)
        else:
            period = duty = frequency = nan
        # The FFT cross-check, on the profile with its slow envelope (a lamp's fall-off) removed: divided by
        # its moving average over ~2 periods, a window that passes the stripe frequency untouched.
        p_fft, agrees = nan, None
        if fft_check:
            p_fft, agrees = self._fft_check(profile, period)
        return StripeFeatures(
            first_row,
            profile.size,
            tuple(edges),
            tuple(rising),
            tuple(bright),
            tuple(dark),
            period,
            frequency,
            duty,
            p_fft,
            agrees,
            contrast,
        )

    def _fft_check(self, profile: FloatArray, period: float) -> tuple[float, bool | None]:
        """The FFT period of the profile, with its slow envelope (a lamp's fall-off) divided out when it
        is long enough (its moving average over ~2 periods, a window that passes the stripe frequency
        untouched), and whether it agrees with the runs' period within 15 % (None when the profile is too
        short to tell)."""
        n = profile.size
        spectral_input = profile
        if math.isfinite(period) and 4.0 * period <= n:
            width = int(2.0 * period + 0.5) | 1
            local = cv2.blur(profile.reshape(-1, 1), (1, width), borderType=cv2.BORDER_REPLICATE).ravel()
            spectral_input = profile / np.maximum(local, 1.0)
        p_fft = self._spectral(spectral_input)
        if math.isfinite(p_fft) and math.isfinite(period) and n >= 2.5 * period:
            return p_fft, abs(p_fft - period) <= 0.15 * period
        return (p_fft if n >= 2.5 * p_fft else math.nan), None

    def _signature_table(
        self, signatures: tuple[Signature, ...], t_row_eff_s: float
    ) -> tuple[FloatArray, FloatArray]:
        """:func:`signature_table`, kept while the signatures and the row time stay the same."""
        key = (signatures, t_row_eff_s)
        if self._table is None or self._table_key != key:
            self._table_key = key
            self._table = signature_table(signatures, t_row_eff_s)
        return self._table

    def classify_many(
        self, features: list[StripeFeatures], signatures: tuple[Signature, ...], t_row_eff_s: float
    ) -> list[Classification]:
        """:meth:`classify` of several LEDs' features in one batch."""
        return classify_many(
            [np.asarray(f.edges_px, dtype=np.float64) - f.first_row for f in features],
            [np.asarray(f.rising, dtype=np.bool_) for f in features],
            [(0.0, float(f.length_px - 1)) for f in features],
            signatures,
            t_row_eff_s,
            self.config,
            self._signature_table(signatures, t_row_eff_s),
        )

    def classify(
        self, features: StripeFeatures, signatures: tuple[Signature, ...], t_row_eff_s: float
    ) -> Classification:
        edges = np.asarray(features.edges_px, dtype=np.float64) - features.first_row
        rising = np.asarray(features.rising, dtype=np.bool_)
        span = (0.0, float(features.length_px - 1))
        table = self._signature_table(signatures, t_row_eff_s)
        return classify(edges, rising, span, signatures, t_row_eff_s, self.config, table)
