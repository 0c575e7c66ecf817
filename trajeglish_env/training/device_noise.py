"""Noisy input tokens drawn on the training device (``TrainConfig.noise_on_device``): the loading processes
tokenize their windows by argmin only and ship, per moving agent-step, the next logged state in the frame of
the tokenized one and the number that draws its noisy token; the training process draws every noisy token of
the batch in one pass over the whole vocabulary.

Why: drawing the noisy tokens is most of a window's cost on the CPU (every template within the noise margin
of the nearest gets its exact distance: about 140 a row at 2,048 tokens per class), and the loading processes
of a GPU machine could not keep its GPU busy. On the device the distances of a few thousand rows to all
templates are one small dense computation.

The draw is the one of :func:`trajeglish_env.tokenizer.noise.sample_nucleus` (softmax of ``-d / sigma`` over
the templates within the margin of the nearest, its nucleus, inverted at the same number, which the loader
draws from the window's generator in the order tokenizing the window draws it): the same token except where
the number falls within rounding of a boundary (the sums run in another order).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from trajeglish_env.geometry import to_local
from trajeglish_env.tokenizer.distance import CORNER_SIGNS
from trajeglish_env.tokenizer.noise import NoiseConfig
from trajeglish_env.tokenizer.vocabulary import MotionVocabulary

NOISE_FIELDS = ("noise_local", "noise_cos", "noise_sin", "noise_uniform")
ROWS_PER_PASS = 4096  # rows whose distances to every template are held at once


def add_noise_fields(
    windows: Sequence[dict[str, np.ndarray]], tokenized_xyh: np.ndarray, rngs: Sequence[np.random.Generator]
) -> None:
    """Add to each window (tokenized by argmin: ``tokens``) what the device needs to draw its noisy input
    tokens: ``noise_local [A,S-1,3]`` (the logged state at t+1 in the frame of the tokenized one at t),
    ``noise_cos``/``noise_sin [A,S-1]`` of its heading and ``noise_uniform [A,S-1]``, one number per moving
    agent-step drawn from the window's generator in tokenizing order (step, then class, then agent).
    ``tokenized_xyh [W,A,S,3]``: the windows' tokenized states (NaN where invalid)."""
    for w, xyh, rng in zip(windows, tokenized_xyh, rngs, strict=True):
        moving = w["tokens"] >= 0  # [A, S-1]
        logged = w["agent_xyh"].astype(np.float64)
        local = np.where(moving[..., None], to_local(np.nan_to_num(xyh[:, :-1]), logged[:, 1:]), 0.0)
        a, t = np.nonzero(moving)
        order = np.lexsort((a, w["agent_kind"][a], t))  # the order tokenize draws its numbers in
        uniform = np.zeros(moving.shape)
        uniform[a[order], t[order]] = rng.random(len(a))
        w["noise_local"] = local
        w["noise_cos"], w["noise_sin"] = np.cos(local[..., 2]), np.sin(local[..., 2])
        w["noise_uniform"] = uniform


@dataclass(frozen=True)
class DeviceTemplates:
    """A vocabulary's templates ``[K,V,3]`` and their headings' cosines and sines on a device (float64)."""

    xyh: torch.Tensor
    cos: torch.Tensor
    sin: torch.Tensor

    @classmethod
    def of(cls, vocabulary: MotionVocabulary, device: torch.device | str) -> DeviceTemplates:
        t = np.asarray(vocabulary.templates, dtype=np.float64)
        return cls(*(torch.from_numpy(a).to(device) for a in (t, np.cos(t[..., 2]), np.sin(t[..., 2]))))


def device_input_tokens(
    batch: dict[str, torch.Tensor], templates: DeviceTemplates, noise: NoiseConfig
) -> torch.Tensor:
    """The batch's input tokens ``[B,A,S-1]`` with a noisy token drawn for every agent-step whose input is
    observed (``input_tokens >= 0``: moving, not hidden by history dropout), from the fields of
    :func:`add_noise_fields`."""
    tokens = batch["input_tokens"]
    if noise.sigma == 0.0:
        return tokens
    sel = tokens >= 0
    out = tokens.clone()
    kind = batch["agent_kind"][:, :, None].expand_as(tokens)[sel]
    size = batch["agent_size"][:, :, None, :].expand(*tokens.shape, 2)[sel].double()
    fields = [batch[k][sel] for k in NOISE_FIELDS]
    drawn = torch.empty_like(kind)
    margin = noise.margin(templates.xyh.shape[1])
    for k in range(templates.xyh.shape[0]):
        rows = torch.nonzero(kind == k).flatten()
        for part in rows.split(ROWS_PER_PASS):
            local, cos, sin, uniform = (f[part] for f in fields)
            d = _corner_distances(templates, k, local, (cos, sin), size[part])
            drawn[part] = _nucleus_draw(d, margin, noise, uniform)
    out[sel] = drawn
    return out


def _corner_distances(
    templates: DeviceTemplates,
    k: int,
    local: torch.Tensor,
    trig: tuple[torch.Tensor, torch.Tensor],
    size: torch.Tensor,
) -> torch.Tensor:
    """Mean corner distances ``[m,V]`` of class ``k``'s templates to ``local [m,3]`` (boxes ``size [m,2]``),
    operation by operation those of :func:`trajeglish_env.tokenizer.distance.corner_distance`."""
    a = templates.xyh[k][None]  # [1,V,3]
    ux = local[:, None, 0] - a[..., 0]
    uy = local[:, None, 1] - a[..., 1]
    dc = trig[0][:, None] - templates.cos[k][None]
    ds = trig[1][:, None] - templates.sin[k][None]
    total = torch.zeros_like(ux)
    for sx, sy in CORNER_SIGNS.tolist():
        px = sx * size[:, 0, None]
        py = sy * size[:, 1, None]
        ex = ux + dc * px - ds * py
        ey = uy + ds * px + dc * py
        total = total + torch.sqrt(ex * ex + ey * ey)
    return total / 4.0


def _nucleus_draw(d: torch.Tensor, margin: float, noise: NoiseConfig, uniform: torch.Tensor) -> torch.Tensor:
    """Template ids ``[m]``: each row's draw from the softmax of ``-d / sigma`` over the templates within
    ``margin`` of its nearest, cut to the nucleus, inverted at ``uniform`` (templates by distance, then
    id)."""
    nearest = d.min(dim=1, keepdim=True).values
    within = d <= nearest + margin
    ranked, order = torch.sort(torch.where(within, d, torch.inf), dim=1, stable=True)
    inside = torch.gather(within, 1, order)
    weight = torch.where(inside, torch.exp(-(ranked - nearest) / noise.sigma), 0.0)
    prob = weight / weight.sum(dim=1, keepdim=True)
    cum = prob.cumsum(dim=1)
    keep = ((cum - prob) < noise.top_p) & inside
    keep[:, 0] = True
    target = uniform * torch.where(keep, prob, 0.0).sum(dim=1)
    count = (keep & (cum < target[:, None])).sum(dim=1)
    pos = torch.minimum(count, keep.sum(dim=1) - 1)
    return torch.gather(order, 1, pos[:, None])[:, 0]


def check(data: Sequence[str], ckpt: str, device: str, windows: int = 64) -> dict[str, float | int | bool]:
    """Draw the noisy tokens of ``windows`` training windows of ``data`` both ways (loaders, ``device``) with
    ``ckpt``'s vocabulary ('shipped': the shipped one): the share that agree and each way's time (a GPU job
    runs it before it trains with the noise on the device, and falls back to the loaders when it fails)."""
    import time

    from trajeglish_env.checkpoint import load_named
    from trajeglish_env.scenario_io import list_scenario_files, load_scenarios
    from trajeglish_env.training.dataset import collate_windows, window_config
    from trajeglish_env.training.training_data import TokenizedWindows

    start = load_named(ckpt)
    scenes = [s for d in data for f in list_scenario_files(d)[:4] for s in load_scenarios(f)]
    args = (scenes, window_config(start.config), start.vocabulary, NoiseConfig(), 0)
    t0 = time.perf_counter()
    loader = collate_windows(TokenizedWindows(*args).__getitems__(range(windows)))
    t1 = time.perf_counter()
    shipped = collate_windows(TokenizedWindows(*args, noise_on_device=True).__getitems__(range(windows)))
    t2 = time.perf_counter()
    batch = {k: v.to(device) for k, v in shipped.items()}
    drawn = device_input_tokens(batch, DeviceTemplates.of(start.vocabulary, device), NoiseConfig()).cpu()
    t3 = time.perf_counter()
    observed = loader["input_tokens"] >= 0
    agree = float((drawn == loader["input_tokens"])[observed].double().mean())
    return {
        "ok": agree >= 0.995,
        "agree": round(agree, 5),
        "inputs": int(observed.sum()),
        "vocab": start.vocabulary.size,
        "loader_ms_per_window": round(1000 * (t1 - t0) / windows, 2),
        "loader_ms_per_window_noise_on_device": round(1000 * (t2 - t1) / windows, 2),
        "device_draw_ms_per_window": round(1000 * (t3 - t2) / windows, 2),
    }


if __name__ == "__main__":  # python -m trajeglish_env.training.device_noise CKPT DEVICE DATA...; 1: failed
    import json
    import sys

    result = check(sys.argv[3:], sys.argv[1], sys.argv[2])
    print(json.dumps(result))
    sys.exit(0 if result["ok"] else 1)
