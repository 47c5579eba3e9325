"""Sequential thresholded least squares (the SINDy regression) for the "other" fallback."""

from __future__ import annotations

import numpy as np


def stlsq(theta: np.ndarray, target: np.ndarray, threshold: float, max_iter: int = 10) -> np.ndarray:
    """Sparse coefficients c with target ~ theta @ c (Brunton et al. 2016, algorithm STLSQ).

    Columns are standardised first, so ``threshold`` applies to the change of the target (in
    target units) per one standard deviation of a term: terms whose effect is below it are
    dropped and the rest refitted, until the support stops changing.
    """
    scale = np.std(theta, axis=0)
    # A constant column has zero spread; scale it by its magnitude instead.
    const = scale < 1e-12
    scale[const] = np.abs(theta[0, const]) if theta.shape[0] else 1.0
    scale[scale < 1e-12] = 1.0
    z = theta / scale
    coef = np.linalg.lstsq(z, target, rcond=None)[0]
    active = np.abs(coef) >= threshold
    for _ in range(max_iter):
        coef = np.zeros(z.shape[1])
        if active.any():
            coef[active] = np.linalg.lstsq(z[:, active], target, rcond=None)[0]
        new_active = np.abs(coef) >= threshold
        if np.array_equal(new_active, active):
            break
        active = new_active
    coef[~active] = 0.0
    return coef / scale


def coefficient_std(theta: np.ndarray, target: np.ndarray, coef: np.ndarray, clusters: np.ndarray) -> np.ndarray:
    """Cluster-robust (sandwich) standard errors of the non-zero coefficients (zeros stay 0)."""
    active = coef != 0
    std = np.zeros_like(coef)
    if not active.any():
        return std
    a = theta[:, active]
    resid = target - theta @ coef
    bread = np.linalg.pinv(a.T @ a)
    scores = a * resid[:, None]
    _, inverse = np.unique(clusters, return_inverse=True)
    g = np.zeros((inverse.max() + 1, a.shape[1]))
    np.add.at(g, inverse, scores)
    cov = bread @ (g.T @ g) @ bread
    std[active] = np.sqrt(np.maximum(np.diag(cov), 0.0))
    return std
