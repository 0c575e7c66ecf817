"""Rounded kerb corners: highway-env's logged vehicles stay on the road they are drawn on."""

from __future__ import annotations

import numpy as np
import pytest

from trajeglish_env.metrics.road_edges import RoadEdges, distance_to_road_edge, signed_distance_to_road_edges
from trajeglish_env.scenario import ROAD_EDGE_KINDS, Scenario
from trajeglish_env.sources.highway import HighwaySceneConfig, generate_scene
from trajeglish_env.sources.kerb_corners import round_kerb_corners


def _edges(sc: Scenario) -> RoadEdges:
    return RoadEdges.from_polylines(
        [sc.polyline(k) for k in np.flatnonzero(np.isin(sc.map_kind, list(ROAD_EDGE_KINDS)))]
    )


def _vehicles_off_road(sc: Scenario) -> int:
    """Logged vehicles whose box ever has a corner beyond a road edge (WOSAC's rule, 1.5 m tall boxes)."""
    n, t = sc.valid.shape
    xyz = np.concatenate([sc.xyh[..., :2], np.zeros((n, t, 1))], -1)
    box = np.concatenate([np.repeat(sc.size[:, None, :2], t, 1), np.full((n, t, 1), 1.5)], -1)
    d = distance_to_road_edge(xyz, sc.xyh[..., 2], box, sc.valid, _edges(sc))
    return int((np.where(sc.valid, d, -np.inf).max(1) > 0).sum())


def _corner(turn_deg: float) -> list[np.ndarray]:
    """Two 20 m edges (road on their left) meeting at the origin, the second turned by ``turn_deg``
    (negative: to the right, away from the road, so the kerb pokes into the road)."""
    a = np.linspace([-20.0, 0.0], [0.0, 0.0], 41)
    phi = np.deg2rad(turn_deg)
    b = np.linspace([0.0, 0.0], [20 * np.cos(phi), 20 * np.sin(phi)], 41)
    return [a, b]


def test_a_reflex_corner_is_rounded_and_only_the_road_grows() -> None:
    sharp = _corner(-90.0)
    rounded = round_kerb_corners(sharp, radius=8.0, spacing=0.5)
    assert len(rounded) == 2
    # the first edge now ends 8 m (radius * tan 45 deg) before the corner on its own line, then curves to
    # where the second one starts, 8 m past the corner
    np.testing.assert_allclose(rounded[1][0], [0.0, -8.0], atol=1e-9)
    np.testing.assert_allclose(rounded[0][-1], rounded[1][0], atol=1e-9)
    assert np.abs(rounded[0][rounded[0][:, 0] < -8.0 - 1e-9, 1]).max() < 1e-9
    # the quadratic fillet's midpoint (-2, -2) is its nearest point to the corner: 2 * sqrt(2) m away
    assert np.linalg.norm(rounded[0], axis=1).min() == pytest.approx(2 * np.sqrt(2), abs=0.02)
    # every point of the new kerb lies on the old kerb or beyond it: nothing drivable was taken away
    old = RoadEdges.from_polylines(sharp)
    assert signed_distance_to_road_edges(np.concatenate(rounded), old).min() > -1e-6
    # a point of the old kerb's corner is on the road now
    assert signed_distance_to_road_edges(np.array([[-0.3, -0.3]]), RoadEdges.from_polylines(rounded))[0] < 0


@pytest.mark.parametrize("turn", [90.0, -5.0, -170.0])
def test_convex_corners_and_gentle_hand_overs_stay(turn: float) -> None:
    sharp = _corner(turn)
    for before, after in zip(sharp, round_kerb_corners(sharp, radius=8.0, spacing=0.5), strict=True):
        np.testing.assert_array_equal(before, after)


def test_unjoined_edges_stay_and_bad_settings_are_named() -> None:
    a, b = _corner(-90.0)
    apart = [a, b + [0.0, -2.0]]  # 2 m apart: no hand-over
    for before, after in zip(apart, round_kerb_corners(apart, radius=8.0, spacing=0.5), strict=True):
        np.testing.assert_array_equal(before, after)
    with pytest.raises(ValueError, match="radius"):
        round_kerb_corners(apart, radius=0.0, spacing=0.5)
    with pytest.raises(ValueError, match="kerb_radius"):
        HighwaySceneConfig(kerb_radius=-1.0)


def test_roundabout_logs_stay_on_the_road_with_rounded_kerbs() -> None:
    """Measured on roundabout seeds 200-203: sharp kerbs put 20 of 38 logged vehicles off the road (by
    0.26 m median), kerbs of 8 m none; the scene's tracks are the same either way."""
    rounded = generate_scene("roundabout", 200)
    sharp = generate_scene("roundabout", 200, HighwaySceneConfig(kerb_radius=0.0))
    np.testing.assert_array_equal(rounded.xyh, sharp.xyh)
    assert _vehicles_off_road(sharp) >= 3
    assert _vehicles_off_road(rounded) == 0
