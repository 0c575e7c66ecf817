"""Who collides with whom: first collisions by class, partner and contact geometry (evaluate's
``collisions_by_class``), on a hand-made scene whose every contact is known, and on a generated one."""

from __future__ import annotations

import numpy as np
import pytest

from trajeglish_env.collision_kinds import FIELDS, collision_kinds, collision_table, pair_hits
from trajeglish_env.evaluation import collisions_over_time, constant_velocity_method, log_method, simulated
from trajeglish_env.evaluation_tables import HEADLINE, markdown_table
from trajeglish_env.scenario import AgentKind, Scenario
from trajeglish_env.sources.highway import generate_scene

STEPS, CURRENT = 31, 10


def _track(x0: float, y0: float, heading: float, speed: float) -> np.ndarray:
    """States ``[STEPS, 3]`` of constant-speed motion along ``heading``."""
    t = (np.arange(STEPS) - CURRENT) * 0.1
    return np.stack(
        [x0 + speed * t * np.cos(heading), y0 + speed * t * np.sin(heading), np.full(STEPS, heading)], -1
    )


def contact_scene() -> Scenario:
    """Four known contacts, far apart from each other:
    - a cyclist (1) rides at 5 m/s into the back of a standing car (0): 2.95 m between them, so they
      first overlap 0.6 s in (future step 5);
    - a car (2) driving north crosses the path of a car (3) driving east at 10 m/s, their corners meeting
      0.7 s in (step 6: 0.675 s to reach each other's sides);
    - two cars (4, 5) drive at each other head-on, fronts 25.5 m apart at 20 m/s: 1.3 s (step 12);
    - two pedestrians (6, 7) already overlap at the current step and keep standing.
    A car (8) drives alone and never collides."""
    tracks = [
        _track(0.0, 0.0, 0.0, 0.0),  # standing car, 4.5 m long: its back at x = -2.25
        _track(-6.0, 0.0, 0.0, 5.0),  # cyclist, 1.6 m long: its front at x = -5.2
        _track(100.0, -10.0, np.pi / 2, 10.0),
        _track(90.0, 0.0, 0.0, 10.0),
        _track(200.0, 0.0, 0.0, 10.0),
        _track(230.0, 0.0, np.pi, 10.0),
        _track(300.0, 0.0, 0.0, 0.0),
        _track(300.3, 0.0, 0.0, 0.0),
        _track(400.0, 50.0, 0.0, 10.0),
    ]
    kinds = [0, 2, 0, 0, 0, 0, 1, 1, 0]
    sizes = [[4.5, 2.0], [1.6, 0.6], [4.5, 2.0], [4.5, 2.0], [4.5, 2.0], [4.5, 2.0], [0.5, 0.5], [0.5, 0.5],
             [4.5, 2.0]]  # fmt: skip
    n = len(tracks)
    return Scenario.from_arrays(
        np.stack(tracks), np.ones((n, STEPS), bool), np.array(sizes), np.array(kinds),
        scenario_id="contacts", current_index=CURRENT, dt=0.1,
    )  # fmt: skip


def test_every_known_contact_is_classed_by_partner_and_geometry() -> None:
    sc = contact_scene()
    sim = simulated(sc)
    fut = log_method(sc, 2, 0)  # the log, twice: every count doubles
    table = collision_table(collision_kinds(sc, fut, sim))
    veh, ped, cyc = table["vehicle"], table["pedestrian"], table["cyclist"]
    assert (veh["agent_rollouts"], ped["agent_rollouts"], cyc["agent_rollouts"]) == (12, 4, 2)
    # the cyclist rides into the standing car ahead; the car is hit from behind by a cyclist
    assert cyc["collided"] == 2 and cyc["partner"] == {"vehicle": 2, "pedestrian": 0, "cyclist": 0}
    assert cyc["geometry"] == {"into_agent_ahead": 2, "from_behind": 0, "crossing": 0, "head_on": 0}
    assert cyc["into_stopped_agent_ahead"] == 2 and cyc["already_overlapping"] == 0
    # cars: 0 from behind (by the cyclist), 2 and 3 crossing, 4 and 5 head-on; car 8 never collides
    assert veh["collided"] == 10 and veh["rate"] == pytest.approx(10 / 12)
    assert veh["partner"] == {"vehicle": 8, "pedestrian": 0, "cyclist": 2}
    assert veh["geometry"] == {"into_agent_ahead": 0, "from_behind": 2, "crossing": 4, "head_on": 4}
    assert veh["into_stopped_agent_ahead"] == 0
    # the pedestrians overlap in the log's own current step
    assert ped["collided"] == 4 and ped["already_overlapping"] == 4 and ped["partner"]["pedestrian"] == 4
    # the same collisions as the collision curve counts: agents colliding at some step
    curve = collisions_over_time(sc, fut)  # [R,H] share of simulated agents overlapping
    assert curve[0, 0] == pytest.approx(2 / 9)  # only the pedestrians at the first future step
    assert curve[0].max() * 9 <= veh["collided"] / 2 + ped["collided"] / 2 + cyc["collided"] / 2


def test_the_contacts_start_when_the_boxes_first_overlap() -> None:
    """Each pair's first overlapping step is the one its geometry gives; a cyclist that stays where it is
    has no contact at all."""
    sc = contact_scene()
    sim = simulated(sc)
    fut = log_method(sc, 1, 0)
    r, i, j, h = pair_hits(sc, fut, sim)
    first = {
        (a, b): int(h[(i == a) & (j == b)].min()) for a, b in set(zip(i.tolist(), j.tolist(), strict=True))
    }
    assert first == {(0, 1): 5, (2, 3): 6, (4, 5): 12, (6, 7): 0}
    still = fut.copy()
    still[:, 1] = sc.xyh[1, CURRENT]  # the cyclist stays where it is
    table = collision_table(collision_kinds(sc, still, sim))
    assert table["cyclist"]["collided"] == 0 and table["cyclist"]["agent_rollouts"] == 1
    assert table["vehicle"]["collided"] == 4 and table["vehicle"]["geometry"]["from_behind"] == 0


def test_a_generated_scene_table_sums_up_and_reaches_the_report() -> None:
    sc = generate_scene("intersection", seed=2)
    sim = simulated(sc)
    cv = constant_velocity_method(sc, 2, 0)
    counts = collision_kinds(sc, cv, sim)
    assert counts.shape == (len(AgentKind), len(FIELDS))
    table = collision_table(counts)
    agents = table["vehicle"]
    assert agents["agent_rollouts"] == 2 * len(sim)
    assert sum(agents["partner"].values()) == sum(agents["geometry"].values()) == agents["collided"]
    # an agent collides in a rollout exactly when the collision curve counts it at some step
    r, i, j, _ = pair_hits(sc, cv, sim)
    assert agents["collided"] == len(set(zip(r, i, strict=True)) | set(zip(r, j, strict=True)))
    assert agents["collided"] > 0  # constant velocity through an intersection collides
    methods = {
        "constant_velocity": {
            "scores": dict.fromkeys(HEADLINE, 0.0),
            "red_light_runs_by_kind": {},
            "collisions_by_class": table,
        }
    }
    clean = {"scores": dict.fromkeys(HEADLINE, 0.0), "red_light_runs_by_kind": {}, "collisions_by_class": {}}
    methods["log"] = clean  # a method without a collision is named, not left out as if not evaluated
    md = markdown_table({"scenes": 1, "rollouts": 2, "metrics_config": "2025", "methods": methods})
    row = next(line for line in md.splitlines() if line.startswith("| constant_velocity | vehicle |"))
    assert f"{agents['collided']} of {agents['agent_rollouts']}" in row
    assert "Who collides with whom (every simulated agent-rollout, pooled over scenes" in md
    assert "no collision at all: log)" in md
    assert "min_ade in metres; collision_rate and offroad_rate: WOSAC's" in md  # which agents each counts
