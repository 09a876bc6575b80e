"""Summary statistics of a stream in constant memory, for a process that runs for weeks.

:class:`StreamStats` keeps the exact count, sum, mean, minimum and maximum of every value it was given, and
its percentiles from a fixed histogram of logarithmic bins: a percentile is the middle of the bin that holds
it, within ``resolution`` (default 0.5 %) of the nearest-rank percentile of all the values given, for any
value between ``low`` and ``high``. Values below ``low`` count in one bin reported as ``low`` (for errors
and latencies, "0 to low"), values from ``high`` up in one reported as the exact maximum. The memory is the
bins, set at construction (about 1,600 counters for the defaults), however many values come.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["StreamStats"]


class StreamStats:
    """Count, mean, min, max exact; percentiles from log bins (relative ``resolution``). Not thread-safe."""

    def __init__(self, low: float = 1e-4, high: float = 1e3, resolution: float = 0.005) -> None:
        if not (0 < low < high) or not (0 < resolution < 1):
            raise ValueError(f"need 0 < low < high and 0 < resolution < 1, got {low}, {high}, {resolution}")
        self.low = low
        self.high = high
        # Bin i holds [low * r^(i-1), low * r^i) for i >= 1 with r = (1 + res) / (1 - res): the middle of
        # its edges is within res of every value in it. Bin 0: below low; the last bin: from high up.
        self._log_ratio = math.log((1 + resolution) / (1 - resolution))
        self._nbins = math.ceil(math.log(high / low) / self._log_ratio) + 2
        self._bins = np.zeros(self._nbins, dtype=np.int64)
        self.count = 0
        self.total = 0.0
        self.min = math.inf
        self.max = -math.inf

    def add(self, value: float) -> None:
        if math.isnan(value):
            return
        self.count += 1
        self.total += value
        self.min = min(self.min, value)
        self.max = max(self.max, value)
        self._bins[self._bin(value)] += 1

    def _bin(self, value: float) -> int:
        if value < self.low:
            return 0
        i = int(math.log(value / self.low) / self._log_ratio) + 1
        return min(i, self._nbins - 1)

    @property
    def mean(self) -> float:
        return self.total / self.count if self.count else math.nan

    def count_at_most(self, limit: float) -> int:
        """How many values were <= ``limit``, to the bin holding ``limit`` (exact when ``limit`` is a bin's
        lower edge; callers that need an exact count keep it themselves)."""
        return int(self._bins[: self._bin(limit) + 1].sum())

    def percentiles(self, *qs: float) -> list[float]:
        """The nearest-rank percentiles ``qs`` (0..100), NaN for each when nothing was added."""
        if not self.count:
            return [math.nan for _ in qs]
        cumulative = np.cumsum(self._bins)
        out = []
        for q in qs:
            rank = max(1, math.ceil(q / 100.0 * self.count))
            i = int(np.searchsorted(cumulative, rank))
            out.append(self._value(i))
        return out

    def _value(self, i: int) -> float:
        if i == 0:
            return min(self.low, self.max)
        if i == self._nbins - 1:
            return self.max
        lower = self.low * math.exp((i - 1) * self._log_ratio)
        middle = 0.5 * lower * (1.0 + math.exp(self._log_ratio))
        return min(max(middle, self.min), self.max)
