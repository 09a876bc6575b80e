"""A 2-D pose graph and its sparse least-squares optimisation (Gauss-Newton with a Huber kernel).

Nodes are poses x_k = (x_m, y_m, yaw_rad). A relative factor (i, j, z, s) says that x_j seen from x_i is z,
with standard deviations s = (s_x, s_y, s_yaw) in x_i's frame; its residual is

    r = diag(1/s) [ R(yaw_i)ᵀ (t_j - t_i) - z_t ;  wrap(yaw_j - yaw_i - z_yaw) ]

or, for a factor with a full covariance C (a scan match that fixes some directions better than others:
a corridor says little along itself), r = S [ ... ] with SᵀS = C⁻¹ (``RelativeFactors.sqrt_information``).

An absolute factor (k, z, s) (a VLP fix) says that x_k is z: r = diag(1/s) (x_k - z), the yaw wrapped.
Each factor's squared Mahalanobis norm e² = |r|² is weighted by Huber's kernel (weight 1 up to ``huber``,
huber / e beyond): a wrong loop closure pulls with a bounded force instead of bending the whole graph.

The normal equations H dx = -g, H = JᵀWJ, are sparse (3 x 3 blocks along the factors). Factors between
consecutive nodes (the chain) and absolute factors make a block-tridiagonal T; every other factor (a loop
closure) adds a rank-3 term, H = T + U Uᵀ with U (3N x 3L) the loops' whitened Jacobians. The solve is
block-tridiagonal elimination for T⁻¹ [g, U] (a few loops' columns at a time: memory) and the Woodbury
identity for the rest:
H⁻¹ g = T⁻¹ g - T⁻¹ U (I + Uᵀ T⁻¹ U)⁻¹ Uᵀ T⁻¹ g, a dense 3L x 3L system (L loops: tens). Plain numpy:
scipy's sparse solver (SuperLU) gave the same steps to rounding, but importing scipy.sparse.linalg puts
about 30 MB into the resident memory of the SLAM process (Intel's whole-log peak was 181 MB with it).
Without absolute factors the first node is held fixed (the gauge); a tiny ridge (1e-9) keeps T positive
definite where a node has no chain factor. Pure numpy: no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from agent.slam.pose import wrap_angle

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


@dataclass(frozen=True)
class RelativeFactors:
    i: IntArray  # (M,)
    j: IntArray  # (M,)
    z: FloatArray  # (M, 3): x_j in x_i's frame
    sigma: FloatArray  # (M, 3)
    # (M, 3, 3) or None: per factor S with SᵀS its information matrix (in x_i's frame), used instead of
    # diag(1 / sigma) where given; ``sqrt_information`` builds it from covariances.
    sqrt_information: FloatArray | None = None

    def whitening(self) -> FloatArray:
        """(M, 3, 3): each factor's S (diag(1 / sigma) where no full information is given)."""
        if self.sqrt_information is not None:
            return self.sqrt_information
        m = self.sigma.shape[0]
        out = np.zeros((m, 3, 3))
        out[:, [0, 1, 2], [0, 1, 2]] = 1.0 / self.sigma
        return out


def sqrt_information(covariance: FloatArray) -> FloatArray:
    """S (..., 3, 3) with SᵀS = C⁻¹ for covariances C (..., 3, 3): S = L⁻¹, C = L Lᵀ (Cholesky)."""
    lower = np.linalg.cholesky(covariance)
    inverse: FloatArray = np.linalg.inv(lower)
    return inverse


@dataclass(frozen=True)
class AbsoluteFactors:
    k: IntArray  # (P,)
    z: FloatArray  # (P, 3)
    sigma: FloatArray  # (P, 3)


@dataclass(frozen=True)
class GraphResult:
    poses: FloatArray
    iterations: int
    chi2_initial: float
    chi2_final: float
    downweighted: int  # factors beyond the Huber threshold at the end


def relative_residuals(poses: FloatArray, f: RelativeFactors) -> FloatArray:
    """(M, 3) whitened residuals of the relative factors."""
    a, b = poses[f.i], poses[f.j]
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    dx, dy = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]
    r = np.stack(
        [
            c * dx + s * dy - f.z[:, 0],
            -s * dx + c * dy - f.z[:, 1],
            wrap_angle(b[:, 2] - a[:, 2] - f.z[:, 2]),
        ],
        axis=1,
    )
    if f.sqrt_information is not None:
        full: FloatArray = np.einsum("mab,mb->ma", f.sqrt_information, r)
        return full
    whitened: FloatArray = r / f.sigma
    return whitened


def absolute_residuals(poses: FloatArray, f: AbsoluteFactors) -> FloatArray:
    d = poses[f.k] - f.z
    d[:, 2] = wrap_angle(d[:, 2])
    whitened: FloatArray = d / f.sigma
    return whitened


def _huber_weights(residuals: FloatArray, huber: float) -> FloatArray:
    e = np.sqrt(np.sum(residuals * residuals, axis=1))
    weights: FloatArray = np.where(e <= huber, 1.0, huber / np.maximum(e, 1e-12))
    return weights


def _chi2(poses: FloatArray, rel: RelativeFactors, ab: AbsoluteFactors | None) -> float:
    total = float(np.sum(relative_residuals(poses, rel) ** 2))
    if ab is not None and ab.k.size:
        total += float(np.sum(absolute_residuals(poses, ab) ** 2))
    return total


def optimize(
    initial: FloatArray,
    relative: RelativeFactors,
    absolute: AbsoluteFactors | None = None,
    huber: float = 3.0,
    max_iterations: int = 20,
    tolerance: float = 1e-6,
) -> GraphResult:
    """The poses (N, 3) minimising the Huber-weighted sum of the factors' squared residuals, from
    ``initial``. Stops when the largest step is below ``tolerance`` (metres or radians)."""
    poses = np.array(initial, dtype=np.float64, copy=True)
    n = poses.shape[0]
    has_absolute = absolute is not None and absolute.k.size > 0
    chi2_initial = _chi2(poses, relative, absolute)
    iterations = 0
    for _ in range(max_iterations):
        iterations += 1
        r = relative_residuals(poses, relative)
        weights_rel = _huber_weights(r, huber)
        a = poses[relative.i]
        b = poses[relative.j]
        c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
        dx, dy = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]
        m = relative.i.size
        # d r / d x_i and d r / d x_j (unwhitened), (M, 3, 3).
        ji = np.zeros((m, 3, 3))
        ji[:, 0, 0], ji[:, 0, 1], ji[:, 0, 2] = -c, -s, -s * dx + c * dy
        ji[:, 1, 0], ji[:, 1, 1], ji[:, 1, 2] = s, -c, -c * dx - s * dy
        ji[:, 2, 2] = -1.0
        jj = np.zeros((m, 3, 3))
        jj[:, 0, 0], jj[:, 0, 1] = c, s
        jj[:, 1, 0], jj[:, 1, 1] = -s, c
        jj[:, 2, 2] = 1.0
        if relative.sqrt_information is not None:
            whiten = relative.sqrt_information * np.sqrt(weights_rel)[:, None, None]
            ji = np.einsum("mab,mbc->mac", whiten, ji)
            jj = np.einsum("mab,mbc->mac", whiten, jj)
        else:
            scale = (np.sqrt(weights_rel)[:, None] / relative.sigma)[:, :, None]
            ji *= scale
            jj *= scale
        rw = r * np.sqrt(weights_rel)[:, None]
        ab_k = ab_j = ab_r = None
        if has_absolute:
            assert absolute is not None
            ra = absolute_residuals(poses, absolute)
            wa = np.sqrt(_huber_weights(ra, huber))
            ab_k = absolute.k
            ab_j = np.zeros((ab_k.size, 3, 3))
            ab_j[:, [0, 1, 2], [0, 1, 2]] = wa[:, None] / absolute.sigma
            ab_r = ra * wa[:, None]
        step = _normal_step(
            n, relative.i, relative.j, ji, jj, rw, ab_k, ab_j, ab_r, fix_first=not has_absolute
        )
        poses += step
        poses[:, 2] = wrap_angle(poses[:, 2])
        if float(np.max(np.abs(step))) < tolerance:
            break
    r = relative_residuals(poses, relative)
    downweighted = int(np.count_nonzero(np.sqrt(np.sum(r * r, axis=1)) > huber))
    return GraphResult(poses, iterations, chi2_initial, _chi2(poses, relative, absolute), downweighted)


_WOODBURY_BYTES = 2 << 20


def _normal_step(
    n: int,
    fi: IntArray,
    fj: IntArray,
    ji: FloatArray,
    jj: FloatArray,
    rw: FloatArray,
    ab_k: IntArray | None,
    ab_j: FloatArray | None,
    ab_r: FloatArray | None,
    fix_first: bool,
) -> FloatArray:
    """The Gauss-Newton step (n, 3): H dx = -g for relative factors with whitened Jacobians ``ji``,
    ``jj`` (M, 3, 3) and residuals ``rw`` (M, 3) and absolute factors (``ab_j`` (P, 3, 3), ``ab_r``) on
    nodes ``ab_k``; node 0 held at 0 if ``fix_first``. See the module docstring."""
    diag = np.zeros((n, 3, 3))
    upper = np.zeros((max(n - 1, 0), 3, 3))  # H[k, k+1]
    g = np.zeros((n, 3))
    np.add.at(g, fi, np.einsum("mai,ma->mi", ji, rw))
    np.add.at(g, fj, np.einsum("mai,ma->mi", jj, rw))
    forward = fj == fi + 1
    backward = fi == fj + 1
    chain = forward | backward
    np.add.at(diag, fi[chain], np.einsum("mai,maj->mij", ji[chain], ji[chain]))
    np.add.at(diag, fj[chain], np.einsum("mai,maj->mij", jj[chain], jj[chain]))
    if ab_k is not None and ab_j is not None and ab_r is not None:
        np.add.at(diag, ab_k, np.einsum("mai,maj->mij", ab_j, ab_j))
        np.add.at(g, ab_k, np.einsum("mai,ma->mi", ab_j, ab_r))
    np.add.at(upper, fi[forward], np.einsum("mai,maj->mij", ji[forward], jj[forward]))
    np.add.at(upper, fj[backward], np.einsum("mai,maj->mij", jj[backward], ji[backward]))
    loops = np.flatnonzero(~chain)
    li, lj = fi[loops], fj[loops]
    # U: one 3-column block per loop factor, its rows Jᵢᵀ at node i and Jⱼᵀ at node j (none at a fixed node).
    a_loop, b_loop = ji[loops], jj[loops]
    if fix_first:
        a_loop = np.where((li == 0)[:, None, None], 0.0, a_loop)
        b_loop = np.where((lj == 0)[:, None, None], 0.0, b_loop)
    diag += 1e-9 * np.eye(3)
    if fix_first:
        diag[0] = np.eye(3)
        g[0] = 0.0
        if n > 1:
            upper[0] = 0.0
    # Woodbury: Y = T⁻¹ U, Uᵀ Y from U's two blocks per loop, H⁻¹ g = T⁻¹ g - Y (I + Uᵀ Y)⁻¹ Uᵀ T⁻¹ g.
    # T⁻¹ [g, U] is eliminated a few loops' columns at a time (~_WOODBURY_BYTES of U each): its
    # elimination's temporaries are several times what they eliminate (Intel, ~900 nodes and ~120 loops:
    # ~8 MB each, ~40 MB at once, the SLAM process's peak RSS); Y itself is kept. Column by column the
    # same operations: the step is the one of a single elimination, bit for bit.
    count = loops.size
    per = max(1, _WOODBURY_BYTES // (n * 3 * 3 * 8))
    x0 = np.empty((n, 3, 1))
    y = np.empty((n, 3, 3 * count))  # contiguous: Y's (3N x 3L) view below is no copy
    for l0 in range(0, max(count, 1), per):
        l1 = min(l0 + per, count)
        cols = 3 * np.arange(l1 - l0)
        u = np.zeros((n, 3, 3 * (l1 - l0)))
        for c in range(3):
            u[li[l0:l1], :, cols + c] = a_loop[l0:l1, c, :]
            u[lj[l0:l1], :, cols + c] += b_loop[l0:l1, c, :]
        if l0 == 0:  # g rides with the first part
            solved = _block_tridiagonal_solve(diag, upper, np.concatenate([g[:, :, None], u], axis=2))
            x0[...] = solved[:, :, :1]
            y[:, :, : 3 * l1] = solved[:, :, 1:]
            del solved
        else:
            y[:, :, 3 * l0 : 3 * l1] = _block_tridiagonal_solve(diag, upper, u)
        del u
    x = x0.reshape(-1)
    if count:
        uty = (a_loop @ y[li] + b_loop @ y[lj]).reshape(3 * count, -1)
        utx = (a_loop @ x0[li] + b_loop @ x0[lj]).reshape(-1)
        capacitance = np.eye(uty.shape[0]) + uty
        x = x - y.reshape(3 * n, -1) @ np.linalg.solve(capacitance, utx)
    out: FloatArray = -x.reshape(n, 3)
    return out


def _block_tridiagonal_solve(diag: FloatArray, upper: FloatArray, rhs: FloatArray) -> FloatArray:
    """X (n, 3, R) with T X = rhs for the symmetric positive definite block-tridiagonal T of diagonal
    blocks ``diag`` (n, 3, 3) and blocks ``upper[k]`` = T[k, k+1]. Cyclic (odd-even) reduction: the odd
    nodes are eliminated all at once, leaving a block-tridiagonal system half the size on the even ones
    (Schur complements of an SPD matrix: stable without pivoting), log2(n) batched levels instead of a
    Python loop over the nodes."""
    n = diag.shape[0]
    if n <= 2:  # dense
        dense = np.zeros((3 * n, 3 * n))
        for k in range(n):
            dense[3 * k : 3 * k + 3, 3 * k : 3 * k + 3] = diag[k]
        if n == 2:
            dense[0:3, 3:6] = upper[0]
            dense[3:6, 0:3] = upper[0].T
        small = np.asarray(np.linalg.solve(dense, rhs.reshape(3 * n, -1)), dtype=np.float64)
        return small.reshape(rhs.shape)
    if n % 2 == 0:  # pad to an odd count with a decoupled node (x = 0 there)
        diag = np.concatenate([diag, np.eye(3)[None]])
        upper = np.concatenate([upper, np.zeros((1, 3, 3))])
        rhs = np.concatenate([rhs, np.zeros((1, *rhs.shape[1:]))])
    odd_inverse = np.linalg.inv(diag[1::2])  # (m, 3, 3), m = (n_odd - 1) / 2 odd nodes
    left, right = upper[0::2], upper[1::2]  # T[o-1, o] and T[o, o+1] for each odd o
    left_t = left.transpose(0, 2, 1)
    right_t = right.transpose(0, 2, 1)
    a = left @ odd_inverse  # T[o-1, o] D_o⁻¹
    b = right_t @ odd_inverse  # T[o+1, o] D_o⁻¹
    even_diag = diag[0::2].copy()
    even_rhs = rhs[0::2].copy()
    even_diag[:-1] -= a @ left_t
    even_diag[1:] -= b @ right
    odd_rhs = rhs[1::2]
    even_rhs[:-1] -= a @ odd_rhs
    even_rhs[1:] -= b @ odd_rhs
    even_x = _block_tridiagonal_solve(even_diag, -(a @ right), even_rhs)
    odd_x = odd_inverse @ (odd_rhs - left_t @ even_x[:-1] - right @ even_x[1:])
    x = np.empty_like(rhs)
    x[0::2] = even_x
    x[1::2] = odd_x
    out: FloatArray = x[:n]
    return out
