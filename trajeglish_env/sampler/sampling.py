"""Token sampling from logits: temperature and nucleus (top-p), with counter-based random numbers so that
a row's draws depend only on its own seed, step and agent (see :mod:`trajeglish_env.sampler.engine`).
"""

from __future__ import annotations

import numpy as np
import torch


def nucleus_mask(probs: torch.Tensor, top_p: float) -> torch.Tensor:
    """Boolean mask of the smallest set of most likely tokens whose total probability is >= ``top_p``."""
    if not 0 < top_p <= 1:
        raise ValueError(f"top_p must be in (0, 1], got {top_p}")
    sorted_p, order = probs.sort(dim=-1, descending=True)
    before = sorted_p.cumsum(-1) - sorted_p  # mass of the strictly more likely tokens
    keep_sorted = before < top_p
    keep_sorted[..., 0] = True
    return torch.zeros_like(keep_sorted).scatter(-1, order, keep_sorted)


_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_MIX1 = np.uint64(0xBF58476D1CE4E5B9)
_MIX2 = np.uint64(0x94D049BB133111EB)


def _splitmix(x: np.ndarray) -> np.ndarray:
    """SplitMix64 finaliser (a bijective 64-bit mixer), vectorized; uint64 arithmetic wraps."""
    x = x ^ (x >> np.uint64(30))
    x = x * _MIX1
    x = x ^ (x >> np.uint64(27))
    x = x * _MIX2
    return x ^ (x >> np.uint64(31))


def stream_seed(seed: int | np.ndarray, index: int | np.ndarray) -> np.ndarray:
    """An independent 64-bit seed for sub-stream ``index`` of ``seed`` (e.g. one per rollout)."""
    s = np.asarray(seed, dtype=np.uint64)
    return _splitmix(s * _GOLDEN + _splitmix(np.asarray(index, dtype=np.uint64) + _GOLDEN))


def counter_uniform(seed: np.ndarray, step: np.ndarray, agent: np.ndarray) -> np.ndarray:
    """Uniform numbers in [0, 1) that depend only on ``(seed, step, agent)`` (counter-based, vectorized):
    a scene's draws are the same whichever other scenes share its batch and in whatever order."""
    x = _splitmix(np.asarray(seed, dtype=np.uint64) ^ _splitmix(np.asarray(step, dtype=np.uint64) * _MIX1))
    x = _splitmix(x + _splitmix(np.asarray(agent, dtype=np.uint64) + _GOLDEN))
    return (x >> np.uint64(11)).astype(np.float64) * 2.0**-53


def second_uniform(uniform: np.ndarray) -> np.ndarray:
    """A second number in [0, 1) per draw, derived from ``uniform`` (a :func:`counter_uniform` number) by
    hashing its 53 bits: as independent of it as the first is of its counter, and as reproducible (the
    guard's redraw where the model's own draw breaks a rule, :mod:`~trajeglish_env.sampler.guard`)."""
    bits = (np.asarray(uniform, dtype=np.float64) * 2.0**53).astype(np.uint64)
    return (_splitmix(bits ^ _MIX2) >> np.uint64(11)).astype(np.float64) * 2.0**-53


def token_probs(logits: torch.Tensor, temperature: float) -> torch.Tensor:
    """Probabilities ``[n, V]`` (float64) of logits ``[n, V]`` at ``temperature > 0``: what every draw of
    :func:`sample_from_probs` inverts (computed once a call, the guard's checks read them too)."""
    if temperature <= 0:
        raise ValueError(f"temperature must be > 0 for probabilities, got {temperature}")
    scaled = logits.to(torch.float64, copy=True).div_(temperature)  # the numbers of ``/``, one copy fewer
    return torch.softmax(scaled, dim=-1)


def draw_tables(logits: torch.Tensor, temperature: float) -> tuple[torch.Tensor, torch.Tensor]:
    """The probabilities ``[n,V]`` (:func:`token_probs`) and their CDF: what a draw at ``top_p = 1``
    inverts and the guard's checks read (row by row the same numbers whichever rows share the call)."""
    probs = token_probs(logits, temperature)
    return probs, probs.cumsum(-1)


def sample_from_probs(probs: torch.Tensor, top_p: float, uniform: np.ndarray) -> np.ndarray:
    """Token ids ``[n]`` drawn from :func:`token_probs` ``[n, V]`` by inverting each row's CDF at
    ``uniform [n]`` (float64), within the nucleus ``top_p``."""
    if top_p < 1.0:
        probs = probs * nucleus_mask(probs, top_p)
    return sample_from_cdf(probs.cumsum(-1), uniform)


def sample_from_cdf(cdf: torch.Tensor, uniform: np.ndarray) -> np.ndarray:
    """Token ids ``[n]``: the first token whose cumulative probability ``cdf [n, V]`` exceeds ``uniform [n]``
    times the row's total (the draw of :func:`sample_from_probs` when its CDF is at hand)."""
    u = torch.from_numpy(np.asarray(uniform, dtype=np.float64))[:, None] * cdf[:, -1:]
    return torch.searchsorted(cdf, u, right=True).clamp_(max=cdf.shape[-1] - 1)[:, 0].numpy()


def sample_with_uniform(
    logits: torch.Tensor, temperature: float, top_p: float, uniform: np.ndarray
) -> np.ndarray:
    """Token ids ``[n]`` from logits ``[n, V]`` by inverting each row's CDF at ``uniform [n]`` (float64;
    ``temperature == 0`` gives the argmax)."""
    if temperature < 0:
        raise ValueError(f"temperature must be >= 0, got {temperature}")
    if temperature == 0:
        return logits.argmax(-1).numpy()
    return sample_from_probs(token_probs(logits, temperature), top_p, uniform)


def draft_draws(logits: np.ndarray, temperature: float, top_p: float, uniform: np.ndarray) -> np.ndarray:
    """Token ids ``[n]`` for *drafts* from logits ``[n, V]`` (float32, a scratch copy: overwritten): the draw
    of :func:`sample_with_uniform` at ``uniform [n]`` up to float32 rounding, in place and without normalising
    (the CDF of ``exp((l - max) / T)``, inverted at ``u`` times its total). A draft only proposes a token
    that the exact draw then accepts or not (:mod:`~trajeglish_env.sampler.parallel`), so rounding here can
    change how many drafts hold, never a token; it is several times cheaper than the float64 draw."""
    if temperature == 0 or top_p < 1.0:
        return sample_with_uniform(torch.from_numpy(logits), temperature, top_p, uniform)
    if temperature < 0:
        raise ValueError(f"temperature must be >= 0, got {temperature}")
    x = torch.from_numpy(logits)
    x.sub_(x.amax(-1, keepdim=True)).div_(temperature).exp_().cumsum_(-1)
    u = torch.from_numpy(np.asarray(uniform, dtype=np.float32))[:, None] * x[:, -1:]
    return torch.searchsorted(x, u, right=True).clamp_(max=x.shape[-1] - 1)[:, 0].numpy()
