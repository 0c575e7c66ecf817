"""Throughput of motion tokenization (exact argmin over V templates with corner distances), in agent-steps/s.

Usage: python benchmarks/bench_tokenizer.py [--agents 20000] [--steps 51] [--threads 1 2] [--data DIR]
       [--json]

Uses the shipped V=384 vocabulary. Without ``--data`` it tokenizes synthetic smooth trajectories of all
three classes; with ``--data`` the scenes of a scenario directory (repeated to reach ``--agents`` rows).
Each setting is run ``--repeats`` times and the best wall time is reported (the machine may be shared).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

from trajeglish_env.scenario import AgentKind
from trajeglish_env.tokenizer import NoiseConfig, load_default_tokenizer, tokenize
from trajeglish_env.tokenizer.synthetic import synthetic_trajectories


def _workload(args: argparse.Namespace) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    if args.data:
        from trajeglish_env.tokenizer.data import load_trajectories

        data = load_trajectories(args.data)
        reps = -(-args.agents // data.num_rows)
        take = slice(0, args.agents)
        return (
            np.tile(data.xyh, (reps, 1, 1))[take],
            np.tile(data.valid, (reps, 1))[take],
            np.tile(data.size, (reps, 1))[take],
            np.tile(data.kind, reps)[take],
        )
    rng = np.random.default_rng(0)
    return synthetic_trajectories(args.agents, args.steps, rng, kinds=tuple(AgentKind), max_speed=20.0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--agents", type=int, default=20000)
    parser.add_argument("--steps", type=int, default=51)
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument(
        "--noise-agents", type=int, default=2000, help="agents for the noisy-tokenization figure"
    )
    parser.add_argument("--data", default=None)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()

    vocab = load_default_tokenizer()
    xyh, valid, size, kind = _workload(args)
    transitions = int((valid[:, 1:] & valid[:, :-1]).sum())
    result: dict = {
        "vocab_size": vocab.size,
        "agents": int(len(xyh)),
        "steps": int(xyh.shape[1]),
        "agent_steps": transitions,
        "cpu_count": os.cpu_count(),
        "load_average_1min": round(os.getloadavg()[0], 2),
        "threads": {},
    }
    for threads in args.threads:
        walls, cpus = [], []
        for _ in range(args.repeats):
            wall0, cpu0 = time.perf_counter(), time.process_time()
            tokenize(vocab, xyh, valid, size, kind, threads=threads)
            walls.append(time.perf_counter() - wall0)
            cpus.append(time.process_time() - cpu0)
        best = int(np.argmin(walls))
        result["threads"][str(threads)] = {
            "seconds": round(walls[best], 3),
            "agent_steps_per_s": round(transitions / walls[best]),
            "agent_steps_per_cpu_s": round(transitions / cpus[best]),
        }
    n = min(args.noise_agents, len(xyh))
    wall0 = time.perf_counter()
    tokenize(vocab, xyh[:n], valid[:n], size[:n], kind[:n], noise=NoiseConfig(), rng=np.random.default_rng(0))
    noisy_steps = int((valid[:n, 1:] & valid[:n, :-1]).sum())
    result["noisy_agent_steps_per_s"] = round(noisy_steps / (time.perf_counter() - wall0))
    if args.json:
        print(json.dumps(result))
    else:
        for threads, r in result["threads"].items():
            print(
                f"tokenize V={vocab.size}, {threads} thread(s): {r['agent_steps_per_s']:,} agent-steps/s "
                f"({r['agent_steps_per_cpu_s']:,} per CPU-second; "
                f"{transitions:,} agent-steps in {r['seconds']} s)"
            )
        print(
            "noisy tokenization (sigma 0.008, top-p 0.95): "
            f"{result['noisy_agent_steps_per_s']:,} agent-steps/s"
        )
        print(
            f"load average at start: {result['load_average_1min']} on {result['cpu_count']} cores",
            file=sys.stderr,
        )


if __name__ == "__main__":
    main()
