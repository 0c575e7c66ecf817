"""Likelihood of logged feature values under the distribution of the simulated ones (WOSAC §3).

Every evaluated object gets its own histogram, pooled over all rollouts and steps (simulated samples
are never masked, NaNs included); every logged value is then scored independently against it.
Edges and binning follow the reference float32 behaviour, NaN included (it falls in the top bin).
"""

from __future__ import annotations

import numpy as np

from trajeglish_env.metrics.config import BernoulliEstimator, HistogramEstimator

__all__ = [
    "bernoulli_log_likelihood",
    "bin_index",
    "histogram_edges",
    "histogram_log_likelihood",
    "masked_score",
]


def histogram_edges(estimator: HistogramEstimator) -> np.ndarray:
    """Bin edges ``[K+1]`` in float32: ``min + k * ((max - min) / K)``, the last one exactly ``max``."""
    lo, hi = np.float32(estimator.min_value), np.float32(estimator.max_value)
    width = (hi - lo) / np.float32(estimator.num_bins)
    edges = lo + np.arange(estimator.num_bins + 1, dtype=np.float32) * width
    edges[0], edges[-1] = lo, hi
    return edges


def bin_index(values: np.ndarray, estimator: HistogramEstimator) -> np.ndarray:
    """Bin of each value (int64, same shape): clipped into range; left-closed bins; NaN -> the top bin."""
    edges = histogram_edges(estimator)
    clipped = np.clip(np.asarray(values, dtype=np.float32), edges[0], edges[-1])
    # searchsorted sorts NaN after every edge, so NaN lands in bin K and is clipped to K - 1.
    index = np.searchsorted(edges, clipped, side="right") - 1
    return np.clip(index, 0, estimator.num_bins - 1)


def histogram_log_likelihood(
    log_values: np.ndarray, sim_values: np.ndarray, estimator: HistogramEstimator
) -> np.ndarray:
    """Log-likelihood ``[E, T]`` of each logged value under its object's histogram of ``sim_values``.

    ``log_values [E, T]``; ``sim_values [R, E, T']`` (all ``R * T'`` samples of object e form its histogram).
    """
    log_values = np.asarray(log_values)
    sim_values = np.asarray(sim_values)
    if log_values.ndim != 2 or sim_values.ndim != 3 or sim_values.shape[1] != log_values.shape[0]:
        raise ValueError(
            f"histogram_log_likelihood: expected log [E, T] and sim [R, E, T'], "
            f"got {log_values.shape} and {sim_values.shape}"
        )
    k = estimator.num_bins
    num_objects = log_values.shape[0]
    sim_bins = bin_index(sim_values, estimator)  # [R, E, T']
    keys = (np.arange(num_objects)[None, :, None] * k + sim_bins).ravel()
    counts = np.bincount(keys, minlength=num_objects * k).reshape(num_objects, k)
    samples = sim_values.shape[0] * sim_values.shape[2]
    log_prob = np.log((counts + estimator.pseudocount) / (samples + k * estimator.pseudocount))
    return np.take_along_axis(log_prob, bin_index(log_values, estimator), axis=1)


def bernoulli_log_likelihood(
    log_flags: np.ndarray, sim_flags: np.ndarray, estimator: BernoulliEstimator
) -> np.ndarray:
    """Log-likelihood ``[E]`` of each object's logged boolean under the rate of its ``sim_flags [R, E]``."""
    log_flags = np.asarray(log_flags, dtype=bool)
    sim_flags = np.asarray(sim_flags, dtype=bool)
    if log_flags.ndim != 1 or sim_flags.ndim != 2 or sim_flags.shape[1] != log_flags.shape[0]:
        raise ValueError(
            f"bernoulli_log_likelihood: expected log [E] and sim [R, E], got {log_flags.shape} "
            f"and {sim_flags.shape}"
        )
    a = estimator.pseudocount
    p_true = (sim_flags.sum(axis=0) + a) / (sim_flags.shape[0] + 2 * a)
    return np.log(np.where(log_flags, p_true, 1.0 - p_true))


def masked_score(log_likelihood: np.ndarray, mask: np.ndarray) -> float:
    """``exp`` of the mean log-likelihood over the masked entries (NaN when the mask is empty)."""
    mask = np.asarray(mask, dtype=bool)
    count = int(mask.sum())
    if count == 0:
        return float("nan")
    return float(np.exp(np.where(mask, log_likelihood, 0.0).sum() / count))
