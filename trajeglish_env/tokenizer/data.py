"""Trajectory collections for fitting and evaluating tokenizers: agents of many scenes as padded rows."""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from trajeglish_env.geometry import to_local
from trajeglish_env.scenario import AgentKind, Scenario
from trajeglish_env.scenario_io import load_scenarios, scenario_files


@dataclass(frozen=True)
class TrajectorySet:
    """All agents of a set of scenes as rows: ``xyh [R,T,3]``, ``valid [R,T]`` (padded with False to the
    longest scene), ``size [R,2]``, ``kind [R]``, ``scene [R]`` (index of the scene each row comes from)."""

    xyh: np.ndarray
    valid: np.ndarray
    size: np.ndarray
    kind: np.ndarray
    scene: np.ndarray
    num_scenes: int
    dt: float = 0.1

    @classmethod
    def from_scenarios(cls, scenarios: Sequence[Scenario]) -> TrajectorySet:
        """Stack the agents of ``scenarios`` (any lengths) into padded rows."""
        if not scenarios:
            raise ValueError("TrajectorySet: no scenes given")
        dts = sorted({round(float(sc.dt), 6) for sc in scenarios})
        if len(dts) != 1:
            raise ValueError(
                f"TrajectorySet: scenes have different time steps {dts} s; tokenize one rate at a time"
            )
        steps = max(sc.num_steps for sc in scenarios)
        rows = sum(sc.num_agents for sc in scenarios)
        xyh = np.zeros((rows, steps, 3))
        valid = np.zeros((rows, steps), dtype=bool)
        start = 0
        for sc in scenarios:  # one block copy per scene
            stop = start + sc.num_agents
            xyh[start:stop, : sc.num_steps] = np.where(sc.valid[..., None], sc.xyh, 0.0)
            valid[start:stop, : sc.num_steps] = sc.valid
            start = stop
        return cls(
            xyh=xyh,
            valid=valid,
            size=np.concatenate([sc.size for sc in scenarios]).astype(np.float64),
            kind=np.concatenate([sc.kind for sc in scenarios]).astype(np.int64),
            scene=np.repeat(np.arange(len(scenarios)), [sc.num_agents for sc in scenarios]),
            num_scenes=len(scenarios),
            dt=dts[0],
        )

    @property
    def num_rows(self) -> int:
        """Number of agent rows (all scenes)."""
        return int(self.xyh.shape[0])

    def select_scenes(self, keep: np.ndarray) -> TrajectorySet:
        """The rows of the scenes where ``keep [num_scenes]`` is True (scene indices renumbered)."""
        keep = np.asarray(keep, dtype=bool)
        rows = keep[self.scene]
        renumber = np.cumsum(keep) - 1
        return TrajectorySet(
            self.xyh[rows],
            self.valid[rows],
            self.size[rows],
            self.kind[rows],
            renumber[self.scene[rows]],
            int(keep.sum()),
            self.dt,
        )

    def split(self, heldout_every: int = 5) -> tuple[TrajectorySet, TrajectorySet]:
        """(fit, held-out) split by scene: every ``heldout_every``-th scene is held out (deterministic)."""
        heldout = np.arange(self.num_scenes) % heldout_every == heldout_every - 1
        return self.select_scenes(~heldout), self.select_scenes(heldout)

    def transitions(self, kind: int | AgentKind) -> np.ndarray:
        """Logged transitions ``[M,3]`` of a class (each next state in the frame of the current one)."""
        rows = self.kind == int(kind)
        xyh, valid = self.xyh[rows], self.valid[rows]
        pair = valid[:, 1:] & valid[:, :-1]
        return to_local(xyh[:, :-1][pair], xyh[:, 1:][pair])

    def transition_counts(self) -> dict[str, int]:
        """Number of transitions per class name."""
        pair = self.valid[:, 1:] & self.valid[:, :-1]
        per_row = pair.sum(1)
        return {k.name.lower(): int(per_row[self.kind == int(k)].sum()) for k in AgentKind}


def load_trajectories(data: str | os.PathLike[str], max_scenes: int | None = None) -> TrajectorySet:
    """The scenes of a scenario file or directory (sorted files; first ``max_scenes``) as a TrajectorySet."""
    files = scenario_files(data)
    scenes: list[Scenario] = []
    for path in files:
        scenes.extend(load_scenarios(path))
        if max_scenes is not None and len(scenes) >= max_scenes:
            scenes = scenes[:max_scenes]
            break
    return TrajectorySet.from_scenarios(scenes)
