"""``train --interaction-weight``: the tokens of agents closing in on the agent ahead weigh more in the loss;
which ones is a function of the states the model's inputs already hold, and validation NLL stays plain."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from test_model import random_scene

from trajeglish_env.model.config import preset
from trajeglish_env.model.network import TrajeglishModel
from trajeglish_env.sources.highway import generate_scene
from trajeglish_env.sources.highway_stops import stop_event_in
from trajeglish_env.training.interaction_weights import closing_in, interaction_weights
from trajeglish_env.training.train import TrainConfig

CAR = (4.5, 2.0)


def lane_scene(follower_speed: float, leader_speed: float, gap: float, lateral: float = 0.0, steps: int = 5):
    """A follower (agent 0) at x = 0 and a leader (agent 1) ``gap`` metres ahead bumper to bumper and
    ``lateral`` to the left, both heading +x at constant speeds (m/s): ``(xyh [1,2,S,3], valid, size)``."""
    t = np.arange(steps) * 0.1
    xyh = np.zeros((1, 2, steps, 3))
    xyh[0, 0, :, 0] = follower_speed * t
    xyh[0, 1, :, 0] = CAR[0] + gap + leader_speed * t
    xyh[0, 1, :, 1] = lateral
    size = np.tile(np.array(CAR), (1, 2, 1))
    return torch.tensor(xyh), torch.ones(1, 2, steps, dtype=torch.bool), torch.tensor(size)


def flags(*scene_args: float, **kw: float) -> np.ndarray:
    xyh, valid, size = lane_scene(*scene_args, **kw)
    return closing_in(xyh, valid, size, xyh.shape[2] - 1)[0].numpy()


def test_closing_in_in_closed_form() -> None:
    # 20 m/s onto a stopped car 30 m ahead (1.5 s to contact): the follower is closing in from step 1 on
    # (step 0 has no earlier state, so no velocity); the stopped leader is not
    f = flags(20.0, 0.0, 30.0)
    assert f[0].tolist() == [False, True, True, True] and not f[1].any()
    assert not flags(20.0, 0.0, 90.0).any()  # 4.5 s away: not yet (and beyond the 40 m reach)
    assert flags(20.0, 14.0, 20.0)[0, 1:].all()  # closing at 6 m/s, 3.3 s to contact
    assert not flags(20.0, 17.0, 20.0).any()  # 6.7 s to contact at 3 m/s, headway 1 s
    assert flags(20.0, 20.0, 10.0)[0, 1:].all()  # no closing, but a 0.5 s headway
    assert not flags(20.0, 0.0, 30.0, lateral=3.5).any()  # the car in the next lane is not in the path
    assert flags(20.0, 0.0, 30.0, lateral=2.2)[0, 1:].all()  # boxes overlapping within the 0.5 m margin


def test_closing_in_depends_on_relative_states_only() -> None:
    xyh, valid, size = lane_scene(20.0, 0.0, 30.0)
    a, shift = 0.7, torch.tensor([120.0, -40.0])
    rot = torch.tensor([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]], dtype=xyh.dtype)
    moved = xyh.clone()
    moved[..., :2] = xyh[..., :2] @ rot.T + shift
    moved[..., 2] = xyh[..., 2] + a
    assert torch.equal(closing_in(moved, valid, size, 4), closing_in(xyh, valid, size, 4))
    valid[0, 1, 2] = False  # a leader not seen at step 2: not there, and its velocity unknown at step 3
    assert closing_in(xyh, valid, size, 4)[0, 0].tolist() == [False, True, False, False]


def test_the_follower_of_a_stopping_vehicle_is_weighed_in_a_generated_scene() -> None:
    sc = generate_scene("highway+stop", 2)  # the sdc brakes from about 20 m/s at step 10 (test_highway_stops)
    stopper, step = stop_event_in(sc)
    xyh, valid = torch.tensor(sc.xyh)[None], torch.tensor(sc.valid)[None]
    f = closing_in(xyh, valid, torch.tensor(sc.size)[None], sc.num_steps)[0].numpy()
    rel = sc.xyh[:, step, :2] - sc.xyh[stopper, step, :2]
    h = sc.xyh[stopper, step, 2]
    along = rel @ np.array([math.cos(h), math.sin(h)])
    across = rel @ np.array([-math.sin(h), math.cos(h)])
    behind = np.flatnonzero(sc.valid[:, step] & (along < 0) & (np.abs(across) < 2.0))
    follower = int(behind[np.argmax(along[behind])])
    # it keeps its 14.8 m/s 29 m behind while the sdc brakes from 19.5 m/s at 3.3 m/s^2: closing in from
    # 4 s before it would reach the sdc at their closing speed (step 53), until it has nearly stopped too
    assert f[follower, : step + 43].sum() == 0 and f[follower, step + 43 : step + 78].all()
    share = f[sc.valid].mean()
    assert 0.01 < share < 0.2, share  # a small share of the scene's agent-steps


def test_weighted_loss() -> None:
    torch.manual_seed(0)
    cfg = preset("tiny")
    model = TrajeglishModel(cfg)
    scene, tokens = random_scene(cfg, padded=2)
    plain, n = model.loss(scene, tokens, tokens)
    ones, total = model.loss(scene, tokens, tokens, weights=torch.ones(tokens.shape))
    assert total == n and torch.allclose(ones, plain)
    weights = torch.ones(tokens.shape)
    weights[:, 0, 3:] = 4.0  # the first agent's later tokens count four times
    weighted, total = model.loss(scene, tokens, tokens, weights=weights)
    logits = model(scene, tokens).transpose(1, 2)  # [B,A,T,V]
    each = torch.nn.functional.cross_entropy(
        logits.reshape(-1, cfg.vocab_size), tokens.reshape(-1).clamp(min=0), reduction="none"
    )
    seen = (tokens.reshape(-1) >= 0) & scene.agent_mask[:, :, None].expand_as(tokens).reshape(-1)
    w = weights.reshape(-1)[seen]
    assert total == pytest.approx(float(w.sum()))
    assert torch.allclose(weighted, (each[seen] * w).sum() / w.sum(), atol=1e-5)


def test_interaction_weights_of_a_batch_and_settings() -> None:
    xyh, valid, size = lane_scene(20.0, 0.0, 30.0)
    batch = {
        "agent_xyh": xyh.float(),
        "agent_valid": valid,
        "agent_mask": torch.ones(1, 2, dtype=torch.bool),
        "agent_size": size.float(),
        "tokens": torch.zeros(1, 2, 4, dtype=torch.long),
    }
    assert interaction_weights(batch, 1.0) is None
    assert interaction_weights(batch, 6.0).tolist() == [[[1.0, 6.0, 6.0, 6.0], [1.0, 1.0, 1.0, 1.0]]]
    batch["agent_mask"][0, 0] = False  # a padding slot is never weighed
    assert interaction_weights(batch, 6.0).max() == 1.0
    with pytest.raises(ValueError, match="interaction_weight must be >= 1, got 0.5"):
        TrainConfig(interaction_weight=0.5)
