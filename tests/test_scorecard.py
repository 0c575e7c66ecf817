"""`trajeglish scorecard`: every figure against its target, parts saved as they finish and reused only for
the same checkpoint file and settings, and a real run on generated scenes."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from helpers import tiny, tiny_checkpoint

import trajeglish_env.scorecard as scorecard
from trajeglish_env.checkpoint import load_checkpoint, save_checkpoint
from trajeglish_env.scorecard import SceneSet, ScorecardConfig, run_scorecard
from trajeglish_env.scorecard_rows import ALONE, GUARDED, markdown, target_rows

TOKENS = "tokenization at the motion limits: largest error, cm (vehicles judged)"


def _scores(meta: float, collision: float, offroad: float, red: float = 0.0) -> dict[str, float]:
    return {
        "metametric": meta,
        "collision_rate": collision,
        "offroad_rate": offroad,
        "traffic_light_violation_rate": red,
        "min_ade": 1.0,
    }


def _source(scenes: int, guarded: dict, alone: dict, first: float, last: float) -> dict:
    return {
        "scenes": scenes,
        "rollouts": 8,
        "methods": {
            "log": _scores(0.88, 0.0, 0.10, red=0.014),
            "constant_velocity": _scores(0.57, 0.112, 0.27),
            ALONE: alone,
            GUARDED: guarded,
        },
        "partial_control": {"first": {"collision_rate": first}, "last": {"collision_rate": last}},
    }


def _rows_by_name(rows: list[dict]) -> dict[str, dict]:
    return {r["row"]: r for r in rows}


def test_every_figure_is_judged_against_its_target() -> None:
    parts = {
        "highway": _source(32, _scores(0.8033, 0.0, 0.11), _scores(0.6278, 0.151, 0.31), 0.141, 0.125),
        "sumo": _source(16, _scores(0.79, 0.03, 0.125, red=0.025), _scores(0.66, 0.05, 0.3), 0.3, 0.2),
        "sumo_partial": _source(16, _scores(0.8, 0.0, 0.1), _scores(0.6, 0.1, 0.3), 0.3, 0.2),
        "brake": {
            "npcs": {
                "trajeglish+guard": {"rear_ends": 2, "episodes": 40, "rear_end_rate": 0.05},
                "trajeglish": {"rear_ends": 37, "episodes": 40, "rear_end_rate": 0.925},
                "idm": {"rear_ends": 0, "episodes": 40, "rear_end_rate": 0.0},
            }
        },
        "long": {
            "seconds": 30.0,
            "split_s": 8.0,
            "collision": {"before": 0.0, "after": 0.0, "ratio": None},
            "offroad": {"before": 0.001, "after": 0.002, "ratio": 2.0},
        },
        "womd": {
            "rollouts": 16,
            "methods": {
                "log": {"collision_rate": 0.5},
                GUARDED: {"collision_rate": 0.56},
                ALONE: {"collision_rate": 0.4},
            },
        },
        "demo": {"scene": "highway-intersection-999000", "npc_collision_rate": 0.0},
        "tokenize": {"vocab_size": 2048, "max_cm": {"vehicle": 4.72, "pedestrian": 5.09, "cyclist": 2.68}},
        "speed": {
            "1": {"model": 1100.0, "shipped": 1130.0, "ratio": 0.973},
            "8": {"model": 2500.0, "shipped": 3000.0, "ratio": 0.833},
            "compute_seconds": 100.0,
        },
    }  # fmt: skip
    rows = _rows_by_name(target_rows(parts))
    met = {name: r["met"] for name, r in rows.items()}
    assert met["highway-env guarded: meta-metric"] is True
    assert rows["highway-env guarded: off-road rate"]["target"] == "<= 0.120 (log + 0.02)"
    assert met["highway-env guarded: off-road rate"] is True
    # alone: constant velocity 0.57 + 0.08 = 0.65 > 0.6278; half of its 0.112 collisions = 0.056 < 0.151
    assert met["highway-env model alone: meta-metric"] is False
    assert rows["highway-env model alone: collision rate (every evaluated agent)"]["target"].startswith(
        "<= 0.056"
    )
    assert met["highway-env partial control (32 scenes): collisions acting first / last"] is True
    assert "highway-env guarded: red-light violations" not in rows  # highway-env has no signals
    assert (
        met["SUMO guarded: meta-metric"] is False
        and met["SUMO guarded: collision rate (every evaluated agent)"] is False
    )
    assert met["SUMO guarded: red-light violations"] is False  # 0.025 > 0.014 + 0.01
    partial = rows["SUMO partial control (16 scenes): collisions acting first / last"]
    assert partial["met"] is None and "needs >= 32 scenes" in partial["target"]  # too few scenes to judge
    assert met["brake test: rear-ended, guarded NPCs"] is True  # 0.05 <= 0 + 0.05
    assert met["brake test: rear-ended, model alone NPCs"] is None  # context only
    assert met["30 s rollouts, guarded: collision onsets per agent-second, after / before 8 s"] is True
    assert met["30 s rollouts, guarded: offroad onsets per agent-second, after / before 8 s"] is False
    assert (
        met["WOMD scene (16 rollouts), guarded: collision rate (every evaluated agent)"] is False
    )  # 0.56 > 0.5 + 0.05
    assert met["demo episode (highway-intersection-999000): NPCs that collide"] is True
    assert met[TOKENS] is True
    speed = rows["env speed against the shipped model (issue 16), guarded, one thread, B = 1 / B = 8"]
    assert speed["value"] == "0.97x / 0.83x (1,100 / 2,500 agent-steps/s)" and speed["met"] is False
    result = {
        "checkpoints": {"a": "a.pt"},
        "scene_sets": {"highway": "trajeglish generate --source highway --scenes 32 --seed 2"},
        "parts": {"a": parts},
        "rows": {"a": list(rows.values())},
        "met": {"a": sum(1 for r in rows.values() if r["met"])},
        "rows_with_a_target": {"a": sum(1 for r in rows.values() if r["met"] is not None)},
    }
    text = markdown(result)
    assert "| SUMO guarded: meta-metric | >= 0.80 | 0.7900 (**not met**) |" in text
    assert "Targets met: `a` 10 of 19" in text


def test_a_run_scores_generated_scenes_and_resumes_from_its_saved_parts(tmp_path: Path, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    path = save_checkpoint(tmp_path / "tiny.pt", tiny_checkpoint().model, tiny_checkpoint().vocabulary)
    config = ScorecardConfig(highway=SceneSet("highway", 1, 2), rollouts=1, parts=("highway", "tokenize"))
    out, data = tmp_path / "card", tmp_path / "data"
    result = run_scorecard({"tiny": load_checkpoint(path)}, config, out, data, progress=False)
    figures = result["parts"]["tiny"]["highway"]["methods"]
    assert figures["log"]["collision_rate"] == 0.0 and figures["log"]["metametric"] > 0.8
    assert set(figures) >= {"constant_velocity", GUARDED, ALONE, "tokenized_log"}
    assert figures[GUARDED]["collision_rate"] == 0.0  # the guard keeps even an untrained model apart
    assert 0.0 <= figures["log"]["vehicle_standing"] < 0.5  # highway-env traffic moves
    rows = _rows_by_name(result["rows"]["tiny"])
    standing = rows["highway-env guarded: vehicles standing (share of steps under 0.5 m/s)"]
    assert standing["met"] is None and standing["value"] == f"{figures[GUARDED]['vehicle_standing']:.3f}"
    assert (
        standing["target"]
        == f"(context: the log's {figures['log']['vehicle_standing']:.3f}; more is timid traffic)"
    )
    assert rows["highway-env partial control (1 scenes): collisions acting first / last"]["met"] is None
    assert rows[TOKENS]["met"] is False
    assert json.loads((out / "scorecard.json").read_text())["rows"] == result["rows"]
    assert (
        "| highway-env guarded: collision rate (every evaluated agent) | <= 0.02 | 0.000 (met) |"
        in (out / "scorecard.md").read_text()
    )
    assert sorted(p.name for p in (data / "highway_1_seed2").iterdir()) == [
        "highway-00000.scn.npz",
        "manifest.json",
    ]

    calls: list[str] = []
    real = dict(scorecard.PART_FUNCTIONS)

    def counting(name: str):  # type: ignore[no-untyped-def]
        def part(card, label, ckpt):  # type: ignore[no-untyped-def]
            calls.append(name)
            return real[name](card, label, ckpt)

        return part

    monkeypatch.setattr(scorecard, "PART_FUNCTIONS", {n: counting(n) for n in real})
    again = run_scorecard({"tiny": load_checkpoint(path)}, config, out, data, progress=False)
    assert calls == [] and again["rows"] == result["rows"]  # every part read back
    saved = next((out / "parts").glob("*/highway.json"))
    saved.write_text(saved.read_text()[:100])  # a damaged file is computed again
    run_scorecard({"tiny": load_checkpoint(path)}, config, out, data, progress=False)
    assert calls == ["highway"]
    more = replace_rollouts(config, 2)  # other settings: computed again
    run_scorecard({"tiny": load_checkpoint(path)}, more, out, data, progress=False)
    assert calls == ["highway", "highway"]
    ckpt = tiny_checkpoint()
    with torch.no_grad():
        next(ckpt.model.parameters()).add_(0.01)
    save_checkpoint(path, ckpt.model, ckpt.vocabulary)  # another checkpoint file: every part again
    run_scorecard({"tiny": load_checkpoint(path)}, config, out, data, progress=False)
    assert calls == ["highway", "highway", "highway", "tokenize"]
    saved = out / "parts" / scorecard.file_sha256(path)[:16] / "highway.json"
    stale = json.loads(saved.read_text())  # the same part, as other code computed it: computed again
    stale["settings"]["code"] = "0" * 16
    stale["result"]["methods"]["log"]["metametric"] = 0.5
    saved.write_text(json.dumps(stale))
    again = run_scorecard({"tiny": load_checkpoint(path)}, config, out, data, progress=False)
    assert calls[-1] == "highway" and len(calls) == 5
    assert again["parts"]["tiny"]["highway"]["methods"]["log"]["metametric"] > 0.8


def test_vehicle_standing_pools_the_steps_of_every_scene_kind() -> None:
    by_kind = {
        "sumo/grid": {"vehicle": {"standing": 30, "steps": 100}, "pedestrian": {"standing": 5, "steps": 10}},
        "sumo/spider": {"vehicle": {"standing": 10, "steps": 100}},
        "sumo/random": {"cyclist": {"standing": 1, "steps": 2}},
    }
    assert scorecard.vehicle_standing(by_kind) == 40 / 200  # pooled, not the mean of 0.3 and 0.1 by kind
    assert scorecard.vehicle_standing({"sumo/random": {"cyclist": {"standing": 1, "steps": 2}}}) is None


def test_rows_over_several_seeds_judge_the_mean_and_show_the_range() -> None:
    # the model alone at three seeds: collisions 0.05 / 0.06 / 0.04 (mean 0.05 <= half of constant
    # velocity's 0.112) and meta 0.66 / 0.64 / 0.65 (mean 0.65 >= 0.57 + 0.08); one seed alone misses each
    def run(coll: float, meta: float, first: float, last: float) -> dict:
        return _source(32, _scores(0.81, 0.0, 0.1), _scores(meta, coll, 0.3), first, last)

    parts = {
        "highway": run(0.05, 0.66, 0.14, 0.05),
        "highway@seed1": run(0.06, 0.64, 0.10, 0.12),
        "highway@seed2": run(0.04, 0.65, 0.15, 0.07),
    }
    rows = _rows_by_name(target_rows(parts))
    alone = rows["highway-env model alone: collision rate (every evaluated agent)"]
    assert alone["value"] == "0.050 (0.040-0.060 over 3 seeds)" and alone["met"] is True
    meta = rows["highway-env model alone: meta-metric"]
    assert meta["value"] == "0.6500 (0.6400-0.6600 over 3 seeds)" and meta["met"] is True
    assert rows["highway-env guarded: meta-metric"]["value"] == "0.8100 (0.8100-0.8100 over 3 seeds)"
    partial = rows["highway-env partial control (32 scenes): collisions acting first / last"]
    # the means: first 0.130, last 0.080; seed 1 alone has last > first
    assert partial["value"] == "0.130 (0.100-0.150 over 3 seeds) / 0.080 (0.050-0.120 over 3 seeds)"
    assert partial["met"] is True
    # seed 1 alone: every model-alone row misses, partial control too
    one = _rows_by_name(target_rows({"highway": parts["highway@seed1"]}))
    assert one["highway-env model alone: collision rate (every evaluated agent)"] == {
        "row": "highway-env model alone: collision rate (every evaluated agent)",
        "value": "0.060",
        "target": "<= 0.056 (half of constant velocity's)",
        "met": False,
    }
    assert one["highway-env model alone: meta-metric"]["met"] is False
    assert one["highway-env partial control (32 scenes): collisions acting first / last"]["met"] is False
    with pytest.raises(ValueError, match="more_seeds must be ints >= 0 that differ .* from seed 0"):
        ScorecardConfig(more_seeds=(1, 0))
    with pytest.raises(ValueError, match="more_seeds"):
        ScorecardConfig(more_seeds=(2, 2))


def test_more_seeds_compute_the_source_parts_again_and_save_them_apart(tmp_path: Path) -> None:
    path = save_checkpoint(tmp_path / "tiny.pt", tiny_checkpoint().model, tiny_checkpoint().vocabulary)
    config = ScorecardConfig(
        highway=SceneSet("highway", 1, 2), rollouts=1, parts=("highway", "tokenize"), more_seeds=(7,)
    )
    out, data = tmp_path / "card", tmp_path / "data"
    result = run_scorecard({"tiny": load_checkpoint(path)}, config, out, data, progress=False)
    parts = result["parts"]["tiny"]
    assert set(parts) == {"highway", "highway@seed7", "tokenize"}  # tokenize does not depend on the seed
    seeds = [parts[k]["methods"][ALONE]["min_ade"] for k in ("highway", "highway@seed7")]
    assert seeds[0] != seeds[1]  # other rollouts of the same scenes
    assert parts["highway"]["methods"]["log"] == parts["highway@seed7"]["methods"]["log"]
    key = scorecard.file_sha256(path)[:16]
    saved = json.loads((out / "parts" / key / "highway@seed7.json").read_text())
    assert saved["settings"]["seed"] == 7 and (out / "parts" / key / "highway.json").is_file()
    assert (out / "evaluate" / f"highway_1_seed2_{key}@seed7").is_dir()
    row = _rows_by_name(result["rows"]["tiny"])["highway-env model alone: meta-metric"]
    metas = [parts[k]["methods"][ALONE]["metametric"] for k in ("highway", "highway@seed7")]
    assert row["value"].startswith(f"{sum(metas) / 2:.4f} (") and row["value"].endswith(" over 2 seeds)")
    assert json.loads((out / "scorecard.json").read_text())["config"]["more_seeds"] == [7]


def replace_rollouts(config: ScorecardConfig, rollouts: int) -> ScorecardConfig:
    from dataclasses import replace

    return replace(config, rollouts=rollouts)


def test_the_code_digest_follows_the_package_sources(tmp_path: Path) -> None:
    (tmp_path / "sampler").mkdir()
    (tmp_path / "sampler" / "guard.py").write_text("RULE = 1\n")
    (tmp_path / "notes.md").write_text("not code")
    before = scorecard.source_digest(tmp_path)
    (tmp_path / "notes.md").write_text("other text")
    assert scorecard.source_digest(tmp_path) == before  # only Python sources count
    (tmp_path / "sampler" / "guard.py").write_text("RULE = 2\n")
    changed = scorecard.source_digest(tmp_path)
    (tmp_path / "sampler" / "guard.py").rename(tmp_path / "guard.py")
    assert len({before, changed, scorecard.source_digest(tmp_path)}) == 3
    digest = scorecard.code_digest()
    assert scorecard.part_settings(ScorecardConfig(), "highway")["code"] == digest and len(digest) == 16


def test_speed_is_timed_in_interleaved_pairs_against_the_shipped_model(tmp_path: Path, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    import trajeglish_env.benchmark.measure as measure
    from trajeglish_env.checkpoint import pretrained_path

    candidate = load_checkpoint(save_checkpoint(tmp_path / "c.pt", tiny().model, tiny().vocabulary))
    order: list[tuple[str, int]] = []

    def fake_env_speed(batch, npc, torch_threads, checkpoint, min_seconds):  # type: ignore[no-untyped-def]
        assert min_seconds == 2.0  # every run long enough for a rate that holds (one window cycle is not)
        who = "shipped" if checkpoint.path == pretrained_path() else "model"
        order.append((who, batch))
        return {"agent_steps_per_s": (1000.0 if who == "shipped" else 900.0) * batch + len(order)}

    monkeypatch.setattr(measure, "env_speed", fake_env_speed)
    card = scorecard.Scorecard(
        ScorecardConfig(speed_batches=(1, 8), speed_repeats=2), tmp_path, tmp_path, False
    )
    result = scorecard.speed_part(card, "c", candidate)
    assert order == [("shipped", 1), ("model", 1), ("shipped", 8), ("model", 8)] + [
        ("model", 1),
        ("shipped", 1),
        ("model", 8),
        ("shipped", 8),
    ]  # the order alternates between the pairs
    assert result["1"]["runs"] == {"model": [902.0, 905.0], "shipped": [1001.0, 1006.0]}
    assert result["1"]["ratio"] == round(903.5 / 1003.5, 3) and result["8"]["ratio"] < 0.91
    shipped = load_checkpoint(pretrained_path())
    assert scorecard.speed_part(card, "shipped", shipped) == {"reference": True}  # nothing timed
    assert len(order) == 8


def test_bad_settings_are_named() -> None:
    with pytest.raises(ValueError, match="ScorecardConfig.parts"):
        ScorecardConfig(parts=("highway", "nope"))
    with pytest.raises(ValueError, match="ScorecardConfig.rollouts"):
        ScorecardConfig(rollouts=0)
    with pytest.raises(ValueError, match="ScorecardConfig.speed_batches"):
        ScorecardConfig(speed_batches=(1, 0))
    with pytest.raises(ValueError, match="ScorecardConfig.speed_min_seconds must be >= 0 s, got -1"):
        ScorecardConfig(speed_min_seconds=-1.0)
    with pytest.raises(ValueError, match="not loaded from a file"):
        run_scorecard({"memory": tiny_checkpoint()}, ScorecardConfig(parts=("tokenize",)))


def test_the_command_prints_the_table_and_writes_the_json(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    from trajeglish_env.cli import main

    path = save_checkpoint(tmp_path / "tiny.pt", tiny().model, tiny().vocabulary)
    argv = [
        "scorecard",
        "--no-shipped",
        "--ckpt",
        f"t={path}",
        "--parts",
        "tokenize",
        "--out",
        str(tmp_path / "c"),
    ]
    assert main([*argv, "--quiet"]) == 0
    out = capsys.readouterr().out
    assert f"| {TOKENS} | vehicles <= 5 cm | 144 tokens: vehicle " in out
    assert "Targets met: `t` 0 of 1" in out
    document = json.loads((tmp_path / "c" / "scorecard.json").read_text())
    assert document["checkpoints"] == {"t": str(path)} and document["config"]["parts"] == ["tokenize"]
    assert document["parts"]["t"]["tokenize"]["max_cm"]["vehicle"] > 5.0
    assert main([*argv, "--quiet", "--more-seeds", "3", "0"]) == 2  # 0 is the scorecard's own seed
    assert "more_seeds must be ints >= 0 that differ from each other and from seed 0, got (3, 0)" in (
        capsys.readouterr().err
    )


def test_two_checkpoints_share_each_row_and_a_skipped_part_is_not_saved(tmp_path: Path, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    small = {"vocab_size": 384, "max_cm": {"vehicle": 7136.05, "pedestrian": 596.6, "cyclist": 475.06}}
    big = {"vocab_size": 2048, "max_cm": {"vehicle": 4.72, "pedestrian": 2.09, "cyclist": 2.68}}
    rows = {"shipped": target_rows({"tokenize": small}), "wide": target_rows({"tokenize": big})}
    result = {
        "checkpoints": {"shipped": "a.pt", "wide": "b.pt"},
        "scene_sets": {},
        "parts": {"shipped": {"tokenize": small}, "wide": {"tokenize": big}},
        "rows": rows,
        "met": {"shipped": 0, "wide": 1},
        "rows_with_a_target": {"shipped": 1, "wide": 1},
    }
    table = [line for line in markdown(result).splitlines() if line.startswith(f"| {TOKENS}")]
    assert table == [
        f"| {TOKENS} | vehicles <= 5 cm | 384 tokens: vehicle 7136.05, pedestrian 596.60, cyclist 475.06 "
        "(**not met**) | 2048 tokens: vehicle 4.72, pedestrian 2.09, cyclist 2.68 (met) |"
    ]  # one row, a column per checkpoint

    path = save_checkpoint(tmp_path / "tiny.pt", tiny().model, tiny().vocabulary)
    with pytest.raises(ValueError, match="--womd .*nope.tfrecord: no such WOMD scenario file"):
        run_scorecard({"t": load_checkpoint(path)}, ScorecardConfig(womd=str(tmp_path / "nope.tfrecord")))
    with pytest.raises(ValueError, match="may not be empty or hold"):
        run_scorecard({"a/b": load_checkpoint(path)}, ScorecardConfig(parts=("tokenize",)), tmp_path / "c")
    import trajeglish_env.benchmark.womd as womd

    monkeypatch.setattr(womd, "locate_womd", lambda explicit=None: "no WOMD scenario here")
    card = run_scorecard(
        {"t": load_checkpoint(path)}, ScorecardConfig(parts=("womd",)), tmp_path / "c", progress=False
    )
    assert card["rows"]["t"] == [
        {"row": "WOMD scene: skipped", "value": "no WOMD scenario here", "target": "", "met": None}
    ]
    assert not list((tmp_path / "c" / "parts").glob("*/womd.json"))  # the next run tries again


def test_the_brake_long_and_demo_parts_run_a_model(tmp_path: Path) -> None:
    path = save_checkpoint(tmp_path / "tiny.pt", tiny().model, tiny().vocabulary)
    config = ScorecardConfig(
        highway=SceneSet("highway", 2, 2),
        sumo=SceneSet("sumo", 1, 2),
        brake_episodes=1,
        long_seconds=8.5,
        long_rollouts=1,
        parts=("brake", "long", "demo"),
    )
    result = run_scorecard({"t": load_checkpoint(path)}, config, tmp_path / "c", progress=False)
    parts = result["parts"]["t"]
    npcs = parts["brake"]["npcs"]
    assert set(npcs) == {"trajeglish+guard", "trajeglish", "idm"} and npcs["idm"]["episodes"] == 1
    assert parts["brake"]["candidates"] >= 1
    assert parts["long"]["seconds"] == 8.5 and parts["long"]["collision"]["after"] == 0.0  # guarded
    assert parts["demo"]["scene"] == "highway-intersection-999000" and parts["demo"]["steps"] > 0
    assert Path(parts["demo"]["video"]).is_file()
    names = [r["row"] for r in result["rows"]["t"]]
    assert names[0] == "brake test: rear-ended, guarded NPCs" and names[-1].startswith("demo episode")
