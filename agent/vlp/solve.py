"""Pose from LED rays: the exact 2-LED closed form, N-LED Gauss-Newton, data association by the pose prior.

Every observation is a *level-plane coordinate* q = d / h (``agent.vlp.geometry``): the LED's horizontal
offset d from the lens, in the camera's level yaw frame, over its height h above the lens. The model
(``reference/vlp.md`` §1.5, the renderer's convention) is

    q_i = R(-psi_i) (L_i - c_i) / h_i,   c_i = c + v dt_i,   psi_i = psi + omega dt_i,
    h_i = Z_i - z_lens + dh

with c, psi the lens position and level yaw at the frame's mid-readout time, dt_i the time of the row that
LED i was exposed in relative to it (the rolling shutter), v and omega the known motion, and dh one common
correction to the surveyed LED heights (with a prior, so two LEDs still give a solution).
"""

from __future__ import annotations

import bisect
import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from agent.vlp.integrity import Linearisation, ProtectionInputs, Row, chi2_threshold
from agent.vlp.model import NO_WORK, AssociationWork

FloatArray = npt.NDArray[np.float64]

# A Cholesky pivot at or below this fraction of its diagonal entry: the normal matrix is singular to working
# precision (the pose is not determined by the rays, e.g. one LED without the height held fixed).
_PIVOT_EPS = 1e-13

__all__ = [
    "LedRay",
    "NoSolution",
    "PoseSolution",
    "SolverConfig",
    "gauss_newton_pose",
    "single_led_position",
    "solve_pose",
    "two_led_closed_form",
]


@dataclass(frozen=True, slots=True)
class LedRay:
    """One LED as the solver sees it: level-plane coordinates ``q`` with standard deviation ``sigma`` (per
    component), the map LEDs it may be (several when ids repeat), and its row time from mid-readout."""

    q: tuple[float, float]
    candidates: tuple[int, ...]
    sigma: float
    dt_s: float = 0.0


@dataclass(frozen=True, slots=True)
class SolverConfig:
    """``map_sigma_m``: survey uncertainty of each LED (per axis), added to the image noise in the weights.
    ``height_sigma_m``: prior on the common LED-height correction (0 disables that unknown).
    ``outlier_sigmas``: a ray whose residual exceeds this many sigmas is dropped (with >= 3 rays).
    ``max_hypotheses``: cap on id-to-LED assignments solved by Gauss-Newton when ids repeat (or a misread id
    breaks the map's distances); ``max_association_checks``: cap on the candidate tests that find them (each
    a few float operations: 6000 is a few milliseconds), whatever the map. ``pair_tolerance`` (relative) and
    ``pair_tolerance_m``: how far a seen LED-to-LED distance may be from the map's (the LED height is only
    known to a few centimetres until the fix solves for it). ``false_alarm``: probability that the chi-square
    test flags a fault-free fix; ``missed_detection`` and ``fault_free_risk``: the risks the protection level
    is computed for (``agent.vlp.integrity``)."""

    map_sigma_m: float = 0.003
    height_sigma_m: float = 0.05
    outlier_sigmas: float = 6.0
    max_iterations: int = 12
    max_hypotheses: int = 16
    max_association_checks: int = 6000
    pair_tolerance: float = 0.08
    pair_tolerance_m: float = 0.08
    prior_gate_sigmas: float = 4.0
    ambiguity_m: float = 0.15
    false_alarm: float = 1e-3
    missed_detection: float = 1e-3
    fault_free_risk: float = 1e-3


@dataclass(frozen=True, slots=True)
class PoseSolution:
    """The lens pose (x, y, level yaw) at mid-readout, its 3x3 covariance, the height correction, which map
    LED each ray was matched to (-1: not used), and per-ray residuals in sigmas.

    Integrity (``agent.vlp.integrity``): ``chi2`` sums every whitened term of the fit (the height
    correction's prior included) over ``dof`` degrees of freedom; ``chi2_threshold`` is the test's limit at
    the configured false-alarm rate (``consistent`` when chi2 is within it); ``protection_level_m`` bounds
    the lens position error a single-LED fault could cause unseen (inf with two LEDs);
    ``alternatives``: other placements, far from this one, that fit about as well given the prior;
    ``prior_ignored``: no placement fitted near the prior, this one is the map's alone.
    ``rms_residual`` is sqrt(chi2 / 2n). ``linearisation``: the used rays' whitened Jacobian rows and
    (J^T J)^-1 at the solution; ``protection``: what the protection level is computed from."""

    x_m: float
    y_m: float
    yaw_rad: float
    height_offset_m: float
    covariance: FloatArray
    assignment: tuple[int, ...]
    residual_sigmas: tuple[float, ...]
    rms_residual: float
    dropped: int
    chi2: float = math.nan
    dof: int = 0
    variance_scale: float = 1.0
    chi2_threshold: float = math.inf
    alternatives: int = 0
    prior_ignored: bool = False
    work: AssociationWork = NO_WORK
    linearisation: Linearisation | None = field(default=None, repr=False, compare=False)
    protection: ProtectionInputs | None = None

    @property
    def protection_level_m(self) -> float:
        """The protection level (computed on reading; inf with fewer than three LEDs)."""
        return self.protection.protection_level_m if self.protection is not None else math.inf

    @property
    def consistent(self) -> bool:
        return not self.chi2 > self.chi2_threshold


def _wrap(a: float) -> float:
    return math.atan2(math.sin(a), math.cos(a))


def two_led_closed_form(
    q1: tuple[float, float], q2: tuple[float, float], p1: tuple[float, float], p2: tuple[float, float]
) -> tuple[float, float, float, float]:
    """The reference 2-LED solver (``positioningCalculation.cpp::VLPbyLED``, reference/vlp.md §1.5), in
    level-plane coordinates q = ((u - cx) s / f, (v - cy) s / f) / 1, so H comes out directly.

    Returns (x, y, yaw, H): lens position, camera yaw (theta - pi) and the LED-plane height above the lens.
    Exact for a level camera under two LEDs at one height.
    """
    (x1, y1), (x2, y2) = p1, p2
    (u1, v1), (u2, v2) = q1, q2
    # 1. Order the pair so that X1 < X2 (Y1 < Y2 when X1 = X2). Map bearing alpha.
    if x1 > x2 or (x1 == x2 and y1 > y2):
        (x1, y1, u1, v1), (x2, y2, u2, v2) = (x2, y2, u2, v2), (x1, y1, u1, v1)
    if x1 == x2:
        alpha = math.pi / 2
    elif y1 == y2:
        alpha = 0.0
    else:
        alpha = math.atan((y2 - y1) / (x2 - x1))
    # 2. Image bearing beta (v down, as the image).
    beta = math.pi / 2 if u1 == u2 else math.atan((v2 - v1) / (u2 - u1))
    # 3. The two-fold ambiguity of atan: theta = alpha - beta if u2 <= u1, else pi + alpha - beta.
    theta = alpha - beta if u2 <= u1 else math.pi + alpha - beta
    # 4. Scale: H = f D12 / d12; in level-plane units d12 is |q1 - q2|.
    d12 = math.hypot(u1 - u2, v1 - v2)
    big_d12 = math.hypot(x1 - x2, y1 - y2)
    if d12 <= 0.0:
        raise ValueError("the two LEDs are imaged at the same point")
    height = big_d12 / d12
    # 5. Offset of the LED midpoint: Xr = (u_mid - cx) s H / f, Yr alike.
    xr, yr = 0.5 * (u1 + u2) * height, 0.5 * (v1 + v2) * height
    # 6. [x; y] = R(theta) [Xr; Yr] + midpoint; the yaw is theta - pi.
    c, s = math.cos(theta), math.sin(theta)
    x = c * xr - s * yr + 0.5 * (x1 + x2)
    y = s * xr + c * yr + 0.5 * (y1 + y2)
    return x, y, _wrap(theta - math.pi), height


def gauss_newton_pose(
    q: FloatArray,
    leds_xyz: FloatArray,
    sigma: FloatArray,
    dt_s: FloatArray,
    lens_z_m: float,
    initial: tuple[float, float, float, float],
    *,
    velocity: tuple[float, float, float] = (0.0, 0.0, 0.0),
    height_sigma_m: float = 0.05,
    max_iterations: int = 12,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Least squares over p = (x, y, psi, dh) of sum_i |q_i - R(-psi_i)(L_i - c_i) / h_i|^2 / sigma_i^2
    (+ dh^2 / height_sigma^2; dh is held at 0 when height_sigma_m is 0).

    Returns (p, covariance of p (4x4, or 3x3 without dh), whitened residuals (n, 2)).
    """
    q_list = np.asarray(q, dtype=np.float64).reshape(-1, 2).tolist()
    xyz_list = np.asarray(leds_xyz, dtype=np.float64).reshape(-1, 3).tolist()
    p, cov, res, _ = _gauss_newton(
        [(a, b) for a, b in q_list],
        [(a, b, c) for a, b, c in xyz_list],
        np.asarray(sigma, dtype=np.float64).ravel().tolist(),
        np.asarray(dt_s, dtype=np.float64).ravel().tolist(),
        lens_z_m,
        initial,
        velocity,
        height_sigma_m,
        max_iterations,
    )
    whitened: FloatArray = np.array(res, dtype=np.float64).reshape(-1, 2)
    return np.array(p, dtype=np.float64), np.array(cov, dtype=np.float64), whitened


def _gauss_newton(
    q: list[tuple[float, float]],
    leds: list[tuple[float, float, float]],
    sigma: list[float],
    dt_s: list[float],
    lens_z_m: float,
    initial: tuple[float, float, float, float],
    velocity: tuple[float, float, float],
    height_sigma_m: float,
    max_iterations: int,
) -> tuple[tuple[float, float, float, float], list[list[float]], list[tuple[float, float]], Linearisation]:
    """:func:`gauss_newton_pose` on plain floats: (p, covariance, whitened residuals per ray, and the
    whitened Jacobian rows per ray with (J^T J)^-1 over all four unknowns at the last linearisation: what
    the protection level needs).

    Ray i gives two whitened residuals r = (q_i - qhat_i) / sigma_i, qhat = R(-psi_i)(L_i - c_i) / h_i, and
    with a = cos(psi_i) / (h_i sigma_i), b = sin(psi_i) / (h_i sigma_i) its two Jacobian rows over
    (x, y, psi, dh) are

        (-a, -b,  qhat_y / sigma, -qhat_x / (h sigma))
        ( b, -a, -qhat_x / sigma, -qhat_y / (h sigma))

    so the normal equations J^T J and J^T r are sums of a few products per ray, accumulated directly (no
    Jacobian matrix), plus the dh prior's row (0, 0, 0, 1 / height_sigma) with residual -dh / height_sigma.
    They are solved by Cholesky; the covariance is (J^T J)^-1 at the last linearisation.
    """
    vx, vy, omega = velocity
    free_h = height_sigma_m > 0.0
    x, y, psi, dh = (float(v) for v in initial)
    if not free_h:
        dh = 0.0
    rays = [
        (lx, ly, lz - lens_z_m, dt, qx, qy, 1.0 / sg)
        for (qx, qy), (lx, ly, lz), sg, dt in zip(q, leds, sigma, dt_s, strict=True)
    ]
    inv_hs = 1.0 / height_sigma_m if free_h else 0.0
    low = (1.0, 0.0, 0.0, 1.0, 0.0, 0.0, 1.0, 1.0)
    residuals: list[tuple[float, float]] = []
    rows: list[tuple[Row, Row]] = []
    # The protection level needs the Jacobian rows only with three rays or more (with two it is inf).
    keep_rows = len(rays) >= 3
    for _ in range(max_iterations):
        a00 = a02 = a03 = a12 = a13 = a22 = a23 = a33 = 0.0
        b0 = b1 = b2 = b3 = 0.0
        residuals = []
        rows = []
        for lx, ly, hz, dt, qx, qy, w in rays:
            ps = psi + omega * dt
            c, s = math.cos(ps), math.sin(ps)
            dx = lx - (x + vx * dt)
            dy = ly - (y + vy * dt)
            inv_h = 1.0 / (hz + dh)
            # Predicted q = R(-psi)(L - c) / h; R(-psi) = [[c, s], [-s, c]].
            px = (c * dx + s * dy) * inv_h
            py = (-s * dx + c * dy) * inv_h
            r0 = (qx - px) * w
            r1 = (qy - py) * w
            ca, sb = c * inv_h * w, s * inv_h * w
            pxw, pyw = px * w, py * w
            pxh, pyh = pxw * inv_h, pyw * inv_h
            residuals.append((r0, r1))
            if keep_rows:
                rows.append(((-ca, -sb, pyw, -pxh), (sb, -ca, -pxw, -pyh)))
            a00 += ca * ca + sb * sb
            a02 -= ca * pyw + sb * pxw
            a03 += ca * pxh - sb * pyh
            a12 += ca * pxw - sb * pyw
            a13 += sb * pxh + ca * pyh
            a22 += pyw * pyw + pxw * pxw
            a23 += pxw * pyh - pyw * pxh
            a33 += pxh * pxh + pyh * pyh
            b0 += sb * r1 - ca * r0
            b1 -= sb * r0 + ca * r1
            b2 += pyw * r0 - pxw * r1
            b3 -= pxh * r0 + pyh * r1
        # The x-y cross term is -a b + b a = 0 for every ray, and the x and y diagonals are equal. Without
        # the height unknown its row and column are those of the identity (the step in it is then 0).
        if free_h:
            a33 += inv_hs * inv_hs
            b3 += inv_hs * (-dh * inv_hs)
        else:
            a03 = a13 = a23 = b3 = 0.0
            a33 = 1.0
        low = _pose_cholesky(a00, a02, a03, a12, a13, a22, a23, a33)
        s0, s1, s2, s3 = _pose_solve(low, b0, b1, b2, b3)
        x += s0
        y += s1
        psi += s2
        dh += s3
        # Gauss-Newton converges quadratically here (small residuals): after a step below 50 um and 50 urad
        # what is left is of the order of its square, nanometres. From the closed-form start (a few mm off)
        # that is two iterations.
        if abs(s0) + abs(s1) < 5e-5 and abs(s2) < 5e-5:
            break
    # The covariance at the solution: (J^T W J)^-1 (J barely moves in the last, tiny step).
    inverse = _pose_inverse(low)
    covariance = [row[:3] for row in inverse[:3]] if not free_h else inverse
    if not free_h:
        # dh held fixed: its Jacobian column is 0 (its row and column of the inverse the identity's).
        rows = [((a[0], a[1], a[2], 0.0), (b[0], b[1], b[2], 0.0)) for a, b in rows]
    return (x, y, psi, dh), covariance, residuals, (rows, inverse)


_PoseFactor = tuple[float, float, float, float, float, float, float, float]


def _pose_cholesky(
    a00: float, a02: float, a03: float, a12: float, a13: float, a22: float, a23: float, a33: float
) -> _PoseFactor:
    """Cholesky factor L (L L^T = A) of the pose's normal matrix

        A = [[a00, 0, a02, a03], [0, a00, a12, a13], [a02, a12, a22, a23], [a03, a13, a23, a33]]

    (x and y decouple: their cross term is 0 and their diagonals are equal), written out for plain floats
    (a LAPACK call costs many times the arithmetic). Returns (l00, l20, l30, l21, l31, l22, l32, l33); the
    other entries are l10 = 0 and l11 = l00. Raises ``np.linalg.LinAlgError`` when a pivot is not positive
    (relative to its diagonal entry): A is singular to working precision, as ``np.linalg.solve`` would
    report."""
    if not a00 > 0.0:
        raise np.linalg.LinAlgError("Singular matrix")
    l00 = math.sqrt(a00)
    l20, l30 = a02 / l00, a03 / l00
    l21, l31 = a12 / l00, a13 / l00
    p22 = a22 - l20 * l20 - l21 * l21
    if not p22 > _PIVOT_EPS * abs(a22):
        raise np.linalg.LinAlgError("Singular matrix")
    l22 = math.sqrt(p22)
    l32 = (a23 - l30 * l20 - l31 * l21) / l22
    p33 = a33 - l30 * l30 - l31 * l31 - l32 * l32
    if not p33 > _PIVOT_EPS * abs(a33):
        raise np.linalg.LinAlgError("Singular matrix")
    return l00, l20, l30, l21, l31, l22, l32, math.sqrt(p33)


def _pose_solve(
    low: _PoseFactor, b0: float, b1: float, b2: float, b3: float
) -> tuple[float, float, float, float]:
    """x with L L^T x = b (:func:`_pose_cholesky`): forward substitution L y = b, then back substitution
    L^T x = y."""
    l00, l20, l30, l21, l31, l22, l32, l33 = low
    y0 = b0 / l00
    y1 = b1 / l00
    y2 = (b2 - l20 * y0 - l21 * y1) / l22
    y3 = (b3 - l30 * y0 - l31 * y1 - l32 * y2) / l33
    x3 = y3 / l33
    x2 = (y2 - l32 * x3) / l22
    x1 = (y1 - l21 * x2 - l31 * x3) / l00
    x0 = (y0 - l20 * x2 - l30 * x3) / l00
    return x0, x1, x2, x3


def _pose_inverse(low: _PoseFactor) -> list[list[float]]:
    """A^-1 = M^T M with M = L^-1 (lower triangular, :func:`_pose_cholesky`'s L inverted column by
    column)."""
    l00, l20, l30, l21, l31, l22, l32, l33 = low
    m00 = m11 = 1.0 / l00
    m22 = 1.0 / l22
    m33 = 1.0 / l33
    m20 = -(l20 * m00) / l22
    m21 = -(l21 * m11) / l22
    m32 = -(l32 * m22) / l33
    m30 = -(l30 * m00 + l32 * m20) / l33
    m31 = -(l31 * m11 + l32 * m21) / l33
    i00 = m00 * m00 + m20 * m20 + m30 * m30
    i01 = m20 * m21 + m30 * m31
    i02 = m20 * m22 + m30 * m32
    i03 = m30 * m33
    i11 = m11 * m11 + m21 * m21 + m31 * m31
    i12 = m21 * m22 + m31 * m32
    i13 = m31 * m33
    i22 = m22 * m22 + m32 * m32
    i23 = m32 * m33
    i33 = m33 * m33
    return [[i00, i01, i02, i03], [i01, i11, i12, i13], [i02, i12, i22, i23], [i03, i13, i23, i33]]


def single_led_position(
    q: tuple[float, float], led_xyz: tuple[float, float, float], lens_z_m: float, yaw_rad: float
) -> tuple[float, float]:
    """One LED and a known yaw: c = L - h R(psi) q (the single-LED solver of the SLO-VLP system)."""
    h = led_xyz[2] - lens_z_m
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    return led_xyz[0] - h * (c * q[0] - s * q[1]), led_xyz[1] - h * (s * q[0] + c * q[1])


_Points = list[tuple[float, float, float]]


def _weights(
    rays: list[LedRay],
    leds: list[int],
    xyz: _Points,
    lens_z_m: float,
    map_sigma_m: float,
    led_sigmas_m: list[float] | None,
) -> list[float]:
    """Per-ray sigma in q units: image noise plus the LED's survey error seen from the lens, sigma_map / h
    (``led_sigmas_m[idx]`` when the map states each LED's, else ``map_sigma_m``)."""
    return [
        math.hypot(
            ray.sigma,
            (led_sigmas_m[idx] if led_sigmas_m is not None else map_sigma_m)
            / max(xyz[idx][2] - lens_z_m, 1e-3),
        )
        for ray, idx in zip(rays, leds, strict=True)
    ]


class _Budget:
    """The association's work counter: every candidate test adds to ``checks``; ``truncated`` once they pass
    ``limit`` (the search then stops where it is). ``solved``: assignments solved by Gauss-Newton."""

    __slots__ = ("checks", "limit", "solved", "truncated")

    def __init__(self, limit: int) -> None:
        self.checks = 0
        self.limit = limit
        self.solved = 0
        self.truncated = False

    def spend(self, n: int) -> bool:
        """Count ``n`` checks; False (and ``truncated`` set) when the budget is gone."""
        self.checks += n
        if self.checks > self.limit:
            self.truncated = True
            return False
        return True


def _gated_options(
    rays: list[LedRay],
    xyz: _Points,
    lens_z_m: float,
    prior: tuple[float, float, float, float, float] | None,
    config: SolverConfig,
    budget: _Budget,
) -> list[tuple[int, ...]]:
    """Each ray's candidate map LEDs near where the prior pose says the ray points (all of them without a
    prior, or when the ray's id is unique): |c + h R(psi) q - L| within ``prior_gate_sigmas`` of the prior's
    position and yaw uncertainty at that reach."""
    options: list[tuple[int, ...]] = []
    for ray in rays:
        cands = ray.candidates
        if prior is not None and len(cands) > 1:
            budget.spend(len(cands))
            px, py, pyaw, sxy, syaw = prior
            c, s = math.cos(pyaw), math.sin(pyaw)
            kept = []
            for idx in cands:
                lx, ly, lz = xyz[idx]
                h = lz - lens_z_m
                # Where the ray says the LED is, seen from the prior pose: c + h R(psi) q.
                ex = px + h * (c * ray.q[0] - s * ray.q[1]) - lx
                ey = py + h * (s * ray.q[0] + c * ray.q[1]) - ly
                reach = h * math.hypot(*ray.q)
                gate = config.prior_gate_sigmas * math.hypot(sxy, syaw * reach) + 0.05
                if math.hypot(ex, ey) <= gate:
                    kept.append(idx)
            cands = tuple(kept)
        options.append(cands)
    return options


def _hypotheses(
    rays: list[LedRay],
    xyz: _Points,
    lens_z_m: float,
    prior: tuple[float, float, float, float, float] | None,
    config: SolverConfig,
    budget: _Budget,
    search: bool,
) -> list[tuple[tuple[int, ...], _Initial | None]]:
    """Assignments of rays to map LEDs worth solving (-1: the ray is left out), at most
    ``config.max_hypotheses``, the search bounded by ``budget``.

    1. Gate each ray's candidates by the prior (:func:`_gated_options`).
    2. Unless ``search``: one candidate each, all different: that one assignment (the normal case; its fit
       is tested by the caller, who asks for the search when it fails).
    3. Otherwise anchor pairs, the rays farthest apart in the image first: every candidate pair of the two
       whose distance matches the map's (|q_a h_a - q_b h_b| = |L_a - L_b|) places the camera (the 2-LED
       closed form, which also gives the LED plane's height); every other ray is then matched to its
       candidate nearest to where that placement says it points, or left out when none is near. An anchor
       pair that leaves rays out (a misread id among them) is followed by the next pair, until a placement
       explains every ray, the pairs run out or the budget does. The work is O(K^2 + P n K) per anchor pair
       (K candidates a ray, P pairs at the right distance), not the K^n of trying every combination.
    4. Keep the placements that explain the most rays (at least two), nearest the prior first, else those
       whose predicted LEDs fell closest to the map's.
    """
    n = len(rays)
    options = _gated_options(rays, xyz, lens_z_m, prior, config, budget)
    if not search and all(len(o) == 1 for o in options):
        combo = tuple(o[0] for o in options)
        if len(set(combo)) == n:
            return [(combo, None)]
    # Each ray's candidates as (x, y, h, index), sorted by x: a placement's predicted LED is looked up by
    # bisection on x instead of against every candidate.
    tables: list[_Table] = []
    for o in options:
        rows = sorted((xyz[i][0], xyz[i][1], xyz[i][2] - lens_z_m, i) for i in o)
        tables.append(([r[0] for r in rows], rows))
    pairs = [(i, j) for i in range(n) for j in range(i + 1, n) if options[i] and options[j]]
    pairs.sort(key=lambda ij: -math.dist(rays[ij[0]].q, rays[ij[1]].q))
    found: dict[tuple[int, ...], tuple[int, float, _Initial]] = {}
    best_count = 0
    for a, b in pairs:
        if best_count == n or budget.truncated:
            break
        _anchor(rays, tables, a, b, prior, config, budget, found)
        best_count = max((v[0] for v in found.values()), default=0)
    if best_count < 2:
        return []
    # Placements that leave one or two rays out stay in the running (a misread or badly measured LED in
    # the right placement), their cost paying for each ray left out: keeping only the placements that
    # explain the most rays would let a periodic map's wrong placement, which happens to explain them
    # all, win unopposed.
    kept = sorted((v[1], k, v[2]) for k, v in found.items() if v[0] >= max(best_count - 2, 2))
    if prior is not None:
        # Ranked by the squared distance of the placement from the prior in its sigmas: one more than 25
        # behind the nearest cannot win (its solved fit is as good at best, the prior's term 5 sigma worse).
        kept = [h for h in kept if h[0] <= kept[0][0] + 25.0]
    elif len(kept) > _AMBIGUITY_SOLVES:
        # Without a prior, placements that explain every ray alike make the fix ambiguous: the few that fit
        # the map best show it (and a lone good one is among them); solving more would change nothing.
        kept = kept[:_AMBIGUITY_SOLVES]
    if len(kept) > config.max_hypotheses:
        budget.truncated = True
    return [(k, init) for _, k, init in kept[: config.max_hypotheses]]


# The work of the normal case: one assignment solved directly, no candidate tested.
_DIRECT_WORK = AssociationWork(0, 1, False)
# Without a prior, at most this many placements are solved (the best by the map's fit).
_AMBIGUITY_SOLVES = 4
_Row = tuple[float, float, float, int]
_Table = tuple[list[float], list[_Row]]
_Initial = tuple[float, float, float, float]


def _anchor(
    rays: list[LedRay],
    tables: list[_Table],
    a: int,
    b: int,
    prior: tuple[float, float, float, float, float] | None,
    config: SolverConfig,
    budget: _Budget,
    found: dict[tuple[int, ...], tuple[int, float, _Initial]],
) -> None:
    """Placements from the anchor rays a, b (:func:`_hypotheses` step 3), into ``found``: assignment ->
    (rays explained, rank: squared distance from the prior in its sigmas, or the predicted LEDs' summed
    misfit; the anchor's closed-form pose as the solver's start)."""
    qa, qb = rays[a].q, rays[b].q
    n = len(rays)
    tol_rel, tol_abs = config.pair_tolerance, config.pair_tolerance_m
    for xa, ya, ha, ca in tables[a][1]:
        for xb, yb, hb, cb in tables[b][1]:
            if not budget.spend(1):
                return
            if ca == cb:
                continue
            true = math.hypot(xa - xb, ya - yb)
            seen = math.hypot(qa[0] * ha - qb[0] * hb, qa[1] * ha - qb[1] * hb)
            if abs(seen - true) > tol_rel * true + tol_abs:
                continue
            try:
                x, y, yaw, height = two_led_closed_form(qa, qb, (xa, ya), (xb, yb))
            except ValueError:
                continue
            rank = 0.0
            if prior is not None:
                px, py, pyaw, sxy, syaw = prior
                dist, turn = math.hypot(x - px, y - py), abs(_wrap(yaw - pyaw))
                gate = config.prior_gate_sigmas
                if dist > gate * sxy + 0.05 or turn > gate * syaw + 0.05:
                    continue
                rank = (dist / sxy) ** 2 + (turn / syaw) ** 2
            dh = height - 0.5 * (ha + hb)
            c, s = math.cos(yaw), math.sin(yaw)
            combo = [-1] * n
            combo[a], combo[b] = ca, cb
            count, misfit = 2, 0.0
            mx, my = 0.5 * (xa + xb), 0.5 * (ya + yb)
            h_anchor = height
            for r in range(n):
                if r in (a, b):
                    continue
                xs, rows = tables[r]
                if not rows:
                    continue
                q0, q1 = rays[r].q
                # Where the placement says ray r's LED is, c + h R(psi) q, at the anchors' LED height (the
                # candidates' own heights differ by centimetres, inside the tolerance).
                ex, ey = x + h_anchor * (c * q0 - s * q1), y + h_anchor * (s * q0 + c * q1)
                tol = tol_rel * math.hypot(ex - mx, ey - my) + tol_abs
                lo, hi = bisect.bisect_left(xs, ex - tol), bisect.bisect_right(xs, ex + tol)
                if not budget.spend(max(hi - lo, 1)):
                    return
                best, best_d = -1, tol
                for lx, ly, lh, cand in rows[lo:hi]:
                    hr = lh + dh
                    d = math.hypot(x + hr * (c * q0 - s * q1) - lx, y + hr * (s * q0 + c * q1) - ly)
                    if d <= best_d and cand not in combo:
                        best, best_d = cand, d
                if best >= 0:
                    combo[r] = best
                    count += 1
                    misfit += best_d
            key = tuple(combo)
            if key not in found:
                found[key] = (count, rank if prior is not None else misfit, (x, y, yaw, dh))


def _initial(
    rays: list[LedRay], combo: tuple[int, ...] | list[int], xyz: _Points, lens_z_m: float
) -> tuple[float, float, float, float]:
    """The 2-LED closed form on the pair farthest apart in the image (the best conditioned)."""
    best, pair = -1.0, (0, 1)
    for i in range(len(rays)):
        for j in range(i + 1, len(rays)):
            d = math.hypot(rays[i].q[0] - rays[j].q[0], rays[i].q[1] - rays[j].q[1])
            if d > best:
                best, pair = d, (i, j)
    i, j = pair
    xi, yi, zi = xyz[combo[i]]
    xj, yj, zj = xyz[combo[j]]
    x, y, yaw, height = two_led_closed_form(rays[i].q, rays[j].q, (xi, yi), (xj, yj))
    surveyed_h = 0.5 * (zi + zj) - lens_z_m
    return x, y, yaw, height - surveyed_h


@dataclass(frozen=True, slots=True)
class NoSolution:
    """No pose from these rays: why (one short sentence), and what the association cost."""

    reason: str
    work: AssociationWork = NO_WORK


def solve_pose(
    rays: list[LedRay],
    xyz: FloatArray,
    lens_z_m: float,
    *,
    velocity: tuple[float, float, float] = (0.0, 0.0, 0.0),
    prior: tuple[float, float, float, float, float] | None = None,
    config: SolverConfig = SolverConfig(),
    map_sigmas_m: list[float] | None = None,
) -> PoseSolution | NoSolution:
    """The pose from two or more rays, or the reason there is none.

    ``map_sigmas_m``: each map LED's survey standard deviation (per axis), when the map states them
    (``LedMap.map_sigmas_m``); None: ``config.map_sigma_m`` for every LED. It weighs each ray, so the
    covariance, the chi-square test and the protection level all carry it.

    ``prior`` is (x, y, yaw, sigma_xy, sigma_yaw) of the *lens*: it gates which map LED a repeated id is,
    and breaks ties between assignments that fit equally well; it does not pull the fix itself. When no
    placement fits near the prior, the fix is made without it if the map alone allows only one placement.
    The association's work is bounded by ``config.max_association_checks`` candidate tests and
    ``config.max_hypotheses`` solves (:func:`_hypotheses`), whatever the map.
    """
    if len(rays) < 2:
        return NoSolution("fewer than two identified LEDs")
    # The map as plain floats: the solver's arithmetic is on a handful of numbers, where numpy costs more
    # per call than the work.
    points: _Points = [(a, b, c) for a, b, c in np.asarray(xyz, dtype=np.float64).reshape(-1, 3).tolist()]
    budget = _Budget(config.max_association_checks)
    if map_sigmas_m is not None and len(map_sigmas_m) != len(points):
        raise ValueError(f"{len(map_sigmas_m)} survey sigmas for a map of {len(points)} LEDs")
    result = _solve(rays, points, lens_z_m, velocity, prior, config, budget, map_sigmas_m)
    if (
        prior is not None
        and isinstance(result, NoSolution)
        and not budget.truncated
        and any(len(ray.candidates) > 1 for ray in rays)
    ):
        # The prior can be what is wrong (a pose carried on odometry through a camera stall, a robot carried
        # elsewhere): the map alone then decides, and only where the seen ids fit it in one place. It shares
        # what is left of the budget; the fix says it went against the prior.
        alone = _solve(rays, points, lens_z_m, velocity, None, config, budget, map_sigmas_m)
        if isinstance(alone, PoseSolution):
            result = dataclasses.replace(alone, prior_ignored=True)
        else:
            result = NoSolution(
                f"no placement of the seen LED ids fits the map near the pose prior ({alone.reason})"
            )
    work = AssociationWork(budget.checks, budget.solved, budget.truncated)
    if isinstance(result, NoSolution):
        if budget.truncated:
            return NoSolution(f"{result.reason} (association work budget exhausted)", work)
        return NoSolution(result.reason, work)
    if work == result.work:
        # The normal case (unique ids: one direct solve, no search) already says so.
        return result
    return dataclasses.replace(result, work=work)


def _solve(
    rays: list[LedRay],
    points: _Points,
    lens_z_m: float,
    velocity: tuple[float, float, float],
    prior: tuple[float, float, float, float, float] | None,
    config: SolverConfig,
    budget: _Budget,
    map_sigmas_m: list[float] | None,
) -> PoseSolution | NoSolution:
    """:func:`solve_pose` with or without the prior: associate, solve each assignment, pick the best.

    The one assignment of unique ids is solved first; only when its fit fails (an LED dropped, or chi^2
    past its limit: a misread id breaks the map's geometry) are the anchor pairs searched for a placement
    that leaves the misread LED out."""
    scored: list[tuple[float, float, PoseSolution]] = []
    solved: set[tuple[int, ...]] = set()
    for search in (False, True):
        hypotheses = _hypotheses(rays, points, lens_z_m, prior, config, budget, search)
        for combo, initial in hypotheses:
            if combo in solved:
                continue
            solved.add(combo)
            budget.solved += 1
            solution = _solve_assignment(
                rays, list(combo), points, lens_z_m, velocity, config, initial, map_sigmas_m
            )
            if solution is None:
                continue
            # chi^2 of the rays used, plus a dropped ray's worth (the outlier threshold squared) for each
            # ray an assignment had to leave out: explaining every LED beats explaining all but one exactly.
            cost = solution.chi2 + solution.dropped * config.outlier_sigmas**2
            prior_term = 0.0
            if prior is not None:
                px, py, pyaw, sxy, syaw = prior
                prior_term = ((solution.x_m - px) ** 2 + (solution.y_m - py) ** 2) / sxy**2
                prior_term += _wrap(solution.yaw_rad - pyaw) ** 2 / syaw**2
            scored.append((cost + prior_term, prior_term, solution))
        if search or len(hypotheses) != 1 or hypotheses[0][1] is not None:
            break
        # The direct assignment of unique ids: searched further only when its fit fails.
        fit = scored[0][2] if scored else None
        if fit is not None and fit.dropped == 0 and fit.consistent:
            break
    if not scored:
        if not solved:
            return NoSolution("no placement of the seen LED ids fits the map")
        return NoSolution("the pose solver did not converge")
    if len(scored) == 1:
        return scored[0][2]
    scored.sort(key=lambda t: t[0])
    best_cost, _, best = scored[0]
    # A rival: a placement far from the best that fits about as well, or that leaves no more LEDs out,
    # whose chi^2 is within the test's limit of the best's (the best may itself fit badly: a moving robot
    # before its velocity is known) and that the prior cannot rule out at the integrity risk (chi^2 of its
    # 3 dof). The chi^2 of two placements that both fit differ by noise: in a map whose ids repeat with a
    # period, only the prior tells them apart, and only when it is much tighter than the period.
    prior_limit = chi2_threshold(3, config.missed_detection)
    rivals = sum(
        1
        for cost, prior_term, other in scored[1:]
        if math.hypot(other.x_m - best.x_m, other.y_m - best.y_m) > config.ambiguity_m
        and (
            cost < best_cost + 9.0
            or (
                other.dropped <= best.dropped
                and other.chi2 <= best.chi2 + other.chi2_threshold
                and prior_term <= prior_limit
            )
        )
    )
    if rivals and prior is None:
        return NoSolution(
            f"ambiguous: {len(scored)} placements of the seen LED ids fit; a pose prior is needed"
        )
    return dataclasses.replace(best, alternatives=rivals) if rivals else best


def _protection(
    linearisation: Linearisation, variance_scale: float, config: SolverConfig, threshold: float
) -> ProtectionInputs | None:
    """What a solution's protection level is computed from (``agent.vlp.integrity``); None with fewer than
    three LEDs (a fault across two is absorbed by the pose; nothing can be ruled out)."""
    rows, inverse = linearisation
    if len(rows) < 3:
        return None
    return ProtectionInputs(
        rows,
        inverse,
        1.0 / config.height_sigma_m if config.height_sigma_m > 0.0 else 0.0,
        threshold,
        variance_scale,
        config.missed_detection,
        config.fault_free_risk,
    )


def _solve_assignment(
    rays: list[LedRay],
    combo: list[int],
    xyz: _Points,
    lens_z_m: float,
    velocity: tuple[float, float, float],
    config: SolverConfig,
    initial: _Initial | None = None,
    map_sigmas_m: list[float] | None = None,
) -> PoseSolution | None:
    """Gauss-Newton on one assignment (-1: ray left out), from ``initial`` (else the closed form on the rays
    farthest apart), dropping the worst ray while it is an outlier and three or more remain."""
    # Rays the association left out (-1) count as dropped from the start.
    active = [k for k in range(len(rays)) if combo[k] >= 0]
    dropped = len(rays) - len(active)
    if len(active) < 2:
        return None
    dropped_here = 0
    while True:
        sub = [rays[k] for k in active]
        idx = [combo[k] for k in active]
        try:
            init = initial if initial is not None and not dropped_here else _initial(sub, idx, xyz, lens_z_m)
        except ValueError:
            return None
        sigma = _weights(sub, idx, xyz, lens_z_m, config.map_sigma_m, map_sigmas_m)
        try:
            p, cov, whitened, linearisation = _gauss_newton(
                [r.q for r in sub],
                [xyz[i] for i in idx],
                sigma,
                [r.dt_s for r in sub],
                lens_z_m,
                init,
                velocity,
                config.height_sigma_m,
                config.max_iterations,
            )
        except np.linalg.LinAlgError:
            return None
        if not all(math.isfinite(v) for v in p):
            return None
        norms = [math.hypot(r0, r1) for r0, r1 in whitened]
        # The first of the largest, as argmax.
        worst = max(range(len(norms)), key=norms.__getitem__)
        if len(active) >= 3 and norms[worst] > config.outlier_sigmas:
            del active[worst]
            dropped += 1
            dropped_here += 1
            continue
        dof = max(2 * len(active) - len(cov) + (1 if config.height_sigma_m > 0 else 0), 0)
        # Every term the fit paid for: the rays' residuals and the height correction's prior (a misread id
        # on two LEDs is otherwise absorbed into dh at no visible cost).
        height_term = (p[3] / config.height_sigma_m) ** 2 if config.height_sigma_m > 0 else 0.0
        chi2 = math.fsum(r0 * r0 + r1 * r1 for r0, r1 in whitened) + height_term
        # With redundancy, inflate the covariance when the residuals say the noise is larger than modelled.
        scale = max(1.0, chi2 / dof) if dof > 0 else 1.0
        assignment = [-1] * len(rays)
        residuals = [math.nan] * len(rays)
        for k, a in enumerate(active):
            assignment[a] = combo[a]
            residuals[a] = norms[k]
        threshold = chi2_threshold(dof, config.false_alarm)
        return PoseSolution(
            p[0],
            p[1],
            _wrap(p[2]),
            p[3],
            np.array([row[:3] for row in cov[:3]], dtype=np.float64) * scale,
            tuple(assignment),
            tuple(residuals),
            math.sqrt(chi2 / max(2 * len(active), 1)),
            dropped,
            chi2,
            dof,
            scale,
            threshold,
            0,
            False,
            _DIRECT_WORK,
            linearisation,
            _protection(linearisation, scale, config, threshold),
        )
