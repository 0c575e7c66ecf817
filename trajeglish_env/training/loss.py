"""The training loss of one batch (:class:`TrainingLoss`): the tokens' likelihood and the optional terms
against colliding (:mod:`.blocked_mass`) and off-road (:mod:`.offroad_mass`) candidate tokens."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import nn

from trajeglish_env.model.neighbours import batch_view
from trajeglish_env.model.network import SceneInputs, TrajeglishModel
from trajeglish_env.training.bend_weights import bend_weights
from trajeglish_env.training.blocked_mass import batch_blocked, logged_weights, term_loss
from trajeglish_env.training.interaction_weights import interaction_weights
from trajeglish_env.training.offroad_mass import offroad_candidates

if TYPE_CHECKING:
    from trajeglish_env.training.train import TrainConfig


class TrainingLoss(nn.Module):
    """Wraps the model so that DDP sees one forward that returns (summed loss, token count): the likelihood
    (interaction weights; rolled-out targets left out) plus the colliding- and off-road-mass terms."""

    def __init__(
        self,
        model: TrajeglishModel,
        config: TrainConfig,
        templates: np.ndarray | None = None,
        term_scenes: np.ndarray | None = None,
    ):
        super().__init__()
        self.model = model
        self.interaction_weight = config.interaction_weight
        self.bend_weight = config.bend_weight
        self.collision_weight = config.collision_weight
        self.templates = templates  # the drawn tokens' motion templates [classes,D,3] (collision_weight)
        self.collision_horizon = config.collision_horizon
        self.only_rolled = config.collision_rolled_out_only
        self.collision_form = config.collision_form
        self.offroad_form = config.offroad_form
        self.term_scenes = (
            term_scenes  # [N] the scenes whose windows the colliding-mass term acts on (None: all)
        )
        self.offroad_weight = config.offroad_weight

    def _weights(self, batch: dict[str, torch.Tensor]) -> torch.Tensor | None:
        """The product of the interaction and bend weights ``[B,A,T]`` (None: all 1)."""
        parts = [interaction_weights(batch, self.interaction_weight), bend_weights(batch, self.bend_weight)]
        kept = [w for w in parts if w is not None]
        return None if not kept else kept[0] if len(kept) == 1 else kept[0] * kept[1]

    def forward(self, batch: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        scene = SceneInputs.from_batch(batch)
        view = batch_view(self.model.cfg.reads_states, batch)
        weights = logged_weights(batch, self._weights(batch))
        if not (self.collision_weight or self.offroad_weight):
            mean, n = self.model.loss(scene, batch["input_tokens"], batch["tokens"], view, weights)
            return mean * n, torch.tensor(float(n), device=mean.device)
        logits = self.model.forward(scene, batch["input_tokens"], view)
        mean, n = self.model.loss_of_logits(logits, scene, batch["tokens"], weights)
        total = mean * n
        drawn = self.model.drawn_targets(batch["tokens"], batch["agent_kind"][:, :, None])
        if self.collision_weight:
            assert self.templates is not None
            horizon, only_rolled = self.collision_horizon, self.only_rolled
            rows = (
                None if self.term_scenes is None else np.flatnonzero(self.term_scenes[batch["scene"].cpu()])
            )
            blocked = batch_blocked(self.model, batch, self.templates, horizon, only_rolled, rows)
            total = total + self.collision_weight * term_loss(self.collision_form, logits, blocked, drawn)
        if self.offroad_weight:
            offroad = offroad_candidates(batch, drawn)
            total = total + self.offroad_weight * term_loss(self.offroad_form, logits, offroad, drawn)
        return total, torch.tensor(float(n), device=mean.device)
