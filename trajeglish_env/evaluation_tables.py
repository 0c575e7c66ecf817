"""The realism evaluation's Markdown report (``evaluation.md``): the table of methods, red lights run, the
scene kinds' table, who collides with whom, vehicles standing still and partial control, from
:func:`trajeglish_env.evaluation.evaluate`'s JSON document."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from trajeglish_env.scenario import AgentKind
from trajeglish_env.standing import STANDING_SPEED

# the headline figures of every method (its row of the first table)
HEADLINE = (
    "metametric",
    "kinematic",
    "interactive",
    "map_based",
    "min_ade",
    "collision_rate",
    "offroad_rate",
)


def _submission_rollouts(result: dict[str, Any]) -> str:
    """`` (the submission row: its file's N)`` where a submission's rollout count per scene differs."""
    sub = result["methods"].get("submission")
    if sub is None:
        return ""
    per_scene = sub["scores"]["num_rollouts"] / max(result["scenes"], 1)  # the mean sums them over scenes
    return "" if per_scene == result["rollouts"] else f" (the submission row: its file's {per_scene:g})"


def markdown_table(result: dict[str, Any]) -> str:
    """The evaluation as a Markdown table (one row per method)."""
    cols = HEADLINE
    lines = [
        f"Held-out scenes: {result['scenes']}, rollouts per scene: {result['rollouts']}"
        + _submission_rollouts(result)
        + f", metrics: WOSAC {result['metrics_config']}",
        "",
        "| method | " + " | ".join(cols) + " |",
        "|---|" + "---|" * len(cols),
    ]
    for name, r in result["methods"].items():
        lines.append(f"| {name} | " + " | ".join(f"{r['scores'][c]:.4f}" for c in cols) + " |")
    lines += [
        "",
        "min_ade in metres; collision_rate and offroad_rate: WOSAC's, the share of each scene's evaluated "
        "agents (the sdc and its tracks to predict; every simulated agent where none are named) that collide "
        "or leave the road in a rollout, averaged over rollouts, then over scenes.",
    ]
    red = {name: r["red_light_runs_by_kind"] for name, r in result["methods"].items()}
    if any(c["agent_rollouts"] for r in red.values() for c in r.values()):
        kinds = [k.name.lower() for k in AgentKind]
        lines += [
            "",
            "Red lights run (share of simulated agent-rollouts crossing a red stop fence on their lane):",
            "",
            "| method | " + " | ".join(kinds) + " |",
            "|---|" + "---|" * len(kinds),
        ]
        for name, r in red.items():
            cells = [f"{r[k]['rate']:.4f} ({r[k]['runs']}/{r[k]['agent_rollouts']})" for k in kinds]
            lines.append(f"| {name} | " + " | ".join(cells) + " |")
    lines += _kind_table(result["methods"])
    lines += _collision_table(result["methods"])
    lines += _standing_table(result["methods"])
    if "partial_control" in result:
        pc = result["partial_control"]
        lines += [
            "",
            f"Partial control ({pc['model']} drives the sdc with the env's default sampling, guard included; "
            "others replay the log; the collision rate is the share of rollouts in which the sdc collides):",
            "",
            "| sdc placed | ADE (m) | collision rate | sdc moved into another | another moved into the sdc |",
            "|---|---|---|---|---|",
        ]
        for place in ("first", "last"):
            r = pc[place]
            lines.append(
                f"| {place} | {r['ade']:.3f} | {r['collision_rate']:.4f} | {r['at_fault_rate']:.4f} | "
                f"{r['struck_rate']:.4f} |"
            )
    return "\n".join(lines) + "\n"


def _kind_table(methods: dict[str, Any]) -> list[str]:
    """Markdown lines of the per-scene-kind table (meta-metric / collision / off-road of each method),
    when the scenes hold more than one kind: where a model fails hides in the means (roundabouts)."""
    kinds = sorted({k for r in methods.values() for k in r.get("scores_by_kind", {})})
    if len(kinds) < 2:
        return []

    def cell(name: str, kind: str) -> str:
        k = methods[name].get("scores_by_kind", {}).get(kind)
        return (
            ""
            if k is None
            else f"{k['metametric']:.3f} / {k['collision_rate']:.3f} / {k['offroad_rate']:.3f}"
        )

    def label(kind: str) -> str:
        count = next(
            m["scores_by_kind"][kind]["scenes"]
            for m in methods.values()
            if kind in m.get("scores_by_kind", {})
        )
        return f"{kind} ({count})"

    title = "By scene kind (meta-metric / collision rate / off-road rate; scenes of the kind in brackets):"
    return _by_kind(title, list(methods), kinds, cell, label)


def _standing_table(methods: dict[str, Any]) -> list[str]:
    """Markdown lines of the share of vehicle steps standing still (``standing_by_kind``), per scene kind
    (rows) and method (columns); none when no method drives a vehicle."""
    names = [
        n for n, r in methods.items() if any("vehicle" in c for c in r.get("standing_by_kind", {}).values())
    ]
    if not names:
        return []
    kinds = sorted({k for n in names for k in methods[n]["standing_by_kind"]})

    def cell(name: str, kind: str) -> str:
        c = methods[name]["standing_by_kind"].get(kind, {}).get("vehicle")
        return "" if c is None else f"{c['share']:.3f}"

    title = (
        f"Vehicles standing still (share of simulated vehicle steps under {STANDING_SPEED:g} m/s, by scene "
        "kind):"
    )
    return _by_kind(title, names, kinds, cell, str)


def _by_kind(
    title: str,
    names: list[str],
    kinds: list[str],
    cell: Callable[[str, str], str],
    label: Callable[[str], str],
) -> list[str]:
    """Markdown lines of a table with a row per scene kind (``label(kind)``) and a column per method
    (``cell(name, kind)``) under ``title``."""
    lines = ["", title, "", "| kind | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
    for kind in kinds:
        lines.append(f"| {label(kind)} | " + " | ".join(cell(name, kind) for name in names) + " |")
    return lines


def _collision_table(methods: dict[str, Any]) -> list[str]:
    """Markdown lines of the first collisions by class (``collisions_by_class``): for each method and
    class that collides, the partners' classes and the contact's geometry."""
    rows = [
        (name, cls, c)
        for name, r in methods.items()
        for cls, c in r.get("collisions_by_class", {}).items()
        if c["collided"]
    ]
    if not rows:
        return []
    clean = [
        name
        for name, r in methods.items()
        if not any(c["collided"] for c in r.get("collisions_by_class", {}).values())
    ]
    lines = [
        "",
        "Who collides with whom (every simulated agent-rollout, pooled over scenes, not only the evaluated "
        "agents of the headline table; each one's first collision, by its class; partner classes vehicle / "
        "pedestrian / cyclist" + (f"; no collision at all: {', '.join(clean)}" if clean else "") + "):",
        "",
        "| method | class | collided | partners | into the one ahead (standing) | from behind | crossing | "
        "head-on | overlapping at the start |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for name, cls, c in rows:
        g = c["geometry"]
        partners = " / ".join(str(v) for v in c["partner"].values())
        lines.append(
            f"| {name} | {cls} | {c['collided']} of {c['agent_rollouts']} ({c['rate']:.3f}) | {partners} | "
            f"{g['into_agent_ahead']} ({c['into_stopped_agent_ahead']}) | {g['from_behind']} | "
            f"{g['crossing']} | {g['head_on']} | {c['already_overlapping']} |"
        )
    return lines
