"""GMapping's improved proposal (Grisetti, Stachniss, Burgard, IEEE T-RO 23(1), 2007, §IV), batched.

For each particle i with previous pose x_{t-1} and odometry increment u:

1. scan-match from the odometry prediction x_{t-1} ⊕ u to the mode x̂ of p(z_t | m, x);
2. evaluate tau(x_j) = p(z_t | m, x_j) p(x_j | x_{t-1}, u) on K points x_j around x̂: a 3x3x3 grid
   x̂ + diag(s) {-1, 0, 1}^3 whose steps s are the match's own standard deviations (the Laplace
   approximation Sigma_L = (J_ᵀJ / sigma^2 T' + Sigma_u⁻¹)⁻¹ from the Gauss-Newton information, clamped),
   so the interval the paper samples in is as wide as the posterior: a corridor gets a long grid, a
   well-constrained corner a tight one;
3. fit a Gaussian: eta = sum_j tau(x_j) prod(s), mu = (1/eta) sum_j x_j tau(x_j) prod(s),
   Sigma = (1/eta) sum_j tau(x_j) prod(s) (x_j - mu)(x_j - mu)ᵀ  (eqs. 18-20; prod(s) is the grid cell
   volume, which differs between particles), plus the grid's own variance s^2/12 per axis (Sheppard's
   correction);
4. draw x_t ~ N(mu, Sigma) and multiply the weight by eta (eq. 21).

A fixed grid (GMapping's llsamplerange / lasamplerange) wider than the posterior would add its own
spread to every update; drawn poses then jitter by the grid step, the map is built at jittered poses and
random-walks (on a synthetic room, a fixed 2 cm / 0.6 deg grid gave 6 cm trajectory error against 7 mm).

Where matching fails (too few endpoints near obstacles: an empty map, a featureless view) the particle
falls back to the motion model: x_t ~ p(x | x_{t-1}, u), and eta is the same grid sum taken around the
odometry prediction, so the two kinds of weight stay comparable; or (``ProposalConfig.failed_match_draw``
"grid") it is drawn from the Gaussian fitted on that grid, so that the pose drawn is the one eta judged.

GMapping's released code skips steps 2-4 (it keeps x̂ and weights it by the likelihood there); the paper's
form is used here because the sampled spread keeps particle diversity that the scan matcher would remove.
p(z | m, x) is tempered, log p / T, because neighbouring beams are not independent.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import numpy.typing as npt

from agent.slam.fix import PoseMeasurement
from agent.slam.grid import ScanPoints, surface_normals
from agent.slam.matcher import (
    DistanceField,
    MatcherConfig,
    MatchResult,
    Residuals,
    SearchConfig,
    correlative_search,
    linearized_log_likelihood,
    log_likelihood_quadratic,
    match,
    match_with_residuals,
    residuals,
    scan_log_likelihood,
    truncated_energy,
)
from agent.slam.motion import OdometryNoise, motion_log_density, sample_motion
from agent.slam.pose import between, compose, wrap_angle

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


@dataclass(frozen=True)
class ProposalConfig:
    sigma_hit_m: float = 0.05
    outlier_m: float = 0.25
    temperature: float = 40.0
    proposal_temperature: float = 1.0
    min_xy_step_m: float = 0.002
    max_xy_step_m: float = 0.1
    min_yaw_step_rad: float = 0.001
    max_yaw_step_rad: float = 0.05
    prior_weight: float = 1.0
    # Weight of an endpoint's offset along its surface in the residual (agent.slam.matcher.residuals):
    # 1 point to point (the default: it closes exp1's loop best), 0 point to line. docs/slam.md has the
    # measurements ("Scan matching").
    along_surface_weight: float = 1.0
    # The scan's surface normals (``grid.surface_normals``, used where along_surface_weight < 1): a point's
    # neighbourhood reaches max(0.25 m, normal_radius_per_m × its range), and it is a line when at most
    # normal_thickness_m thick. 0 / 0.015 (a fixed 0.25 m) by default and for every source in ``eval
    # slam`` (``eval_slam.NORMAL_RADIUS_PER_M``, ``NORMAL_THICKNESS_M``; docs/slam.md, "Scan matching").
    normal_radius_per_m: float = 0.0
    normal_thickness_m: float = 0.015
    matcher: MatcherConfig = field(default_factory=MatcherConfig)
    search: SearchConfig | None = field(default_factory=SearchConfig)
    # How eta (the weight) integrates p(z|m, x)^(1/T) p(x|x_{t-1}, u) where the match holds: "grid", the
    # sum over the proposal's grid (the default); "laplace", in closed form around the match
    # (:func:`laplace_log_eta`, which explains why the grid sum is biased). Opt-in: on exp1 it only helps
    # together with a higher proposal_temperature, which costs the simulated office (docs/slam.md, "Open
    # problems").
    eta_integral: Literal["grid", "laplace"] = "grid"
    # Where the correlative search runs: match every particle from the search's start and from the
    # prior's too, and keep the one of lower truncated energy (see ``improved_proposal``). On for radish
    # logs in ``eval slam``, where the search runs at nearly every update (docs/slam.md, "Scan matching").
    keep_better_start: bool = False
    # Where a particle's match fails: "motion", a draw from the motion model (the default), its weight
    # eta the grid sum around the odometry prediction wherever the draw lands; "grid", a draw from the
    # Gaussian fitted on that grid (its steps the motion model's deviations, clamped as the match's are),
    # the pose eta was taken for. "grid" for radish logs in ``eval slam``, whose 1 m updates give the
    # motion model ~13 deg of heading spread (Intel seed 2: a draw 33 deg off the scans won the resampling
    # with the prediction's weight and bent the rest of the map); exp1's loop (0.25 m updates) closed for
    # 2 seeds of 6 with it instead of 5 (docs/slam.md, "The filter").
    failed_match_draw: Literal["motion", "grid"] = "motion"
    # How much of the motion model's spread a drawn pose keeps in the directions the scan (and a fix, if
    # any) does not constrain, a corridor's length: the draw's deviation is scaled as if the motion prior
    # were this many times tighter there (:func:`degenerate_scaling`): by this factor where only the prior
    # holds the pose, by ~1 where the scan does. 1: off (the paper's draw, the default). ``eval slam``
    # sets 0.3 for the simulated robot (``eval_slam.log_proposal``; docs/slam.md, "Scan matching").
    degenerate_noise_scale: float = 1.0


def scan_normals(scan: ScanPoints, kept: IntArray, config: ProposalConfig) -> FloatArray:
    """The surface normals (robot frame) of ``scan``'s endpoints ``kept`` (indices into ``hit_xy``),
    their neighbourhoods as ``config`` says (``normal_radius_per_m``, ``normal_thickness_m``)."""
    return surface_normals(
        scan.hit_xy,
        kept,
        max_thickness_m=config.normal_thickness_m,
        radius_per_m=config.normal_radius_per_m,
        origin_xy=scan.origin_xy,
    )


@dataclass(frozen=True)
class ProposalResult:
    poses: FloatArray  # (P, 3) drawn poses
    log_eta: FloatArray  # (P,) log weight increments
    matched: npt.NDArray[np.bool_]  # (P,) scan matching trusted
    match: MatchResult
    residuals: Residuals  # the match's residuals at its poses (``match.poses``)


_UNIT_GRID = np.stack(
    [g.ravel() for g in np.meshgrid([-1.0, 0.0, 1.0], [-1.0, 0.0, 1.0], [-1.0, 0.0, 1.0], indexing="ij")],
    axis=1,
)


def improved_proposal(
    field: DistanceField,
    window_index: IntArray,
    points_xy: FloatArray,
    previous: FloatArray,
    increment: FloatArray,
    noise: OdometryNoise,
    config: ProposalConfig,
    rng: np.random.Generator,
    log_weights: FloatArray | None = None,
    normals_xy: FloatArray | None = None,
    measurement: PoseMeasurement | None = None,
) -> ProposalResult:
    """Draw one new pose per particle from the improved proposal; see the module docstring.

    ``measurement`` (absolute fixes carried to now, ``agent.slam.fix.fuse_fixes``) joins the proposal as
    a third factor: tau(x) = p(z|m, x) p(x|x_{t-1}, u) p(z_fix|x), in the match (a second Gaussian prior)
    and in the grid; eta then includes it. Weighting alone would not do: the proposal's spread is a few
    millimetres, so when the whole cloud has drifted from the fixes every particle is equally wrong and
    the weights cannot pull it back."""
    p = previous.shape[0]
    predicted = compose(previous, increment[None, :])
    # The motion prior in matcher units. The match is the mode of p(z|x)^(1/T') p(x|x', u) with T' the
    # proposal temperature: with log p(z|x) = -sum d^2 / (2 sigma^2), the Gaussian motion term
    # -1/2 eᵀ Σ⁻¹ e enters E = sum d^2 as sigma^2 T' eᵀ Σ⁻¹ e (Σ from the increment, in the robot frame,
    # rotated into the world frame of each particle). With the weight temperature instead, odometry
    # would outweigh the scan several times over and its errors would pass straight into the map.
    sig = noise.sigmas(increment)
    c, s = np.cos(predicted[:, 2]), np.sin(predicted[:, 2])
    rot = np.zeros((p, 3, 3))
    rot[:, 0, 0], rot[:, 0, 1], rot[:, 1, 0], rot[:, 1, 1], rot[:, 2, 2] = c, -s, s, c, 1.0
    local_info = np.diag(1.0 / sig**2)
    prior = (
        config.prior_weight
        * config.sigma_hit_m**2
        * config.proposal_temperature
        * np.einsum("pij,jk,plk->pil", rot, local_info, rot)
    )
    centre_prior = predicted
    matcher_prior = prior
    if measurement is not None:
        # Two Gaussian priors make one: Λ = Λ_u + Λ_z, centre Λ⁻¹ (Λ_u x_u + Λ_z z) (yaw taken near x_u).
        fix_info = config.sigma_hit_m**2 * config.proposal_temperature * measurement.information
        z = np.broadcast_to(measurement.mean, predicted.shape).copy()
        z[:, 2] = predicted[:, 2] + wrap_angle(z[:, 2] - predicted[:, 2])
        matcher_prior = prior + fix_info[None, :, :]
        rhs = np.einsum("pij,pj->pi", prior, predicted) + np.einsum("ij,pj->pi", fix_info, z)
        centre_prior = np.linalg.solve(matcher_prior + 1e-12 * np.eye(3)[None], rhs[..., None])[..., 0]
        centre_prior[:, 2] = wrap_angle(centre_prior[:, 2])
    start = centre_prior
    if config.search is not None:
        # One correlative search, for the most likely particle, against its map: the correction it finds
        # (mostly odometry heading error, the same for every particle) moves all starting poses, so
        # Gauss-Newton starts inside its basin even after a large odometry error.
        lead = int(np.argmax(log_weights)) if log_weights is not None else 0
        found, _ = correlative_search(
            field, int(window_index[lead]), points_xy, centre_prior[lead], config.search, matcher_prior[lead]
        )
        start = compose(centre_prior, between(centre_prior[lead], found)[None, :])
    if config.search is not None and config.keep_better_start:
        # Each particle matched from both starts, the search's and the prior's; it keeps the match of
        # lower truncated energy (the matcher's own objective, prior included). The search scores the
        # lead alone on a coarse lattice, and where the scans overlap little (Intel's 1 m updates, 20-40 %
        # of the endpoints on mapped walls) its best cell can be a wrong turn that every particle would
        # otherwise follow.
        two, two_res = match_with_residuals(
            field,
            np.concatenate([window_index, window_index]),
            points_xy,
            np.vstack([start, centre_prior]),
            config.matcher,
            np.concatenate([matcher_prior, matcher_prior]),
            centre=np.vstack([centre_prior, centre_prior]),
            normals_xy=normals_xy,
            along_weight=config.along_surface_weight,
        )
        energy = truncated_energy(
            field,
            np.concatenate([window_index, window_index]),
            points_xy,
            two.poses,
            config.matcher.stages[-1][0],
            np.concatenate([matcher_prior, matcher_prior]),
            np.vstack([centre_prior, centre_prior]),
            normals_xy,
            config.along_surface_weight,
            two_res,
            config.matcher.gate_on_residual,
        )
        use_prior = two.ok[p:] & (~two.ok[:p] | (energy[p:] < energy[:p]))
        pick = np.where(use_prior, np.arange(p) + p, np.arange(p))
        matched_res = two_res.rows(pick)
        result = MatchResult(
            two.poses[pick],
            two.information[pick],
            two.inlier_fraction[pick],
            two.rms_m[pick],
            two.ok[pick],
            two.known_inlier_fraction[pick],
        )
    else:
        result, matched_res = match_with_residuals(
            field,
            window_index,
            points_xy,
            start,
            config.matcher,
            matcher_prior,
            centre=centre_prior,
            normals_xy=normals_xy,
            along_weight=config.along_surface_weight,
        )
    ok = result.ok
    centre = np.where(ok[:, None], result.poses, centre_prior)
    # The residuals at the centres: the match's own where it was trusted (each pose's row depends on
    # that pose alone), sampled afresh at the prior where it failed.
    at_centres = matched_res
    if not ok.all():
        failed_rows = np.flatnonzero(~ok)
        at_centres = matched_res.with_rows(
            failed_rows,
            residuals(
                field,
                window_index[failed_rows],
                points_xy,
                centre_prior[failed_rows],
                normals_xy,
                config.along_surface_weight,
                gate_residual=config.matcher.gate_on_residual,
            ),
        )
    # Grid steps: the Laplace standard deviations of the match (motion model's where matching failed).
    scale = config.sigma_hit_m**2 * config.proposal_temperature
    eye = np.eye(3)[None, :, :]
    laplace = np.linalg.inv(result.information + matcher_prior + 1e-9 * eye) * scale
    motion_world = np.linalg.inv(matcher_prior + 1e-12 * eye) * scale
    variances = np.where(
        ok[:, None], np.diagonal(laplace, axis1=1, axis2=2), np.diagonal(motion_world, axis1=1, axis2=2)
    )
    steps = np.sqrt(np.maximum(variances, 0.0))
    steps[:, :2] = np.clip(steps[:, :2], config.min_xy_step_m, config.max_xy_step_m)
    steps[:, 2] = np.clip(steps[:, 2], config.min_yaw_step_rad, config.max_yaw_step_rad)
    offsets = _UNIT_GRID[None, :, :] * steps[:, None, :]  # (P, K, 3)
    candidates = centre[:, None, :] + offsets
    candidates[..., 2] = wrap_angle(candidates[..., 2])
    # The likelihood on the grid: linearised at the match (the grid spans its standard deviation), exact
    # around the prior where matching failed (there the grid spans the motion model's, centimetres).
    log_lik = linearized_log_likelihood(
        field,
        window_index,
        points_xy,
        centre,
        offsets,
        config.sigma_hit_m,
        config.outlier_m,
        normals_xy,
        config.along_surface_weight,
        at_centres,
        config.matcher.gate_on_residual,
    )
    if not ok.all():
        failed = np.flatnonzero(~ok)
        log_lik[failed] = scan_log_likelihood(
            field,
            window_index[failed],
            points_xy,
            candidates[failed],
            config.sigma_hit_m,
            config.outlier_m,
            normals_xy,
            config.along_surface_weight,
            config.matcher.gate_on_residual,
        )
    log_motion = motion_log_density(previous, candidates, increment, noise)  # (P, K)
    if measurement is not None:
        log_motion = log_motion + measurement.log_likelihood(candidates)
    log_volume = np.log(steps).sum(axis=1)
    # eta (the weight) with the weight temperature ...
    log_tau = log_lik / config.temperature + log_motion
    peak = log_tau.max(axis=1, keepdims=True)
    log_eta = peak[:, 0] + np.log(np.exp(log_tau - peak).sum(axis=1)) + log_volume
    if config.eta_integral == "laplace":
        l0, l_grad, l_hess = log_likelihood_quadratic(
            field,
            window_index,
            points_xy,
            centre,
            config.sigma_hit_m,
            config.outlier_m,
            normals_xy,
            config.along_surface_weight,
            config.matcher.gate_on_residual,
        )
        laplace = laplace_log_eta(
            previous, centre, increment, noise, l0, l_grad, l_hess, config.temperature, measurement
        )
        log_eta = np.where(ok, laplace, log_eta)
    # ... the proposal's shape with its own (see ProposalConfig).
    log_tau_shape = log_lik / config.proposal_temperature + log_motion
    tau = np.exp(log_tau_shape - log_tau_shape.max(axis=1, keepdims=True))
    # mu and Sigma over the offsets (relative to the centre, so no angle wrapping inside the sums).
    weights = tau / tau.sum(axis=1, keepdims=True)
    mean_offset = np.einsum("pk,pki->pi", weights, offsets)
    dev = offsets - mean_offset[:, None, :]
    cov = np.einsum("pk,pki,pkj->pij", weights, dev, dev)
    cov += np.einsum("pi,ij->pij", steps**2 / 12.0, np.eye(3))
    chol = np.linalg.cholesky(cov)
    noise_xyz = np.einsum("pij,pj->pi", chol, rng.standard_normal((p, 3)))
    if config.degenerate_noise_scale != 1.0:
        # Measured information: the scan's, and a fix's where one joined the prior (matcher_prior - prior).
        measured = result.information + (matcher_prior - prior)
        scaling = degenerate_scaling(measured, prior, config.degenerate_noise_scale)
        noise_xyz = np.einsum("pij,pj->pi", scaling, noise_xyz)
    draw = centre + mean_offset + noise_xyz
    # Where matching failed: the motion model (with a measurement, the Gaussian fitted around the prior,
    # which holds it; with ``failed_match_draw`` "grid", the Gaussian fitted on the grid around the
    # prediction, where eta was taken). The motion model's draw is taken in either case, so that the
    # random stream stays as it was.
    fallback = sample_motion(previous, increment, noise, rng) if measurement is None else draw
    if config.failed_match_draw == "grid":
        fallback = draw
    poses = np.where(ok[:, None], draw, fallback)
    poses[:, 2] = wrap_angle(poses[:, 2])
    return ProposalResult(poses, log_eta, ok, result, matched_res)


def degenerate_scaling(information: FloatArray, prior: FloatArray, scale: float) -> FloatArray:
    """(P, 3, 3) maps M that shrink a draw's noise in the directions only the motion prior constrains.

    In the prior's whitened coordinates y = Lᵀ x (Λ = L Lᵀ the prior's information) the prior is the
    identity and the scan's information A = L⁻¹ H L⁻ᵀ = U diag(λ) Uᵀ; the posterior's standard deviation
    along eigenvector u_i is (1 + λ_i)^-1/2, and with the prior k = ``scale`` times tighter it would be
    (1/k² + λ_i)^-1/2. M = L⁻ᵀ U diag(sqrt((1 + λ) / (1/k² + λ))) Uᵀ Lᵀ rescales by their ratio: k along
    a direction the scan says nothing about (λ = 0: a corridor's length), 1 where the scan dominates.
    Why: in such a direction no weight can tell particles apart, so every update's draw is a random
    step that resampling keeps at random, and the trajectory random-walks with the motion model's
    spread (which is wider than the odometry's real error) instead of the odometry's."""
    eye = np.eye(3)[None, :, :]
    lower = np.linalg.cholesky(prior + 1e-12 * eye)
    lower_inv = np.linalg.inv(lower)
    whitened = lower_inv @ information @ np.swapaxes(lower_inv, 1, 2)
    lam, vec = np.linalg.eigh(0.5 * (whitened + np.swapaxes(whitened, 1, 2)))
    lam = np.maximum(lam, 0.0)
    gain = np.sqrt((1.0 + lam) / (1.0 / scale**2 + lam))
    inner = np.einsum("pij,pj,pkj->pik", vec, gain, vec)
    out: FloatArray = np.swapaxes(lower_inv, 1, 2) @ inner @ np.swapaxes(lower, 1, 2)
    return out


def laplace_log_eta(
    previous: FloatArray,
    centre: FloatArray,
    increment: FloatArray,
    noise: OdometryNoise,
    l0: FloatArray,
    l_grad: FloatArray,
    l_hess: FloatArray,
    temperature: float,
    measurement: PoseMeasurement | None,
) -> FloatArray:
    """log eta = log ∫ p(z|m, x)^(1/T) p(x|x_{t-1}, u) [p(z_fix|x)] dx for each particle (P,), in closed
    form around the match: the log-likelihood is the quadratic of its linearised residuals
    (``l0, l_grad, l_hess``), the motion density is exactly quadratic in x (x_{t-1}⁻¹ ⊕ x is affine in x),
    the fix a Gaussian; with f(delta) = f0 + gᵀ delta - 1/2 deltaᵀ A delta,
    log eta = f0 + 1/2 gᵀ A⁻¹ g + 1/2 log det(2 pi A⁻¹).

    Why not the grid sum: the grid spans the match's standard deviation at the proposal temperature T'
    (1), but the weight's likelihood is tempered by T (40), so its integrand is ~sqrt(T/T') times wider:
    the grid saw only the middle of it, where the motion density is all that varies, and eta came out as
    little more than p(match | x_{t-1}, u). When the wheels slip (exp1's corner before the long corridor:
    odometry 20 cm longer than the scans over one 0.3 m update, 5 sigma of the motion model) every match
    sits in the motion model's tail, and 1 cm more or less slide, noise of each particle's own map,
    changed a weight by e; one update then took N_eff to 7 of 30 and decided which heading hypothesis
    survived the turn. Integrated over the tempered likelihood's real width, the mismatch is judged
    against the motion noise plus the scan's own (tempered) uncertainty along the slide, as the product
    of the two Gaussians says it should be.

    Opt-in (``ProposalConfig.eta_integral``): on its own it flattens the weights (8 resamplings instead of
    15 over exp1's loop) and exp1's loop closes for fewer seeds, because the grid's bias had been
    rewarding the particles that agree with odometry, which on exp1 helps; with proposal_temperature 3
    it closes the most seeds measured, but T' = 3 costs the simulated office (docs/slam.md).
    """
    cos_prev, sin_prev = np.cos(previous[:, 2]), np.sin(previous[:, 2])
    # d(x_{t-1}⁻¹ ⊕ x)/dx = blockdiag(R(yaw_{t-1})ᵀ, 1).
    jac = np.zeros((previous.shape[0], 3, 3))
    jac[:, 0, 0], jac[:, 0, 1], jac[:, 1, 0], jac[:, 1, 1], jac[:, 2, 2] = (
        cos_prev,
        sin_prev,
        -sin_prev,
        cos_prev,
        1.0,
    )
    inv_var = 1.0 / noise.sigmas(increment) ** 2
    err = between(previous, centre) - increment[None, :]
    err[:, 2] = wrap_angle(err[:, 2])
    f0 = l0 / temperature - 0.5 * np.einsum("pi,i,pi->p", err, inv_var, err)
    grad = l_grad / temperature - np.einsum("pji,j,pj->pi", jac, inv_var, err)
    hess = l_hess / temperature + np.einsum("pki,k,pkj->pij", jac, inv_var, jac)
    if measurement is not None:
        fix_err = centre - measurement.mean
        fix_err[:, 2] = wrap_angle(fix_err[:, 2])
        f0 = f0 - 0.5 * np.einsum("pi,ij,pj->p", fix_err, measurement.information, fix_err)
        grad = grad - np.einsum("ij,pj->pi", measurement.information, fix_err)
        hess = hess + measurement.information[None, :, :]
    solved = np.linalg.solve(hess, grad[..., None])[..., 0]
    _sign, log_det = np.linalg.slogdet(hess)
    out: FloatArray = (
        f0 + 0.5 * np.einsum("pi,pi->p", grad, solved) - 0.5 * log_det + 1.5 * np.log(2.0 * np.pi)
    )
    return out


@dataclass(frozen=True)
class TravelCheck:
    """:func:`travel_reversed`'s verdict and the truncated energies it compared. ``share``: the share of the
    odometry increment's translation the scan says the robot drove (1 the odometry's, -1 reversed, 0 no net
    translation: it turned round within the update); the energies of the matches from the odometry's
    prediction, from the prediction with the translation reversed and (where that hypothesis was tried,
    NaN otherwise) from the one without it."""

    share: float
    energy_forward: float
    energy_reversed: float
    energy_in_place: float = math.nan

    @property
    def reversed(self) -> bool:
        return self.share < 0.0


def travel_reversed(
    field: DistanceField,
    window: int,
    points_xy: FloatArray,
    previous: FloatArray,
    increment: FloatArray,
    noise: OdometryNoise,
    config: ProposalConfig,
    ratio: float,
    normals_xy: FloatArray | None = None,
    in_place_ratio: float | None = None,
) -> TravelCheck:
    """Whether the scan says the robot drove the odometry increment's translation the other way (or, with
    ``in_place_ratio``, not at all).

    One particle (``previous``, (3,), with its map's ``window`` of ``field``) is matched from x ⊕ u and from
    x ⊕ ū, where ū is ``increment`` with its translation reversed (the same turn), each under the motion
    prior centred on its own prediction (the proposal's prior, so a scan the match cannot place, a
    featureless corridor, costs both the same). Reversed when the reversed match is trusted and its
    truncated energy (:func:`agent.slam.matcher.truncated_energy`, each with its own prior) is below
    ``ratio`` times the forward one's. Odometry rebuilt from unsigned increments (the radish logs': the
    robot backs out of a room and the odometry drives on forward) puts the prediction twice the step off,
    beyond Gauss-Newton's reach, and the match follows the odometry. Where the proposal searches
    (``config.search``), a reversal must also beat the forward side's best fit from a correlative search
    around its prediction (below).

    With ``in_place_ratio`` a third hypothesis, the turn without the translation, is matched the same way
    and taken where its energy is below ``in_place_ratio`` times the forward one's and below the best of
    the others that qualify: an update in which the robot stopped and turned round drove part of its path
    one way and part the other, its net translation anywhere between u's and ū's, and from either end the
    match may settle short of it (``RbpfSlam`` tries it at the first update after a standstill)."""
    # The check's energies as its ratio was measured: endpoints judged by their distance to the nearest
    # obstacle whatever ``MatcherConfig.gate_on_residual`` says (with the residual gate, ACES seed 1
    # reversed one update falsely and ended 8.6 m off).
    matcher = dataclasses.replace(config.matcher, gate_on_residual=False)
    # The hypotheses: the share of the translation driven, and the ratio to the forward energy under which
    # each is taken.
    shares = [1.0, -1.0] + ([0.0] if in_place_ratio is not None else [])
    limits = [1.0, ratio] + ([in_place_ratio] if in_place_ratio is not None else [])
    k = len(shares)
    factors = np.array([[a, a, 1.0] for a in shares])
    predicted = compose(np.broadcast_to(previous, (k, 3)), increment[None, :] * factors)
    # The same prior for each (the motion model's spread for the odometry's increment: it does not depend
    # on the direction of travel, and the turn is the same), rotated into the world frame at the predicted
    # heading.
    sig = noise.sigmas(increment)
    c, s = math.cos(predicted[0, 2]), math.sin(predicted[0, 2])
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    prior = (
        config.prior_weight
        * config.sigma_hit_m**2
        * config.proposal_temperature
        * (rot @ np.diag(1.0 / sig**2) @ rot.T)
    )
    # The test: the match from the reversed prediction fits clearly better than the one from the odometry's
    # (``ratio``). Where the proposal searches, each direction is also matched from the best pose of a
    # correlative search around its prediction, and a reversal must also beat the forward side's best fit
    # so found: a forward match stuck in a local minimum (an odometry error beyond Gauss-Newton's reach)
    # is not read as a reversal (ACES seed 5, one record per ~1 m: forward 1.04 against reversed 0.35 was
    # reversed and broke the map, 10.9 m; searched, the forward side fits at 0.32).
    centres = predicted
    starts = predicted
    if config.search is not None:
        search = config.search
        found = np.stack(
            [correlative_search(field, window, points_xy, x, search, prior)[0] for x in predicted]
        )
        centres = np.vstack([predicted, predicted])
        starts = np.vstack([predicted, found])
    windows = np.full(starts.shape[0], window, dtype=np.int64)
    result = match(
        field,
        windows,
        points_xy,
        starts,
        matcher,
        prior,
        centre=centres,
        normals_xy=normals_xy,
        along_weight=config.along_surface_weight,
    )
    energy = truncated_energy(
        field,
        windows,
        points_xy,
        result.poses,
        config.matcher.stages[-1][0],
        prior,
        centres,
        normals_xy,
        config.along_surface_weight,
        # An endpoint a hypothesis puts among unmapped cells pays as one far from every wall: counted as
        # the mean of the others it costs nothing, and a robot backing out of a dead end, the end wall's
        # endpoints pushed behind the mapped wall by the odometry's forward prediction, was called forward
        # (the match there fitted the corridor's walls as well as the reversed one did).
        unknown_as_bound=True,
    )
    # Rows: the hypotheses from their predictions, then the same from the searches' poses; each
    # hypothesis's best fit is the lower of its two.
    rows = energy.reshape(-1, k)
    best = rows.min(axis=0)
    forward = float(rows[0, 0])
    chosen = 0
    for h in range(1, k):
        if bool(result.ok[h]) and float(rows[0, h]) < limits[h] * forward and best[h] < best[chosen]:
            chosen = h
    in_place = float(rows[0, 2]) if k > 2 else math.nan
    return TravelCheck(shares[chosen], forward, float(rows[0, 1]), in_place)
