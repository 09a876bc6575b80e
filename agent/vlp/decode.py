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

import math
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt
from scipy.interpolate import CubicSpline

from agent.vlp.model import Signature

FloatArray = npt.NDArray[np.float64]
ImageU8 = npt.NDArray[np.uint8]

__all__ = [
    "Classification",
    "DecoderConfig",
    "SpectralPeriod",
    "SplineInterpolator",
    "StripeDecoder",
    "StripeFeatures",
    "classify",
    "classify_many",
    "fft_period",
    "lexw_threshold",
    "signature_table",
    "stripe_edges",
    "stripe_profile",
]

MODES = ("row_mean", "middle_column")


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
    misfit counts as this much. ``min_confidence``: below it, a frame's id is left undecided."""

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

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got {self.mode!r}")
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
    log-likelihood of every signature (in the order given to :func:`classify`)."""

    id: str | None
    confidence: float
    log_likelihood: tuple[float, ...]


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
    lo_all, hi_all = float(smooth.min()), float(smooth.max())
    global_level = 0.5 * (max(lo_all, background_dn) + hi_all)
    # Local extrema: where the sign of the first difference changes (XOR of the binarised difference with
    # its shift), plus both ends.
    rising = smooth[1:] > smooth[:-1]
    turns = (rising[1:] != rising[:-1]).nonzero()[0] + 1
    ext = np.concatenate(([0], turns, [n - 1]))
    a, b = smooth[ext[:-1]], smooth[ext[1:]]
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
    levels = 0.5 * (lo + hi)
    good = edge.nonzero()[0]
    if good.size == 0:
        window_level = np.full(edge.size, global_level)
    else:
        # Each non-edge window takes the level of the edge window before it (the first ones: the first).
        source = np.maximum.accumulate(np.where(edge, np.arange(edge.size), -1))
        source[source < 0] = good[0]
        window_level = levels[source]
    lengths = ext[1:] - ext[:-1]
    lengths[-1] += 1
    thresholds = np.repeat(window_level, lengths)
    return samples > thresholds, thresholds


def stripe_edges(
    samples: FloatArray, binary: npt.NDArray[np.bool_], thresholds: FloatArray, step: float
) -> tuple[FloatArray, npt.NDArray[np.bool_]]:
    """Edge positions (in original samples, fractional) and whether each is rising (dark -> bright)."""
    change = (binary[1:] != binary[:-1]).nonzero()[0]
    if change.size == 0:
        return np.empty(0), np.empty(0, dtype=np.bool_)
    s0, s1 = samples[change], samples[change + 1]
    frac = (thresholds[change] - s0) / np.where(s1 != s0, s1 - s0, 1.0)
    positions: FloatArray = (change + np.minimum(np.maximum(frac, 0.0), 1.0)) * step
    return positions, binary[change + 1]


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
        return Classification(None, 0.0, ())
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
    chosen = signatures[best].id if (confidence >= config.min_confidence and misfit_ok) else None
    return Classification(chosen, confidence if misfit_ok else 0.0, tuple(loglik.tolist()))


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
        period, duty = table
        inv_p = 1.0 / period
        cap2 = config.edge_cap_px**2
        counts = np.array([edges_px[i].size for i in batch])
        starts = np.concatenate(([0], np.cumsum(counts)[:-1]))
        seg = np.repeat(np.arange(len(batch)), counts)
        edges = np.concatenate([edges_px[i] for i in batch])
        up = np.concatenate([rising[i] for i in batch])
        lo = np.array([spans_px[i][0] for i in batch]) + config.end_margin_px
        hi = np.array([spans_px[i][1] for i in batch]) - config.end_margin_px
        phase = edges[None, :] * inv_p[:, None] - np.where(up, 0.0, duty[:, None])
        angle = (2.0 * math.pi) * phase
        phi = np.arctan2(
            np.add.reduceat(np.sin(angle), starts, axis=1), np.add.reduceat(np.cos(angle), starts, axis=1)
        ) * (0.5 / math.pi)
        resid = (np.mod(phase - phi[:, seg] + 0.5, 1.0) - 0.5) * period[:, None]
        sq = resid * resid
        misfit = np.add.reduceat(np.minimum(sq, cap2), starts, axis=1)
        inside = (edges >= lo[seg] - config.edge_cap_px) & (edges <= hi[seg] + config.edge_cap_px)
        matched = (sq <= cap2) & inside
        matched_r = np.add.reduceat(matched & up, starts, axis=1)
        matched_f = np.add.reduceat(matched, starts, axis=1) - matched_r
        lo_c = lo[None, :] * inv_p[:, None] - phi
        hi_c = hi[None, :] * inv_p[:, None] - phi
        pred_r = np.floor(hi_c) - np.ceil(lo_c) + 1.0
        pred_f = np.floor(hi_c - duty[:, None]) - np.ceil(lo_c - duty[:, None]) + 1.0
        missing = np.maximum(pred_r - matched_r, 0.0) + np.maximum(pred_f - matched_f, 0.0)
        chi2 = (misfit + missing * cap2) * (1.0 / config.edge_sigma_px**2)
        loglik = -0.5 * chi2
        best = loglik.argmax(axis=0)
        cols = np.arange(len(batch))
        confidence = 1.0 / np.exp(loglik - loglik[best, cols]).sum(axis=0)
        best_chi2 = chi2[best, cols]
        rows = loglik.T.tolist()
        for j, i in enumerate(batch):
            n_edges = int(counts[j])
            ok = n_edges >= 2 and float(best_chi2[j]) <= config.max_misfit_per_edge**2 * n_edges
            conf = float(confidence[j])
            chosen = signatures[int(best[j])].id if (conf >= config.min_confidence and ok) else None
            out[i] = Classification(chosen, conf if ok else 0.0, tuple(rows[j]))
    return [c if c is not None else Classification(None, 0.0, ()) for c in out]


class StripeDecoder:
    """Profile -> spline -> LEXW -> edges, runs, period, frequency, duty, FFT check -> classification.

    Keeps the spline operators between frames (hence a class); otherwise stateless.
    """

    def __init__(self, config: DecoderConfig = DecoderConfig()) -> None:
        self.config = config
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
        cfg = self.config
        profile, first_row = stripe_profile(image, centre_px, radius_px, cfg)
        n = profile.size
        nan = math.nan
        if n < 4:
            return StripeFeatures(first_row, n, (), (), (), (), nan, nan, nan, nan, None, 0.0)
        samples, step = self._spline(profile)
        binary, thresholds = lexw_threshold(samples, background_dn, cfg, smoothed=True)
        edge_arr, rising_arr = stripe_edges(samples, binary, thresholds, step)
        contrast = float(profile.max() - profile.min())
        edges = (edge_arr + first_row).tolist()
        rising = rising_arr.tolist()
        # Interior runs: between consecutive edges; the runs before the first and after the last edge are
        # cut by the disk outline and say nothing about the period.
        runs = edge_arr[1:] - edge_arr[:-1]
        starts_bright = rising_arr[:-1]
        bright = runs[starts_bright].tolist()
        dark = runs[~starts_bright].tolist()
        # Period: the complete periods the runs make up, counted between edges of the same kind (from the
        # first to the last rising edge, and likewise falling): sum of spans / number of periods. This is
        # the mean of (bright + dark) over complete periods, each period counted once.
        span, periods = 0.0, 0
        for same in (rising_arr.nonzero()[0], (~rising_arr).nonzero()[0]):
            if same.size >= 2:
                span += float(edge_arr[same[-1]] - edge_arr[same[0]])
                periods += same.size - 1
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
            n,
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

    def classify_many(
        self, features: list[StripeFeatures], signatures: tuple[Signature, ...], t_row_eff_s: float
    ) -> list[Classification]:
        """:meth:`classify` of several LEDs' features in one batch."""
        key = (signatures, t_row_eff_s)
        if self._table_key != key:
            self._table_key = key
            self._table = signature_table(signatures, t_row_eff_s)
        return classify_many(
            [np.asarray(f.edges_px, dtype=np.float64) - f.first_row for f in features],
            [np.asarray(f.rising, dtype=np.bool_) for f in features],
            [(0.0, float(f.length_px - 1)) for f in features],
            signatures,
            t_row_eff_s,
            self.config,
            self._table,
        )

    def classify(
        self, features: StripeFeatures, signatures: tuple[Signature, ...], t_row_eff_s: float
    ) -> Classification:
        edges = np.asarray(features.edges_px, dtype=np.float64) - features.first_row
        rising = np.asarray(features.rising, dtype=np.bool_)
        span = (0.0, float(features.length_px - 1))
        key = (signatures, t_row_eff_s)
        if self._table_key != key:
            self._table_key = key
            self._table = signature_table(signatures, t_row_eff_s)
        return classify(edges, rising, span, signatures, t_row_eff_s, self.config, self._table)
