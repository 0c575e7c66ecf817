"""Red lights of guarded sampling: a vehicle's or cyclist's candidate that would cross the stop fence of a
red signal of the lane it is on -- the WOSAC violation rule (:mod:`~trajeglish_env.metrics.traffic_lights`),
the fence and the lane chosen as the reference chooses them -- is masked with the road-edge rule (and
dropped with it when nothing else is left: a vehicle too fast to stop before the line goes on).

The model reads no signal states; the guard makes its vehicles and cyclists stop at red without changing
any other draw (a vehicle with no red stop point within reach of its candidates is not checked)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from trajeglish_env.metrics.traffic_lights import SignalFences, TrafficSignals, has_signals, on_signal_lane
from trajeglish_env.scenario import MapKind, Scenario

# Stop points farther than this (m) beyond the reach of a vehicle's candidates are not looked at.
SIGNAL_SLACK = 2.0


@dataclass(frozen=True)
class SceneSignals:
    """A scene's lanes and signals as the violation rule sees them, and the fences of all its steps."""

    signals: TrafficSignals
    fences: SignalFences

    @classmethod
    def of(cls, sc: Scenario) -> SceneSignals | None:
        """The signals of ``sc``, or None where it has none (no violation is possible)."""
        if sc.signal_state is None or not len(sc.signal_lane_id):
            return None
        lanes = np.flatnonzero(sc.map_kind == MapKind.LANE_SURFACE_STREET)
        signals = TrafficSignals.build(
            [sc.map_points[sc.map_offsets[k] : sc.map_offsets[k + 1]] for k in lanes],
            [int(sc.map_id[k]) for k in lanes],
            sc.signal_lane_id,
            sc.signal_state,
            np.broadcast_to(sc.signal_xy, (sc.num_steps, *sc.signal_xy.shape)),
        )
        if not has_signals(signals):
            return None
        return cls(signals, SignalFences.of(signals, np.arange(sc.num_steps)))

    def near_red(self, origin: np.ndarray, t: np.ndarray, reach: np.ndarray) -> np.ndarray:
        """``[m, L]`` the signals red at step ``t + 1`` whose stop point lies within ``reach [m]`` (plus
        :data:`SIGNAL_SLACK`) of ``origin [m, 2]`` (``t [m]``: the steps the candidates start from)."""
        g = np.minimum(t + 1, self.fences.red.shape[0] - 1)
        stop = self.signals.stop[g]  # [m, L, 2]
        d = np.hypot(stop[..., 0] - origin[:, None, 0], stop[..., 1] - origin[:, None, 1])
        return self.fences.red[g] & (d <= (reach + SIGNAL_SLACK)[:, None])

    def violations(self, origin: np.ndarray, cand: np.ndarray, t: np.ndarray, near: np.ndarray) -> np.ndarray:
        """``[m, c]`` which candidates ``cand [m, c, 2]`` of vehicles at ``origin [m, 2]`` (step ``t [m]``)
        would run one of the red lights ``near [m, L]`` between ``t`` and ``t + 1``."""
        f = self.fences
        last = f.red.shape[0] - 1
        now, g = np.minimum(t, last), np.minimum(t + 1, last)
        behind = f.along(origin, now) < f.stop_at[now]  # [m, L]
        ahead = f.along(cand, g[:, None]) > f.stop_at[g][:, None]  # [m, c, L]
        crossed = (behind & near)[:, None] & ahead
        out = np.zeros(cand.shape[:2], bool)
        i, k = np.nonzero(crossed.any(axis=2))
        if len(i):
            out[i, k] = on_signal_lane(self.signals, f, cand[i, k], crossed[i, k])
        return out


class SignalCache:
    """The :class:`SceneSignals` of each scene object an engine's rows hold (built once per scene)."""

    def __init__(self) -> None:
        self._hits: dict[int, tuple[Scenario, SceneSignals | None]] = {}

    def get(self, sc: Scenario) -> SceneSignals | None:
        hit = self._hits.get(id(sc))
        if hit is None or hit[0] is not sc:
            if len(self._hits) > 256:
                self._hits.clear()
            hit = self._hits[id(sc)] = (sc, SceneSignals.of(sc))
        return hit[1]
