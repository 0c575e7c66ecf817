"""Signals of guarded sampling, two rules masked with the road-edge rule (and dropped with it when nothing
else is left):

- red: a vehicle's or cyclist's candidate that would cross the stop fence of a red signal of the lane it is
  on -- the WOSAC violation rule (:mod:`~trajeglish_env.metrics.traffic_lights`), the fence and the lane
  chosen as the reference chooses them -- is masked (a vehicle too fast to stop before the line goes on);
- green: a vehicle or cyclist behind the stop line of a green signal on its lane (and of no red one), with
  the way ahead clear, may not stand still or creep: its candidates moving less than :data:`DEPART_STEP`,
  or under 1.5 m/s less than :data:`DEPART_GAIN` more than its last step, are masked (so it leaves the line
  at pace instead of creeping onto it), until it is :data:`DEPART_OVERSHOOT` m past the line. The model
  reads no signal states, so without this rule a queue stopped at red stays stopped when the light turns
  green (on SUMO scenes the logged vehicles that set off
  during the 8 s were left at 0.1 m/s on average against the log's 2.1).

A vehicle with no red stop point within reach of its candidates, and no green one ahead, is not checked."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from trajeglish_env.metrics.traffic_lights import SignalFences, TrafficSignals, has_signals, on_signal_lane
from trajeglish_env.scenario import MapKind, Scenario, SignalState

# Stop points farther than this (m) beyond the reach of a vehicle's candidates are not looked at.
SIGNAL_SLACK = 2.0
GO_STATES = (SignalState.ARROW_GO, SignalState.GO)
# The green rule applies to a rider whose front is at most DEPART_REACH m behind a stop point on its lane
# (the point within DEPART_LATERAL m of its centre line, the lane at the fence within DEPART_ALIGN cosine of
# its heading; a front up to DEPART_OVERSHOOT m past the point still counts: farther, it may be waiting in the
# junction to turn, as 24 of SUMO's 173 standing drivers there do), and
# masks its candidates that move less than DEPART_STEP m forward in the step (the shipped vocabulary's four
# standstill templates) or, below DEPART_PACE m a step (1.5 m/s), less than DEPART_GAIN m more than its last
# step (1 m/s^2): a rider creeping on at 0.3-0.4 m/s stood in the junction after 0.5 m, its queue behind it.
DEPART_REACH, DEPART_LATERAL, DEPART_ALIGN, DEPART_OVERSHOOT = 30.0, 1.5, 0.8, 0.5
DEPART_STEP, DEPART_GAIN, DEPART_PACE = 0.02, 0.01, 0.15


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

    def _ahead_on_lane(
        self, origin: np.ndarray, length: np.ndarray, t: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The steps ``g [m]`` (``t + 1``), the distance ``[m, L]`` from the front of each rider at ``origin
        [m, 3]`` (box ``length [m]``) to each stop point, and which stop points lie ahead on its lane."""
        g = np.minimum(t + 1, self.fences.red.shape[0] - 1)
        stop, direction = self.signals.stop[g], self.fences.direction[g]  # [m, L, 2]
        c, s = np.cos(origin[:, 2])[:, None], np.sin(origin[:, 2])[:, None]
        dx, dy = stop[..., 0] - origin[:, None, 0], stop[..., 1] - origin[:, None, 1]
        ahead = dx * c + dy * s - length[:, None] / 2  # from the front to the stop point
        norm = np.maximum(np.hypot(direction[..., 0], direction[..., 1]), 1e-9)
        on_lane = (
            (ahead > -DEPART_OVERSHOOT)
            & (ahead < DEPART_REACH)
            & (np.abs(dy * c - dx * s) < DEPART_LATERAL)
            & ((direction[..., 0] * c + direction[..., 1] * s) / norm > DEPART_ALIGN)
        )
        return g, ahead, on_lane

    def green_ahead(self, origin: np.ndarray, length: np.ndarray, t: np.ndarray) -> np.ndarray:
        """``[m]`` riders at ``origin [m, 3]`` (box ``length [m]``, step ``t [m]``) with a signal green at
        ``t + 1`` ahead on their lane and no red one there (a lane's connections may differ)."""
        g, _, on_lane = self._ahead_on_lane(origin, length, t)
        go = np.isin(self.signals.state[g], GO_STATES) & on_lane
        return go.any(axis=1) & ~(self.fences.red[g] & on_lane).any(axis=1)

    def red_gap(self, origin: np.ndarray, length: np.ndarray, t: np.ndarray) -> np.ndarray:
        """``[m]`` metres from the front of each rider at ``origin [m, 3]`` (box ``length [m]``, step ``t
        [m]``) to the nearest stop point of a signal red at ``t + 1`` ahead on its lane (up to
        :data:`DEPART_REACH` m; inf where none): where a rule-based driver (IDM) stops."""
        g, ahead, on_lane = self._ahead_on_lane(origin, length, t)
        red = self.fences.red[g] & on_lane & (ahead >= 0)
        return np.where(red, ahead, np.inf).min(axis=1, initial=np.inf)

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
