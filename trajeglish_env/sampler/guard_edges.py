"""Road edges of guarded sampling: which sampled vehicles a candidate could take off the road, and the env's
off-road rule for their candidate boxes (a corner more than the margin beyond a road edge, the edge chosen
and signed as the WOSAC reference does), answered from the maps' road-edge cells
(:mod:`~trajeglish_env.edge_cells`).

A vehicle is left unchecked only where no candidate can be off the road, which is proved, not assumed:
every cell within reach of its candidates' corners is safe (all its points on the road side). Any other
vehicle's candidate corners are checked one by one: a corner in a safe cell is on the road, any other one
is measured against its cell's few segments, number for number the reference's distance.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from trajeglish_env.edge_cells import EdgeCells
from trajeglish_env.sampler.rows import RowStates


@dataclass(frozen=True)
class RoadView:
    """The road edges of a call's ``n`` pairs: ``road [n]`` where the road-edge rule applies (a vehicle
    that a candidate could take off the road) and ``limit [n]`` how far (m) a candidate box's corner may
    then lie beyond a road edge; each pair's ``maps [n]`` in ``cells`` (-1: none) and ``rows [n]``; the
    rows' padded road edges ``padded`` (columns, links, count)."""

    road: np.ndarray
    limit: np.ndarray
    maps: np.ndarray
    rows: np.ndarray
    cells: EdgeCells
    padded: tuple[np.ndarray, np.ndarray, np.ndarray]

    def box_excess(self, sel: np.ndarray, xyh: np.ndarray, size: np.ndarray) -> np.ndarray:
        """``[m,c]`` how far (m) the most off-road corner of each box ``xyh [m,c,3]`` of pairs ``sel [m]``
        (sizes ``[m,2]``) lies beyond a road edge (the env's signed distance; -inf where every corner lies in
        a safe cell, i.e. on the road)."""
        m, c = xyh.shape[:2]
        pick = np.repeat(sel, c)
        boxes = xyh.reshape(m * c, 3), np.repeat(size, c, axis=0)
        return self.cells.box_excess(self.maps[pick], self.rows[pick], *boxes, self.padded).reshape(m, c)

    def beyond(self, sel: np.ndarray, xyh: np.ndarray, size: np.ndarray) -> np.ndarray:
        """``[m,c]`` True where a candidate box (as in :meth:`box_excess`) has a corner more than its pair's
        ``limit`` beyond a road edge."""
        return self.box_excess(sel, xyh, size) > self.limit[sel][:, None]


def road_view(
    cells: EdgeCells,
    rs: RowStates,
    rr: np.ndarray,
    padded: tuple[np.ndarray, np.ndarray, np.ndarray],
    margin: float,
) -> RoadView:
    """The road edges of pairs of rows ``rr`` given the rows' padded road edges ``padded = (columns, links,
    count)``, the rule applying to none of them yet (:func:`road_rule` says to which)."""
    n = len(rr)
    maps = cells.map_ids(rs.edges)[rr]
    return RoadView(np.zeros(n, bool), np.full(n, float(margin)), maps, rr, cells, padded)


def road_rule(
    view: RoadView, sel: np.ndarray, origin: np.ndarray, size: np.ndarray, extent: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """For vehicles ``sel [m]`` on a map (at ``origin [m,3]``, their boxes there of ``size [m,2]``, their
    candidates' corners, and those of their kept-up motion, within ``extent [m]``): ``[m]`` whether the rule
    applies (unless every cell within reach is safe) and ``[m]`` how far beyond a road edge a candidate
    corner may then lie: the view's margin, or as far as the vehicle's box lies already if that is farther
    (a vehicle off the road may not go farther off). Where every cell within reach is safe, no candidate is
    masked either way, so the answer does not depend on which cells earlier queries computed."""
    road = ~view.cells.all_safe(view.maps[sel], origin[:, :2], extent)
    limit = view.limit[sel].copy()
    c = np.flatnonzero(road)
    if len(c):
        limit[c] = np.maximum(limit[c], view.box_excess(sel[c], origin[c][:, None], size[c])[:, 0])
    return road, limit
