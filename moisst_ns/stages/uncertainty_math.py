"""Standard deviations of least-squares parameters from residuals and their Jacobian (Gauss-Newton / Fisher).

At a least-squares solution ``x`` of residuals ``r(x)`` with Jacobian ``J``, the Gauss-Newton information is
``H = J^T J``. Two estimates of ``Cov(x)``:

* *classical*: ``s^2 H^-1`` with ``s^2 = r^T r / (n - p)``: exact for independent residuals of equal variance;
* *cluster-robust* (sandwich, Liang & Zeger 1986): ``H^-1 (sum_g J_g^T r_g r_g^T J_g) H^-1 G / (G - 1)`` over clusters
  ``g`` (e.g. the frames the rays come from): valid for any correlation *within* a cluster (neighbouring pixels
  of a NeRF share its errors), it is the linearised jackknife over clusters: how far the estimate would move if
  the frames were drawn again.

``sigmas`` takes, per parameter, the larger of the two (the classical one guards against a sandwich that is
unreliable with few clusters). A parameter the residuals do not constrain (``H`` singular along it) gets inf.

Pure numpy: nothing here imports nerfstudio.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from jaxtyping import Float, Int


@dataclass
class LeastSquaresSigma:
    """Standard deviations of the parameters of a least-squares fit."""

    sigma: Float[np.ndarray, "p"]
    """Reported standard deviation per parameter: max of classical and cluster-robust (parameter units)."""
    classical: Float[np.ndarray, "p"]
    """``sqrt(diag(s^2 H^-1))``."""
    robust: Float[np.ndarray, "p"]
    """``sqrt(diag)`` of the cluster-robust sandwich (nan with fewer than 2 clusters)."""
    residual_rms: float
    """``s``, residual units."""
    clusters: int
    """Number of clusters."""


def least_squares_sigma(
    jacobian: Float[np.ndarray, "n p"], residuals: Float[np.ndarray, "n"], clusters: Int[np.ndarray, "n"],
    rcond: float = 1e-10,
) -> LeastSquaresSigma:
    """Classical and cluster-robust standard deviations at a least-squares solution.

    Args:
        jacobian: ``d r / d x`` (residual units per parameter unit).
        residuals: residuals at the solution.
        clusters: cluster label of every residual (residuals of one cluster may be correlated).
        rcond: relative eigenvalue below which a direction of ``H`` counts as unconstrained (sigma inf).

    Returns:
        ``LeastSquaresSigma``.
    """
    jac = np.asarray(jacobian, dtype=np.float64)
    res = np.asarray(residuals, dtype=np.float64)
    n, p = jac.shape
    info = jac.T @ jac
    vals, vecs = np.linalg.eigh(info)
    keep = vals > rcond * max(float(vals.max()), 1e-300)
    inv = (vecs[:, keep] / vals[keep]) @ vecs[:, keep].T
    free = np.abs(vecs[:, ~keep]).max(axis=1) > 1e-6 if (~keep).any() else np.zeros(p, dtype=bool)
    s2 = float(res @ res) / max(n - p, 1)
    classical = np.sqrt(np.maximum(np.diag(inv) * s2, 0.0))
    labels, index = np.unique(np.asarray(clusters), return_inverse=True)
    groups = len(labels)
    if groups >= 2:
        scores = np.zeros((groups, p))
        np.add.at(scores, index, jac * res[:, None])
        meat = scores.T @ scores * groups / (groups - 1)
        robust = np.sqrt(np.maximum(np.diag(inv @ meat @ inv), 0.0))
    else:
        robust = np.full(p, np.nan)
    sigma = np.fmax(classical, robust)
    sigma[free] = np.inf
    classical[free] = np.inf
    return LeastSquaresSigma(sigma, classical, robust, float(np.sqrt(s2)), groups)
