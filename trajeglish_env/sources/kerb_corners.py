"""Round the kerb corners where one road edge hands over to the next (highway-env maps).

highway-env draws a junction of two lanes (a roundabout ring and its exit, say) as two painted sides that
meet at a sharp corner, and its vehicles cut that corner: with sharp corners 53-62 % of the logged
roundabout vehicles crossed a drawn edge (by 0.26 m median). Real kerbs are rounded there. Where one edge
polyline ends within ``join`` metres of where another begins and the chain turns away from the road (the
kerb pokes into the road: a reflex corner of the drivable area) by 10-140 degrees, both are trimmed back
by the tangent length of a fillet of ``radius`` metres and joined by a curve through the corner's cut-off,
which only widens the road. Sharper hand-overs, the noses of splitter islands and the gores of ramps
(155-180 degrees), stay sharp.
"""

from __future__ import annotations

import numpy as np

from trajeglish_env.geometry import resample_polyline

MIN_TURN = np.deg2rad(10.0)  # gentler hand-overs are a continuing kerb, not a corner
MAX_TURN = np.deg2rad(140.0)  # sharper ones are the nose of an island or a gore, which no lane cuts


def _cumulative(line: np.ndarray) -> np.ndarray:
    """``[n]`` arc length from the first point."""
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(line, axis=0), axis=1))])


def _point_at(line: np.ndarray, arc: np.ndarray, s: float) -> np.ndarray:
    """The point ``s`` metres along ``line`` (arc lengths ``arc``)."""
    return np.column_stack([np.interp(s, arc, line[:, 0]), np.interp(s, arc, line[:, 1])])[0]


def _direction(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Unit vector from ``a`` to ``b``."""
    d = b - a
    return d / max(float(np.linalg.norm(d)), 1e-9)


def round_kerb_corners(
    edges: list[np.ndarray], radius: float, spacing: float, join: float = 0.75
) -> list[np.ndarray]:
    """``edges`` (polylines ``[n, 2]``, road on their left) with each reflex hand-over rounded.

    The tangent length ``radius * tan(turn / 2)`` is capped at half of each polyline, so short pieces
    keep their middle; the fillet is a quadratic curve from the trimmed end through the corner to the
    trimmed start, sampled every ``spacing`` metres at most. Polylines keep their order and count.
    """
    if not radius > 0 or not spacing > 0 or not join >= 0:
        raise ValueError(
            f"round_kerb_corners: radius, spacing > 0 and join >= 0 expected, got {radius}, {spacing}, {join}"
        )
    lines = [np.asarray(e, dtype=np.float64) for e in edges]
    arcs = [_cumulative(e) for e in lines]
    if not lines:
        return []
    starts = np.array([e[0] for e in lines])
    # for each polyline's end, the polyline starting nearest to it (not itself), when within `join`
    trim_end = np.zeros(len(lines))
    trim_start = np.zeros(len(lines))
    fillets: dict[int, tuple[int, float]] = {}
    for i, line in enumerate(lines):
        if arcs[i][-1] <= 0:
            continue
        gap = np.linalg.norm(starts - line[-1], axis=1)
        gap[i] = np.inf
        j = int(np.argmin(gap))
        if gap[j] > join or arcs[j][-1] <= 0:
            continue
        probe_in = min(1.0, arcs[i][-1] / 2)
        probe_out = min(1.0, arcs[j][-1] / 2)
        d_in = _direction(_point_at(line, arcs[i], arcs[i][-1] - probe_in), line[-1])
        d_out = _direction(lines[j][0], _point_at(lines[j], arcs[j], probe_out))
        cross = d_in[0] * d_out[1] - d_in[1] * d_out[0]
        turn = float(np.arctan2(abs(cross), float(d_in @ d_out)))
        if cross >= 0 or not MIN_TURN <= turn <= MAX_TURN:  # a left turn is a convex road corner: it stays
            continue
        tangent = radius * np.tan(turn / 2)
        fillets[i] = (j, tangent)
    for i, (j, tangent) in fillets.items():
        trim_end[i] = min(tangent, arcs[i][-1] / 2)
        trim_start[j] = max(trim_start[j], min(tangent, arcs[j][-1] / 2))
    out = []
    for i, line in enumerate(lines):
        arc = arcs[i]
        lo, hi = trim_start[i], arc[-1] - trim_end[i]
        if lo == 0 and hi == arc[-1]:
            out.append(line)
            continue
        keep = (arc > lo) & (arc < hi)
        piece = np.vstack([_point_at(line, arc, lo), line[keep], _point_at(line, arc, hi)])
        if i in fillets:
            j = fillets[i][0]
            corner = 0.5 * (line[-1] + lines[j][0])
            end = _point_at(lines[j], arcs[j], trim_start[j])
            u = np.linspace(0.0, 1.0, 17)[1:, None]
            curve = (1 - u) ** 2 * piece[-1] + 2 * u * (1 - u) * corner + u**2 * end
            piece = np.vstack([piece, curve])
        out.append(resample_polyline(piece, spacing))
    return out
