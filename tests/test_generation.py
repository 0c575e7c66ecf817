"""Parallel, resumable, atomic scene generation (``trajeglish generate``)."""

from __future__ import annotations

import json

import pytest

from trajeglish_env.cli import main
from trajeglish_env.scenario_io import list_scenario_files, load_scenarios
from trajeglish_env.sources import generation
from trajeglish_env.sources.generation import GenerationConfig, generate

FAST = ("two-way", "u-turn")


def _scenes(directory):
    return [s for f in list_scenario_files(directory) for s in load_scenarios(f)]


def test_output_is_independent_of_workers_and_resumes_after_damage(tmp_path) -> None:
    config = GenerationConfig("highway", scenes=5, seed=3, kinds=FAST, scenes_per_shard=2)
    one = generate(config, tmp_path / "one", workers=1, progress=False)
    assert one["shards"] == 3 and one["generated"] == 5 and one["resumed_from"] == 0
    files = list_scenario_files(tmp_path / "one")
    assert [f.name for f in files] == [
        "highway-00000.scn.npz",
        "highway-00001.scn.npz",
        "highway-00002.scn.npz",
    ]
    assert [len(load_scenarios(f)) for f in files] == [2, 2, 1]
    two = generate(config, tmp_path / "two", workers=2, progress=False)
    assert two["generated"] == 5
    a, b = _scenes(tmp_path / "one"), _scenes(tmp_path / "two")
    assert all(x.equals(y) for x, y in zip(a, b, strict=True))
    assert len({s.scenario_id for s in a}) == 5

    # damage: one shard deleted, one truncated, one with bytes flipped inside a member (its header still
    # reads) -> only those are regenerated, identically
    files[0].unlink()
    files[2].write_bytes(files[2].read_bytes()[:100])
    flipped = bytearray(files[1].read_bytes())
    flipped[len(flipped) // 2 : len(flipped) // 2 + 32] = bytes(
        255 - b for b in flipped[len(flipped) // 2 :][:32]
    )
    files[1].write_bytes(bytes(flipped))
    again = generate(config, tmp_path / "one", workers=1, progress=False)
    assert again["generated"] == 5 and again["resumed_from"] == 0
    assert all(x.equals(y) for x, y in zip(_scenes(tmp_path / "one"), b, strict=True))
    nothing = generate(config, tmp_path / "one", workers=1, progress=False)
    assert nothing["generated"] == 0 and nothing["resumed_from"] == 5


def test_interrupted_run_leaves_no_partial_shard(tmp_path, monkeypatch) -> None:
    config = GenerationConfig("highway", scenes=4, seed=1, kinds=FAST, scenes_per_shard=2)
    real = generation._write_shard
    calls = []

    def crash_on_second(cfg, index, out):
        calls.append(index)
        if len(calls) == 2:
            raise KeyboardInterrupt  # as if the user pressed Ctrl-C while shard 1 was being made
        return real(cfg, index, out)

    monkeypatch.setattr(generation, "_write_shard", crash_on_second)
    with pytest.raises(KeyboardInterrupt):
        generate(config, tmp_path, workers=1, progress=False)
    assert [p.name for p in tmp_path.iterdir() if p.name != "manifest.json"] == ["highway-00000.scn.npz"]
    monkeypatch.setattr(generation, "_write_shard", real)
    resumed = generate(config, tmp_path, workers=1, progress=False)
    assert resumed["generated"] == 2 and resumed["resumed_from"] == 2
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_mismatched_resume_and_bad_kinds_are_refused(tmp_path) -> None:
    generate(GenerationConfig("highway", 1, seed=0, kinds=("two-way",)), tmp_path, progress=False)
    with pytest.raises(ValueError, match="generated with different settings"):
        generate(GenerationConfig("highway", 1, seed=1, kinds=("two-way",)), tmp_path, progress=False)
    # a directory of the sharp-kerb generator (version 1, no generator_version recorded) is not resumed
    manifest = tmp_path / "manifest.json"
    doc = json.loads(manifest.read_text())
    assert doc["generator_version"] == 3
    manifest.write_text(json.dumps({k: v for k, v in doc.items() if k != "generator_version"}))
    with pytest.raises(ValueError, match="version 1 of the highway generator, this is version 3"):
        generate(GenerationConfig("highway", 1, seed=0, kinds=("two-way",)), tmp_path, progress=False)
    # shards without a manifest (settings unknown), or files this run would not write: never mixed in
    manifest.unlink()
    with pytest.raises(ValueError, match="holds scene shards but no manifest.json"):
        generate(GenerationConfig("highway", 1, seed=0, kinds=("two-way",)), tmp_path, progress=False)
    (tmp_path / "sumo-00000.scn.npz").write_bytes((tmp_path / "highway-00000.scn.npz").read_bytes())
    with pytest.raises(
        ValueError, match=r"holds scene files this run would not write \(sumo-00000.scn.npz\)"
    ):
        generate(GenerationConfig("highway", 1, seed=0, kinds=("two-way",)), tmp_path, progress=False)
    (tmp_path / "sumo-00000.scn.npz").unlink()
    manifest.write_text(json.dumps(doc))
    with pytest.raises(ValueError, match=r"unknown highway scene kinds \['parking'\]"):
        generate(GenerationConfig("highway", 1, kinds=("parking",)), tmp_path / "x", progress=False)
    with pytest.raises(ValueError, match="unknown scene source 'carla'"):
        generate(GenerationConfig("carla", 1), tmp_path / "y", progress=False)
    for text, message in (
        ("", "not a readable manifest"),
        ("[1, 2]", "not a scene folder's manifest"),
        (json.dumps({**doc, "version": 7}), "manifest version 7, this build reads 1"),
    ):
        manifest.write_text(text)
        with pytest.raises(ValueError, match=f"manifest.json: {message}"):
            generate(GenerationConfig("highway", 1, seed=0, kinds=("two-way",)), tmp_path, progress=False)


def test_cli_generate_json(tmp_path, capsys) -> None:
    args = ["generate", "--scenes", "2", "--out", str(tmp_path), "--kinds", "u-turn", "--seed", "5", "--json"]
    assert main([*args, "--quiet"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["generated"] == 2 and result["kinds"] == ["u-turn"] and result["scenes_per_second"] > 0
    manifest = json.loads((tmp_path / "manifest.json").read_text())
    assert manifest["config"] == {
        "source": "highway",
        "scenes": 2,
        "seed": 5,
        "kinds": ["u-turn"],
        "scenes_per_shard": 8,
    }
    assert main(["generate", "--scenes", "2", "--out", str(tmp_path), "--kinds", "nope", "--quiet"]) == 2
    assert "unknown highway scene kinds" in capsys.readouterr().err


def test_kinds_with_spaces_are_read_and_an_empty_list_is_refused(tmp_path, capsys) -> None:
    """`--kinds "u-turn, two-way"` was refused for its space, `--kinds ","` generated every kind."""
    args = ["generate", "--scenes", "2", "--out", str(tmp_path / "a"), "--quiet", "--json"]
    assert main([*args, "--kinds", "u-turn, two-way"]) == 0
    assert json.loads(capsys.readouterr().out)["kinds"] == ["u-turn", "two-way"]
    assert main(["generate", "--scenes", "2", "--out", str(tmp_path / "b"), "--kinds", ",", "--quiet"]) == 2
    assert "--kinds ',': no kind named" in capsys.readouterr().err
