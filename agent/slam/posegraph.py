"""A 2-D pose graph and its sparse least-squares optimisation (Gauss-Newton with a Huber kernel).

Nodes are poses x_k = (x_m, y_m, yaw_rad). A relative factor (i, j, z, s) says that x_j seen from x_i is z,
with standard deviations s = (s_x, s_y, s_yaw) in x_i's frame; its residual is

    r = diag(1/s) [ R(yaw_i)ᵀ (t_j - t_i) - z_t ;  wrap(yaw_j - yaw_i - z_yaw) ]

or, for a factor with a full covariance C (a scan match that fixes some directions better than others:
a corridor says little along itself), r = S [ ... ] with SᵀS = C⁻¹ (``RelativeFactors.sqrt_information``).

An absolute factor (k, z, s) (a VLP fix) says that x_k is z: r = diag(1/s) (x_k - z), the yaw wrapped.
Each factor's squared Mahalanobis norm e² = |r|² is weighted by Huber's kernel (weight 1 up to ``huber``,
huber / e beyond): a wrong loop closure pulls with a bounded force instead of bending the whole graph.

The normal equations JᵀWJ dx = -JᵀWr are sparse (3 x 3 blocks along the factors) and solved with
``scipy.sparse.linalg.spsolve`` (SuperLU); without absolute factors the first node is held fixed (the
gauge). Pure numpy / scipy: no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp
import scipy.sparse.linalg as spla

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
        rows = np.arange(3 * m).reshape(m, 3)
        data = [ji.reshape(-1), jj.reshape(-1)]
        row_idx = [np.repeat(rows, 3, axis=1).reshape(-1)] * 2
        col_i = (3 * relative.i[:, None, None] + np.arange(3)[None, None, :]).repeat(3, axis=1)
        col_j = (3 * relative.j[:, None, None] + np.arange(3)[None, None, :]).repeat(3, axis=1)
        col_idx = [col_i.reshape(-1), col_j.reshape(-1)]
        residual_parts = [rw.reshape(-1)]
        if has_absolute:
            assert absolute is not None
            ra = absolute_residuals(poses, absolute)
            wa = np.sqrt(_huber_weights(ra, huber))
            p = absolute.k.size
            base = 3 * m
            jab = np.zeros((p, 3, 3))
            jab[:, [0, 1, 2], [0, 1, 2]] = wa[:, None] / absolute.sigma
            prow = base + np.arange(3 * p).reshape(p, 3)
            data.append(jab.reshape(-1))
            row_idx.append(np.repeat(prow, 3, axis=1).reshape(-1))
            col_idx.append(
                (3 * absolute.k[:, None, None] + np.arange(3)[None, None, :]).repeat(3, axis=1).reshape(-1)
            )
            residual_parts.append((ra * wa[:, None]).reshape(-1))
        residual = np.concatenate(residual_parts)
        jac = sp.csr_matrix(
            (np.concatenate(data), (np.concatenate(row_idx), np.concatenate(col_idx))),
            shape=(residual.size, 3 * n),
        )
        free = np.arange(3 * n) if has_absolute else np.arange(3, 3 * n)  # gauge: node 0 fixed
        jf = jac[:, free]
        h = (jf.T @ jf).tocsc() + sp.identity(free.size, format="csc") * 1e-9
        g = jf.T @ residual
        step = np.asarray(spla.spsolve(h, -g), dtype=np.float64)
        full = np.zeros(3 * n)
        full[free] = step
        poses += full.reshape(n, 3)
        poses[:, 2] = wrap_angle(poses[:, 2])
        if float(np.max(np.abs(step))) < tolerance:
            break
    r = relative_residuals(poses, relative)
    downweighted = int(np.count_nonzero(np.sqrt(np.sum(r * r, axis=1)) > huber))
    return GraphResult(poses, iterations, chi2_initial, _chi2(poses, relative, absolute), downweighted)
