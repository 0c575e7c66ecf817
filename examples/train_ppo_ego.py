"""Train an ego with PPO (Stable-Baselines3) in ``trajeglish_env/Ego-v0`` against Trajeglish NPCs, log the
learning curve, and compare the trained ego with a random and a constant-velocity ego.

    python examples/train_ppo_ego.py --timesteps 100000 --envs 16        # the CPU-sized run
    python examples/train_ppo_ego.py --npc idm --smoke                   # a minute-long check

Training steps ``--envs`` scenes in one batched env (:class:`~trajeglish_env.env.sb3.SB3VecEnv`: the
NPCs of its scenes are decoded together, the scenes split over ``--processes`` forked workers, by default
one per free core); ``--workers N`` uses N SubprocVecEnv workers
of unbatched ``EgoEnv`` instead. Scenes: the bundled held-out scenes (training episodes draw a scene per
reset; evaluation plays every scene with fixed seeds, all evaluation episodes of an ego in one batch).
Training shows a progress bar (timesteps, recent mean episode return). A PPO rollout is ``--n-steps``
(512) steps per env (fewer when ``--timesteps`` is smaller than one rollout), and PPO trains whole
rollouts, so the run may take a few more steps than asked: ``comparison.json`` reports the steps taken
(``timesteps``) and asked.
Outputs in ``--out``: ``ppo_ego.zip``, ``learning_curve.csv`` / ``.png`` (episode return vs timesteps,
from the Monitor logs) and ``comparison.json``.
"""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path
from typing import Any

import numpy as np

from policies import ConstantVelocityPolicy, RandomPolicy
from trajeglish_env.env import EgoEnv, TrajeglishNPC
from trajeglish_env.env.scenes import load_bundle
from trajeglish_env.env.vector import BatchedEgoEnv


def make_env_kwargs(args: argparse.Namespace) -> dict[str, Any]:
    npc = TrajeglishNPC(args.checkpoint) if args.npc == "trajeglish" else args.npc
    return {"npc": npc, "max_cycles": args.max_cycles}


def evaluate_ego(venv: BatchedEgoEnv, choose: Any, seed: int) -> dict[str, float]:
    """Mean return, collision / off-road / goal rates and progress of an ego over one episode per scene
    of the batched env (env ``k`` plays scene ``k % scenes`` with seed ``seed + k``), all at once."""
    n = venv.num_envs
    obs = np.stack(
        [
            env.reset(seed=seed + k, options={"scene": k % len(env.scenes)})[0]
            for k, env in enumerate(venv.envs)
        ]
    )
    returns, final = np.zeros(n), [None] * n
    while any(f is None for f in final):
        actions = np.stack([choose(env, o) for env, o in zip(venv.envs, obs, strict=True)])
        results = venv.step_each(actions)
        for k, (_, reward, _, _, _, end) in enumerate(results):
            if final[k] is None:
                returns[k] += reward
                final[k] = end[1] if end is not None else None
        obs = np.stack([r[0] for r in results])
    return {
        "mean_return": float(np.mean(returns)),
        "collision_rate": float(np.mean([f["collision"] for f in final])),
        "offroad_rate": float(np.mean([f["offroad"] for f in final])),
        "goal_rate": float(np.mean([f["goal"] for f in final])),
        "mean_route_fraction": float(np.mean([f["route_fraction"] for f in final])),
    }


def ProgressBar(total: int) -> Any:  # noqa: N802 (a callback class made where SB3 is imported)
    """An SB3 callback showing the timesteps done and the recent mean episode return (tqdm, on stderr)."""
    from stable_baselines3.common.callbacks import BaseCallback
    from tqdm import tqdm

    class _Bar(BaseCallback):
        def _on_training_start(self) -> None:
            self.bar = tqdm(total=total, unit="step", desc="PPO")

        def _on_step(self) -> bool:
            self.bar.update(self.model.num_timesteps - self.bar.n)
            episodes = self.model.ep_info_buffer
            if episodes and self.n_calls % 64 == 0:
                self.bar.set_postfix(mean_return=f"{np.mean([e['r'] for e in episodes]):.3f}")
            return True

        def _on_training_end(self) -> None:
            self.bar.close()

    return _Bar()


def learning_curve(monitor_dir: Path, out: Path, title: str) -> list[tuple[int, float]]:
    """Episode returns from the Monitor logs, in timestep order, smoothed over 20 episodes; CSV + PNG."""
    rows = []
    for path in sorted(monitor_dir.glob("*.monitor.csv")):
        with open(path) as fh:
            next(fh)  # the JSON header line
            rows += [(float(r["t"]), float(r["r"]), int(r["l"])) for r in csv.DictReader(fh)]
    rows.sort()
    steps = np.cumsum([r[2] for r in rows])
    rewards = np.array([r[1] for r in rows])
    window = np.ones(min(20, max(len(rewards), 1)))
    smooth = np.convolve(rewards, window, "valid") / len(window) if len(rewards) else rewards
    curve = list(zip(steps[len(window) - 1 :].tolist(), smooth.tolist(), strict=True))
    with open(out / "learning_curve.csv", "w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(["timesteps", "episode_return_smoothed"])
        writer.writerows(curve)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.plot([c[0] for c in curve], [c[1] for c in curve])
    ax.set_xlabel("timesteps")
    ax.set_ylabel("episode return (20-episode mean)")
    ax.set_title(title)
    fig.tight_layout()
    fig.savefig(out / "learning_curve.png", dpi=120)
    plt.close(fig)
    return curve


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--timesteps", type=int, default=100_000)
    parser.add_argument("--envs", type=int, default=16, help="scenes of the batched training env")
    parser.add_argument(
        "--processes",
        type=lambda v: v if v == "auto" else int(v),
        default="auto",
        help="worker processes of the batched training env (auto: one per free core, >= 4 scenes each)",
    )
    parser.add_argument(
        "--workers", type=int, default=0, help="SubprocVecEnv workers of unbatched envs instead (0: batched)"
    )
    parser.add_argument(
        "--npc", default="trajeglish", choices=("trajeglish", "idm", "replay", "constant_velocity")
    )
    parser.add_argument(
        "--ckpt",
        "--checkpoint",
        dest="checkpoint",
        help="Trajeglish model for the NPCs (default: the shipped one)",
    )
    parser.add_argument("--max-cycles", type=int, default=None, help="episode length cap")
    parser.add_argument("--n-steps", type=int, default=512, help="PPO rollout steps per env")
    parser.add_argument("--eval-episodes", type=int, default=40)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="out/ppo_ego")
    parser.add_argument("--smoke", action="store_true", help="a few hundred steps, 2 envs, 2 eval episodes")
    args = parser.parse_args(argv)
    if args.smoke:
        args.timesteps, args.envs, args.eval_episodes, args.max_cycles = 256, 2, 2, args.max_cycles or 12

    import torch
    from stable_baselines3 import PPO
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import SubprocVecEnv, VecMonitor

    from trajeglish_env.env.sb3 import SB3VecEnv

    torch.set_num_threads(1)
    out = Path(args.out)
    monitor_dir = out / "monitor"
    monitor_dir.mkdir(parents=True, exist_ok=True)
    for stale in monitor_dir.glob("*.monitor.csv"):
        stale.unlink()
    env_kwargs = make_env_kwargs(args)
    if args.workers > 0:
        vec = make_vec_env(
            EgoEnv,
            n_envs=args.workers,
            seed=args.seed,
            env_kwargs=env_kwargs,
            monitor_dir=str(monitor_dir),
            vec_env_cls=SubprocVecEnv,
            vec_env_kwargs={"start_method": "spawn"},
        )
    else:
        batched = SB3VecEnv(args.envs, processes=args.processes, **env_kwargs)
        vec = VecMonitor(batched, filename=str(monitor_dir / "batched"))
        vec.seed(args.seed)
    # steps per env and PPO rollout: --n-steps (512: 8,192 over the 16 batched scenes), fewer when the
    # whole run is shorter than one rollout
    n_steps = 64 if args.smoke else max(16, min(args.n_steps, args.timesteps // vec.num_envs))
    model = PPO(
        "MlpPolicy",
        vec,
        n_steps=n_steps,
        batch_size=128,
        gamma=0.99,
        # small initial exploration noise: full-range random steering leaves the road within a second
        policy_kwargs={"log_std_init": -1.0, "net_arch": [128, 128]},
        seed=args.seed,
        device="cpu",
        verbose=0,
    )
    model.learn(total_timesteps=args.timesteps, callback=ProgressBar(args.timesteps))
    vec.close()
    model.save(out / "ppo_ego.zip")
    curve = learning_curve(monitor_dir, out, f"PPO ego in Ego-v0, {args.npc} NPCs")

    venv = BatchedEgoEnv(args.eval_episodes, **env_kwargs)
    random_policy, cv_policy = RandomPolicy(args.seed), ConstantVelocityPolicy()
    egos = {
        "ppo": lambda e, obs: model.predict(obs, deterministic=True)[0],
        "random": lambda e, obs: random_policy.act(e, e.agent, obs),
        "constant_velocity": lambda e, obs: cv_policy.act(e, e.agent, obs),
    }
    seed = 10_000  # evaluation seeds differ from the training ones
    comparison = {name: evaluate_ego(venv, choose, seed) for name, choose in egos.items()}
    result = {
        "timesteps": int(model.num_timesteps),  # whole rollouts: at least the requested count
        "timesteps_requested": args.timesteps,
        "npc": args.npc,
        "scenes": len(load_bundle()),
        "eval_episodes": args.eval_episodes,
        "final_smoothed_return": curve[-1][1] if curve else None,
        "comparison": comparison,
        "ppo_beats_both": comparison["ppo"]["mean_return"]
        > max(comparison["random"]["mean_return"], comparison["constant_velocity"]["mean_return"]),
    }
    (out / "comparison.json").write_text(json.dumps(result, indent=2))
    print(f"{'ego':>18} {'return':>8} {'collision':>9} {'off-road':>8} {'goal':>6} {'route':>6}")
    for name, m in comparison.items():
        print(
            f"{name:>18} {m['mean_return']:8.3f} {m['collision_rate']:9.2f} {m['offroad_rate']:8.2f} "
            f"{m['goal_rate']:6.2f} {m['mean_route_fraction']:6.2f}"
        )
    print(f"results in {out}/ (comparison.json, learning_curve.png)")
    return result


if __name__ == "__main__":
    main()
