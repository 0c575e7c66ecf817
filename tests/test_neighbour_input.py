"""The neighbour input (ModelConfig.neighbour_input): features in closed form, frame invariance, a model
extended with it starts as it was, and the sampler reads exactly what training reads."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch
from helpers import (
    extended_tiny_checkpoint,
    greedy_window,
    random_scene_inputs,
    small_scenes,
    straight_road_scene,
    tiny_checkpoint,
)

from trajeglish_env.checkpoint import Checkpoint, load_into, load_pretrained
from trajeglish_env.model import SceneInputs
from trajeglish_env.model.neighbours import NEIGHBOURS, REACH, batch_view, neighbour_view, window_view
from trajeglish_env.model.network import TrajeglishModel
from trajeglish_env.training.closed_loop import ClosedLoopConfig, closed_loop_batch
from trajeglish_env.training.dataset import collate_windows
from trajeglish_env.training.train import window_config
from trajeglish_env.training.training_data import TokenizedWindows


def _neighbour_checkpoint() -> Checkpoint:
    return extended_tiny_checkpoint("neighbour_input")


def test_features_in_closed_form() -> None:
    # agent 0 at the origin heading +y, moving 1 m a step; agent 1 10 m ahead of it (+y), heading +x, still;
    # agent 2 beyond the reach; agent 3 absent
    xyh = torch.tensor([[0.0, 0.0, math.pi / 2], [0.0, 10.0, 0.0], [0.0, REACH + 1, 0.0], [1.0, 1.0, 0.0]])
    prev = xyh.clone()
    prev[0, 1] = -1.0
    valid = torch.tensor([True, True, True, False])
    size = torch.tensor([[4.0, 2.0], [5.0, 2.5], [4.0, 2.0], [4.0, 2.0]])
    view = neighbour_view(xyh, valid, prev, torch.ones(4, dtype=torch.bool), size)
    assert view.pairs.shape == (4, NEIGHBOURS, 9) and view.mask.shape == (4, NEIGHBOURS)
    torch.testing.assert_close(view.own[0], torch.tensor([1.0, 0.0, 1.0]))  # forward in its own frame
    assert view.mask[0].tolist() == [True] + [False] * (NEIGHBOURS - 1)  # only agent 1 is read
    # agent 1 seen from agent 0: 10 m straight ahead, heading -90 deg relative, closing at 1 m a step
    want = torch.tensor([0.5, 0.0, 0.0, -1.0, -1.0, 0.0, 1.0, 1.0, 0.5])
    torch.testing.assert_close(view.pairs[0, 0], want, atol=1e-6, rtol=0)
    assert not view.mask[3].any() and (view.pairs[3] == 0).all()  # an absent agent reads nobody
    assert view.mask[1].tolist()[:1] == [True]  # agent 1 reads agent 0


def test_features_do_not_depend_on_the_frame() -> None:
    g = torch.Generator().manual_seed(3)
    xyh = torch.rand(2, 7, 3, generator=g, dtype=torch.float64) * torch.tensor([40.0, 40.0, 6.0])
    prev = xyh + torch.randn(2, 7, 3, generator=g, dtype=torch.float64) * 0.5
    valid = torch.rand(2, 7, generator=g) > 0.2
    size = torch.rand(2, 7, 2, generator=g, dtype=torch.float64) * 4 + 1

    def moved(s: torch.Tensor, angle: float, shift: tuple[float, float]) -> torch.Tensor:
        c, si = math.cos(angle), math.sin(angle)
        x = c * s[..., 0] - si * s[..., 1] + shift[0]
        y = si * s[..., 0] + c * s[..., 1] + shift[1]
        return torch.stack([x, y, s[..., 2] + angle], -1)

    a = neighbour_view(xyh, valid, prev, valid, size)
    b = neighbour_view(
        moved(xyh, 1.1, (2500.0, -800.0)), valid, moved(prev, 1.1, (2500.0, -800.0)), valid, size
    )
    assert torch.equal(a.mask, b.mask)
    torch.testing.assert_close(a.pairs, b.pairs, atol=1e-5, rtol=0)
    torch.testing.assert_close(a.own, b.own, atol=1e-5, rtol=0)


def test_an_extended_model_starts_as_the_checkpoint_did() -> None:
    base = tiny_checkpoint()
    cfg = dataclasses.replace(base.model.cfg, neighbour_input=True)
    model = TrajeglishModel(cfg)
    load_into(model, base, base.vocabulary)
    model.eval()
    a, t = cfg.max_agents, cfg.steps
    g = torch.Generator().manual_seed(0)
    scene = random_scene_inputs(cfg, g)
    tokens = torch.randint(0, cfg.vocab_size, (1, a, t), generator=g)
    view = window_view(
        torch.randn(1, a, t + 1, 3, generator=g) * 5,
        torch.ones(1, a, t + 1, dtype=torch.bool),
        torch.ones(1, a, 2) * 4,
        t,
    )
    with torch.no_grad():
        torch.testing.assert_close(model(scene, tokens, view), base.model(scene, tokens), rtol=0, atol=0)
        with pytest.raises(ValueError, match="neighbour_input"):
            model(scene, tokens)


def test_sampling_reads_what_training_reads(monkeypatch: pytest.MonkeyPatch) -> None:
    """Greedy decoding through prime + decode_at (the sampler's features from its own states) picks the
    argmax of the teacher-forced forward pass whose features come from the same states as in training
    (:func:`window_view`): the two paths compute the same inputs."""
    ckpt = _neighbour_checkpoint()
    model = ckpt.model
    gw = greedy_window(ckpt, monkeypatch, straight_road_scene(num_agents=5, steps=30))
    view = window_view(*(torch.from_numpy(x)[None] for x in (gw.xyh, gw.valid, gw.size)), model.cfg.steps)
    with torch.no_grad():
        logits = model(gw.scene, gw.inputs, view)[0]
        plain = model(gw.scene, gw.inputs, _no_neighbours(view))[0]
    assert gw.checked(logits) >= 3 * gw.horizon
    assert not torch.equal(logits, plain)  # the features change the model's output


def _no_neighbours(view):  # type: ignore[no-untyped-def]
    return dataclasses.replace(view, pairs=torch.zeros_like(view.pairs), mask=torch.zeros_like(view.mask))


def test_closed_loop_windows_read_their_rolled_out_neighbours() -> None:
    """CAT-K with a neighbour model: the rollout's features come from its own states, and the closed-loop
    windows carry those states, so teacher forcing them gives the logits the rollout chose from."""
    base = load_pretrained()
    cfg = dataclasses.replace(base.config, neighbour_input=True)
    model = TrajeglishModel(cfg)
    load_into(model, base, base.vocabulary)
    torch.manual_seed(2)
    torch.nn.init.normal_(model.neighbours.out[1].weight, std=0.5)
    model.eval()
    ds = TokenizedWindows(small_scenes(), window_config(cfg), base.vocabulary, None, seed=3)
    batch = collate_windows([ds[g] for g in range(2)])
    k = 3
    closed = closed_loop_batch(model, batch, base.vocabulary, ClosedLoopConfig(top_k=k, teacher_forced=False))
    assert not torch.equal(closed["agent_xyh"], batch["agent_xyh"])  # the rolled-out states
    tokens = closed["input_tokens"]
    with torch.no_grad():
        logits = model(SceneInputs.from_batch(closed), tokens, batch_view(True, closed))
        logged = model(SceneInputs.from_batch(batch), tokens, batch_view(True, batch))
    chosen = tokens.transpose(1, 2)

    def worst_rank(lg: torch.Tensor) -> int:
        picked = lg.gather(-1, chosen.clamp(min=0)[..., None])
        return int((lg > picked).sum(-1)[chosen >= 0].max())

    assert worst_rank(logits) < k
    assert worst_rank(logged) >= k  # the logged states' features are not what the rollout read


def test_the_features_of_some_agents_are_those_of_all_agents_picked() -> None:
    g = torch.Generator().manual_seed(5)
    xyh = torch.rand(3, 9, 3, generator=g, dtype=torch.float64) * torch.tensor([50.0, 50.0, 6.0])
    prev = xyh + torch.randn(3, 9, 3, generator=g, dtype=torch.float64) * 0.3
    valid, prev_valid = torch.rand(3, 9, generator=g) > 0.2, torch.rand(3, 9, generator=g) > 0.2
    size = torch.rand(3, 9, 2, generator=g, dtype=torch.float64) * 4 + 1
    every = neighbour_view(xyh, valid, prev, prev_valid, size)
    focal = torch.tensor([[4, 0], [8, 8], [2, 5]])
    some = neighbour_view(xyh, valid, prev, prev_valid, size, focal)
    rows = torch.arange(3)[:, None]
    assert torch.equal(some.mask, every.mask[rows, focal])
    assert torch.equal(some.pairs, every.pairs[rows, focal]) and torch.equal(some.own, every.own[rows, focal])
