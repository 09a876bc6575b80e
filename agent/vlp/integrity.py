"""Integrity of a VLP fix: the chi-square consistency test and the protection level.

A fix is a weighted least-squares solution over p = (x, y, psi, dh) from m = 2n + 1 whitened measurements
(two per LED ray, one for the prior on the common LED-height correction dh), so with the noise as modelled
its residual sum of squares (every term it fitted, dh's penalty included) is chi-square with
dof = m - 4 = 2n - 3 degrees of freedom. The test flags a fix whose chi^2 exceeds the (1 - p_fa) quantile.

The protection level bounds the position error a fault could cause without the test seeing it (the RAIM
slope method, e.g. Brown & Chin 1997, in whitened units): with J the whitened Jacobian (m x 4),
S = (J^T J)^-1 J^T the estimator and P = I - J S the residual projector, a fault f on the two measurements of
LED i moves the position by e = S_xy,i f and the test statistic by f^T P_ii f, so the largest position error
per unit of sqrt(chi^2) is

    slope_i = sqrt(lambda_max(S_xy,i P_ii^-1 S_xy,i^T))

(for the height prior's single row, |S_xy,h| / sqrt(P_hh)). A fault the test misses with probability p_md
has a non-centrality of at most about (sqrt(T) + k_md)^2, T the test's threshold, hence

    PL = max(k_ff sigma_major, max_i slope_i (sqrt(T) + k_md))

k_ff covering the fault-free error in the worst direction. With two LEDs a fault across them is absorbed by
the yaw and position (P_ii is singular): nothing can be ruled out, PL is infinite.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

from scipy.stats import chi2 as chi2_distribution
from scipy.stats import norm

__all__ = ["ProtectionInputs", "chi2_threshold", "protection_level"]

# A 2x2 block of the residual projector whose determinant is below this share of its trace squared: the
# LED's fault is (nearly) unobservable.
_SINGULAR = 1e-9


@functools.lru_cache(maxsize=256)
def chi2_threshold(dof: int, false_alarm: float) -> float:
    """T with P(chi^2_dof > T) = ``false_alarm`` (inf without redundancy)."""
    if dof <= 0:
        return math.inf
    return float(chi2_distribution.isf(false_alarm, dof))


@functools.lru_cache(maxsize=16)
def _one_sided_k(probability: float) -> float:
    """k with P(N(0, 1) > k) = ``probability``."""
    return float(norm.isf(probability))


Row = tuple[float, float, float, float]
# Per used LED its two whitened Jacobian rows over (x, y, psi, dh), and (J^T J)^-1 (4 x 4).
Linearisation = tuple[list[tuple[Row, Row]], list[list[float]]]


def protection_level(
    rows: list[tuple[Row, Row]],
    inverse: list[list[float]],
    height_weight: float,
    *,
    threshold: float,
    variance_scale: float,
    missed_detection: float,
    fault_free_risk: float,
) -> float:
    """PL in metres of a fix: ``rows`` are each LED's two whitened Jacobian rows over (x, y, psi, dh)
    (``solve._jacobian_rows``), ``inverse`` (J^T J)^-1 (4 x 4, the height prior's row included),
    ``height_weight`` 1 / height_sigma (0: dh held fixed, its row and column the identity's);
    ``variance_scale`` the factor by which the fix's covariance was inflated (chi^2 / dof when above 1).

    Plain floats (a handful of LEDs: numpy would cost more per call than the arithmetic). Per LED,
    H = (J^T J)^-1 J_i^T (4 x 2); then S_xy,i is H's first two rows and P_ii = I - J_i H."""
    if len(rows) < 3 or not math.isfinite(threshold):
        return math.inf
    slope_sq = 0.0
    (i00, i01, i02, i03), (_, i11, i12, i13), (_, _, i22, i23), (_, _, _, i33) = inverse
    for (a0, a1, a2, a3), (b0, b1, b2, b3) in rows:
        # H = (J^T J)^-1 J_i^T, written out (the inverse is symmetric).
        h00 = i00 * a0 + i01 * a1 + i02 * a2 + i03 * a3
        h01 = i01 * a0 + i11 * a1 + i12 * a2 + i13 * a3
        h02 = i02 * a0 + i12 * a1 + i22 * a2 + i23 * a3
        h03 = i03 * a0 + i13 * a1 + i23 * a2 + i33 * a3
        h10 = i00 * b0 + i01 * b1 + i02 * b2 + i03 * b3
        h11 = i01 * b0 + i11 * b1 + i12 * b2 + i13 * b3
        h12 = i02 * b0 + i12 * b1 + i22 * b2 + i23 * b3
        h13 = i03 * b0 + i13 * b1 + i23 * b2 + i33 * b3
        p00 = 1.0 - (a0 * h00 + a1 * h01 + a2 * h02 + a3 * h03)
        p01 = -(a0 * h10 + a1 * h11 + a2 * h12 + a3 * h13)
        p11 = 1.0 - (b0 * h10 + b1 * h11 + b2 * h12 + b3 * h13)
        det = p00 * p11 - p01 * p01
        if det <= _SINGULAR * (p00 + p11) ** 2:
            return math.inf
        s00, s01, s10, s11 = h00, h10, h01, h11
        # M = S P^-1 S^T, P^-1 = [[p11, -p01], [-p01, p00]] / det; its larger eigenvalue.
        u00, u01 = (s00 * p11 - s01 * p01) / det, (s01 * p00 - s00 * p01) / det
        u10, u11 = (s10 * p11 - s11 * p01) / det, (s11 * p00 - s10 * p01) / det
        m00 = u00 * s00 + u01 * s01
        m01 = u00 * s10 + u01 * s11
        m11 = u10 * s10 + u11 * s11
        slope_sq = max(slope_sq, 0.5 * (m00 + m11) + math.sqrt(0.25 * (m00 - m11) ** 2 + m01 * m01))
    if height_weight > 0.0:
        # The height prior's row (0, 0, 0, w): H = w (J^T J)^-1 e_dh.
        p_h = 1.0 - height_weight * height_weight * inverse[3][3]
        s_h = height_weight * height_weight * (inverse[0][3] ** 2 + inverse[1][3] ** 2)
        slope_sq = max(slope_sq, s_h / p_h if p_h > _SINGULAR else math.inf)
    a, b, d = inverse[0][0], inverse[0][1], inverse[1][1]
    sigma_major = math.sqrt(max(0.5 * (a + d) + math.sqrt(0.25 * (a - d) ** 2 + b * b), 0.0) * variance_scale)
    slope = math.sqrt(slope_sq * variance_scale)
    k_ff = _one_sided_k(0.5 * fault_free_risk)
    k_md = _one_sided_k(missed_detection)
    return max(k_ff * sigma_major, slope * (math.sqrt(threshold) + k_md))


@dataclass(frozen=True, slots=True)
class ProtectionInputs:
    """What a fix's protection level is computed from (:func:`protection_level`): kept with the fix so that
    only a consumer that reads the level pays for it (~25 us for four LEDs, a few percent of a frame).
    ``margin_m`` is added to it (the lens-to-base offset times the yaw's error bound)."""

    rows: list[tuple[Row, Row]] = field(repr=False, compare=False)
    inverse: list[list[float]] = field(repr=False, compare=False)
    height_weight: float
    threshold: float
    variance_scale: float
    missed_detection: float
    fault_free_risk: float
    margin_m: float = 0.0

    @property
    def protection_level_m(self) -> float:
        return self.margin_m + protection_level(
            self.rows,
            self.inverse,
            self.height_weight,
            threshold=self.threshold,
            variance_scale=self.variance_scale,
            missed_detection=self.missed_detection,
            fault_free_risk=self.fault_free_risk,
        )

    def with_margin(self, margin_m: float) -> ProtectionInputs:
        return ProtectionInputs(
            self.rows,
            self.inverse,
            self.height_weight,
            self.threshold,
            self.variance_scale,
            self.missed_detection,
            self.fault_free_risk,
            margin_m,
        )
