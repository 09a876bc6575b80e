"""The EKF (agent.fusion): the textbook steps against independent computations, and the filter over time
on seeded simulated runs (consistency, late measurements, gating, relocalisation, bias)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import chi2

from agent.fusion import (
    _H_POSE,
    _H_POSITION,
    N_STATE,
    FilterNoise,
    PoseFilter,
    Source,
    _inverse_small,
    ekf_predict,
    ekf_update,
    gate_threshold,
)

MS = 1_000_000


# -- the steps -------------------------------------------------------------------------------------------
def test_predict_moves_along_the_mid_interval_heading_and_its_jacobian_is_the_derivative() -> None:
    rng = np.random.default_rng(1)
    noise = FilterNoise()
    for _ in range(20):
        x = np.array([*rng.uniform(-5, 5, 2), rng.uniform(-math.pi, math.pi), rng.uniform(-1, 1), 0.01])
        P = np.eye(N_STATE) * 1e-4
        ds, dt = float(rng.uniform(-0.05, 0.05)), 0.02
        x1, _ = ekf_predict(x, P, ds, dt, noise)
        yaw_mid = x[2] + x[3] * dt / 2
        assert x1[0] == pytest.approx(x[0] + ds * math.cos(yaw_mid))
        assert x1[1] == pytest.approx(x[1] + ds * math.sin(yaw_mid))
        assert x1[2] == pytest.approx(math.remainder(x[2] + x[3] * dt, math.tau))
        # F from the covariance propagation of a state-only P (Q subtracted) against finite differences.
        F_numeric = np.zeros((N_STATE, N_STATE))
        for j in range(N_STATE):
            h = 1e-6
            xp, xm = x.copy(), x.copy()
            xp[j] += h
            xm[j] -= h
            fp, _ = ekf_predict(xp, P, ds, dt, noise)
            fm, _ = ekf_predict(xm, P, ds, dt, noise)
            d = fp - fm
            d[2] = math.remainder(d[2], math.tau)
            F_numeric[:, j] = d / (2 * h)
        E = np.eye(N_STATE)
        _, P_unit = ekf_predict(x, E, ds, dt, noise)
        _, Q = ekf_predict(x, np.zeros((N_STATE, N_STATE)), ds, dt, noise)
        np.testing.assert_allclose(P_unit - Q, F_numeric @ F_numeric.T, atol=1e-6)


def test_update_matches_the_standard_form_and_is_symmetric() -> None:
    rng = np.random.default_rng(2)
    A = rng.normal(size=(N_STATE, N_STATE))
    P = A @ A.T + np.eye(N_STATE) * 0.1
    x = rng.normal(size=N_STATE)
    H = np.eye(3, N_STATE)
    R = np.diag([0.01, 0.02, 0.03])
    z = H @ x + np.array([0.05, -0.02, 0.01])
    x1, P1, d2, ok = ekf_update(x, P, z, H, R, gate_d2=1e9, yaw_row=2)
    S = H @ P @ H.T + R
    K = P @ H.T @ np.linalg.inv(S)
    y = z - H @ x
    assert ok
    np.testing.assert_allclose(x1, x + K @ y, atol=1e-12)
    np.testing.assert_allclose(P1, (np.eye(N_STATE) - K @ H) @ P, atol=1e-10)  # equal for the optimal gain
    np.testing.assert_allclose(P1, P1.T)
    assert d2 == pytest.approx(float(y @ np.linalg.solve(S, y)))


def test_a_yaw_innovation_is_wrapped() -> None:
    x = np.array([0.0, 0.0, math.pi - 0.01, 0.0, 0.0])
    P = np.diag([1e-2, 1e-2, 1e-2, 1e-2, 1e-4])
    z = np.array([0.0, 0.0, -math.pi + 0.01])
    x1, _, d2, ok = ekf_update(x, P, z, np.eye(3, N_STATE), np.diag([1e-2] * 3), 20.0, yaw_row=2)
    assert ok and d2 == pytest.approx(0.02**2 / 0.02)  # 0.02 rad apart, not 2 pi - 0.02
    assert abs(math.remainder(x1[2] - math.pi, math.tau)) < 0.011


def test_gate_thresholds_are_chi_square_quantiles_and_outliers_are_refused() -> None:
    assert gate_threshold(2, 0.99) == pytest.approx(-2 * math.log(0.01))
    assert gate_threshold(3, 0.999) == pytest.approx(chi2.ppf(0.999, 3))
    x = np.zeros(N_STATE)
    P = np.eye(N_STATE) * 0.01
    x1, P1, d2, ok = ekf_update(x, P, np.array([1.0, 0.0]), np.eye(2, N_STATE), np.eye(2) * 0.01, 13.8)
    assert not ok and d2 == pytest.approx(1.0 / 0.02)
    assert x1 is x and P1 is P


# -- the filter over time --------------------------------------------------------------------------------
class Run:
    """A seeded drive: a base on a curving path, odometry every 20 ms (with noise, and host times off by
    ``stamp_jitter_ns``, one standard deviation), a gyro every 10 ms, and VLP fixes every 33 ms that arrive
    ``vlp_delay`` later."""

    def __init__(
        self, seed: int = 0, gyro_bias: float = 0.0, vlp_sigma: float = 0.004, stamp_jitter_ns: int = 2 * MS
    ) -> None:
        self.rng = np.random.default_rng(seed)
        self.gyro_bias = gyro_bias
        self.vlp_sigma = vlp_sigma
        self.stamp_jitter_ns = stamp_jitter_ns
        self.dt_ns = 2 * MS

    def truth(self, seconds: float) -> tuple[np.ndarray, np.ndarray]:
        n = int(seconds * 1e9 / self.dt_ns)
        t = np.arange(n) * self.dt_ns
        v = 0.2 + 0.05 * np.sin(t * 1e-9)
        omega = 0.6 * np.sin(0.5 * t * 1e-9)
        yaw = np.cumsum(omega) * self.dt_ns * 1e-9
        x = np.cumsum(v * np.cos(yaw)) * self.dt_ns * 1e-9
        y = np.cumsum(v * np.sin(yaw)) * self.dt_ns * 1e-9
        s = np.cumsum(v) * self.dt_ns * 1e-9
        return t, np.stack([x, y, yaw, omega, s], axis=1)

    def events(self, seconds: float, vlp_delay_ns: int = 30 * MS) -> list[tuple[int, str, tuple[float, ...]]]:
        """(arrival time, kind, values), sorted by arrival."""
        t, s = self.truth(seconds)
        out: list[tuple[int, str, tuple[float, ...]]] = []
        step = 10  # odometry every 20 ms
        for k in range(step, len(t), step):
            jitter = int(self.rng.normal(0, self.stamp_jitter_ns))  # the host time of a read is late or early
            t0 = int(t[k - step]) + (out[-1][2][1] - t[k - step] if out and out[-1][1] == "odo" else 0)
            t1 = int(t[k]) + jitter
            ds = (s[k, 4] - s[k - step, 4]) * (1 + self.rng.normal(0, 0.01))
            dyaw = s[k, 2] - s[k - step, 2] + self.rng.normal(0, 1e-4)
            out.append((t1 + 3 * MS, "odo", (float(t0), float(t1), float(ds), float(dyaw))))
        for k in range(0, len(t), 5):
            out.append(
                (int(t[k]) + MS, "gyro", (float(t[k]), s[k, 3] + self.gyro_bias + self.rng.normal(0, 0.003)))
            )
        for k in range(0, len(t), 17):
            z = s[k, :3] + self.rng.normal(0, self.vlp_sigma, 3) * np.array([1, 1, 0.5])
            out.append((int(t[k]) + vlp_delay_ns, "vlp", (float(t[k]), *map(float, z))))
        out.sort(key=lambda e: e[0])
        return out

    def feed(self, f: PoseFilter, events: list[tuple[int, str, tuple[float, ...]]]) -> None:
        cov = np.diag([self.vlp_sigma**2, self.vlp_sigma**2, (self.vlp_sigma / 2) ** 2])
        for arrival, kind, v in events:
            if kind == "odo":
                f.add_odometry(int(v[0]), int(v[1]), v[2], v[3], arrival_ns=arrival)
            elif kind == "gyro":
                f.add_gyro(int(v[0]), v[1], arrival_ns=arrival)
            else:
                f.add_pose(Source.VLP, int(v[0]), v[1], v[2], v[3], cov, arrival_ns=arrival, relocalize=True)


def new_filter(x0: tuple[float, float, float] = (0.0, 0.0, 0.0), **kw: object) -> PoseFilter:
    return PoseFilter(np.array(x0), np.diag([0.01**2, 0.01**2, 0.01**2]), 0, **kw)  # type: ignore[arg-type]


def test_a_drive_is_tracked_to_millimetres_and_the_filter_is_consistent() -> None:
    run = Run(seed=3)
    _, truth = run.truth(20.0)
    f = new_filter()
    nees = []
    errors = []
    t_truth, _ = run.truth(20.0)
    for arrival, kind, v in run.events(20.0):
        run.feed(f, [(arrival, kind, v)])
        if kind == "vlp" and arrival > 2e9:
            est = f.estimate()
            k = int(np.searchsorted(t_truth, est.t_ns))
            k = min(k, len(t_truth) - 1)
            e = np.array(
                [
                    est.x_m - truth[k, 0],
                    est.y_m - truth[k, 1],
                    math.remainder(est.yaw_rad - truth[k, 2], math.tau),
                ]
            )
            errors.append(math.hypot(e[0], e[1]))
            nees.append(float(e @ np.linalg.solve(est.covariance[:3, :3], e)))
    assert np.percentile(errors, 95) < 0.006
    # NEES of a consistent filter averages the state dimension (3); a grossly optimistic one does not.
    assert 0.5 < float(np.mean(nees)) < 6.0
    counts = f.counters()
    assert counts.get("vlp_rejected", 0) <= 0.02 * counts["vlp_fused"]
    assert counts["reset_counter"] == 0


def test_a_late_fix_gives_the_state_it_would_have_given_on_time() -> None:
    run = Run(seed=4)
    events = run.events(3.0, vlp_delay_ns=0)
    on_time, late = new_filter(), new_filter()
    run.feed(on_time, events)
    # The same measurements, but every VLP fix arrives 60 ms late, after odometry and gyro samples.
    delayed = sorted(
        [(a + 60 * MS, k, v) if k == "vlp" else (a, k, v) for a, k, v in events], key=lambda e: e[0]
    )
    run.feed(late, delayed)
    a, b = on_time.estimate(), late.estimate()
    assert a.t_ns == b.t_ns
    np.testing.assert_allclose([b.x_m, b.y_m, b.yaw_rad], [a.x_m, a.y_m, a.yaw_rad], atol=1e-9)
    np.testing.assert_allclose(b.covariance, a.covariance, atol=1e-12)
    assert late.counters()["replayed_events"] > on_time.counters()["replayed_events"]


def test_an_outlier_fix_is_refused_and_a_consistent_run_of_them_relocalizes() -> None:
    f = new_filter(history_s=2.0)
    cov = np.diag([0.005**2, 0.005**2, 0.01**2])
    for k in range(20):
        f.add_odometry(k * 20 * MS, (k + 1) * 20 * MS, 0.0, 0.0)
        f.add_pose(Source.VLP, (k + 1) * 20 * MS, 0.0, 0.0, 0.0, cov, relocalize=True)
    r = f.add_pose(Source.VLP, 420 * MS, 0.5, 0.0, 0.0, cov, relocalize=True)
    assert not r.accepted and r.mahalanobis_d2 > 1000
    assert f.estimate().x_m == pytest.approx(0.0, abs=1e-3)
    # The robot was carried 2 m away: the fixes agree with each other, not with the filter.
    results = [
        f.add_pose(Source.VLP, (430 + 10 * k) * MS, 2.0, 1.0, 0.5, cov, relocalize=True) for k in range(5)
    ]
    assert [r.relocalized for r in results] == [False, False, False, False, True]
    est = f.estimate()
    assert (est.x_m, est.y_m, est.yaw_rad) == pytest.approx((2.0, 1.0, 0.5), abs=1e-9)
    assert est.reset_counter == 1
    assert f.counters()["relocalizations"] == 1


def test_scattered_outliers_do_not_relocalize() -> None:
    f = new_filter()
    cov = np.diag([0.005**2, 0.005**2, 0.01**2])
    rng = np.random.default_rng(5)
    for k in range(10):
        xy = rng.uniform(-3, 3, 2)
        r = f.add_pose(Source.VLP, (k + 1) * 10 * MS, float(xy[0]), float(xy[1]), 0.0, cov, relocalize=True)
        assert not r.accepted and not r.relocalized
    assert f.reset_counter == 0


def test_the_gyro_bias_is_learnt_from_the_wheels() -> None:
    run = Run(seed=6, gyro_bias=0.02)
    f = new_filter()
    run.feed(f, [e for e in run.events(30.0) if e[1] != "vlp"])
    assert f.estimate().gyro_bias_radps == pytest.approx(0.02, abs=0.004)


def test_a_changing_turn_is_not_taken_for_gyro_bias() -> None:
    """Exact wheels and an exact, unbiased gyro through turns that speed up and slow down: the bias stays
    at zero. (The wheels' mean rate over an interval is the rate at its middle; taken at the interval's
    start it led the gyro, and the filter learnt the difference as a bias of 0.003 rad/s.)"""
    run = Run(seed=0)
    t, truth = run.truth(10.0)
    f = new_filter()
    events: list[tuple[int, str, tuple[float, ...]]] = []
    for k in range(10, len(t), 10):
        ds, dyaw = truth[k, 4] - truth[k - 10, 4], truth[k, 2] - truth[k - 10, 2]
        events.append((int(t[k]), "odo", (float(t[k - 10]), float(t[k]), float(ds), float(dyaw))))
    events += [(int(t[k]), "gyro", (float(t[k]), float(truth[k, 3]))) for k in range(0, len(t), 5)]
    biases = []
    for event in sorted(events, key=lambda e: e[0]):
        run.feed(f, [event])
        biases.append(f.estimate().gyro_bias_radps)
    assert max(abs(b) for b in biases) < 5e-4


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_wheel_reads_stamped_late_or_early_in_a_turn_do_not_throw_the_heading(seed: int) -> None:
    """Wheel reads whose host times are 4 ms off (a busy bus or CPU) while the robot turns: each interval's
    yaw rate is off by rate x (e1 - e0) / dt, tenths of a rad/s. Weighed as such against the gyro
    (``odometry_time_sigma_s``) they leave the heading within 0.3 deg; taken at the wheels' flat 0.02 rad/s
    they pulled it 0.4-0.6 deg off."""
    run = Run(seed=seed, stamp_jitter_ns=4 * MS)
    t, truth = run.truth(10.0)
    f = new_filter()
    worst = 0.0
    for event in run.events(10.0):
        run.feed(f, [event])
        if event[1] == "gyro" and event[0] > 1e9:
            est = f.estimate()
            k = min(int(np.searchsorted(t, est.t_ns)), len(t) - 1)
            worst = max(worst, abs(math.remainder(est.yaw_rad - truth[k, 2], math.tau)))
    assert math.degrees(worst) < 0.3


def test_a_measurement_older_than_the_history_is_refused() -> None:
    f = new_filter(history_s=0.5)
    for k in range(100):
        f.add_gyro(k * 10 * MS, 0.0)
    r = f.add_pose(Source.SLAM, 100 * MS, 0.0, 0.0, 0.0, np.eye(3) * 1e-4)
    assert r.too_old and not r.accepted
    assert f.counters()["slam_too_old"] == 1


def test_jittery_odometry_timestamps_do_not_throw_the_extrapolation() -> None:
    """One interval's speed is as jittery as its timestamps; what is held past the last sample is the
    speed over the last 200 ms (a 20 ms read stamped 15 ms late once made the filter jump 6 cm)."""
    f = new_filter()
    t = 0
    for k in range(20):
        dt = 20 * MS if k != 19 else 5 * MS  # the last read stamped 15 ms early: 0.8 m/s over 5 ms
        f.add_odometry(t, t + dt, 0.004, 0.0)
        t += dt
    ahead = f.estimate(t + 80 * MS)
    assert ahead.x_m == pytest.approx(0.080 + 0.2 * 0.080, abs=0.01)  # ~0.2 m/s held, not 0.8 m/s
    assert ahead.v_mps == pytest.approx(0.2, abs=0.05)


def test_sources_are_live_within_their_timeouts() -> None:
    f = new_filter()
    f.add_gyro(10 * MS, 0.0, arrival_ns=10 * MS)
    f.add_pose(Source.VLP, 20 * MS, 0.0, 0.0, 0.0, np.eye(3) * 1e-4, arrival_ns=40 * MS)
    timeouts = {Source.VLP: 100 * MS, Source.IMU: 50 * MS}
    assert f.live(50 * MS, timeouts) == {Source.VLP, Source.IMU}
    assert f.live(100 * MS, timeouts) == {Source.VLP}
    assert f.live(200 * MS, timeouts) == set()


def test_position_only_fixes_and_bad_input() -> None:
    f = new_filter()
    r = f.add_pose(Source.VLP, 10 * MS, 0.001, 0.0, None, np.eye(2) * 1e-4)
    assert r.accepted
    with pytest.raises(ValueError, match="covariance"):
        f.add_pose(Source.VLP, 20 * MS, 0.0, 0.0, 0.0, np.eye(2))
    with pytest.raises(ValueError, match="finite"):
        f.add_pose(Source.VLP, 20 * MS, math.nan, 0.0, 0.0, np.eye(3))
    assert not f.add_odometry(50 * MS, 40 * MS, 0.1, 0.0).accepted
    with pytest.raises(ValueError):
        PoseFilter(np.zeros(4), np.eye(3), 0)


def test_update_matches_the_textbook_formulas() -> None:
    # ekf_update inverts S by cofactors and reuses P H^T: the same numbers as the formulas written out.
    rng = np.random.default_rng(7)
    for H in (_H_POSE, _H_POSITION):
        m = H.shape[0]
        for _ in range(20):
            a = rng.normal(size=(5, 5))
            P = a @ a.T * 0.01 + 1e-4 * np.eye(5)
            b = rng.normal(size=(m, m))
            R = b @ b.T * 1e-3 + 1e-5 * np.eye(m)
            x = rng.normal(size=5)
            z = H @ x + rng.normal(size=m) * 0.01
            S = H @ P @ H.T + R
            assert np.allclose(_inverse_small(S), np.linalg.inv(S), rtol=1e-9, atol=0.0)
            K = P @ H.T @ np.linalg.inv(S)
            y = z - H @ x
            I_KH = np.eye(5) - K @ H
            P_ref = I_KH @ P @ I_KH.T + K @ R @ K.T
            x_new, P_new, d2, ok = ekf_update(x, P, z, H, R, 1e9)
            assert ok
            assert d2 == pytest.approx(float(y @ np.linalg.inv(S) @ y), rel=1e-9)
            assert np.allclose(x_new[[0, 1, 3, 4]], (x + K @ y)[[0, 1, 3, 4]], rtol=1e-9, atol=1e-12)
            assert np.allclose(P_new, 0.5 * (P_ref + P_ref.T), rtol=1e-9, atol=1e-15)
