"""The scorecard's rows: each figure of :mod:`trajeglish_env.scorecard`'s parts against the NPC-quality
issue's target (the env's default NPC settings: temperature 0.75, guarded sampling), and the Markdown
report."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from trajeglish_env.evaluation import method_name
from trajeglish_env.sampler.config import DEFAULT_TEMPERATURE

PARTIAL_MIN_SCENES = 32  # the partial-control row asks for at least this many scenes
GUARDED = method_name("model", DEFAULT_TEMPERATURE, True)
ALONE = method_name("model", DEFAULT_TEMPERATURE, False)
STANDING = "vehicle_standing"  # share of vehicle steps under 0.5 m/s (a timid model stands more than the log)
CONTEXT = "(context: the env's NPCs are guarded)"
SPEED_FLOOR = 0.95  # interleaved pairs of env runs on a 2-core machine differ by a few % between runs


def _row(row: str, value: str, target: str, met: bool | None) -> dict[str, Any]:
    return {"row": row, "value": value, "target": target, "met": met}


class _Seeds:
    """One figure over a part's rollout seeds (the part, then ``more_seeds``' ``NAME@seedS``): its mean
    judges the row, and with two seeds or more the value shows the range as well."""

    def __init__(self, runs: list[dict[str, Any]]):
        self.runs = runs

    def mean(self, pick: Callable[[dict[str, Any]], float]) -> float:
        return sum(pick(r) for r in self.runs) / len(self.runs)

    def text(self, pick: Callable[[dict[str, Any]], float], digits: int) -> str:
        values = [pick(r) for r in self.runs]
        mean = f"{sum(values) / len(values):.{digits}f}"
        if len(values) == 1:
            return mean
        return f"{mean} ({min(values):.{digits}f}-{max(values):.{digits}f} over {len(values)} seeds)"


def _seeded(parts: dict[str, dict[str, Any]], name: str) -> _Seeds:
    """Part ``name`` at the scorecard's seed and at each further seed, in the order they were computed."""
    return _Seeds([parts[name]] + [p for key, p in parts.items() if key.startswith(f"{name}@seed")])


def _source_rows(title: str, seeds: _Seeds, red_light: bool) -> list[dict[str, Any]]:
    """Guarded realism, collisions, off-road (and red lights) against the log; the model alone against
    constant velocity (the log's and constant velocity's figures do not depend on the seed)."""
    m = seeds.runs[0]["methods"]
    log = m["log"]

    def score(method: str, key: str) -> Callable[[dict[str, Any]], float]:
        return lambda run: float(run["methods"][method][key])

    meta, coll, off = (score(GUARDED, k) for k in ("metametric", "collision_rate", "offroad_rate"))
    rows = [
        _row(f"{title} guarded: meta-metric", seeds.text(meta, 4), ">= 0.80", seeds.mean(meta) >= 0.80),
        _row(
            f"{title} guarded: collision rate (every evaluated agent)",
            seeds.text(coll, 3),
            "<= 0.02",
            seeds.mean(coll) <= 0.02,
        ),
        _row(
            f"{title} guarded: off-road rate",
            seeds.text(off, 3),
            f"<= {log['offroad_rate'] + 0.02:.3f} (log + 0.02)",
            seeds.mean(off) <= log["offroad_rate"] + 0.02,
        ),
    ]
    if red_light:
        red, limit = (
            score(GUARDED, "traffic_light_violation_rate"),
            log["traffic_light_violation_rate"] + 0.01,
        )
        rows.append(
            _row(
                f"{title} guarded: red-light violations",
                seeds.text(red, 4),
                f"<= {limit:.4f} (log + 0.01)",
                seeds.mean(red) <= limit,
            )
        )
    if all(run["methods"][GUARDED].get(STANDING) is not None for run in seeds.runs):
        rows.append(
            _row(
                f"{title} guarded: vehicles standing (share of steps under 0.5 m/s)",
                seeds.text(score(GUARDED, STANDING), 3),
                f"(context: the log's {log[STANDING]:.3f}; more is timid traffic)",
                None,
            )
        )
    if ALONE in m:
        cv = m["constant_velocity"]
        meta, coll = score(ALONE, "metametric"), score(ALONE, "collision_rate")
        rows += [
            _row(
                f"{title} model alone: meta-metric",
                seeds.text(meta, 4),
                f">= {cv['metametric'] + 0.08:.4f} (constant velocity + 0.08)",
                seeds.mean(meta) >= cv["metametric"] + 0.08,
            ),
            _row(
                f"{title} model alone: collision rate (every evaluated agent)",
                seeds.text(coll, 3),
                f"<= {cv['collision_rate'] / 2:.3f} (half of constant velocity's)",
                seeds.mean(coll) <= cv["collision_rate"] / 2,
            ),
        ]
    return rows


def _partial_row(title: str, seeds: _Seeds) -> dict[str, Any]:
    scenes = seeds.runs[0]["scenes"]

    def rate(placement: str) -> Callable[[dict[str, Any]], float]:
        return lambda run: float(run["partial_control"][placement]["collision_rate"])

    first, last = rate("first"), rate("last")
    enough = scenes >= PARTIAL_MIN_SCENES
    target = "last < first" + ("" if enough else f" (needs >= {PARTIAL_MIN_SCENES} scenes)")
    return _row(
        f"{title} partial control ({scenes} scenes): collisions acting first / last",
        f"{seeds.text(first, 3)} / {seeds.text(last, 3)}",
        target,
        seeds.mean(last) < seeds.mean(first) if enough else None,
    )


def _skipped(name: str, part: dict[str, Any]) -> dict[str, Any]:
    return _row(f"{name}: skipped", part["skipped"], "", None)


def target_rows(parts: dict[str, dict[str, Any]]) -> list[dict[str, Any]]:
    """Every row the computed ``parts`` of one checkpoint give, in the issue's order; ``met`` is None for
    rows without a target (shown for context) or whose part is too small to judge."""
    rows: list[dict[str, Any]] = []
    if "highway" in parts:
        rows += _source_rows("highway-env", _seeded(parts, "highway"), red_light=False)
        rows.append(_partial_row("highway-env", _seeded(parts, "highway")))
    if "sumo" in parts:
        rows += _source_rows("SUMO", _seeded(parts, "sumo"), red_light=True)
    if "sumo_partial" in parts:
        rows.append(_partial_row("SUMO", _Seeds([parts["sumo_partial"]])))
    if "brake" in parts:
        npcs = parts["brake"]["npcs"]
        idm = npcs["idm"]["rear_end_rate"]
        for name, title in (("trajeglish+guard", "guarded"), ("trajeglish", "model alone")):
            r = npcs[name]
            rows.append(
                _row(
                    f"brake test: rear-ended, {title} NPCs",
                    f"{r['rear_ends']}/{r['episodes']}",
                    f"<= {idm + 0.05:.3f} (IDM {npcs['idm']['rear_ends']}/{npcs['idm']['episodes']} + 0.05)"
                    if name == "trajeglish+guard"
                    else CONTEXT,
                    r["rear_end_rate"] <= idm + 0.05 if name == "trajeglish+guard" else None,
                )
            )
        guarded = npcs["trajeglish+guard"]
        if "harsh_braking_rate" in guarded:  # parts of stop 82 on: how the followers stop, not only whether
            rows.append(
                _row(
                    "brake test: guarded followers braking harder than 10 m/s^2 (median peak braking)",
                    f"{guarded['harsh_braking_rate']:.3f} ({guarded['median_peak_braking_mps2']:.1f} m/s^2; "
                    f"IDM {npcs['idm']['median_peak_braking_mps2']:.1f})",
                    CONTEXT,
                    None,
                )
            )
        if "harsh_braking_05s_rate" in guarded:  # parts of stop 83 on: over 0.5 s, past the tokens' levels
            rows.append(
                _row(
                    "brake test: guarded followers braking harder than 10 m/s^2 over 0.5 s (median peak)",
                    f"{guarded['harsh_braking_05s_rate']:.3f} ({guarded['median_peak_braking_05s_mps2']:.1f} "
                    f"m/s^2; IDM {npcs['idm']['median_peak_braking_05s_mps2']:.1f})",
                    CONTEXT,
                    None,
                )
            )
    if "long" in parts:
        long = parts["long"]
        for event in ("collision", "offroad"):
            e = long[event]
            rows.append(
                _row(
                    f"{long['seconds']:g} s rollouts, guarded: {event} onsets per agent-second, after / "
                    f"before {long['split_s']:g} s",
                    f"{e['after']:.4f} / {e['before']:.4f}",
                    "after <= 1.5x before",
                    e["after"] <= 1.5 * e["before"],
                )
            )
    if "womd" in parts:
        w = parts["womd"]
        if "skipped" in w:
            rows.append(_skipped("WOMD scene", w))
        else:
            m, log = w["methods"], w["methods"]["log"]["collision_rate"]
            for name, title in ((GUARDED, "guarded"), (ALONE, "model alone")):
                rate = m[name]["collision_rate"]
                rows.append(
                    _row(
                        f"WOMD scene ({w['rollouts']} rollouts), {title}: collision rate "
                        "(every evaluated agent)",
                        f"{rate:.3f}",
                        f"<= {log + 0.05:.3f} (log + 0.05)" if name == GUARDED else CONTEXT,
                        rate <= log + 0.05 if name == GUARDED else None,
                    )
                )
    if "demo" in parts:
        d = parts["demo"]
        rows.append(
            _row(
                f"demo episode ({d['scene']}): NPCs that collide",
                f"{d['npc_collision_rate']:.3f}",
                "0",
                d["npc_collision_rate"] == 0.0,
            )
        )
    if "tokenize" in parts:
        t = parts["tokenize"]
        cells = ", ".join(f"{k} {v:.2f}" for k, v in t["max_cm"].items())
        rows.append(
            _row(
                "tokenization at the motion limits: largest error, cm (vehicles judged)",
                f"{t['vocab_size']} tokens: {cells}",
                "vehicles <= 5 cm",
                t["max_cm"]["vehicle"] <= 5.0,
            )
        )
    if "speed" in parts and "skipped" in parts["speed"]:
        rows.append(_skipped("env speed against the shipped model", parts["speed"]))
    elif "speed" in parts and not parts["speed"].get("reference"):
        speed = {k: v for k, v in parts["speed"].items() if k != "compute_seconds"}
        batches = " / ".join(f"B = {b}" for b in speed)
        ratios = " / ".join(f"{v['ratio']:.2f}x" for v in speed.values())
        steps = " / ".join(f"{v['model']:,.0f}" for v in speed.values())
        rows.append(
            _row(
                f"env speed against the shipped model (issue 16), guarded, one thread, {batches}",
                f"{ratios} ({steps} agent-steps/s)",
                f">= {SPEED_FLOOR:.2f}x (nothing slower, within the machine's noise)",
                all(v["ratio"] >= SPEED_FLOOR for v in speed.values()),
            )
        )
    return rows


def _cell(row: dict[str, Any]) -> str:
    mark = {True: " (met)", False: " (**not met**)", None: ""}[row["met"]]
    return f"{row['value']}{mark}"


def markdown(result: dict[str, Any]) -> str:
    """The scorecard as Markdown: one column per checkpoint, each row against its target."""
    labels = list(result["rows"])
    seconds = {
        label: sum(p.get("compute_seconds", 0.0) for p in result["parts"][label].values()) for label in labels
    }
    lines = [
        "# Scorecard: the NPC-quality targets",
        "",
        "Checkpoints: " + ", ".join(f"`{label}` ({result['checkpoints'][label]})" for label in labels),
        "",
        "Held-out scenes: " + "; ".join(f"`{cmd}`" for cmd in result["scene_sets"].values()),
        "",
        "Targets met: "
        + ", ".join(
            f"`{label}` {result['met'][label]} of {result['rows_with_a_target'][label]}" for label in labels
        ),
        "",
        "Seconds the parts took when they were computed: "
        + ", ".join(f"`{label}` {seconds[label]:.0f}" for label in labels),
        "",
        "| row | target | " + " | ".join(f"`{label}`" for label in labels) + " |",
        "|---|---|" + "---|" * len(labels),
    ]
    order: list[str] = []
    cells: dict[str, dict[str, dict[str, Any]]] = {}
    for label in labels:
        for row in result["rows"][label]:
            if row["row"] not in cells:
                order.append(row["row"])
                cells[row["row"]] = {}
            cells[row["row"]][label] = row
    for name in order:
        by_label = cells[name]
        target = next(iter(by_label.values()))["target"]
        values = " | ".join(_cell(by_label[label]) if label in by_label else "" for label in labels)
        lines.append(f"| {name} | {target} | {values} |")
    return "\n".join(lines) + "\n"
