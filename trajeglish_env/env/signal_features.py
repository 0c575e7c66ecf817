"""The traffic signals an external agent sees (``ObservationConfig.signals``): the nearest stop points of
signal-controlled lanes within the observation radius, in the agent's frame, with their state now.

Per signal: present, x, y (/ radius, x forward, y left), red, yellow, green (one-hot of the lane's state at
the step being played: stop / caution / go, arrows and flashing included; unknown: all 0). Beyond the end of
the log the last logged states hold. All observers of many scenes in one NumPy pass (scenes padded to the
most signals any has).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from trajeglish_env.geometry import to_local
from trajeglish_env.scenario import SignalState

SIGNAL_FEATURES = 6
_COLOUR = np.zeros((len(SignalState), 3), dtype=np.float32)  # SignalState -> (red, yellow, green)
for _state in (SignalState.ARROW_STOP, SignalState.STOP, SignalState.FLASHING_STOP):
    _COLOUR[_state, 0] = 1.0
for _state in (SignalState.ARROW_CAUTION, SignalState.CAUTION, SignalState.FLASHING_CAUTION):
    _COLOUR[_state, 1] = 1.0
for _state in (SignalState.ARROW_GO, SignalState.GO):
    _COLOUR[_state, 2] = 1.0


def signal_features(
    signal_xy: Sequence[np.ndarray],
    signal_state: Sequence[np.ndarray | None],
    steps: Sequence[int],
    scene: np.ndarray,
    own: np.ndarray,
    count: int,
    radius: float,
) -> np.ndarray:
    """``[Q, count * SIGNAL_FEATURES]`` for observers in scene ``scene[q]`` at state ``own [Q,3]``, of
    scenes whose signals are ``signal_xy[b] [L_b,2]`` and ``signal_state[b] [T_b,L_b]`` (None: none),
    played at step ``steps[b]``: the ``count`` nearest within ``radius``, nearest first, zero padded."""
    q = len(scene)
    out = np.zeros((q, count, SIGNAL_FEATURES), dtype=np.float32)
    most = max((len(xy) for xy in signal_xy), default=0)
    if q == 0 or most == 0:
        return out.reshape(q, count * SIGNAL_FEATURES)
    b = len(signal_xy)
    xy = np.zeros((b, most, 2))
    colour = np.zeros((b, most, 3), dtype=np.float32)
    real = np.zeros((b, most), dtype=bool)
    for k, (points, states, t) in enumerate(zip(signal_xy, signal_state, steps, strict=True)):
        if states is None or not len(points):
            continue
        xy[k, : len(points)] = points
        colour[k, : len(points)] = _COLOUR[np.asarray(states[min(t, len(states) - 1)], dtype=np.int64)]
        real[k, : len(points)] = True
    frame = np.concatenate([xy[scene], np.zeros((q, most, 1))], axis=-1)  # [Q, L, 3]
    local = to_local(own[:, None, :], frame)[..., :2]
    dist = np.linalg.norm(local, axis=-1)
    seen = real[scene] & (dist <= radius)
    order = np.argsort(np.where(seen, dist, np.inf), axis=1, kind="stable")[:, :count]
    take = np.take_along_axis(seen, order, axis=1)
    rows = np.arange(q)[:, None]
    shown = min(count, most)
    out[:, :shown, 0] = take
    out[:, :shown, 1:3] = np.where(take[..., None], local[rows, order] / radius, 0.0)
    out[:, :shown, 3:] = np.where(take[..., None], colour[scene][rows, order], 0.0)
    return out.reshape(q, count * SIGNAL_FEATURES)
