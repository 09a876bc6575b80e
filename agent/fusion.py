"""Pose fusion: an extended Kalman filter over wheel odometry, IMU yaw rate, VLP fixes and the SLAM pose.

State (map frame, SI units)::

    x = [x_m, y_m, yaw_rad, omega_radps, gyro_bias_radps]

* **Prediction** (wheel odometry as the control input): over dt the base rolls ``ds_m`` (from the wheel
  encoders) along the heading at mid-interval, and turns at the yaw rate in the state::

      yaw_mid = yaw + omega dt / 2
      x' = x + ds cos(yaw_mid),  y' = y + ds sin(yaw_mid),  yaw' = yaw + omega dt,  omega' = omega,  b' = b

  The odometry's errors enter as input noise along and across the heading (standard deviation
  ``odometry_sigma_m_per_m`` per metre rolled), the yaw rate and the gyro bias as random walks.
* **Yaw rate**, two measurements of ``omega``: the wheels' (``z = dyaw_odom / dt``, the mean rate over
  an odometry interval, taken at the interval's middle where it equals the rate of a steadily changing
  turn, ``H = [0 0 0 1 0]``) and the gyro's (``z = omega + b``, ``H = [0 0 0 1 1]``), which makes the
  bias observable whenever both are there.
* **Pose**, from VLP and SLAM: ``z = (x, y, yaw)`` with the source's covariance, ``H = [I3 0]``; the yaw
  residual is wrapped to [-pi, pi).
* **Gating**: every update's innovation ``y`` with covariance ``S = H P H^T + R`` is tested by its squared
  Mahalanobis distance ``d^2 = y^T S^-1 y`` against the chi-square quantile for its dimension at
  ``gate_probability``; an outlier is counted and not fused. A run of rejected VLP fixes that agree with
  each other means the filter, not the camera, is lost: it is re-initialised on the fix (relocalisation,
  ``reset_counter`` + 1).
* **Integrity** (:class:`FixIntegrity`, :class:`IntegrityPolicy`): a fix its source flags ``degraded``, or
  whose protection level exceeds the alert limit, is never fused as nominal. A degraded one is refused
  (unless the policy's ``fuse_degraded``); one past the alert limit is *guarded*: fused only when the gate
  against the predicted pose can check it to within the alert limit (the largest position innovation the
  gate passes, ``sqrt(chi2_2(gate) lambda_max(S_xy))`` with the fix's own covariance, is at most
  ``alert_limit_m``) and it passes that gate, and then with its covariance inflated by
  ``sigma_scale**2``; it never relocalises the filter. Acquisition: while no fix of the source has been
  fused yet (the pose is the configured initial guess, which nothing else can check a fix against), an
  unflagged fix past the alert limit is checked by the gate alone. A refused fix is counted and not fused:
  the pose coasts on the other sources, as when no fix comes, and the source stops counting as live
  (:meth:`PoseFilter.live`) at its timeout.
* **Late measurements**: a VLP fix is stamped with the frame's capture time and arrives a frame period
  later, a SLAM pose with its scan's time a filter update later. :class:`PoseFilter` keeps the measurements
  of the last ``history_s`` seconds in time order with the filter state after each; a late one is inserted
  where it belongs and the filter re-runs from there ("re-filtering" out-of-sequence measurements), so
  every measurement is fused at the time it was taken.

Pure numpy, no I/O, no clock: times are given by the caller (``time.monotonic_ns`` in the agent).
:class:`PoseFilter` is thread-safe (one lock); the functions :func:`ekf_predict` and :func:`ekf_update` are
the textbook steps it is built from.
"""

from __future__ import annotations

import bisect
import dataclasses
import enum
import math
import threading
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy.special import chdtri

__all__ = [
    "N_STATE",
    "Estimate",
    "FilterNoise",
    "FixIntegrity",
    "IntegrityPolicy",
    "PoseFilter",
    "Refusal",
    "Source",
    "UpdateResult",
    "ekf_predict",
    "ekf_update",
    "gate_threshold",
]

FloatArray = npt.NDArray[np.float64]

N_STATE = 5
IX, IY, IYAW, IOMEGA, IBIAS = range(N_STATE)
_EYE = np.eye(N_STATE)
_H_POSE = np.eye(3, N_STATE)
_H_POSITION = np.eye(2, N_STATE)
_H_ODOMETRY_RATE = np.array([[0.0, 0.0, 0.0, 1.0, 0.0]])
_H_GYRO = np.array([[0.0, 0.0, 0.0, 1.0, 1.0]])
# The speed held past the last odometry is the mean over this much of it.
_SPEED_WINDOW_NS = 200_000_000


class Source(enum.StrEnum):
    VLP = "vlp"
    SLAM = "slam"
    ODOMETRY = "odometry"
    IMU = "imu"


@dataclass(frozen=True, slots=True)
class FilterNoise:
    """Noise model. ``unseen_speed_mps``: how fast the base may move unobserved when no odometry covers
    an interval (random walk on x and y, variance ``unseen_speed_mps**2 * dt``).
    ``odometry_time_sigma_s``: how far the host time of a wheel read may be from when the servos sampled
    (a reply that waited for a busy bus or CPU). An interval ``dt`` stamped off by e0 and e1 at its ends
    gives a yaw rate off by ``rate (e1 - e0) / dt``: the wheels' rate has variance
    ``odometry_yaw_rate_sigma_radps**2 + 2 (rate odometry_time_sigma_s / dt)**2``, so in a turn the gyro
    beside it counts for more."""

    odometry_sigma_m_per_m: float = 0.02
    odometry_floor_m: float = 1e-4
    odometry_yaw_rate_sigma_radps: float = 0.02
    odometry_time_sigma_s: float = 0.002
    gyro_sigma_radps: float = 0.005
    yaw_rate_walk_radps2: float = 2.0
    gyro_bias_walk_radps: float = 1e-4
    unseen_speed_mps: float = 0.05


@dataclass(frozen=True, slots=True)
class FixIntegrity:
    """What a fix's source says of its integrity: ``degraded`` (the source's own tests flagged it) and its
    protection level (the largest position error it cannot rule out; inf: none can be, e.g. a two-LED VLP
    fix)."""

    degraded: bool = False
    protection_level_m: float = math.inf


@dataclass(frozen=True, slots=True)
class IntegrityPolicy:
    """How fixes that carry a :class:`FixIntegrity` are fused.

    ``alert_limit_m``: the largest position error the application tolerates (the aviation notion): a fix
    whose protection level exceeds it is not nominal. ``sigma_scale``: a guarded fix's (past the alert
    limit) standard deviations are multiplied by this before it is fused; 0: such fixes are never fused.
    ``fuse_degraded``: a fix its source flagged degraded is guarded too, not refused."""

    alert_limit_m: float = 0.10
    sigma_scale: float = 3.0
    fuse_degraded: bool = False

    def __post_init__(self) -> None:
        if not (self.alert_limit_m > 0.0 and math.isfinite(self.alert_limit_m)):
            raise ValueError(f"alert_limit_m must be finite and > 0, got {self.alert_limit_m}")
        if not (self.sigma_scale == 0.0 or 1.0 <= self.sigma_scale < math.inf):
            raise ValueError(f"sigma_scale must be 0 or >= 1, got {self.sigma_scale}")


class Refusal(enum.StrEnum):
    """Why a fix with integrity information was not fused (besides the ordinary gate)."""

    NONE = ""
    INTEGRITY = "integrity"  # degraded by its source (refused; with fuse_degraded: failed the guard)
    ALERT_LIMIT = "alert_limit"  # nominal by its source, but its protection level exceeds the alert limit


@dataclass(frozen=True, slots=True)
class UpdateResult:
    """What one measurement did: fused or not, and its squared Mahalanobis distance. ``guarded``: a fix
    fused (or tried) under the integrity guard; ``refused``: why a fix with integrity information was not
    fused (``Refusal.NONE`` when it was, or when the ordinary gate rejected a nominal fix)."""

    source: Source
    accepted: bool
    mahalanobis_d2: float
    too_old: bool = False
    relocalized: bool = False
    guarded: bool = False
    refused: Refusal = Refusal.NONE


@dataclass(frozen=True, slots=True)
class Estimate:
    """The fused state at ``t_ns``: pose, yaw rate, gyro bias, the 5x5 covariance and its summaries."""

    t_ns: int
    x_m: float
    y_m: float
    yaw_rad: float
    omega_radps: float
    gyro_bias_radps: float
    covariance: FloatArray
    reset_counter: int
    v_mps: float = 0.0
    version: int = 0  # how many inputs the filter had taken when this was read (replay matches on it)

    @property
    def sigma_xy_m(self) -> float:
        """sqrt of the larger eigenvalue of the 2x2 position covariance (the worst direction)."""
        a, b, d = self.covariance[0, 0], self.covariance[0, 1], self.covariance[1, 1]
        return math.sqrt(max(0.5 * (a + d) + math.sqrt(0.25 * (a - d) ** 2 + b * b), 0.0))

    @property
    def sigma_yaw_rad(self) -> float:
        return math.sqrt(max(float(self.covariance[2, 2]), 0.0))


def _json_float(value: float) -> float | str:
    """A float a JSON recording can hold (inf as the string "inf")."""
    return value if math.isfinite(value) else str(value)


def _wrap(angle_rad: float) -> float:
    return (angle_rad + math.pi) % (2.0 * math.pi) - math.pi


def gate_threshold(dimension: int, probability: float) -> float:
    """The chi-square quantile a squared Mahalanobis distance of ``dimension`` degrees is gated at.

    ``chdtri`` is the inverse of the chi-square survival function, so this is ``chi2.ppf(probability,
    dimension)`` without importing ``scipy.stats`` (over a second and ~60 MB at start-up on a small
    computer)."""
    return float(chdtri(dimension, 1.0 - probability))


# -- the textbook steps --------------------------------------------------------------------------------
def ekf_predict(
    x: FloatArray, P: FloatArray, ds_m: float, dt_s: float, noise: FilterNoise, odometry_known: bool = True
) -> tuple[FloatArray, FloatArray]:
    """Time update over ``dt_s`` with ``ds_m`` rolled by the wheels (x, P in place of copies)."""
    yaw, omega = x[IYAW], x[IOMEGA]
    yaw_mid = yaw + 0.5 * omega * dt_s
    c, s = math.cos(yaw_mid), math.sin(yaw_mid)
    # x_k|k-1 = f(x_k-1|k-1, u_k)
    x_pred = x.copy()
    x_pred[IX] += ds_m * c
    x_pred[IY] += ds_m * s
    x_pred[IYAW] = _wrap(yaw + omega * dt_s)
    # F = df/dx at x_k-1|k-1
    F = _EYE.copy()
    F[IX, IYAW] = -ds_m * s
    F[IX, IOMEGA] = -ds_m * s * 0.5 * dt_s
    F[IY, IYAW] = ds_m * c
    F[IY, IOMEGA] = ds_m * c * 0.5 * dt_s
    F[IYAW, IOMEGA] = dt_s
    # P_k|k-1 = F P F^T + Q, with Q = G_along var G_along^T + G_across var G_across^T + random walks. The
    # along and across unit vectors are orthonormal, so their outer products sum to the identity: the
    # wheel noise adds sigma^2 to x and y alike.
    P_pred = F @ P @ F.T
    if odometry_known:
        sigma = noise.odometry_sigma_m_per_m * abs(ds_m) + noise.odometry_floor_m * (ds_m != 0.0)
        q_xy = sigma * sigma
    else:
        q_xy = noise.unseen_speed_mps**2 * dt_s
    P_pred[IX, IX] += q_xy
    P_pred[IY, IY] += q_xy
    P_pred[IOMEGA, IOMEGA] += noise.yaw_rate_walk_radps2**2 * dt_s
    P_pred[IBIAS, IBIAS] += noise.gyro_bias_walk_radps**2 * dt_s
    return x_pred, P_pred


def ekf_update(
    x: FloatArray,
    P: FloatArray,
    z: FloatArray,
    H: FloatArray,
    R: FloatArray,
    gate_d2: float,
    yaw_row: int | None = None,
) -> tuple[FloatArray, FloatArray, float, bool]:
    """Measurement update of a linear measurement ``z = H x + v``, ``v ~ N(0, R)``, with gating.

    ``yaw_row``: the row of ``z`` that is an angle (its innovation is wrapped). Returns the new x, P, the
    squared Mahalanobis distance of the innovation and whether the measurement was fused.
    """
    if H.shape[0] == 1:
        return _ekf_update_scalar(x, P, float(z[0]), H[0], float(R[0, 0]), gate_d2)
    # y = z - H x (innovation; angles wrapped)
    y = z - H @ x
    if yaw_row is not None:
        y[yaw_row] = _wrap(float(y[yaw_row]))
    # S = H P H^T + R (innovation covariance), P H^T kept for the gain
    PHt = P @ H.T
    S = H @ PHt + R
    S_inv = _inverse_small(S)
    # d^2 = y^T S^-1 y (squared Mahalanobis distance)
    S_inv_y = S_inv @ y
    d2 = float(y @ S_inv_y)
    if not d2 <= gate_d2:
        return x, P, d2, False
    # K = P H^T S^-1 (Kalman gain); x = x + K y
    K = PHt @ S_inv
    x_new = x + PHt @ S_inv_y
    x_new[IYAW] = _wrap(float(x_new[IYAW]))
    # P = (I - K H) P (I - K H)^T + K R K^T (Joseph form: stays symmetric and positive definite)
    I_KH = _EYE - K @ H
    P_new = I_KH @ P @ I_KH.T + K @ R @ K.T
    return x_new, 0.5 * (P_new + P_new.T), d2, True


def _inverse_small(S: FloatArray) -> FloatArray:
    """The inverse of a symmetric 2x2 or 3x3 innovation covariance by cofactors (``np.linalg.inv``'s
    LAPACK call costs several times more at this size); larger ones through ``np.linalg.inv``."""
    n = S.shape[0]
    if n == 2:
        (a, b), (c, d) = S.tolist()
        det = a * d - b * c
        if det != 0.0 and math.isfinite(det):
            return np.array([[d / det, -b / det], [-c / det, a / det]])
    elif n == 3:
        (a, b, c), (d, e, f), (g, h, i) = S.tolist()
        c00, c01, c02 = e * i - f * h, f * g - d * i, d * h - e * g
        det = a * c00 + b * c01 + c * c02
        if det != 0.0 and math.isfinite(det):
            inv = 1.0 / det
            return np.array(
                [
                    [c00 * inv, (c * h - b * i) * inv, (b * f - c * e) * inv],
                    [c01 * inv, (a * i - c * g) * inv, (c * d - a * f) * inv],
                    [c02 * inv, (b * g - a * h) * inv, (a * e - b * d) * inv],
                ]
            )
    inverse: FloatArray = np.asarray(np.linalg.inv(S), dtype=np.float64)
    return inverse


def _ekf_update_scalar(
    x: FloatArray, P: FloatArray, z: float, h: FloatArray, r: float, gate_d2: float
) -> tuple[FloatArray, FloatArray, float, bool]:
    """:func:`ekf_update` for one scalar measurement z = h . x + v (the yaw rates, many times a second).

    With S = h P h^T + r a scalar and K = P h^T / S, the Joseph form (I - K h) P (I - K h)^T + K r K^T
    reduces exactly to P - (P h^T)(P h^T)^T / S: symmetric by construction, no matrix inverse."""
    ph = P @ h
    s = float(h @ ph) + r
    y = z - float(h @ x)
    d2 = y * y / s
    if not d2 <= gate_d2:
        return x, P, d2, False
    x_new = x + ph * (y / s)
    x_new[IYAW] = _wrap(float(x_new[IYAW]))
    return x_new, P - np.outer(ph, ph) * (1.0 / s), d2, True


# -- the filter over time ------------------------------------------------------------------------------
class _Kind(enum.IntEnum):
    # At equal times: the wheels' yaw rate first, then the rest.
    ODOMETRY_RATE = 0
    GYRO = 1
    POSE = 2
    POSITION = 3


@dataclass(slots=True)
class _Event:
    t_ns: int
    kind: _Kind
    serial: int
    source: Source
    z: FloatArray
    R: FloatArray
    accepted: bool = False
    d2: float = math.nan
    # A guarded fix (FixIntegrity: degraded or past the alert limit): fused only within the alert limit
    # of the prediction, with R inflated; refused otherwise (always, with ``refuse``).
    guarded: bool = False
    refuse: bool = False
    acquiring: bool = False  # no fix of its source fused yet: the gate alone checks it

    @property
    def key(self) -> tuple[int, int, int]:
        return (self.t_ns, int(self.kind), self.serial)


@dataclass(frozen=True, slots=True)
class _Segment:
    """Wheel odometry between two samples: rolled ``ds_m`` over [t0_ns, t1_ns]."""

    t0_ns: int
    t1_ns: int
    ds_m: float


def _segment_end(segment: _Segment) -> int:
    return segment.t1_ns


@dataclass
class _Relocalizer:
    """Consecutive rejected VLP fixes; enough that agree with one another re-initialise the filter."""

    needed: int = 5
    spread_m: float = 0.1
    recent: list[FloatArray] = field(default_factory=list)

    def rejected(self, z: FloatArray) -> bool:
        self.recent.append(z)
        if len(self.recent) < self.needed:
            return False
        pts = np.array([r[:2] for r in self.recent[-self.needed :]])
        agree = bool(np.all(np.linalg.norm(pts - pts.mean(axis=0), axis=1) <= self.spread_m))
        if agree:
            self.recent.clear()
        return agree

    def accepted(self) -> None:
        self.recent.clear()


class PoseFilter:
    """The EKF with a time-ordered buffer of the last ``history_s`` seconds of measurements.

    Feed it with :meth:`add_odometry` (one wheel interval), :meth:`add_gyro`, :meth:`add_pose`, in any
    order of their times; read :meth:`estimate`. Thread-safe.
    """

    def __init__(
        self,
        x0: FloatArray,
        P0: FloatArray,
        t0_ns: int,
        noise: FilterNoise = FilterNoise(),
        gate_probability: float = 0.999,
        history_s: float = 1.0,
        odometry_hold_s: float = 0.3,
        relocalize_after: int = 5,
        observer: Callable[[dict[str, Any]], None] | None = None,
        integrity: IntegrityPolicy = IntegrityPolicy(),
    ) -> None:
        """``observer``: called with every input, in the order the filter applies them (under its lock),
        as a dict a recording can hold (``agent.runtime.recorder``); it must not block. ``integrity``: how
        fixes given with a :class:`FixIntegrity` are fused."""
        x0 = np.asarray(x0, dtype=np.float64).reshape(-1)
        P0 = np.asarray(P0, dtype=np.float64)
        if x0.shape == (3,):
            x0 = np.concatenate([x0, [0.0, 0.0]])
        if x0.shape != (N_STATE,):
            raise ValueError(f"x0 must have 3 or {N_STATE} elements, got {x0.shape}")
        if P0.shape == (3, 3):
            full = np.diag([0.0, 0.0, 0.0, 0.1**2, 0.01**2])
            full[:3, :3] = P0
            P0 = full
        if P0.shape != (N_STATE, N_STATE):
            raise ValueError(f"P0 must be 3x3 or {N_STATE}x{N_STATE}, got {P0.shape}")
        if not 0.0 < gate_probability < 1.0:
            raise ValueError(f"gate_probability must be in (0, 1), got {gate_probability}")
        self.noise = noise
        self.integrity = integrity
        self.gate = {n: gate_threshold(n, gate_probability) for n in (1, 2, 3)}
        self.history_ns = int(history_s * 1e9)
        self.hold_ns = int(odometry_hold_s * 1e9)
        self._lock = threading.Lock()
        x0[IYAW] = _wrap(float(x0[IYAW]))
        self._base: tuple[int, FloatArray, FloatArray] = (t0_ns, x0.copy(), P0.copy())
        self._events: list[_Event] = []
        self._keys: list[tuple[int, int, int]] = []
        self._states: list[tuple[FloatArray, FloatArray]] = []  # after each event
        self._segments: deque[_Segment] = deque()
        self._serial = 0
        self.reset_counter = 0
        self._relocalizer = _Relocalizer(needed=relocalize_after)
        self.last_accepted_ns: dict[Source, int] = {}
        # Arrival of each source's last fix refused for integrity (FixIntegrity): newer than its last
        # fused one, an integrity alert (integrity_alert(), for the status line).
        self.last_refused_ns: dict[Source, int] = {}
        self.counts: dict[str, int] = {}
        self.replayed_events = 0
        self.inputs = 0
        self.observer = observer
        self.parameters: dict[str, Any] = {
            "x0": x0.tolist(),
            "P0": P0.tolist(),
            "t0_ns": int(t0_ns),
            "noise": dataclasses.asdict(noise),
            "gate_probability": gate_probability,
            "history_s": history_s,
            "odometry_hold_s": odometry_hold_s,
            "relocalize_after": relocalize_after,
            "integrity": dataclasses.asdict(integrity),
        }

    @classmethod
    def from_parameters(cls, parameters: dict[str, Any]) -> PoseFilter:
        """A filter set up as the one whose :attr:`parameters` these are (to replay its inputs)."""
        return cls(
            np.asarray(parameters["x0"], dtype=np.float64),
            np.asarray(parameters["P0"], dtype=np.float64),
            int(parameters["t0_ns"]),
            FilterNoise(**parameters["noise"]),
            gate_probability=float(parameters["gate_probability"]),
            history_s=float(parameters["history_s"]),
            odometry_hold_s=float(parameters["odometry_hold_s"]),
            relocalize_after=int(parameters["relocalize_after"]),
            # A recording made before the integrity policy existed fused every fix as nominal.
            integrity=IntegrityPolicy(**parameters.get("integrity", {})),
        )

    def _observe(self, record: dict[str, Any]) -> None:
        self.inputs += 1
        if self.observer is not None:
            self.observer(record)

    # -- feeding --------------------------------------------------------------------------------------
    def add_odometry(
        self, t0_ns: int, t1_ns: int, ds_m: float, dyaw_rad: float, arrival_ns: int | None = None
    ) -> UpdateResult:
        """The wheels rolled ``ds_m`` and turned ``dyaw_rad`` between their samples at ``t0_ns`` and
        ``t1_ns``: the control input for that interval and a measurement of the yaw rate over it."""
        record = {"k": "odometry", "t0": t0_ns, "t1": t1_ns, "ds": ds_m, "dyaw": dyaw_rad, "a": arrival_ns}
        if t1_ns <= t0_ns:
            with self._lock:
                self._observe(record)
                self._count("odometry_time_reversals")
            return UpdateResult(Source.ODOMETRY, False, math.nan)
        dt_s = (t1_ns - t0_ns) * 1e-9
        rate = dyaw_rad / dt_s
        with self._lock:
            self._observe(record)
            if t0_ns < self._base[0]:
                self._count("odometry_too_old")
                return UpdateResult(Source.ODOMETRY, False, math.nan, too_old=True)
            while self._segments and self._segments[-1].t1_ns > t0_ns:
                # A restarted odometry (a reconnect) overlapping the last interval: the newer one wins.
                self._segments.pop()
            self._segments.append(_Segment(t0_ns, t1_ns, ds_m))
            noise = self.noise
            timing = rate * noise.odometry_time_sigma_s / dt_s
            variance = noise.odometry_yaw_rate_sigma_radps**2 + 2.0 * timing * timing
            # The mean rate over the interval is the rate at its middle (exactly so for a rate that
            # changes linearly); taken at t0 it would lead the gyro through every change of the turn and
            # the difference would be learnt as gyro bias.
            event = self._new_event(
                (t0_ns + t1_ns) // 2,
                _Kind.ODOMETRY_RATE,
                Source.ODOMETRY,
                np.array([rate]),
                np.array([[variance]]),
            )
            # The interval changes every prediction after t0: re-run from there.
            result = self._insert(
                event, arrival_ns if arrival_ns is not None else t1_ns, replay_from_ns=t0_ns
            )
            self._prune(t1_ns)
            return result

    def add_gyro(self, t_ns: int, omega_radps: float, arrival_ns: int | None = None) -> UpdateResult:
        with self._lock:
            self._observe({"k": "gyro", "t": t_ns, "w": omega_radps, "a": arrival_ns})
            sigma = self.noise.gyro_sigma_radps
            event = self._new_event(
                t_ns, _Kind.GYRO, Source.IMU, np.array([omega_radps]), np.array([[sigma**2]])
            )
            result = self._insert(event, arrival_ns if arrival_ns is not None else t_ns)
            self._prune(t_ns)
            return result

    def add_pose(
        self,
        source: Source,
        t_ns: int,
        x_m: float,
        y_m: float,
        yaw_rad: float | None,
        covariance: FloatArray,
        arrival_ns: int | None = None,
        relocalize: bool = False,
        integrity: FixIntegrity | None = None,
    ) -> UpdateResult:
        """An absolute pose (VLP, SLAM) taken at ``t_ns``; ``yaw_rad`` None for a position-only fix, with a
        2x2 ``covariance`` then (else 3x3). ``relocalize``: a run of rejected fixes from this source may
        re-initialise the filter (for a source that is right when the filter is not: VLP). ``integrity``:
        what the source says of the fix; a degraded one, or one whose protection level exceeds the policy's
        alert limit, is fused only under the guard (module docstring) and never relocalises; None: the
        fix is taken as nominal (SLAM)."""
        cov = np.asarray(covariance, dtype=np.float64)
        if yaw_rad is None:
            if cov.shape[0] >= 2:
                cov = cov[:2, :2]
            z = np.array([x_m, y_m])
            kind = _Kind.POSITION
        else:
            z = np.array([x_m, y_m, _wrap(yaw_rad)])
            kind = _Kind.POSE
        n = z.size
        if cov.shape != (n, n) or not np.all(np.isfinite(cov)) or not np.all(np.isfinite(z)):
            raise ValueError(f"a {source} fix needs finite values and a {n}x{n} covariance, got {cov.shape}")
        with self._lock:
            self._observe(
                {
                    "k": "pose",
                    "src": source.value,
                    "t": t_ns,
                    "x": x_m,
                    "y": y_m,
                    "yaw": yaw_rad,
                    "cov": np.asarray(covariance, dtype=np.float64).tolist(),
                    "a": arrival_ns,
                    "reloc": relocalize,
                    **(
                        {}
                        if integrity is None
                        else {"deg": integrity.degraded, "pl": _json_float(integrity.protection_level_m)}
                    ),
                }
            )
            event = self._new_event(t_ns, kind, source, z, 0.5 * (cov + cov.T))
            refusal = Refusal.NONE
            if integrity is not None:
                if integrity.degraded:
                    event.guarded, refusal = True, Refusal.INTEGRITY
                    event.refuse = not self.integrity.fuse_degraded
                elif not integrity.protection_level_m <= self.integrity.alert_limit_m:
                    event.guarded, refusal = True, Refusal.ALERT_LIMIT
                    event.acquiring = source not in self.last_accepted_ns
            arrival = arrival_ns if arrival_ns is not None else t_ns
            result = self._insert(event, arrival)
            if event.guarded:
                if not result.too_old:
                    if result.accepted:
                        self._count(f"{source}_fused_guarded")
                    else:
                        self._count(f"{source}_refused_{refusal}")
                        self.last_refused_ns[source] = max(self.last_refused_ns.get(source, 0), arrival)
                        result = dataclasses.replace(result, refused=refusal)
                result = dataclasses.replace(result, guarded=True)
            elif relocalize and not result.too_old:
                if result.accepted:
                    self._relocalizer.accepted()
                elif self._relocalizer.rejected(
                    z if n == 3 else np.concatenate([z, [self._latest()[0][IYAW]]])
                ):
                    self._relocalize(event, arrival)
                    result = UpdateResult(source, True, result.mahalanobis_d2, relocalized=True)
            self._prune(t_ns)
            return result

    # -- reading --------------------------------------------------------------------------------------
    def estimate(self, t_ns: int | None = None) -> Estimate:
        """The state after the newest measurement, or predicted to ``t_ns`` (later than that) without
        changing the filter."""
        with self._lock:
            t_last = self._events[-1].t_ns if self._events else self._base[0]
            x, P = self._latest()
            if t_ns is not None and t_ns > t_last:
                x, P = self._predict(x, P, t_last, t_ns)
                t_last = t_ns
            v = self._velocity(t_last)
            return Estimate(
                t_last,
                float(x[IX]),
                float(x[IY]),
                float(x[IYAW]),
                float(x[IOMEGA]),
                float(x[IBIAS]),
                P.copy(),
                self.reset_counter,
                v,
                self.inputs,
            )

    def estimate_at(self, t_ns: int) -> Estimate:
        """The state at ``t_ns`` as the buffered measurements up to then give it (for a prior at a frame's
        time); after the newest measurement, as :meth:`estimate`."""
        with self._lock:
            i = bisect.bisect_right(self._keys, (t_ns, len(_Kind), 0))
            if i > 0:
                t_from = self._events[i - 1].t_ns
                x, P = self._states[i - 1]
            else:
                t_from, x, P = self._base
            if t_ns > t_from:
                x, P = self._predict(x, P, t_from, t_ns)
            else:
                t_ns = t_from
            return Estimate(
                t_ns,
                float(x[IX]),
                float(x[IY]),
                float(x[IYAW]),
                float(x[IOMEGA]),
                float(x[IBIAS]),
                P.copy(),
                self.reset_counter,
                self._velocity(t_ns),
                self.inputs,
            )

    def live(self, now_ns: int, timeouts_ns: dict[Source, int]) -> set[Source]:
        """The sources fused (accepted) within their timeout before ``now_ns`` (a fix refused for integrity
        is not fused: a source whose fixes are all refused drops out at its timeout)."""
        with self._lock:
            return {s for s, t in self.last_accepted_ns.items() if now_ns - t <= timeouts_ns.get(s, 0)}

    def integrity_alert(self, source: Source) -> bool:
        """Whether ``source``'s newest fix was refused for integrity (nothing fused from it since)."""
        with self._lock:
            return self.last_refused_ns.get(source, -1) >= self.last_accepted_ns.get(source, 0)

    def counters(self) -> dict[str, int]:
        with self._lock:
            out = dict(self.counts)
            out["replayed_events"] = self.replayed_events
            out["reset_counter"] = self.reset_counter
            out["buffered_events"] = len(self._events)
            return out

    # -- internals (lock held) -------------------------------------------------------------------------
    def _count(self, what: str) -> None:
        self.counts[what] = self.counts.get(what, 0) + 1

    def _new_event(self, t_ns: int, kind: _Kind, source: Source, z: FloatArray, R: FloatArray) -> _Event:
        self._serial += 1
        return _Event(int(t_ns), kind, self._serial, source, z, R)

    def _latest(self) -> tuple[FloatArray, FloatArray]:
        return self._states[-1] if self._states else (self._base[1], self._base[2])

    def _speed_before(self, t_ns: int) -> float:
        """Forward speed over the ``_SPEED_WINDOW_NS`` of odometry ending at ``t_ns``: one wheel interval's
        speed is as jittery as its timestamps (a read delayed by a busy bus or scheduler shifts its host
        time, not its distance), the distance over several is not."""
        ds = 0.0
        span = 0
        for seg in reversed(self._segments):
            if seg.t0_ns >= t_ns:
                continue
            if seg.t1_ns <= t_ns - _SPEED_WINDOW_NS:
                break
            ds += seg.ds_m
            span += seg.t1_ns - seg.t0_ns
        return ds / (span * 1e-9) if span > 0 else 0.0

    def _velocity(self, t_ns: int) -> float:
        """Forward speed at ``t_ns`` (held for ``hold_ns`` after the last odometry)."""
        if not self._segments or t_ns - self._segments[-1].t1_ns > self.hold_ns:
            return 0.0
        return self._speed_before(min(t_ns, self._segments[-1].t1_ns))

    def _rolled(self, a_ns: int, b_ns: int) -> tuple[float, bool]:
        """Metres rolled between ``a_ns`` and ``b_ns`` (linear within each odometry interval, the last
        interval's speed held for ``hold_ns`` after it) and whether odometry covers the span."""
        if not self._segments:
            return 0.0, False
        ds = 0.0
        covered_ns = 0
        segments = self._segments
        # The segments are in time order: start at the first one that ends after a_ns.
        for k in range(bisect.bisect_right(segments, a_ns, key=_segment_end), len(segments)):
            seg = segments[k]
            if seg.t0_ns >= b_ns:
                break
            lo = a_ns if a_ns > seg.t0_ns else seg.t0_ns
            hi = b_ns if b_ns < seg.t1_ns else seg.t1_ns
            if hi > lo:
                ds += seg.ds_m * (hi - lo) / (seg.t1_ns - seg.t0_ns)
                covered_ns += hi - lo
        last = segments[-1]
        lo, hi = max(a_ns, last.t1_ns), min(b_ns, last.t1_ns + self.hold_ns)
        if hi > lo:
            ds += self._speed_before(last.t1_ns) * (hi - lo) * 1e-9
            covered_ns += hi - lo
        return ds, covered_ns >= 0.5 * (b_ns - a_ns)

    def _predict(self, x: FloatArray, P: FloatArray, a_ns: int, b_ns: int) -> tuple[FloatArray, FloatArray]:
        if b_ns <= a_ns:
            return x, P
        ds, known = self._rolled(a_ns, b_ns)
        return ekf_predict(x, P, ds, (b_ns - a_ns) * 1e-9, self.noise, known)

    def _apply(self, event: _Event, x: FloatArray, P: FloatArray) -> tuple[FloatArray, FloatArray]:
        if event.kind is _Kind.ODOMETRY_RATE:
            H, yaw_row = _H_ODOMETRY_RATE, None
        elif event.kind is _Kind.GYRO:
            H, yaw_row = _H_GYRO, None
        elif event.kind is _Kind.POSE:
            H, yaw_row = _H_POSE, 2
        else:
            H, yaw_row = _H_POSITION, None
        if event.guarded:
            return self._apply_guarded(event, x, P, H, yaw_row)
        x, P, d2, ok = ekf_update(x, P, event.z, H, event.R, self.gate[event.z.size], yaw_row)
        event.accepted, event.d2 = ok, d2
        return x, P

    def _apply_guarded(
        self, event: _Event, x: FloatArray, P: FloatArray, H: FloatArray, yaw_row: int | None
    ) -> tuple[FloatArray, FloatArray]:
        """A fix that cannot vouch for itself: checked against the prediction, fused only if the check
        bounds it within the alert limit and it passes, then with its covariance inflated."""
        policy = self.integrity
        y = event.z - H @ x
        if yaw_row is not None:
            y[yaw_row] = _wrap(float(y[yaw_row]))
        S = H @ P @ H.T + event.R
        d2 = float(y @ _inverse_small(S) @ y)
        event.d2 = d2
        # The largest position innovation the gate lets through (the worst direction of S's position
        # block): a wrong fix that passes is at most this far from the prediction.
        a, b, d = float(S[0, 0]), float(S[0, 1]), float(S[1, 1])
        lambda_max = 0.5 * (a + d) + math.sqrt(0.25 * (a - d) ** 2 + b * b)
        window_m = math.sqrt(self.gate[2] * lambda_max)
        if (
            event.refuse
            or policy.sigma_scale == 0.0
            or (window_m > policy.alert_limit_m and not event.acquiring)
            or not d2 <= self.gate[event.z.size]
        ):
            event.accepted = False
            return x, P
        R = event.R * policy.sigma_scale**2
        x, P, _, ok = ekf_update(x, P, event.z, H, R, math.inf, yaw_row)
        event.accepted = ok
        return x, P

    def _insert(self, event: _Event, arrival_ns: int, replay_from_ns: int | None = None) -> UpdateResult:
        """Put ``event`` in its place and re-run the filter from it, or from the first event after
        ``replay_from_ns`` when that is earlier (new odometry changes the predictions from its start)."""
        if event.t_ns < self._base[0]:
            self._count(f"{event.source}_too_old")
            return UpdateResult(event.source, False, math.nan, too_old=True)
        i = bisect.bisect_left(self._keys, event.key)
        self._events.insert(i, event)
        self._keys.insert(i, event.key)
        start = i
        if replay_from_ns is not None:
            start = min(i, bisect.bisect_right(self._keys, (replay_from_ns, len(_Kind), 0)))
        del self._states[start:]
        self._replay(start)
        if event.accepted:
            self.last_accepted_ns[event.source] = max(self.last_accepted_ns.get(event.source, 0), arrival_ns)
            self._count(f"{event.source}_fused")
        else:
            self._count(f"{event.source}_rejected")
        return UpdateResult(event.source, event.accepted, event.d2)

    def _replay(self, start: int) -> None:
        """Recompute the states from event ``start`` on (the states before it are kept)."""
        if start > 0:
            t_prev = self._events[start - 1].t_ns
            x, P = self._states[start - 1]
        else:
            t_prev, x, P = self._base
        for k in range(start, len(self._events)):
            event = self._events[k]
            x, P = self._predict(x, P, t_prev, event.t_ns)
            x, P = self._apply(event, x, P)
            self._states.append((x, P))
            t_prev = event.t_ns
        self.replayed_events += len(self._events) - start - 1 if len(self._events) > start else 0

    def _prune(self, newest_ns: int) -> None:
        """Fold events older than the history into the base state; forget odometry before it."""
        horizon = newest_ns - self.history_ns
        n = 0
        while n < len(self._events) - 1 and self._events[n].t_ns < horizon:
            n += 1
        if n:
            x, P = self._states[n - 1]
            self._base = (self._events[n - 1].t_ns, x, P)
            del self._events[:n], self._keys[:n], self._states[:n]
        base_t = self._base[0]
        while len(self._segments) > 1 and self._segments[0].t1_ns < base_t:
            self._segments.popleft()

    def _relocalize(self, event: _Event, arrival_ns: int) -> None:
        """Start again from a fix the filter kept rejecting: keep yaw rate and bias, drop the history."""
        x, P = self._latest()
        x = x.copy()
        P = P.copy()
        n = event.z.size
        x[:n] = event.z
        P[:n, :] = 0.0
        P[:, :n] = 0.0
        P[:n, :n] = event.R
        if n == 2:
            P[IYAW, IYAW] = max(P[IYAW, IYAW], math.radians(20.0) ** 2)
        self._base = (event.t_ns, x, P)
        self._events.clear()
        self._keys.clear()
        self._states.clear()
        self.reset_counter = (self.reset_counter + 1) % 256
        self.last_accepted_ns[event.source] = arrival_ns
        self._count("relocalizations")
