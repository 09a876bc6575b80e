"""The camera's row time from LEDs of known frequency: period_rows x t_row_eff = 1 / f.

Pure functions (numpy in, numbers out). Each sighting of an LED whose driver frequency f is known and whose
stripe period P was measured (output rows, below the row: ``agent.vlp.decode.fit_period``) gives one
estimate t_row = 1 / (f P a), a the sensor rows per output row. The estimate combines them robustly: the
median, sightings further than ``reject_sigmas`` robust deviations (1.4826 MAD) from it rejected, then the
mean of the rest. Its uncertainty is the larger of the sightings' standard error and the spread of the
per-LED means over the number of LEDs (sightings of one LED from one place share its blob's errors, so they
are not independent of each other). An LED whose own row time (over all its sightings, rejected ones too:
the mean of those within ``reject_sigmas`` robust deviations of its own median) stands apart says its
frequency in the map is not the one its driver blinks at (``led_deviation``). Its mean, not its median: an
LED of few stripe periods across its disk reads its periods with a skewed spread (Environment 1's L1, 3.4
periods of 8 px over 28 px: sightings 2.6 % below to 1.9 % above the estimate, their median 0.40-0.84 %
below it where their mean is 0.1-0.2 % below), and a median then stands apart from a right frequency.

Which signature a sighting is (``recognise_signatures``) is decided for all sightings together: a row-time
error scales every frequency read by the same factor, so the factor is searched (within the largest error
allowed for) that puts the most sightings on some signature; each sighting is then the signature nearest its
frequency read divided by that factor. One sighting alone cannot tell 2000 Hz read 3 % high from 2100 Hz
read 2 % low, but the set can: a factor that moves each LED onto its neighbour's signature leaves the LED at
the end of the range on none. When two factors far apart explain the sightings about as well (only LEDs of
evenly spaced signatures in the middle of the range in view), there is no answer, and the reason says so.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from agent.vlp.model import Signature

__all__ = ["RowTimeEstimate", "ScaleMatch", "estimate_row_time", "match_signature", "recognise_signatures"]


@dataclass(frozen=True, slots=True)
class RowTimeEstimate:
    """``t_row_s`` with its standard uncertainty ``sigma_s``; ``used`` / ``rejected`` sightings; per LED id
    its own row time (the robust mean of all its sightings) and how many sightings (``per_led``)."""

    t_row_s: float
    sigma_s: float
    used: int
    rejected: int
    per_led: dict[str, tuple[float, int]]

    @property
    def relative_sigma(self) -> float:
        return self.sigma_s / self.t_row_s

    def led_deviation(self) -> dict[str, float]:
        """Each LED's mean row time relative to the estimate, minus one."""
        return {k: v / self.t_row_s - 1.0 for k, (v, _) in self.per_led.items()}


def match_signature(
    period_rows: float,
    duty: float,
    signatures: Sequence[Signature],
    t_row_eff_s: float,
    max_error: float = 0.05,
    max_duty_error: float = 0.15,
) -> Signature | None:
    """The signature a stripe period belongs to when the row time may be off by up to ``max_error``: the
    one signature (with the duty within ``max_duty_error``) whose frequency lies within that error of the
    measured one; None when none does, or several do (a row-time error could then swap them: 3000 and
    3100 Hz are 3.3 % apart, so with the row time 3 % off an LED at 3000 Hz reads 3090 Hz)."""
    if not (math.isfinite(period_rows) and period_rows > 0):
        return None
    measured = 1.0 / (period_rows * t_row_eff_s)
    band = math.log1p(max_error)
    near = [
        s
        for s in signatures
        if abs(math.log(measured / s.frequency_hz)) <= band
        and (not math.isfinite(duty) or abs(duty - s.duty) <= max_duty_error)
    ]
    return near[0] if len(near) == 1 else None


@dataclass(frozen=True, slots=True)
class ScaleMatch:
    """What :func:`recognise_signatures` found: the factor every frequency was read off by (read / true,
    ~ true row time / stated row time), each sighting's signature (None: none near once the factor is
    taken out, or its period unknown), and the cost of the best other factor against this one's (the
    margin; ``inf`` without a rival)."""

    factor: float
    signatures: tuple[Signature | None, ...]
    cost: float
    rival_factor: float
    rival_cost: float

    @property
    def recognised(self) -> int:
        return sum(s is not None for s in self.signatures)


def recognise_signatures(
    periods_rows: Sequence[float],
    duties: Sequence[float],
    signatures: Sequence[Signature],
    t_row_eff_s: float,
    max_error: float = 0.05,
    sigma: float = 0.015,
    max_duty_error: float = 0.15,
    min_margin: float = 25.0,
) -> ScaleMatch | str:
    """Each sighting's signature when the row time may be off by up to ``max_error`` (a fraction): the
    common factor s (|log s| <= log(1 + max_error)) minimising sum_i min(min_k (log f_i - log s -
    log f_k)^2 / sigma^2, 9) over the signatures k whose duty is within ``max_duty_error`` of the sighting's
    (``sigma``: one sighting's relative frequency error; a sighting 3 sigma from every signature costs 9
    whatever it is), searched on a grid of sigma / 8 and refined. A rival factor (the lowest cost among the
    factors more than 3 sigma from the best) within ``min_margin`` of the best's cost makes it ambiguous:
    the reason (a string) is returned. Each sighting is then the signature within 3 sigma of its corrected
    frequency (the nearest), else None."""
    if not (0.0 < max_error < 0.5 and sigma > 0.0 and t_row_eff_s > 0.0):
        raise ValueError("need 0 < max_error < 0.5, sigma > 0 and t_row_eff_s > 0")
    if len(periods_rows) != len(duties):
        raise ValueError("need as many duties as periods")
    if not signatures:
        return "no signatures to recognise"
    p = np.asarray(periods_rows, dtype=np.float64)
    d = np.asarray(duties, dtype=np.float64)
    ok = np.isfinite(p) & (p > 0.0)
    if not ok.any():
        return "no sighting with a measured period"
    log_f = np.full(p.shape, np.nan)
    log_f[ok] = -np.log(p[ok] * t_row_eff_s)
    log_sig = np.log(np.array([s.frequency_hz for s in signatures], dtype=np.float64))
    sig_duty = np.array([s.duty for s in signatures], dtype=np.float64)
    # Sightings x signatures: the log-ratio read / signature (inf where the duty rules the signature out).
    duty_ok = ~np.isfinite(d)[:, None] | (np.abs(d[:, None] - sig_duty[None, :]) <= max_duty_error)
    ratio = np.where(duty_ok, log_f[:, None] - log_sig[None, :], np.inf)[ok]
    cap = 9.0
    band = math.log1p(max_error)

    def cost(u: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        r = np.min(np.abs(ratio[None, :, :] - u[:, None, None]), axis=2) / sigma
        total: npt.NDArray[np.float64] = np.minimum(r * r, cap).sum(axis=1)
        return total

    grid = np.arange(-band, band + 1e-12, sigma / 8.0)
    costs = cost(grid)
    best = int(np.argmin(costs))
    fine = grid[best] + np.linspace(-sigma / 8.0, sigma / 8.0, 33)
    fine_costs = cost(fine)
    u_best = float(fine[int(np.argmin(fine_costs))])
    c_best = float(fine_costs.min())
    far = np.abs(grid - u_best) > 3.0 * sigma
    rival_u, rival_c = math.nan, math.inf
    if far.any():
        k = int(np.argmin(np.where(far, costs, np.inf)))
        rival_u, rival_c = float(grid[k]), float(costs[k])
    if rival_c < c_best + min_margin:
        return (
            f"the frequencies read fit the map's signatures about as well with the row time "
            f"{100.0 * math.expm1(u_best):+.1f} % and {100.0 * math.expm1(rival_u):+.1f} % off (cost "
            f"{c_best:.1f} against {rival_c:.1f}): LEDs of evenly spaced signatures, none at the end of "
            "their range, are in view; take frames where more LEDs, or others, are in view"
        )
    found: list[Signature | None] = [None] * p.size
    residual = np.abs(ratio - u_best)
    for row, i in enumerate(np.flatnonzero(ok).tolist()):
        k = int(np.argmin(residual[row]))
        if residual[row, k] <= 3.0 * sigma:
            found[i] = signatures[k]
    return ScaleMatch(math.exp(u_best), tuple(found), c_best, math.exp(rival_u), rival_c)


def estimate_row_time(
    periods_rows: Sequence[float],
    frequencies_hz: Sequence[float],
    ids: Sequence[str],
    sensor_rows_per_row: float,
    reject_sigmas: float = 4.0,
) -> RowTimeEstimate:
    """The row time from sightings (see the module docstring). Raises ValueError without sightings."""
    p = np.asarray(periods_rows, dtype=np.float64)
    f = np.asarray(frequencies_hz, dtype=np.float64)
    if p.size == 0 or p.size != f.size or p.size != len(ids):
        raise ValueError("need as many periods, frequencies and ids, at least one")
    t = 1.0 / (f * p * sensor_rows_per_row)
    keep = _near_median(t, reject_sigmas)
    kept = t[keep]
    mean = float(kept.mean())
    n = kept.size
    se = float(kept.std(ddof=1)) / math.sqrt(n) if n > 1 else math.inf
    kept_ids = [i for i, k in zip(ids, keep.tolist(), strict=True) if k]
    kept_means = [
        float(kept[[j for j, i in enumerate(kept_ids) if i == led]].mean()) for led in dict.fromkeys(kept_ids)
    ]
    if len(kept_means) > 1:
        se = max(se, float(np.std(kept_means, ddof=1)) / math.sqrt(len(kept_means)))
    # Per LED over all its sightings (the rejected too): an LED whose frequency in the map is wrong shows.
    # The mean of those near its own median (a misread is not its row time), not the median itself.
    per_led: dict[str, tuple[float, int]] = {}
    for led in dict.fromkeys(ids):
        values = t[[j for j, i in enumerate(ids) if i == led]]
        per_led[led] = (float(values[_near_median(values, reject_sigmas)].mean()), int(values.size))
    return RowTimeEstimate(mean, se, int(n), int(p.size - n), per_led)


def _near_median(values: npt.NDArray[np.float64], reject_sigmas: float) -> npt.NDArray[np.bool_]:
    """Which ``values`` lie within ``reject_sigmas`` robust deviations (1.4826 MAD, at least 1e-5 of the
    median) of their median: the sightings the estimate keeps, and those an LED's own row time averages."""
    median = float(np.median(values))
    mad = 1.4826 * float(np.median(np.abs(values - median)))
    near: npt.NDArray[np.bool_] = np.abs(values - median) <= reject_sigmas * max(mad, 1e-5 * median)
    return near
