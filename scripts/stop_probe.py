"""Reactivity probes on logged stops, in ``+stop`` scenes (``trajeglish generate --kinds highway+stop,...``):

- rollouts: the stop event's vehicle replays its log (it brakes hard to a stop and holds) while the model
  drives every other agent; the share of rollouts in which a model-driven agent's box runs into it. The
  log has none (scenes with a crash are not kept), so any hit is the model's.
- teacher-forced NLL of the tokens of the agents that react in the log (they slow by more than 3 m/s over
  a window that starts 0.4 s before the stop, or at it), from 0.6 s into the window, with the stopper in
  the window and with its slot masked out (the same window otherwise): how much the model's predictions
  of the reaction use the vehicle that causes it; and the same with the reacting agents' own input tokens
  hidden (``hidden_*``: what a model trained with ``--history-dropout`` reads from the current states
  alone, without the trend of its own last tokens).

    python scripts/stop_probe.py --data DIR [--ckpt FILE] [--rollouts 4] [--guard] [--json]
"""

from __future__ import annotations

import argparse
import dataclasses
import json

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from trajeglish_env.checkpoint import Checkpoint, load_checkpoint, load_pretrained
from trajeglish_env.metrics.boxes import box_collisions
from trajeglish_env.model.neighbours import batch_view
from trajeglish_env.model.network import SceneInputs
from trajeglish_env.sampler.config import SamplingConfig
from trajeglish_env.sampler.rollouts import rollout
from trajeglish_env.scenario import Scenario
from trajeglish_env.sources.highway_stops import stop_event_in
from trajeglish_env.training.dataset import SceneStore, collate_windows, make_window
from trajeglish_env.training.train import window_config
from trajeglish_env.training.training_data import with_tokens

SKIP = 6  # window steps before the scored tokens: the reaction needs the stop to have begun


def hits_stopper(
    xyh: np.ndarray, valid: np.ndarray, size: np.ndarray, stopper: int, first: int
) -> np.ndarray:
    """``[R]`` whether any other agent's box overlaps the stopper's at some step from ``first`` on
    (``xyh [R,N,T,3]``, ``valid [R,N,T]``)."""
    hit = np.zeros(xyh.shape[0], dtype=bool)
    others = np.arange(xyh.shape[1]) != stopper
    for r in range(xyh.shape[0]):
        for t in range(first, xyh.shape[2]):
            idx = np.flatnonzero(valid[r, :, t] & others)
            if box_collisions(xyh[r, stopper, t], size[stopper], xyh[r, idx, t], size[idx]).any():
                hit[r] = True
                break
    return hit


@torch.no_grad()
def _window_nll(
    ckpt: Checkpoint, window: dict[str, np.ndarray], scored: np.ndarray, hide: bool = False
) -> np.ndarray:
    """NLL (nats) of the observed tokens of window slots ``scored`` from step SKIP on (``hide``: with
    their input tokens hidden, as ``train --history-dropout`` hides them)."""
    batch = collate_windows(with_tokens([dict(window)], ckpt.vocabulary))
    if hide:
        batch["input_tokens"][0, scored] = -1
    model = ckpt.model.eval()
    logits = model(
        SceneInputs.from_batch(batch), batch["input_tokens"], batch_view(model.cfg.neighbour_input, batch)
    )
    scene = SceneInputs.from_batch(batch)
    drawn = model.drawn_targets(batch["tokens"], scene.agent_kind[:, :, None])  # a reading model's copies
    target = drawn.transpose(1, 2)[0, SKIP:, scored]  # [T', K]
    seen = target >= 0
    return F.cross_entropy(logits[0, SKIP:, scored][seen], target[seen], reduction="none").numpy()


def reaction_nll(
    ckpt: Checkpoint, scene: Scenario, stopper: int, step: int, hide: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """NLL of the reacting agents' tokens with the stopper and with its slot masked (paired, same order);
    ``hide``: with the reacting agents' own input tokens hidden."""
    config = window_config(ckpt.model.cfg)
    speed = scene.speed()
    with_it, without = [], []
    for lead in (4, 0):
        start = max(step - lead, 0)
        stop = start + config.steps
        if stop > scene.num_steps:
            continue
        slowed = speed[:, start : start + 5].mean(1) - speed[:, stop - 3 : stop].mean(1) > 3.0
        reacting = np.flatnonzero(
            scene.valid[:, start:stop].all(1) & slowed & (np.arange(scene.num_agents) != stopper)
        )
        part = dataclasses.replace(
            scene,
            xyh=scene.xyh[:, start:stop].copy(),
            valid=scene.valid[:, start:stop].copy(),
            current_index=0,
        )
        window = make_window(part, config, np.random.default_rng(start))
        slot = np.flatnonzero(window["agent_track_id"] == scene.track_id[stopper])
        scored = np.flatnonzero(np.isin(window["agent_track_id"], scene.track_id[reacting]))
        if not len(slot) or not len(scored):
            continue
        with_it.append(_window_nll(ckpt, window, scored, hide))
        masked = {k: v.copy() for k, v in window.items()}
        masked["agent_mask"][slot] = False
        masked["agent_valid"][slot] = False
        without.append(_window_nll(ckpt, masked, scored, hide))
    return np.concatenate(with_it or [np.zeros(0)]), np.concatenate(without or [np.zeros(0)])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", nargs="+", required=True, help="directories of +stop scenes")
    parser.add_argument("--ckpt", help="checkpoint (default: the shipped model)")
    parser.add_argument("--rollouts", type=int, default=4)
    parser.add_argument("--guard", action="store_true", help="guarded sampling (default: the model alone)")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    ckpt = load_checkpoint(args.ckpt) if args.ckpt else load_pretrained()
    config = SamplingConfig(guard=args.guard)
    scenes = SceneStore(args.data).scenes
    events = [(s, stop_event_in(s)) for s in scenes]
    # stops that begin after the current step, so the model sees the whole stop
    events = [(s, e) for s, e in events if e is not None and e[1] > s.current_index]
    if not events:
        raise SystemExit(f"stop_probe: no +stop scene with its event after the current step in {args.data}")
    hits: list[np.ndarray] = []
    nll: dict[bool, tuple[list[np.ndarray], list[np.ndarray]]] = {False: ([], []), True: ([], [])}
    for scene, (stopper, step) in tqdm(events, desc="stop probe"):
        for hide, (nll_with, nll_without) in nll.items():
            a, b = reaction_nll(ckpt, scene, stopper, step, hide)
            nll_with.append(a)
            nll_without.append(b)
        controlled = scene.valid[:, scene.current_index].copy()
        controlled[stopper] = False
        r = rollout(ckpt, scene, rollouts=args.rollouts, controlled=controlled, config=config)
        hits.append(hits_stopper(r.xyh, r.valid, scene.size, stopper, scene.current_index + 1))
    hit = np.concatenate(hits)
    result = {
        "scenes": len(events),
        "rollouts": int(hit.size),
        "hits": int(hit.sum()),
        "rate": float(hit.mean()),
    }
    for hide, (nll_with, nll_without) in nll.items():
        a, b = np.concatenate(nll_with), np.concatenate(nll_without)
        diff, key = a - b, "hidden_reaction" if hide else "reaction"
        result[f"{key}_tokens"] = int(a.size)
        if a.size:
            result[f"{key}_nll_with_stopper"] = round(float(a.mean()), 4)
            result[f"{key}_nll_without_stopper"] = round(float(b.mean()), 4)
            result[f"{key}_nll_gain"] = round(float(-diff.mean()), 4)
            result[f"{key}_nll_gain_se"] = round(float(diff.std() / np.sqrt(diff.size)), 4)
    print(
        json.dumps(result)
        if args.json
        else f"{result['hits']} of {result['rollouts']} rollouts hit the stopper: {result['rate']:.3f}; "
        f"reaction NLL gain from the stopper {result.get('reaction_nll_gain')} nats/token"
    )


if __name__ == "__main__":
    main()
