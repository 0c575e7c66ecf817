"""Agents standing still (evaluate's ``standing_by_kind``): exact counts on a hand-made scene, the
per-kind table and its Markdown lines through ``evaluate_methods`` on a generated scene."""

from __future__ import annotations

import numpy as np

from trajeglish_env.evaluation import (
    EvalConfig,
    constant_velocity_method,
    evaluate_methods,
    log_method,
    simulated,
)
from trajeglish_env.evaluation_tables import markdown_table
from trajeglish_env.scenario import Scenario, scene_kind
from trajeglish_env.sources.highway import generate_scene
from trajeglish_env.standing import STANDING_SPEED, standing_counts, standing_table

STEPS, CURRENT = 31, 10
H = STEPS - CURRENT - 1


def _track(x0: float, speed: float) -> np.ndarray:
    t = (np.arange(STEPS) - CURRENT) * 0.1
    return np.stack([x0 + speed * t, np.zeros(STEPS), np.zeros(STEPS)], -1)


def still_scene() -> Scenario:
    """A standing car, a car at 10 m/s, a cyclist at 0.3 m/s (under the threshold: it stands) and a
    pedestrian walking at 1.2 m/s, 50 m apart."""
    tracks = [_track(0.0, 0.0), _track(50.0, 10.0), _track(100.0, 0.3), _track(150.0, 1.2)]
    sizes = np.array([[4.5, 2.0], [4.5, 2.0], [1.6, 0.6], [0.5, 0.5]])
    return Scenario.from_arrays(
        np.stack(tracks), np.ones((4, STEPS), bool), sizes, np.array([0, 0, 2, 1]),
        scenario_id="still", current_index=CURRENT, dt=0.1,
    )  # fmt: skip


def test_standing_steps_are_counted_per_class_exactly() -> None:
    sc = still_scene()
    sim = simulated(sc)
    counts = standing_counts(sc, log_method(sc, 3, 0), sim)  # the log, three times
    assert counts.tolist() == [[3 * H, 2 * 3 * H], [0, 3 * H], [3 * H, 3 * H]]
    fut = log_method(sc, 2, 0).copy()
    fut[1, 1, 12:] = fut[1, 1, 11]  # in rollout 1 the moving car stops after its 12th future step
    counts = standing_counts(sc, fut, sim)
    assert counts[0].tolist() == [2 * H + (H - 12), 2 * 2 * H]
    table = standing_table(counts)
    assert table["vehicle"]["standing"] == 2 * H + H - 12
    assert np.isclose(table["vehicle"]["share"], (2 * H + H - 12) / (4 * H))
    assert table["cyclist"]["share"] == 1.0 and table["pedestrian"]["share"] == 0.0
    assert STANDING_SPEED == 0.5


def test_evaluate_reports_standing_by_kind_with_its_markdown_table() -> None:
    sc = generate_scene("intersection", seed=6)  # 7 vehicles, 80 future steps; some wait at the junction
    methods = {"log": log_method, "constant_velocity": constant_velocity_method}
    result = evaluate_methods([sc], methods, EvalConfig(rollouts=2, scenes=1), progress=False)
    kind = scene_kind(sc)
    sim = simulated(sc)
    expected = standing_table(standing_counts(sc, log_method(sc, 2, 0), sim))
    assert result["log"]["standing_by_kind"] == {kind: expected}
    assert expected["vehicle"]["standing"] == 2 * 139 and expected["vehicle"]["steps"] == 2 * 7 * 80
    cv = result["constant_velocity"]["standing_by_kind"][kind]["vehicle"]
    # one vehicle stands at the current step, and constant velocity keeps it there for all 80 steps (x 2)
    assert (cv["standing"], cv["steps"]) == (2 * 80, 2 * 7 * 80)
    doc = {"scenes": 1, "rollouts": 2, "metrics_config": "2025", "methods": result}
    text = markdown_table(doc)
    assert "Vehicles standing still" in text
    row = next(line for line in text.splitlines() if line.startswith(f"| {kind} |") and line.count("|") == 4)
    assert row.split("|")[2:4] == [" 0.248 ", " 0.143 "]
