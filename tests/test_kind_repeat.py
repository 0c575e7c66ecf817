"""train --repeat KIND=N: scene kinds drawn N times an epoch, each copy with its own window; checked
requests, a clear error for a kind no scene has, and a resumed run that equals an uninterrupted one."""

from __future__ import annotations

import dataclasses
from collections import Counter
from pathlib import Path

import pytest
import torch
from helpers import grid_vocabulary, straight_road_scene, tiny_config

from trajeglish_env.checkpoint import load_checkpoint
from trajeglish_env.cli import main
from trajeglish_env.scenario_io import save_scenarios
from trajeglish_env.training.kind_repeat import RepeatedOrder, parse_repeat, repeat_counts, window_order
from trajeglish_env.training.train import TrainConfig, train


def _scenes() -> list:
    ids = ["highway-roundabout-11", "highway-merge-12", "sumo-grid-13", "highway-roundabout-14"]
    return [
        dataclasses.replace(
            straight_road_scene(num_agents=5, seed=k, steps=40), scenario_id=sid, source=sid.split("-")[0]
        )
        for k, sid in enumerate(ids)
    ]


def test_requests_are_checked_and_the_longest_key_wins() -> None:
    assert parse_repeat(["sumo=2", "highway/roundabout=3"]) == (("highway/roundabout", 3), ("sumo", 2))
    for bad in (["sumo"], ["sumo=0"], ["sumo=x"], ["=2"], ["sumo=101"]):
        with pytest.raises(ValueError, match="expected KIND=N"):
            parse_repeat(bad)
    with pytest.raises(ValueError, match="given twice"):
        parse_repeat(["sumo=2", "sumo=3"])
    scenes = _scenes()
    counts = repeat_counts(scenes, parse_repeat(["highway=2", "highway/roundabout=3"]))
    assert counts.tolist() == [3, 2, 1, 3]  # a kind's own key beats its source's, whatever the order
    with pytest.raises(ValueError, match=r"no training scene is of kind 'highway/u-turn'.*highway/merge"):
        repeat_counts(scenes, (("highway/u-turn", 2),))


def test_an_epoch_holds_each_scene_count_times_with_distinct_windows() -> None:
    order = RepeatedOrder((3, 2, 1, 3), seed=5)
    epoch = [order(g) for g in range(9)]
    assert Counter(scene for _, scene in epoch) == {0: 3, 1: 2, 2: 1, 3: 3}
    assert len({key for key in epoch}) == 9  # every copy seeds its own window
    assert [order(g) for g in range(9)] == epoch  # a pure function of the counter
    assert Counter(scene for _, scene in (order(g) for g in range(9, 18))) == {0: 3, 1: 2, 2: 1, 3: 3}
    assert window_order(_scenes(), (), 0, 5) is None  # nothing asked: the plain order


def test_a_repeated_run_resumes_exactly_and_the_cli_refuses_unknown_kinds(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data = tmp_path / "scenes"
    save_scenarios(data / "a.scn.npz", _scenes())
    cfg = TrainConfig(
        steps=4,
        batch_size=2,
        warmup_steps=1,
        val_every=100,
        checkpoint_every=100,
        num_workers=0,
        val_fraction=0.0,
        repeat=parse_repeat(["highway/roundabout=3"]),
    )
    kw = dict(vocabulary=grid_vocabulary(), progress=False)
    straight = train(data, tmp_path / "a", tiny_config(), cfg, **kw)
    cut = train(data, tmp_path / "b", tiny_config(), cfg, time_limit=0.0, **kw)
    assert cut["steps"] == 1
    resumed = train(data, tmp_path / "b", tiny_config(), cfg, resume=True, **kw)
    assert resumed["steps"] == straight["steps"] == 4
    a = load_checkpoint(tmp_path / "a" / "model.pt").model.state_dict()
    b = load_checkpoint(tmp_path / "b" / "model.pt").model.state_dict()
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=0, atol=0, msg=f"{k} differs after a resume")
    plain = train(data, tmp_path / "c", tiny_config(), dataclasses.replace(cfg, repeat=()), **kw)
    c = load_checkpoint(tmp_path / "c" / "model.pt").model.state_dict()
    assert plain["steps"] == 4 and any(not torch.equal(a[k], c[k]) for k in a)  # another data mix
    args = ["train", "--data", str(data), "--out", str(tmp_path / "d"), "--preset", "tiny", "--quiet"]
    assert main([*args, "--steps", "1", "--repeat", "highway/u-turn=2"]) == 2
    assert "no training scene is of kind 'highway/u-turn'" in capsys.readouterr().err
    assert main([*args, "--steps", "1", "--repeat", "sumo=2", "--shard-cache", "1"]) == 2
    assert "--repeat needs every scene in memory" in capsys.readouterr().err
