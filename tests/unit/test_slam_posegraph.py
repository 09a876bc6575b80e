"""The pose graph's numpy solver (block-tridiagonal cyclic reduction + Woodbury) against a dense solve of
the same normal equations."""

from __future__ import annotations

import numpy as np
import pytest

from agent.slam import posegraph
from agent.slam.pose import between
from agent.slam.posegraph import (
    AbsoluteFactors,
    RelativeFactors,
    _block_tridiagonal_solve,
    _normal_step,
    optimize,
)


def _dense_step(
    n: int,
    fi: np.ndarray,
    fj: np.ndarray,
    ji: np.ndarray,
    jj: np.ndarray,
    rw: np.ndarray,
    ab: tuple[np.ndarray, np.ndarray, np.ndarray] | None,
    fix_first: bool,
) -> np.ndarray:
    """-H⁻¹ g from the dense Jacobian (the reference)."""
    rows = []
    residual = []
    for m in range(fi.size):
        block = np.zeros((3, 3 * n))
        block[:, 3 * fi[m] : 3 * fi[m] + 3] = ji[m]
        block[:, 3 * fj[m] : 3 * fj[m] + 3] += jj[m]
        rows.append(block)
        residual.append(rw[m])
    if ab is not None:
        k, jab, rab = ab
        for p in range(k.size):
            block = np.zeros((3, 3 * n))
            block[:, 3 * k[p] : 3 * k[p] + 3] = jab[p]
            rows.append(block)
            residual.append(rab[p])
    jac = np.vstack(rows)
    r = np.concatenate(residual)
    free = np.arange(3, 3 * n) if fix_first else np.arange(3 * n)
    jf = jac[:, free]
    h = jf.T @ jf + 1e-9 * np.eye(free.size)
    step = np.zeros(3 * n)
    step[free] = -np.linalg.solve(h, jf.T @ r)
    return step.reshape(n, 3)


@pytest.mark.parametrize("n", [1, 2, 3, 8, 37, 64])
def test_block_tridiagonal_solve_matches_dense(n: int) -> None:
    rng = np.random.default_rng(n)
    a = rng.normal(size=(n, 3, 3))
    diag = np.einsum("nij,nkj->nik", a, a) + 5.0 * np.eye(3)
    upper = 0.5 * rng.normal(size=(max(n - 1, 0), 3, 3))
    dense = np.zeros((3 * n, 3 * n))
    for k in range(n):
        dense[3 * k : 3 * k + 3, 3 * k : 3 * k + 3] = diag[k]
        if k + 1 < n:
            dense[3 * k : 3 * k + 3, 3 * k + 3 : 3 * k + 6] = upper[k]
            dense[3 * k + 3 : 3 * k + 6, 3 * k : 3 * k + 3] = upper[k].T
    rhs = rng.normal(size=(n, 3, 4))
    x = _block_tridiagonal_solve(diag, upper, rhs)
    np.testing.assert_allclose(dense @ x.reshape(3 * n, 4), rhs.reshape(3 * n, 4), atol=1e-9)


@pytest.mark.parametrize(
    ("n", "absolute", "part_bytes"),
    [(30, False, None), (31, True, None), (2, False, None), (30, False, 1), (31, True, 2000)],
)
def test_normal_step_matches_dense(
    n: int, absolute: bool, part_bytes: int | None, monkeypatch: pytest.MonkeyPatch
) -> None:
    if part_bytes is not None:  # T⁻¹ [g, U] eliminated in parts of one / two loops
        monkeypatch.setattr(posegraph, "_WOODBURY_BYTES", part_bytes)
    rng = np.random.default_rng(n)
    chain = np.arange(n - 1)
    loops_i = rng.integers(0, max(n - 5, 1), 6)
    loops_j = np.minimum(loops_i + rng.integers(2, 5, 6), n - 1)
    keep = loops_j - loops_i >= 2
    # One chain factor written backwards (j -> i) and loops from node 0: both layouts must be handled.
    fi = np.concatenate([chain, loops_i[keep], [0] if n > 3 else []]).astype(np.int64)
    fj = np.concatenate([chain + 1, loops_j[keep], [n - 1] if n > 3 else []]).astype(np.int64)
    if n > 3:
        fi[1], fj[1] = fj[1], fi[1]
    m = fi.size
    # As a pose graph's (whitened) Jacobians are: near -R and R, here near -I and I.
    ji = -np.eye(3) + 0.2 * rng.normal(size=(m, 3, 3))
    jj = np.eye(3) + 0.2 * rng.normal(size=(m, 3, 3))
    rw = rng.normal(size=(m, 3))
    ab = None
    if absolute:
        k = np.array([0, n // 2], dtype=np.int64)
        ab = (k, np.tile(np.diag([10.0, 10.0, 20.0]), (2, 1, 1)), rng.normal(size=(2, 3)))
    if ab is None:
        got = _normal_step(n, fi, fj, ji, jj, rw, None, None, None, fix_first=True)
    else:
        got = _normal_step(n, fi, fj, ji, jj, rw, ab[0], ab[1], ab[2], fix_first=False)
    want = _dense_step(n, fi, fj, ji, jj, rw, ab, not absolute)
    np.testing.assert_allclose(got, want, rtol=1e-7, atol=1e-9)


def test_optimize_closes_a_drifted_loop() -> None:
    """A square driven twice with drifting odometry and loop factors back to the first lap."""
    rng = np.random.default_rng(3)
    side = 10
    truth = []
    x, y, yaw = 0.0, 0.0, 0.0
    for _lap in range(2):
        for _ in range(4):
            for _ in range(side):
                truth.append((x, y, yaw))
                x += np.cos(yaw)
                y += np.sin(yaw)
            yaw += np.pi / 2
    poses = np.array(truth)
    n = poses.shape[0]
    motions = between(poses[:-1], poses[1:]) + rng.normal(0.0, [0.01, 0.01, 0.01], (n - 1, 3))
    motions[:, 2] += 0.01  # a yaw bias: the second lap drifts away from the first
    drifted = np.zeros_like(poses)
    for k in range(1, n):
        c, s = np.cos(drifted[k - 1, 2]), np.sin(drifted[k - 1, 2])
        dx, dy, dyaw = motions[k - 1]
        drifted[k] = drifted[k - 1] + (c * dx - s * dy, s * dx + c * dy, dyaw)
    lap = 4 * side
    li = np.arange(0, lap, 5)
    i = np.concatenate([np.arange(n - 1), li])
    j = np.concatenate([np.arange(1, n), li + lap])
    z = np.vstack([motions, between(poses[li], poses[li + lap])])
    sigma = np.vstack([np.tile([0.02, 0.02, 0.01], (n - 1, 1)), np.tile([0.02, 0.02, 0.01], (li.size, 1))])
    result = optimize(drifted, RelativeFactors(i, j, z, sigma))
    before = np.abs(drifted[lap:, :2] - drifted[:lap, :2]).max()
    after = np.abs(result.poses[lap:, :2] - result.poses[:lap, :2]).max()
    assert before > 1.0
    assert after < 0.2
    assert result.chi2_final < result.chi2_initial
    absolute = AbsoluteFactors(np.array([0]), poses[:1], np.array([[0.01, 0.01, 0.01]]))
    anchored = optimize(drifted, RelativeFactors(i, j, z, sigma), absolute)
    np.testing.assert_allclose(anchored.poses[0], poses[0], atol=0.05)
