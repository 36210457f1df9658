"""The closed-form Gaussian solves of a person's fold-in (``foldin``'s module docstring
gives the model): the plain posterior, the scale mixture over prior scales with each
scale's marginal likelihood, and the ridge override; LAPACK's Cholesky directly, in float64."""
from __future__ import annotations

from typing import Sequence

import numpy as np
from scipy.linalg import lapack

from stars_ros.personalisation.prior import PRIOR_SCALES


def cholesky(matrix: np.ndarray) -> np.ndarray:
    """The lower Cholesky factor of a symmetric positive-definite float64 ``matrix``, by
    LAPACK's potrf directly: ``scipy.linalg.cho_factor``'s checks and wrapping cost more than
    the factorisation itself at the fold-in's sizes (d + 1 = 65), and an update factorises
    once per prior scale."""
    factor, info = lapack.dpotrf(matrix, lower=1, clean=0)
    if info != 0:
        raise np.linalg.LinAlgError(f'matrix is not positive definite (LAPACK potrf info {info})')
    return factor


def cho_solve(factor: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """matrix⁻¹ ``rhs`` from ``cholesky(matrix)`` (LAPACK's potrs; ``rhs`` a vector or columns)."""
    solution, info = lapack.dpotrs(factor, rhs, lower=1)
    if info != 0:
        raise ValueError(f'LAPACK potrs: argument {-info} is invalid')
    return solution


def gaussian_posterior(x: np.ndarray, y: np.ndarray, noise: np.ndarray, prior_mean: np.ndarray,
                       prior_precision: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(mean, covariance) of θ given y ~ N(xθ, diag(noise)) and θ ~ N(prior_mean, prior_precision⁻¹)."""
    x = np.asarray(x, dtype=np.float64)
    weighted = x / np.asarray(noise, dtype=np.float64)[:, None]
    factor = cholesky(prior_precision + weighted.T @ x)
    mean = cho_solve(factor, prior_precision @ prior_mean + weighted.T @ np.asarray(y, dtype=np.float64))
    return mean, cho_solve(factor, np.eye(len(mean)))


def scale_mixture_posterior(x: np.ndarray, y: np.ndarray, noise: np.ndarray, prior_mean: np.ndarray,
                            prior_precision: np.ndarray, prior_logdet: float,
                            scales: Sequence[float] = PRIOR_SCALES,
                            with_covariance: bool = True) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """(mean, covariance, weights) of θ given y ~ N(xθ, diag(noise)) and θ ~ N(prior_mean, τΣ)
    with τ equally likely each of ``scales`` (Σ = prior_precision⁻¹, ``prior_logdet`` its log
    determinant; τ = 0 pins θ to the mean). ``weights`` [scales] are the posterior
    probabilities of the scales, from each one's marginal likelihood of y; the mean and
    covariance are the mixture's (``with_covariance`` False: None, and d fewer solves per scale)."""
    x, noise = np.asarray(x, dtype=np.float64), np.asarray(noise, dtype=np.float64)
    size = len(prior_mean)
    if not len(x):
        covariance = float(np.mean(scales)) * np.linalg.inv(prior_precision) if with_covariance else None
        return prior_mean.copy(), covariance, np.full(len(scales), 1 / len(scales))
    residual = np.asarray(y, dtype=np.float64) - x @ prior_mean
    weighted = x / noise[:, None]
    gram, pull = weighted.T @ x, weighted.T @ residual
    base = float(residual @ (residual / noise) + np.sum(np.log(noise)))
    means, covariances, log_evidence = [], [], []
    for scale in scales:
        if scale == 0:
            means.append(prior_mean)
            covariances.append(np.zeros((size, size)))
            log_evidence.append(-0.5 * base)
            continue
        factor = cholesky(prior_precision / scale + gram)
        shift = cho_solve(factor, pull)
        logdet = 2 * np.sum(np.log(np.diag(factor)))
        log_evidence.append(-0.5 * (base - pull @ shift + size * np.log(scale) + prior_logdet + logdet))
        means.append(prior_mean + shift)
        if with_covariance:
            covariances.append(cho_solve(factor, np.eye(size)))
    log_evidence = np.array(log_evidence)
    weights = np.exp(log_evidence - log_evidence.max())
    weights /= weights.sum()
    mean = np.einsum('s,sd->d', weights, np.array(means))
    if not with_covariance:
        return mean, None, weights
    spread = np.array(means) - mean
    covariance = np.einsum('s,sde->de', weights, np.array(covariances)) + (spread * weights[:, None]).T @ spread
    return mean, covariance, weights


def solve_ridge(x: np.ndarray, y: np.ndarray, prior: np.ndarray, regularisation: float) -> np.ndarray:
    """argmin_θ ‖xθ − y‖² + λ‖θ − prior‖² via the normal equations (λ > 0 keeps them regular)."""
    if not regularisation > 0:
        raise ValueError('regularisation must be positive')
    x = np.asarray(x, dtype=np.float64)
    gram = x.T @ x + regularisation * np.eye(x.shape[1])
    return np.linalg.solve(gram, x.T @ np.asarray(y, dtype=np.float64) + regularisation * prior)
