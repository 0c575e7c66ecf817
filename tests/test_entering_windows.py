"""Agents the log brings in mid-window join an existing model context: they act last in the subset nearest
them (a padding slot, else the slot of a context-only member, never an external agent's), only that window
is encoded and primed anew, and the others keep theirs until they were due to be rebuilt."""

from __future__ import annotations

import numpy as np
from helpers import straight_road_scene, tiny

from trajeglish_env.sampler.config import SamplingConfig
from trajeglish_env.sampler.engine import BatchEngine, RowSpec
from trajeglish_env.sampler.subsets import admit, plan_subsets
from trajeglish_env.scenario import Scenario


def test_an_agent_takes_a_padding_slot_and_acts_last_in_its_subset() -> None:
    positions = np.array([[0.0, 0], [5, 0], [10, 0], [30, 0]])
    active = np.array([True, True, True, False])
    plan = plan_subsets(positions, active, 5, 0)
    assert plan.slots.tolist() == [[-1, -1, 0, 1, 2]]
    far = positions.copy()
    far[3] = [200.0, 0.0]  # beyond ADMIT_REACH of every centre: its windows are to be planned anew
    assert admit(plan, 3, far, np.zeros(4, bool)) is None
    got = admit(plan, 3, positions, np.zeros(4, bool))
    assert got is not None
    new, rank = got
    assert rank == 0 and new.slots.tolist() == [[-1, 0, 1, 2, 3]]
    assert new.acting_order.tolist() == [0, 1, 2, 3]


def test_a_full_subset_gives_up_its_farthest_context_member_never_an_external() -> None:
    positions = np.stack([np.arange(8) * 10.0, np.zeros(8)], axis=1)
    active = np.ones(8, bool)
    active[7] = False  # enters later, beside agent 6
    plan = plan_subsets(positions, active, 4, 0)
    assert plan.slots.tolist() == [[0, 1, 2, 3], [2, 3, 4, 5], [3, 4, 5, 6]]
    assert plan.centres.tolist() == [0, 4, 6]
    protect = np.zeros(8, bool)
    new, rank = admit(plan, 7, positions, protect)  # type: ignore[misc]
    # the subset around agent 6 is nearest; agents 3-5 act earlier and are context there, 3 the farthest
    assert rank == 2 and new.slots[2].tolist() == [4, 5, 6, 7]
    assert np.array_equal(new.slots[:2], plan.slots[:2]) and new.acting_order.tolist() == list(range(8))
    protect[3] = True  # an external agent stays in every context it is in
    new, _ = admit(plan, 7, positions, protect)  # type: ignore[misc]
    assert new.slots[2].tolist() == [3, 5, 6, 7]
    alone = np.arange(5) < 4  # one subset of agents 0-3, all acting in it: no room for agent 4
    full = plan_subsets(positions[:5], alone, 4, 0)
    assert full.slots.tolist() == [[0, 1, 2, 3]] and admit(full, 4, positions[:5], np.zeros(5, bool)) is None


def entering_scene() -> Scenario:
    """Ten cars on a two-lane road; the log brings cars 8 and 9 in 4 and 3 steps after the current step."""
    sc = straight_road_scene(10, 40)
    valid = np.ones_like(sc.valid)
    valid[8, : sc.current_index + 4] = False
    valid[9, : sc.current_index + 3] = False
    return Scenario.from_arrays(sc.xyh, valid, sc.size, sc.kind, sdc=sc.sdc, current_index=sc.current_index)


Trace = list[tuple[int, np.ndarray, np.ndarray]]


def run(sc: Scenario, steps: int, seed: int = 3) -> tuple[BatchEngine, Trace]:
    """The tiny model drives every agent of ``sc`` (the late ones from their entry) for ``steps`` steps;
    per step, the step and the window starts before and after it."""
    engine = BatchEngine(tiny(), 1, SamplingConfig(seed=0, compute_dtype="float32"))
    controlled = sc.valid[:, sc.current_index].copy()
    engine.start_rows([0], RowSpec(sc, steps, controlled, entering=True), [seed])
    trace = []
    for _ in range(steps):
        now, before = int(engine.now[0]), np.array([w.start[0] for w in engine.windows])
        engine.step()
        trace.append((now, before, np.array([w.start[0] for w in engine.windows])))
    return engine, trace


def test_entering_agents_rebuild_only_the_window_they_join() -> None:
    sc = entering_scene()
    engine, trace = run(sc, 9)
    cur = sc.current_index
    plan = engine.plan[0]
    assert plan is not None and {8, 9} <= set(plan.acting_order.tolist())
    # the tiny model's windows are planned every 6 steps (at cur, cur + 6); cars 9 and 8 enter at cur + 3
    # and cur + 4, inside the first cycle: each restarts one window, the others keep theirs
    for now, before, after in trace[1:]:
        if now == cur + 6:
            continue  # planned anew
        restarted = np.flatnonzero(after[: len(before)] != before)
        assert len(restarted) == (1 if now in (cur + 3, cur + 4) else 0), now
        assert all(after[k] == now - 2 for k in restarted)  # primed with the 2 steps before
    assert engine.valid[0, 8, cur + 4 :].all() and engine.valid[0, 9, cur + 3 :].all()
    assert engine.row_controlled[0, [8, 9]].all() and (engine.tokens[0, 8, cur + 4 : cur + 9] >= 0).all()
    again, _ = run(sc, 9)
    assert np.array_equal(engine.tokens, again.tokens)  # same seed, same rollout


def test_an_agent_entering_far_from_every_window_has_the_row_planned_anew() -> None:
    sc = entering_scene()
    xyh = sc.xyh.copy()
    xyh[9, :, 1] += 300.0  # car 9 enters 300 m beside the road: no window's centre is within reach
    far = Scenario.from_arrays(xyh, sc.valid, sc.size, sc.kind, sdc=sc.sdc, current_index=sc.current_index)
    engine, trace = run(far, 5)
    cur = sc.current_index
    now, before, after = trace[3]
    assert now == cur + 3 and (after[: len(before)] == now - 2).all()  # every window restarted
    assert int(engine.window_step[0]) == cur + 3 and engine.row_controlled[0, 9]
