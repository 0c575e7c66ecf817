"""What the model is shown of the road ahead: for each vehicle of a window that moves, the share of its next
logged states within ``tolerance`` m of a lane-centre chunk among those the window gives the model (the
config's ``max_polylines`` chunks of ``points_per_polyline`` points, chosen by ``map_select``, every
``map_stride``-th map point), and how far ahead (s) its first state off those chunks lies. Per scene kind:
the figures behind :attr:`~trajeglish_env.model.config.ModelConfig.map_stride` (``trajeglish
map-coverage``)."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np

from trajeglish_env.geometry import to_local
from trajeglish_env.model.config import ModelConfig
from trajeglish_env.model.map_chunks import chunk_map, nearest_chunks, scene_anchors
from trajeglish_env.scenario import LANE_KINDS, AgentKind, Scenario, scene_kind

STEPS_PER_SECOND = 10


@dataclass(frozen=True)
class CoverageConfig:
    """``horizon`` future steps looked at, ``tolerance`` m from a lane-centre chunk that counts as shown,
    vehicles that travel at least ``min_travel`` m over the horizon (standing ones need no road ahead), the
    window's map radius (m) as in training."""

    horizon: int = 80
    tolerance: float = 2.0
    min_travel: float = 5.0
    map_radius: float = 100.0

    def __post_init__(self) -> None:
        if self.horizon < 1 or not self.tolerance > 0 or self.min_travel < 0:
            raise ValueError(f"CoverageConfig: need horizon >= 1, tolerance > 0, min_travel >= 0, got {self}")


def _segment_distances(points: np.ndarray, chunk_points: np.ndarray, chunk_mask: np.ndarray) -> np.ndarray:
    """``[Q]`` distance from ``points [Q,2]`` to the nearest segment of the chunks ``[M,P,2]`` (inf: none)."""
    real = (chunk_mask[:, :-1] & chunk_mask[:, 1:]).reshape(-1)
    a = chunk_points[:, :-1].reshape(-1, 2)[real].astype(np.float64)
    d = chunk_points[:, 1:].reshape(-1, 2)[real].astype(np.float64) - a
    if not len(a):
        return np.full(len(points), np.inf)
    length2 = np.maximum((d * d).sum(-1), 1e-12)
    u = points[:, None] - a[None]
    t = np.clip((u * d[None]).sum(-1) / length2[None], 0.0, 1.0)
    r = u - t[..., None] * d[None]
    return np.sqrt((r * r).sum(-1)).min(-1)


def vehicle_coverage(
    scene: Scenario, cfg: ModelConfig, config: CoverageConfig = CoverageConfig()
) -> np.ndarray:
    """``[V,2]`` per moving vehicle of the window framed on the sdc at the current step (its ``max_agents``
    agents nearest the sdc): the share of its next ``horizon`` logged states shown, and the seconds ahead
    of its first state not shown (``horizon`` / 10 when all are, or the log's end when it comes first)."""
    t0 = scene.current_index
    frame = scene.xyh[scene.sdc, t0]
    live = np.flatnonzero(scene.valid[:, t0])
    gap = np.hypot(*(scene.xyh[live, t0, :2] - frame[:2]).T)
    chosen = live[np.argsort(gap, kind="stable")[: cfg.max_agents]]
    anchors = scene_anchors(cfg.map_select, scene, chosen, t0)
    chunks = chunk_map(scene, cfg.points_per_polyline, cfg.map_stride)
    points, point_mask, kind, mask, _ = nearest_chunks(
        chunks, frame, cfg.max_polylines, config.map_radius, anchors=anchors
    )
    lanes = mask & np.isin(kind, sorted(LANE_KINDS))
    end = min(t0 + 1 + config.horizon, scene.num_steps)
    out = []
    for i in chosen[scene.kind[chosen] == AgentKind.VEHICLE]:
        future = np.flatnonzero(scene.valid[i, t0 + 1 : end]) + t0 + 1
        if (
            len(future) < 2
            or np.hypot(*(scene.xyh[i, future[-1], :2] - scene.xyh[i, t0, :2])) < config.min_travel
        ):
            continue
        local = to_local(frame, scene.xyh[i, future])[:, :2]
        shown = _segment_distances(local, points[lanes], point_mask[lanes]) <= config.tolerance
        # the step of the first state off the shown lanes; all shown: the last step looked at (the cap)
        ahead = future[int(np.argmin(shown))] - t0 if not shown.all() else end - 1 - t0
        out.append((shown.mean(), ahead / STEPS_PER_SECOND))
    return np.asarray(out, dtype=np.float64).reshape(-1, 2)


def coverage_by_kind(
    scenes: Iterable[Scenario],
    cfg: ModelConfig,
    strides: Iterable[int],
    config: CoverageConfig = CoverageConfig(),
) -> dict[str, dict[str, Any]]:
    """Per scene kind and stride (``"stride N"``): ``vehicles``, ``path_shown`` (mean share of the next
    states shown) and ``seconds_ahead_median``; ``"all"`` pools the kinds."""
    per: dict[tuple[str, int], list[np.ndarray]] = {}
    strides = tuple(strides)
    for scene in scenes:
        for stride in strides:
            got = vehicle_coverage(scene, dataclasses.replace(cfg, map_stride=stride), config)
            for key in ((scene_kind(scene), stride), ("all", stride)):
                per.setdefault(key, []).append(got)
    out: dict[str, dict[str, Any]] = {}
    for (kind, stride), parts in sorted(per.items()):
        values = np.concatenate(parts)
        out.setdefault(kind, {})[f"stride {stride}"] = {
            "vehicles": len(values),
            "path_shown": round(float(values[:, 0].mean()), 3) if len(values) else None,
            "seconds_ahead_median": round(float(np.median(values[:, 1])), 2) if len(values) else None,
        }
    return out


def coverage_table(by_kind: dict[str, dict[str, Any]]) -> str:
    """A Markdown table of :func:`coverage_by_kind`: per kind, each stride's share shown and seconds ahead."""
    strides = sorted({s for row in by_kind.values() for s in row}, key=lambda s: int(s.split()[1]))
    head = "| kind | vehicles | " + " | ".join(f"{s}: path shown / s ahead" for s in strides) + " |"
    lines = [head, "|" + "---|" * (len(strides) + 2)]
    for kind, row in by_kind.items():
        first = next(iter(row.values()))
        cells = [
            f"{row[s]['path_shown']} / {row[s]['seconds_ahead_median']}"
            if s in row and row[s]["vehicles"]
            else "-"
            for s in strides
        ]
        lines.append(f"| {kind} | {first['vehicles']} | " + " | ".join(cells) + " |")
    return "\n".join(lines)
