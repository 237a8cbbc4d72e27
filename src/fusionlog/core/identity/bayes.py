"""Bayesian identity fusion (Challa & Koks, seed 004, Sec. 3.2, eqs. 35-41).

Equation numbers are those of Challa & Koks, "Bayesian and Dempster-Shafer fusion"
(``shared/seeds/004_e832512ceaf07c5b.txt``).

Sensor i reports, for each class x, either a likelihood (y^i | x, Y_0^i) of its latest
measurement (eq. 37) or a posterior (x | Y_1^i) computed with its own prior (x | Y_0^i); in the
second case the sensor's prior is divided out, eq. (38) for two sensors and (41) for three or
more:

    (x | Y_1^1 ... Y_1^S) = c prod_i [(x | Y_1^i) / (x | Y_0^i)] (x | Y_0^1 ... Y_0^S),

with c normalising over the classes x.

Pure functions (numpy only, no I/O). Invalid input raises ValueError with a one-line message.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

__all__ = ["bayes_fusion", "bayes_fusion_posteriors"]


def _nonneg_finite(a: ArrayLike, name: str) -> np.ndarray:
    arr = np.asarray(a, dtype=float)
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite")
    if np.any(arr < 0):
        raise ValueError(f"{name} must be non-negative (got {arr.min():g})")
    return arr


def bayes_fusion(likelihoods: ArrayLike, prior: ArrayLike) -> np.ndarray:
    """Fuse several sensors' class likelihoods with the fusion node's prior, eqs. (36)-(37).

    (x | Y_1^1 ... Y_1^S) = prod_i (y_1^i | x, Y_0^i) (x | Y_0^1 ... Y_0^S) / normalisation: the
    measurements are conditionally independent given the class (eq. 36), so the joint likelihood
    is the product of the sensors' likelihoods (eq. 37).

    Args:
        likelihoods: shape (..., S, C): for each of S sensors, the likelihood of its latest data
            for each of C classes (non-negative; need not sum to one; only ratios matter). Leading
            dimensions are batch dimensions (runs, steps, ...). One sensor is shape (..., 1, C).
        prior: the fusion node's prior (x | Y_0^1 ... Y_0^S), broadcastable to (..., C);
            non-negative, normalised by the function.

    Returns:
        Normalised fused class probabilities, shape broadcast(likelihoods[..., 0, :], prior).

    Computed in log space, so many sensors with small likelihoods do not underflow.
    """
    lik = _nonneg_finite(likelihoods, "likelihoods")
    pri = _nonneg_finite(prior, "prior")
    if lik.ndim < 2:
        raise ValueError(
            f"likelihoods must have shape (..., sensors, classes), got {lik.shape}; "
            "use shape (1, C) for one sensor"
        )
    if pri.ndim < 1 or pri.shape[-1] != lik.shape[-1]:
        raise ValueError(
            f"prior has {pri.shape[-1] if pri.ndim else 0} classes but likelihoods have "
            f"{lik.shape[-1]}"
        )
    try:
        out_shape = np.broadcast_shapes(lik.shape[:-2] + lik.shape[-1:], pri.shape)
    except ValueError:
        raise ValueError(
            f"prior shape {pri.shape} does not broadcast against likelihoods shape {lik.shape}"
        ) from None
    with np.errstate(divide="ignore"):
        log_post = np.log(lik).sum(axis=-2) + np.log(pri)
    log_post = np.broadcast_to(log_post, out_shape)
    top = log_post.max(axis=-1, keepdims=True)
    if np.any(np.isneginf(top)):
        raise ValueError(
            "fused evidence is zero for every class (prior and sensors exclude all classes)"
        )
    w = np.exp(log_post - top)
    return w / w.sum(axis=-1, keepdims=True)


def bayes_fusion_posteriors(
    posteriors: ArrayLike, sensor_priors: ArrayLike, prior: ArrayLike
) -> np.ndarray:
    """Fuse sensors' class posteriors, dividing out each sensor's own prior, eqs. (38) and (41).

    (x | Y_1^1 ... Y_1^S) = c prod_i [(x | Y_1^i) / (x | Y_0^i)] (x | Y_0^1 ... Y_0^S),
    c normalising over x: eq. (38) for S = 2 and eq. (41) for S = 3 ("and so on for more
    sensors"). By Bayes' rule, (x | Y_1^i) / (x | Y_0^i) is proportional in x to the likelihood
    (y_1^i | x, Y_0^i), so this is :func:`bayes_fusion` applied to those ratios.
    This is the paper's Tables 1-2 example.

    Args:
        posteriors: shape (..., S, C): each sensor's posterior (x | Y_1^i) after its latest data.
        sensor_priors: broadcastable to (..., S, C): each sensor's previous posterior
            (x | Y_0^i), strictly positive (it is divided by).
        prior: the fusion node's prior (x | Y_0^1 ... Y_0^S), broadcastable to (..., C).

    Returns:
        Normalised fused class probabilities, shape (..., C).
    """
    post = _nonneg_finite(posteriors, "posteriors")
    sp = _nonneg_finite(sensor_priors, "sensor_priors")
    if np.any(sp == 0):
        raise ValueError("sensor_priors must be strictly positive (eqs. 38/41 divide by them)")
    if post.ndim < 2:
        raise ValueError(
            f"posteriors must have shape (..., sensors, classes), got {post.shape}; "
            "use shape (1, C) for one sensor"
        )
    try:
        np.broadcast_shapes(post.shape, sp.shape)
    except ValueError:
        raise ValueError(
            f"sensor_priors shape {sp.shape} does not broadcast against posteriors shape "
            f"{post.shape}"
        ) from None
    if sp.ndim < 1 or sp.shape[-1] != post.shape[-1]:
        raise ValueError("sensor_priors and posteriors have different numbers of classes")
    return bayes_fusion(post / sp, prior)
