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

import itertools
import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

__all__ = [
    "LedRay",
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
    ``max_hypotheses``: cap on id-to-LED assignments tried when ids repeat."""

    map_sigma_m: float = 0.003
    height_sigma_m: float = 0.05
    outlier_sigmas: float = 6.0
    max_iterations: int = 12
    max_hypotheses: int = 256
    pair_tolerance: float = 0.08
    pair_tolerance_m: float = 0.08
    prior_gate_sigmas: float = 4.0
    ambiguity_m: float = 0.15


@dataclass(frozen=True, slots=True)
class PoseSolution:
    """The lens pose (x, y, level yaw) at mid-readout, its 3x3 covariance, the height correction, which map
    LED each ray was matched to (-1: not used), and per-ray residuals in sigmas."""

    x_m: float
    y_m: float
    yaw_rad: float
    height_offset_m: float
    covariance: FloatArray
    assignment: tuple[int, ...]
    residual_sigmas: tuple[float, ...]
    rms_residual: float
    dropped: int


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
    vx, vy, omega = velocity
    n = q.shape[0]
    free_h = height_sigma_m > 0.0
    n_par = 4 if free_h else 3
    p = np.array(initial, dtype=np.float64)
    if not free_h:
        p[3] = 0.0
    lx, ly, lz = leds_xyz[:, 0], leds_xyz[:, 1], leds_xyz[:, 2]
    w = 1.0 / sigma
    jac = np.zeros((2 * n + (1 if free_h else 0), n_par))
    res = np.zeros(jac.shape[0])
    for _ in range(max_iterations):
        psi = p[2] + omega * dt_s
        c, s = np.cos(psi), np.sin(psi)
        dx = lx - (p[0] + vx * dt_s)
        dy = ly - (p[1] + vy * dt_s)
        h = lz - lens_z_m + p[3]
        inv_h = 1.0 / h
        # Predicted q = R(-psi)(L - c) / h; R(-psi) = [[c, s], [-s, c]].
        px = (c * dx + s * dy) * inv_h
        py = (-s * dx + c * dy) * inv_h
        res[0 : 2 * n : 2] = (q[:, 0] - px) * w
        res[1 : 2 * n : 2] = (q[:, 1] - py) * w
        # d q / d (x, y, psi, dh): -R(-psi)/h, (py, -px), -q/h.
        jac[0 : 2 * n : 2, 0] = -c * inv_h * w
        jac[0 : 2 * n : 2, 1] = -s * inv_h * w
        jac[0 : 2 * n : 2, 2] = py * w
        jac[1 : 2 * n : 2, 0] = s * inv_h * w
        jac[1 : 2 * n : 2, 1] = -c * inv_h * w
        jac[1 : 2 * n : 2, 2] = -px * w
        if free_h:
            jac[0 : 2 * n : 2, 3] = -px * inv_h * w
            jac[1 : 2 * n : 2, 3] = -py * inv_h * w
            res[-1] = -p[3] / height_sigma_m
            jac[-1, 3] = 1.0 / height_sigma_m
        normal = jac.T @ jac
        step = np.linalg.solve(normal, jac.T @ res)
        p[:n_par] += step
        # Gauss-Newton converges quadratically here (small residuals): after a step below 50 um and 50 urad
        # what is left is of the order of its square, nanometres. From the closed-form start (a few mm off)
        # that is two iterations.
        if abs(step[0]) + abs(step[1]) < 5e-5 and abs(step[2]) < 5e-5:
            break
    # The covariance at the solution: (J^T W J)^-1 (J barely moves in the last, tiny step).
    covariance: FloatArray = np.linalg.inv(normal)
    whitened: FloatArray = res[: 2 * n].reshape(n, 2)
    return p, covariance, whitened


def single_led_position(
    q: tuple[float, float], led_xyz: tuple[float, float, float], lens_z_m: float, yaw_rad: float
) -> tuple[float, float]:
    """One LED and a known yaw: c = L - h R(psi) q (the single-LED solver of the SLO-VLP system)."""
    h = led_xyz[2] - lens_z_m
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    return led_xyz[0] - h * (c * q[0] - s * q[1]), led_xyz[1] - h * (s * q[0] + c * q[1])


def _weights(
    rays: list[LedRay], leds: list[int], xyz: FloatArray, lens_z_m: float, map_sigma_m: float
) -> FloatArray:
    """Per-ray sigma in q units: image noise plus the survey error seen from the lens, sigma_map / h."""
    out = np.empty(len(rays))
    for k, (ray, idx) in enumerate(zip(rays, leds, strict=True)):
        h = max(float(xyz[idx, 2]) - lens_z_m, 1e-3)
        out[k] = math.hypot(ray.sigma, map_sigma_m / h)
    return out


def _hypotheses(
    rays: list[LedRay],
    xyz: FloatArray,
    lens_z_m: float,
    prior: tuple[float, float, float, float, float] | None,
    config: SolverConfig,
) -> list[tuple[int, ...]]:
    """Assignments of rays to map LEDs worth solving: gated by the prior (each candidate must be near where
    the prior pose says its ray points) and by pairwise distances (|q_i h_i - q_j h_j| = |L_i - L_j|)."""
    options: list[list[int]] = []
    for ray in rays:
        cands = list(ray.candidates)
        if prior is not None and len(cands) > 1:
            px, py, pyaw, sxy, syaw = prior
            c, s = math.cos(pyaw), math.sin(pyaw)
            kept = []
            for idx in cands:
                h = float(xyz[idx, 2]) - lens_z_m
                # Where the ray says the LED is, seen from the prior pose: c + h R(psi) q.
                ex = px + h * (c * ray.q[0] - s * ray.q[1]) - float(xyz[idx, 0])
                ey = py + h * (s * ray.q[0] + c * ray.q[1]) - float(xyz[idx, 1])
                reach = h * math.hypot(*ray.q)
                gate = config.prior_gate_sigmas * math.hypot(sxy, syaw * reach) + 0.05
                if math.hypot(ex, ey) <= gate:
                    kept.append(idx)
            cands = kept
        options.append(cands)
    if any(not o for o in options):
        return []
    count = 1
    for o in options:
        count *= len(o)
    out: list[tuple[int, ...]] = []
    for combo in itertools.product(*options):
        if len(set(combo)) < len(combo):
            continue
        if count > 1 and not _pairs_consistent(rays, combo, xyz, lens_z_m, config):
            continue
        out.append(combo)
        if len(out) >= config.max_hypotheses:
            break
    return out


def _pairs_consistent(
    rays: list[LedRay], combo: tuple[int, ...], xyz: FloatArray, lens_z_m: float, config: SolverConfig
) -> bool:
    for i in range(len(rays)):
        hi = float(xyz[combo[i], 2]) - lens_z_m
        for j in range(i + 1, len(rays)):
            hj = float(xyz[combo[j], 2]) - lens_z_m
            seen = math.hypot(rays[i].q[0] * hi - rays[j].q[0] * hj, rays[i].q[1] * hi - rays[j].q[1] * hj)
            true = math.hypot(xyz[combo[i], 0] - xyz[combo[j], 0], xyz[combo[i], 1] - xyz[combo[j], 1])
            if abs(seen - true) > config.pair_tolerance * true + config.pair_tolerance_m:
                return False
    return True


def _initial(
    rays: list[LedRay], combo: tuple[int, ...], xyz: FloatArray, lens_z_m: float
) -> tuple[float, float, float, float]:
    """The 2-LED closed form on the pair farthest apart in the image (the best conditioned)."""
    best, pair = -1.0, (0, 1)
    for i in range(len(rays)):
        for j in range(i + 1, len(rays)):
            d = math.hypot(rays[i].q[0] - rays[j].q[0], rays[i].q[1] - rays[j].q[1])
            if d > best:
                best, pair = d, (i, j)
    i, j = pair
    x, y, yaw, height = two_led_closed_form(
        rays[i].q, rays[j].q, (xyz[combo[i], 0], xyz[combo[i], 1]), (xyz[combo[j], 0], xyz[combo[j], 1])
    )
    surveyed_h = 0.5 * (xyz[combo[i], 2] + xyz[combo[j], 2]) - lens_z_m
    return x, y, yaw, height - surveyed_h


def solve_pose(
    rays: list[LedRay],
    xyz: FloatArray,
    lens_z_m: float,
    *,
    velocity: tuple[float, float, float] = (0.0, 0.0, 0.0),
    prior: tuple[float, float, float, float, float] | None = None,
    config: SolverConfig = SolverConfig(),
) -> PoseSolution | str:
    """The pose from two or more rays, or the reason there is none.

    ``prior`` is (x, y, yaw, sigma_xy, sigma_yaw) of the *lens*: it gates which map LED a repeated id is,
    and breaks ties between assignments that fit equally well; it does not pull the fix itself.
    """
    if len(rays) < 2:
        return "fewer than two identified LEDs"
    hypotheses = _hypotheses(rays, xyz, lens_z_m, prior, config)
    if not hypotheses:
        return "no placement of the seen LED ids fits the map" + (" near the pose prior" if prior else "")
    scored: list[tuple[float, PoseSolution]] = []
    for combo in hypotheses:
        solution = _solve_assignment(rays, list(combo), xyz, lens_z_m, velocity, config)
        if solution is None:
            continue
        # chi^2 of the rays used, plus a dropped ray's worth (the outlier threshold squared) for each ray an
        # assignment had to leave out: explaining every LED beats explaining all but one exactly.
        cost = solution.rms_residual**2 * max(2 * (len(rays) - solution.dropped), 1)
        cost += solution.dropped * config.outlier_sigmas**2
        if prior is not None:
            px, py, pyaw, sxy, syaw = prior
            cost += ((solution.x_m - px) ** 2 + (solution.y_m - py) ** 2) / sxy**2
            cost += _wrap(solution.yaw_rad - pyaw) ** 2 / syaw**2
        scored.append((cost, solution))
    if not scored:
        return "the pose solver did not converge"
    scored.sort(key=lambda t: t[0])
    best_cost, best = scored[0]
    if prior is None and len(scored) > 1:
        for cost, other in scored[1:]:
            far = math.hypot(other.x_m - best.x_m, other.y_m - best.y_m) > config.ambiguity_m
            if far and cost < best_cost + 9.0:
                return f"ambiguous: {len(scored)} placements of the seen LED ids fit; a pose prior is needed"
    return best


def _solve_assignment(
    rays: list[LedRay],
    combo: list[int],
    xyz: FloatArray,
    lens_z_m: float,
    velocity: tuple[float, float, float],
    config: SolverConfig,
) -> PoseSolution | None:
    active = list(range(len(rays)))
    dropped = 0
    while True:
        sub = [rays[k] for k in active]
        idx = [combo[k] for k in active]
        try:
            init = _initial(sub, tuple(idx), xyz, lens_z_m)
        except ValueError:
            return None
        q = np.array([r.q for r in sub], dtype=np.float64)
        sigma = _weights(sub, idx, xyz, lens_z_m, config.map_sigma_m)
        dt = np.array([r.dt_s for r in sub], dtype=np.float64)
        try:
            p, cov, whitened = gauss_newton_pose(
                q,
                xyz[idx],
                sigma,
                dt,
                lens_z_m,
                init,
                velocity=velocity,
                height_sigma_m=config.height_sigma_m,
                max_iterations=config.max_iterations,
            )
        except np.linalg.LinAlgError:
            return None
        if not np.all(np.isfinite(p)):
            return None
        norms = np.hypot(whitened[:, 0], whitened[:, 1])
        worst = int(np.argmax(norms))
        if len(active) >= 3 and norms[worst] > config.outlier_sigmas:
            del active[worst]
            dropped += 1
            continue
        dof = max(2 * len(active) - cov.shape[0] + (1 if config.height_sigma_m > 0 else 0), 0)
        chi2 = float(np.sum(whitened**2))
        # With redundancy, inflate the covariance when the residuals say the noise is larger than modelled.
        scale = max(1.0, chi2 / dof) if dof > 0 else 1.0
        assignment = [-1] * len(rays)
        residuals = [math.nan] * len(rays)
        for k, a in enumerate(active):
            assignment[a] = combo[a]
            residuals[a] = float(norms[k])
        return PoseSolution(
            float(p[0]),
            float(p[1]),
            _wrap(float(p[2])),
            float(p[3]),
            cov[:3, :3] * scale,
            tuple(assignment),
            tuple(residuals),
            math.sqrt(chi2 / max(2 * len(active), 1)),
            dropped,
        )
