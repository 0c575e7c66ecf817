"""Agent subsets for scenes larger than the model's context (paper appendix "Extended rollouts").

Every active agent defines a candidate subset: itself and its nearest neighbours, ``size`` agents in all.
The sdc's subset is chosen first; then, among agents not yet covered, the one whose subset holds the most
already-covered agents is the next centre, until every active agent is in some subset. Rule
``"overlap"`` (the paper's) takes the centre's nearest neighbours as its subset: most context from earlier
subsets, but a subset may add only a few new agents. Rule ``"cover"`` fills a subset with the centre's
nearest *uncovered* agents within ``reach`` metres first and completes it with the nearest covered ones:
fewest subsets, so fewest model positions per step (the same plan whenever one subset holds everyone).
Inside a subset the order is: padding first, then the agents that already acted in an earlier subset
(in acting order), then the rest by (priority, distance to the centre agent) -- so the sdc, as centre of
the first subset, acts first at every timestep.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

SUBSET_RULES = ("overlap", "cover")
# An agent joins an existing subset only when its centre is this near (m): training windows hold the agents
# within 60 m of their frame agent (the paper's appendix; the training windows' ``agent_radius``).
ADMIT_REACH = 60.0


@dataclass(frozen=True)
class SubsetPlan:
    """Subsets of one scene: ``slots [K, size]`` agent indices in acting order (-1 = padding, first),
    ``centres [K]`` centre agents, ``acting_order [n]`` every covered agent in the order it acts."""

    slots: np.ndarray
    centres: np.ndarray
    acting_order: np.ndarray

    @property
    def num_subsets(self) -> int:
        return int(self.slots.shape[0])


def candidate_subsets(positions: np.ndarray, active: np.ndarray, size: int) -> np.ndarray:
    """``[N, m]`` nearest active agents of every agent (itself first), ``m = min(size, #active)``."""
    idx = np.flatnonzero(active)
    d = np.linalg.norm(positions[:, None, :] - positions[None, idx, :], axis=-1)  # [N, n]
    m = min(size, len(idx))
    near = np.argsort(d, axis=1, kind="stable")[:, :m]
    return idx[near]


def plan_subsets(
    positions: np.ndarray,
    active: np.ndarray,
    size: int,
    first: int,
    priority: np.ndarray | None = None,
    rule: str = "overlap",
    reach: float = 60.0,
) -> SubsetPlan:
    """Cover every active agent with subsets of ``size`` agents; see the module docstring for the rules.

    ``positions [N,2]``, ``active [N]`` bool, ``first`` the agent whose subset goes first (the sdc; if it
    is inactive, the lowest-priority active agent), ``priority [N]`` lower acts earlier (default 0),
    ``rule``: ``"overlap"`` or ``"cover"``, ``reach``: metres (see the module docstring).
    """
    if rule not in SUBSET_RULES:
        raise ValueError(f"subset rule must be one of {SUBSET_RULES}, got {rule!r}")
    n_agents = positions.shape[0]
    active = np.asarray(active, dtype=bool)
    if size < 1:
        raise ValueError(f"subset size must be >= 1, got {size}")
    prio = np.zeros(n_agents) if priority is None else np.asarray(priority, dtype=np.float64)
    if not active.any():
        return SubsetPlan(np.zeros((0, size), np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64))
    cands = candidate_subsets(positions, active, size)
    if not active[first]:
        act = np.flatnonzero(active)
        first = int(act[np.argmin(prio[act])])
    covered = np.zeros(n_agents, dtype=bool)
    acted_rank = np.full(n_agents, -1, dtype=np.int64)
    order: list[int] = []
    slots, centres = [], []
    centre = first
    act_idx = np.flatnonzero(active)
    while True:
        members = cands[centre]
        if rule == "cover" and slots:
            d = np.linalg.norm(positions[act_idx] - positions[centre], axis=-1)
            near = np.argsort(d, kind="stable")
            new = act_idx[near[~covered[act_idx[near]] & (d[near] <= reach)]][:size]
            old = act_idx[near[covered[act_idx[near]]]][: size - len(new)]
            members = np.concatenate([new, old])
        acted = members[acted_rank[members] >= 0]
        acted = acted[np.argsort(acted_rank[acted], kind="stable")]
        fresh = members[acted_rank[members] < 0]
        dist = np.linalg.norm(positions[fresh] - positions[centre], axis=-1)
        fresh = fresh[np.lexsort((dist, prio[fresh]))]
        acted_rank[fresh] = len(order) + np.arange(len(fresh))
        order.extend(fresh.tolist())
        row = np.full(size, -1, dtype=np.int64)
        body = np.concatenate([acted, fresh])
        row[size - len(body) :] = body
        slots.append(row)
        centres.append(centre)
        covered[members] = True
        todo = np.flatnonzero(active & ~covered)
        if len(todo) == 0:
            break
        overlap = covered[cands[todo]].sum(axis=1)
        if rule == "cover":  # most new agents first, then most overlap (m - overlap = new agents)
            overlap = (cands.shape[1] - overlap) * (cands.shape[1] + 1) + overlap
        centre = int(todo[np.argmax(overlap)])  # ties: the lowest index
    return SubsetPlan(np.stack(slots), np.array(centres, dtype=np.int64), np.array(order, dtype=np.int64))


def admit(
    plan: SubsetPlan, agent: int, positions: np.ndarray, protect: np.ndarray, reach: float = ADMIT_REACH
) -> tuple[SubsetPlan, int] | None:
    """``plan`` with ``agent`` (active now, in no subset: one the log brings in) acting last in the subset
    whose centre is nearest it (within ``reach`` m) that has room for it: a padding slot, else the slot of
    the member farthest from it among those that act in an earlier subset (context there) and that
    ``protect [N]`` does not keep (external agents). Returns the plan and the rank of the subset it changed,
    or None when no subset has room (plan anew then). The other subsets and everyone's acting order stay as
    they were."""
    k_all = plan.num_subsets
    seen = np.zeros(len(positions), dtype=bool)
    earlier = []  # per rank: which slots hold an agent of an earlier subset
    for k in range(k_all):
        row = plan.slots[k]
        earlier.append((row >= 0) & seen[np.maximum(row, 0)])
        seen[row[row >= 0]] = True
    here = positions[agent]
    away_k = np.hypot(*(positions[plan.centres] - here).T)
    for k in np.argsort(away_k, kind="stable").tolist():
        if away_k[k] > reach:
            break
        row = plan.slots[k]
        if (row < 0).any():
            drop = int(np.flatnonzero(row < 0)[0])
        else:
            context = earlier[k] & ~protect[row]
            if not context.any():
                continue
            away = np.hypot(*(positions[row] - here).T)
            drop = int(np.argmax(np.where(context, away, -np.inf)))
        slots = plan.slots.copy()
        slots[k] = np.append(np.delete(row, drop), agent)  # padding, acted, fresh: it acts last here
        after = int(np.flatnonzero(plan.acting_order == row[-1])[0]) + 1  # the subset's last to act so far
        order = np.insert(plan.acting_order, after, agent)
        return SubsetPlan(slots, plan.centres, order), k
    return None
