"""Noisy tokenization (paper, appendix "Regularization"): sample input tokens near the true next state.

The input token is drawn from ``softmax(-d_i / sigma)`` restricted to its nucleus (the smallest set of most
likely templates whose probability reaches ``top_p``), where ``d_i`` is the mean corner distance between
template ``i`` (applied from the tokenized current state) and the true next state. The training target
stays the argmin token. ``sigma = 0`` (or ``top_p`` small enough to keep one template) gives the argmin.
Templates whose weight relative to the nearest is below ``exp(-7) / V`` are ignored (less than 0.1% of
the mass in all), which keeps the number of exact distance evaluations per step small.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

# Templates farther than sigma * (ln V + _TAIL_LOGITS) beyond the nearest one are left out of the softmax:
# together they hold less than exp(-_TAIL_LOGITS) < 0.1% of the probability mass (keeps candidate sets small).
_TAIL_LOGITS = 7.0


@dataclass(frozen=True)
class NoiseConfig:
    """Temperature ``sigma`` (metres of corner distance) and nucleus ``top_p`` of noisy tokenization."""

    sigma: float = 0.008
    top_p: float = 0.95

    def __post_init__(self) -> None:
        if not (math.isfinite(self.sigma) and self.sigma >= 0):
            raise ValueError(f"NoiseConfig.sigma must be a finite number >= 0 (metres), got {self.sigma}")
        if not (0 < self.top_p <= 1):
            raise ValueError(f"NoiseConfig.top_p must be in (0, 1], got {self.top_p}")

    def margin(self, vocab_size: int) -> float:
        """Distance beyond the nearest template past which templates carry negligible probability (< 0.1%)."""
        return self.sigma * (math.log(max(vocab_size, 1)) + _TAIL_LOGITS)


def sample_nucleus(
    rows: np.ndarray, dists: np.ndarray, config: NoiseConfig, uniform: np.ndarray
) -> np.ndarray:
    """Sample one template position per row from candidate pairs sorted by (row, distance).

    ``rows [P]`` gives each candidate's row (every row ``0..len(uniform)-1`` must have at least one) and
    ``uniform [rows]`` each row's number in [0, 1); returns, per row, the position in ``rows`` of the sampled
    candidate.
    """
    num_rows = len(uniform)
    starts = np.flatnonzero(np.r_[True, rows[1:] != rows[:-1]])
    if len(starts) != num_rows:
        raise ValueError(f"sample_nucleus: expected candidates for {num_rows} rows, got {len(starts)}")
    if config.sigma == 0.0:
        return starts
    nearest = dists[starts][rows]
    weight = np.exp(-(dists - nearest) / config.sigma)
    total = np.add.reduceat(weight, starts)
    prob = weight / total[rows]
    cum = np.cumsum(prob)
    before_segment = np.r_[0.0, cum[starts[1:] - 1]] if num_rows > 1 else np.zeros(1)
    cum = cum - before_segment[rows]
    # Nucleus: keep templates (by decreasing probability) until the cumulative probability reaches top_p.
    keep = (cum - prob) < config.top_p
    keep[starts] = True
    kept_total = np.add.reduceat(np.where(keep, prob, 0.0), starts)
    target = uniform * kept_total
    below = keep & (cum < target[rows])
    count = np.add.reduceat(below.astype(np.int64), starts)
    kept_count = np.add.reduceat(keep.astype(np.int64), starts)
    return starts + np.minimum(count, kept_count - 1)
