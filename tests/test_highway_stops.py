"""Stop events (``KIND+stop`` highway-env scene kinds): one vehicle brakes at a constant rate to a stop and
holds, the traffic behind it reacts, and nothing before the event differs from the base kind's scene."""

from __future__ import annotations

import functools
import json
import subprocess
import sys

import numpy as np
import pytest
from helpers import REPO

from trajeglish_env.metrics.boxes import box_collisions
from trajeglish_env.scenario import Scenario, scene_kind
from trajeglish_env.scenario_io import save_scenarios
from trajeglish_env.sources import highway
from trajeglish_env.sources.generation import GenerationConfig, generate
from trajeglish_env.sources.highway import EXTRA_KINDS, KINDS, generate_scene
from trajeglish_env.sources.highway_stops import draw_stop_event, split_kind, stop_event_in
from trajeglish_env.training.kind_repeat import repeat_counts

SEED = 2  # highway+stop seed 2: the sdc stops from about 20 m/s, on the first try


@functools.cache
def scene(kind: str, seed: int = SEED) -> Scenario:
    return generate_scene(kind, seed)


def _stopper(sc: Scenario, step: int, decel: float) -> int:
    """The agent whose speed falls by ``decel * dt`` every step after ``step`` until it stands."""
    speed = sc.speed()
    found = []
    for i in np.flatnonzero(sc.valid.all(axis=1)):
        braking = speed[i, step + 2 :]
        braking = braking[: int(np.argmax(braking < decel * sc.dt * 1.5)) or len(braking)]
        drops = -np.diff(braking)
        if len(drops) >= 5 and np.allclose(drops, decel * sc.dt, rtol=0.05):
            found.append(int(i))
    assert len(found) == 1, f"expected one stopping agent, found {found}"
    return found[0]


def test_kinds_and_names() -> None:
    assert EXTRA_KINDS == tuple(k + "+stop" for k in KINDS)
    assert split_kind("two-way+stop") == ("two-way", True) and split_kind("two-way") == ("two-way", False)
    sc = scene("highway+stop")
    assert sc.scenario_id == f"highway-highway+stop-{SEED}-stop-a{sc.track_id[sc.sdc]}-t10"  # who and when
    assert scene_kind(sc) == "highway/highway+stop"
    assert repeat_counts([sc, scene("highway")], (("highway/highway+stop", 3),)).tolist() == [3, 1]
    quiet = generate_scene("merge+stop", 2)  # no vehicle with a follower close behind: no event, no suffix
    assert quiet.scenario_id == "highway-merge+stop-2" and stop_event_in(quiet) is None
    with pytest.raises(ValueError, match=r"unknown highway scene kind 'highway\+go'.*highway\+stop"):
        generate_scene("highway+go", 0)


def test_a_vehicle_brakes_to_a_stop_and_holds_and_its_follower_reacts() -> None:
    sc = scene("highway+stop")
    event = draw_stop_event(SEED, 0, sc.current_index, sc.num_steps)
    assert sc.current_index - 5 <= event.step <= sc.current_index + 30 and 3.0 <= event.decel <= 6.0
    i = _stopper(sc, event.step, event.decel)
    assert stop_event_in(sc) == (i, event.step) and i == sc.sdc
    assert stop_event_in(scene("highway")) is None
    speed = sc.speed()
    assert speed[i, event.step] > 10.0  # it was moving
    stopped = np.flatnonzero(speed[i] < 0.01)
    assert len(stopped) and np.all(speed[i, stopped[0] :] < 0.01)  # stands still to the end
    assert np.ptp(sc.xyh[i, event.step :, 2]) < 0.01  # in its lane: no lane change while stopping
    # the vehicles behind it slow down well below their speed at the event, and nobody's box overlaps
    rel = sc.xyh[:, event.step, :2] - sc.xyh[i, event.step, :2]
    forward = np.array([np.cos(sc.xyh[i, event.step, 2]), np.sin(sc.xyh[i, event.step, 2])])
    left = np.array([-forward[1], forward[0]])
    behind = sc.valid[:, event.step] & (rel @ forward < 0) & (np.abs(rel @ left) < 2.0)
    behind[i] = False
    assert behind.any()
    j = int(np.flatnonzero(behind)[np.argmax((rel @ forward)[behind])])  # the nearest one behind
    assert speed[j, event.step :].min() < 0.5 * speed[j, event.step]
    for t in range(sc.num_steps):
        others = np.flatnonzero(sc.valid[:, t] & (np.arange(sc.num_agents) != i))
        assert not box_collisions(sc.xyh[i, t], sc.size[i], sc.xyh[others, t], sc.size[others]).any()


def test_nothing_before_the_event_differs_from_the_base_kind() -> None:
    base, stop = scene("highway"), scene("highway+stop")
    event = draw_stop_event(SEED, 0, stop.current_index, stop.num_steps)
    shared = np.intersect1d(base.track_id, stop.track_id)
    assert len(shared) >= 5
    a = base.xyh[[base.agent_index(t) for t in shared], : event.step + 1]
    b = stop.xyh[[stop.agent_index(t) for t in shared], : event.step + 1]
    np.testing.assert_array_equal(a, b)
    later = base.xyh[[base.agent_index(t) for t in shared]], stop.xyh[[stop.agent_index(t) for t in shared]]
    assert not np.array_equal(*later)
    assert scene("highway+stop").equals(generate_scene("highway+stop", SEED))  # deterministic


def test_generate_takes_stop_kinds_only_when_asked(tmp_path) -> None:
    out = generate(GenerationConfig("highway", 2, seed=4, kinds=("u-turn+stop",)), tmp_path, progress=False)
    assert out["kinds"] == ["u-turn+stop"]
    assert all("+stop" not in k for k in highway.KINDS)
    with pytest.raises(ValueError, match=r"unknown highway scene kinds \['u-turn\+go'\]"):
        generate(GenerationConfig("highway", 1, kinds=("u-turn+go",)), tmp_path / "x", progress=False)


def test_stop_probe_script(tmp_path) -> None:
    """scripts/stop_probe.py: the stopper replays its log, the model drives the rest; guarded, none hit it."""
    save_scenarios(tmp_path / "stop" / "s.scn.npz", [scene("u-turn+stop", 3)])  # stops at step 25
    save_scenarios(tmp_path / "base" / "s.scn.npz", [scene("highway", 1)])
    script = [sys.executable, str(REPO / "scripts" / "stop_probe.py"), "--rollouts", "2", "--json"]
    done = subprocess.run(
        [*script, "--data", str(tmp_path / "stop"), "--guard"], capture_output=True, text=True
    )
    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout)
    assert {k: result[k] for k in ("scenes", "rollouts", "hits", "rate")} == {
        "scenes": 1,
        "rollouts": 2,
        "hits": 0,
        "rate": 0.0,
    }
    assert result["reaction_tokens"] > 0  # the car behind slows within the window: its tokens are scored
    assert result["reaction_nll_with_stopper"] > 0 and result["reaction_nll_without_stopper"] > 0
    # the same tokens with the reacting agents' own inputs hidden: harder to predict for the shipped model,
    # which was never trained without them
    assert result["hidden_reaction_tokens"] == result["reaction_tokens"]
    assert result["hidden_reaction_nll_with_stopper"] > result["reaction_nll_with_stopper"]
    done = subprocess.run([*script, "--data", str(tmp_path / "base")], capture_output=True, text=True)
    assert done.returncode != 0 and "no +stop scene with its event after the current step" in done.stderr
