"""Does the model see a turn coming, or only continue one? Teacher-forced on logged windows, the heading
change the model expects (its sampling distribution at ``--temperature``, over its drawn templates)
against the logged one, at vehicle tokens where a turn *begins* (the heading still over the last 0.3 s,
turning over the next) and where one *continues*. A model that reads the road expects most of the turn at
both; one that copies its own last tokens (the copycat problem, docs/evaluation.md "Weighing the tokens
where the road bends") expects it only where it continues, and alone on a racetrack drives straight on at
the bend.

    python scripts/turn_onset_probe.py --data DIR [--ckpt FILE] [--windows 6] [--scenes N] [--json]
"""

from __future__ import annotations

import argparse
import collections
import json

import numpy as np
import torch
from lone_vehicle_probe import scene_kind
from tqdm import tqdm

from trajeglish_env.checkpoint import load_checkpoint, load_pretrained
from trajeglish_env.model import SceneInputs
from trajeglish_env.model.neighbours import batch_view
from trajeglish_env.scenario import AgentKind, Scenario
from trajeglish_env.training.dataset import SceneStore, collate_windows
from trajeglish_env.training.train import window_config
from trajeglish_env.training.training_data import TokenizedWindows

SPAN = 3  # steps over which the turn rate before and after a token is measured
STILL = 0.004  # rad a step: slower heading change is no turn
TURNING = 0.015  # rad a step: faster heading change is a turn
BATCH = 8  # windows per teacher-forced call


def turn_phases(
    heading: np.ndarray, valid: np.ndarray, tokens: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Onset and turning masks ``[A,tokens]`` of the tokens (state t -> t+1) of agents with headings
    ``heading [A,S]`` (``valid [A,S]``), and the turn's sign ``[A,tokens]``. Onset: the heading changed less
    than :data:`STILL` a step over the :data:`SPAN` steps before t and more than :data:`TURNING` over the
    :data:`SPAN` steps after; turning: more than :data:`TURNING` both before and after, the same way."""
    a, s = heading.shape
    past = np.full((a, tokens), np.nan)
    future = np.full((a, tokens), np.nan)
    t = np.arange(tokens)
    before, after = t[t >= SPAN], t[t + SPAN < s]
    wrap = lambda x: (x + np.pi) % (2 * np.pi) - np.pi  # noqa: E731
    ok_b = valid[:, before] & valid[:, before - SPAN]
    past[:, before] = np.where(ok_b, wrap(heading[:, before] - heading[:, before - SPAN]) / SPAN, np.nan)
    ok_a = valid[:, after] & valid[:, after + SPAN]
    future[:, after] = np.where(ok_a, wrap(heading[:, after + SPAN] - heading[:, after]) / SPAN, np.nan)
    with np.errstate(invalid="ignore"):
        onset = (np.abs(past) < STILL) & (np.abs(future) > TURNING)
        turning = (np.abs(past) > TURNING) & (np.abs(future) > TURNING) & (np.sign(past) == np.sign(future))
    return onset, turning, np.sign(np.nan_to_num(future))


def probe(scenes: list[Scenario], ckpt: object, windows: int, temperature: float, seed: int) -> dict:
    """Counts and mean heading changes (rad a step, signed toward the turn: logged and expected by the model)
    at onset and turning tokens, per scene kind and overall; ``share``: expected over logged."""
    model = ckpt.model.eval()  # type: ignore[attr-defined]
    dh = torch.tensor(ckpt.vocabulary.templates[:, : model.cfg.drawn, 2], dtype=torch.float32)  # type: ignore[attr-defined]
    sums: dict[str, collections.Counter[str]] = collections.defaultdict(collections.Counter)
    for w in tqdm(range(windows), desc="windows", leave=False):
        ds = TokenizedWindows(scenes, window_config(model.cfg), ckpt.vocabulary, None, seed=seed + w)  # type: ignore[attr-defined]
        for lo in range(0, len(scenes), BATCH):
            idx = list(range(lo, min(lo + BATCH, len(scenes))))
            batch = collate_windows([ds[g] for g in idx])
            with torch.no_grad():
                logits = model(
                    SceneInputs.from_batch(batch),
                    batch["input_tokens"],
                    batch_view(model.cfg.reads_states, batch),
                )
            kind = batch["agent_kind"].clamp(min=0)
            probs = torch.softmax(logits.float() / temperature, dim=-1)  # [B,T,A,D]
            expected = (probs * dh[kind][:, None]).sum(-1).transpose(1, 2).numpy()  # [B,A,T]
            tokens = batch["tokens"].shape[-1]
            for b, g in enumerate(idx):
                heading = batch["agent_xyh"][b, :, :, 2].double().numpy()
                valid = (batch["agent_valid"][b] & batch["agent_mask"][b][:, None]).numpy()
                onset, turning, sign = turn_phases(heading, valid, tokens)
                vehicle = (batch["agent_kind"][b] == AgentKind.VEHICLE).numpy()[:, None]
                logged = np.diff(heading, axis=1)[:, :tokens]
                logged = (logged + np.pi) % (2 * np.pi) - np.pi
                c = sums[scene_kind(scenes[g])]
                for name, where in (("onset", onset & vehicle), ("turning", turning & vehicle)):
                    c[name] += int(where.sum())
                    c[name + "_log"] += float((logged * sign)[where].sum())
                    c[name + "_model"] += float((expected[b] * sign)[where].sum())
    sums["all"] = sum(sums.values(), collections.Counter())

    def row(c: collections.Counter[str]) -> dict:
        out: dict[str, float | int | None] = {}
        for name in ("onset", "turning"):
            n = c[name]
            out[name + "s"] = n
            out[name + "_log"] = c[name + "_log"] / n if n else None
            out[name + "_model"] = c[name + "_model"] / n if n else None
            out[name + "_share"] = c[name + "_model"] / c[name + "_log"] if n and c[name + "_log"] else None
        return out

    return {
        "scenes": len(scenes),
        "windows": windows,
        "by_kind": {k: row(c) for k, c in sorted(sums.items())},
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", required=True, help="scenario directory or file (*.scn.npz)")
    ap.add_argument("--ckpt", help="checkpoint (default: the shipped model)")
    ap.add_argument(
        "--windows", type=int, default=6, help="windows drawn per scene (seeds SEED, SEED+1, ...)"
    )
    ap.add_argument("--scenes", type=int, help="the first N scenes only")
    ap.add_argument("--temperature", type=float, default=0.75, help="of the expected heading change")
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    if args.windows < 1 or args.temperature <= 0:
        ap.error(f"--windows must be >= 1 and --temperature > 0, got {args.windows} and {args.temperature}")
    torch.set_num_threads(1)
    ckpt = load_checkpoint(args.ckpt) if args.ckpt else load_pretrained()
    scenes = SceneStore(args.data).scenes[: args.scenes]
    result = probe(scenes, ckpt, args.windows, args.temperature, args.seed)
    if args.json:
        print(json.dumps(result))
        return
    for kind, r in result["by_kind"].items():
        fmt = lambda x: "-" if x is None else f"{x:.3f}"  # noqa: E731
        print(
            f"{kind}: onsets {r['onsets']} (model {fmt(r['onset_share'])} of the logged turn), "
            f"turning {r['turnings']} (model {fmt(r['turning_share'])})"
        )


if __name__ == "__main__":
    main()
