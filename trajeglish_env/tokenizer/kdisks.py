"""k-disks (paper, Alg. 1): sample template sets that cover the observed transitions at a resolution epsilon.

Repeatedly pick a transition uniformly among those still uncovered, keep it as a template, and drop every
transition within ``epsilon`` (mean corner distance of a 1 m x 1 m box) of it. Dense regions of the data get
templates first and every template is at least ``epsilon`` from the others.
"""

from __future__ import annotations

import numpy as np

from trajeglish_env.tokenizer.distance import UNIT_BOX_R2, corner_distance, mean_square_corner_distance

# Paper, appendix "Tokenization Analysis": epsilon (m) per vocabulary size.
KDISKS_EPSILON = {128: 0.035, 256: 0.035, 384: 0.035, 512: 0.030}
_UNIT_SIZE = np.array([1.0, 1.0])


def default_epsilon(vocab_size: int) -> float:
    """The paper's epsilon for ``vocab_size`` (3.5 cm up to 384 templates, 3.0 cm above)."""
    return KDISKS_EPSILON.get(vocab_size, 0.035 if vocab_size <= 384 else 0.030)


def _within(center: np.ndarray, points: np.ndarray, epsilon: float) -> np.ndarray:
    """Mask of ``points [M,3]`` within ``epsilon`` of ``center [3]`` (unit box, exact distances)."""
    meansq = mean_square_corner_distance(center, points, UNIT_BOX_R2)
    near = meansq <= epsilon**2  # d <= sqrt(meansq) <= epsilon
    unsure = np.flatnonzero(
        ~near & (meansq <= 2 * epsilon**2)
    )  # sqrt(meansq/2) <= d: only these can go either way
    if len(unsure):
        near[unsure] = corner_distance(center, points[unsure], _UNIT_SIZE) <= epsilon
    return near


def sample_kdisks(
    transitions: np.ndarray, vocab_size: int, epsilon: float, rng: np.random.Generator
) -> np.ndarray:
    """One candidate template set ``[vocab_size, 3]`` drawn from ``transitions [M,3]`` by Alg. 1.

    If every transition is covered before ``vocab_size`` templates are chosen (little or repetitive data),
    sampling continues with epsilon halved (then quartered, ...) among transitions farther than the new
    epsilon from all chosen templates, so the set is always full; fewer distinct transitions than
    ``vocab_size`` is an error.
    """
    transitions = np.asarray(transitions, dtype=np.float64)
    if transitions.ndim != 2 or transitions.shape[1] != 3:
        raise ValueError(f"sample_kdisks: transitions must be [M,3] (dx, dy, dh), got {transitions.shape}")
    chosen: list[np.ndarray] = []
    eps = float(epsilon)
    alive = np.arange(len(transitions))
    while len(chosen) < vocab_size:
        if len(alive) == 0:
            eps /= 2.0
            if eps < 1e-6:
                raise ValueError(
                    f"sample_kdisks: only {len(chosen)} distinct transitions for a vocabulary of {vocab_size}"
                )
            alive = np.arange(len(transitions))
            for template in chosen:  # re-cover with the smaller radius (at most vocab_size passes, rare)
                alive = alive[~_within(template, transitions[alive], eps)]
            continue
        pick = transitions[alive[rng.integers(len(alive))]]
        chosen.append(pick)
        alive = alive[~_within(pick, transitions[alive], eps)]
    return np.stack(chosen)
