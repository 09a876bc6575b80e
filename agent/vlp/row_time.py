"""The camera's row time from LEDs of known frequency: period_rows x t_row_eff = 1 / f.

Pure functions (numpy in, numbers out). Each sighting of an LED whose driver frequency f is known and whose
stripe period P was measured (output rows, below the row: ``agent.vlp.decode.fit_period``) gives one
estimate t_row = 1 / (f P a), a the sensor rows per output row. The estimate combines them robustly: the
median, sightings further than ``reject_sigmas`` robust deviations (1.4826 MAD) from it rejected, then the
mean of the rest. Its uncertainty is the larger of the sightings' standard error and the spread of the
per-LED means over the number of LEDs (sightings of one LED from one place share its blob's errors, so they
are not independent of each other). An LED whose own median (over all its sightings, rejected ones too)
stands apart says its frequency in the map is not the one its driver blinks at (``led_deviation``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from agent.vlp.model import Signature

__all__ = ["RowTimeEstimate", "estimate_row_time", "match_signature"]


@dataclass(frozen=True, slots=True)
class RowTimeEstimate:
    """``t_row_s`` with its standard uncertainty ``sigma_s``; ``used`` / ``rejected`` sightings; per LED id
    the median row time of all its sightings and how many (``per_led``)."""

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
    median = float(np.median(t))
    mad = 1.4826 * float(np.median(np.abs(t - median)))
    keep = np.abs(t - median) <= reject_sigmas * max(mad, 1e-5 * median)
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
    per_led: dict[str, tuple[float, int]] = {}
    for led in dict.fromkeys(ids):
        values = t[[j for j, i in enumerate(ids) if i == led]]
        per_led[led] = (float(np.median(values)), int(values.size))
    return RowTimeEstimate(mean, se, int(n), int(p.size - n), per_led)
