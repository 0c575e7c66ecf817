"""The ``trajeglish`` command line: JSON contract, exit codes and clear errors."""

from __future__ import annotations

import json

import pytest
from helpers import womd_tfrecord

from trajeglish_env.cli import main
from trajeglish_env.scenario_io import load_scenario, save_scenario


def _json(capsys: pytest.CaptureFixture[str]) -> dict:
    return json.loads(capsys.readouterr().out)


def test_convert_womd_then_render(tmp_path, capsys) -> None:
    assert main(["convert-womd", str(womd_tfrecord()), "--out", str(tmp_path), "--json", "--quiet"]) == 0
    result = _json(capsys)
    assert result["scenes"] == 1 and result["failed"] == []
    shard = tmp_path / "motion_data_one_scenario.scn.npz"
    assert load_scenario(shard).scenario_id == "637f20cafde22ff8"
    assert main(["render", str(shard), "--out", str(tmp_path / "w.png"), "--json"]) == 0
    assert _json(capsys) == {
        "scene": "637f20cafde22ff8",
        "source": "womd",
        "agents": 83,  # every track of the scene
        "agents_now": 50,  # present at its current step: the picture's "agents=50 now of 83"
        "out": str(tmp_path / "w.png"),
    }
    # a corrupt file among the inputs makes the command fail, but the good file stays converted
    bad = tmp_path / "bad.tfrecord"
    bad.write_bytes(womd_tfrecord().read_bytes()[:1000])
    out2 = tmp_path / "second"
    assert (
        main(["convert-womd", str(womd_tfrecord()), str(bad), "--out", str(out2), "--json", "--quiet"]) == 1
    )
    result = _json(capsys)
    assert result["failed"][0]["file"].endswith("bad.tfrecord") and "record 0" in result["failed"][0]["error"]
    assert (out2 / "motion_data_one_scenario.scn.npz").is_file()


def test_errors_are_one_line_and_exit_2(tmp_path, capsys, straight_scene) -> None:
    assert main(["render", str(tmp_path / "nope.scn.npz"), "--out", str(tmp_path / "x.png"), "--json"]) == 2
    captured = capsys.readouterr()
    assert json.loads(captured.out)["error"].endswith("nope.scn.npz: no such scenario file")
    assert "trajeglish render: error:" in captured.err
    path = save_scenario(tmp_path / "s.scn.npz", straight_scene)
    assert main(["render", str(path), "--out", str(tmp_path / "x.bmp")]) == 2
    assert "expected a .png, .gif or .mp4" in capsys.readouterr().err
    # a bad command line: the same one line naming the (sub)command, and the JSON error with --json
    usage = {
        ("tokenizer", "fit", "--data", "d", "--out", "v", "--vocab", "100"): (
            "trajeglish tokenizer fit: error: argument --vocab: invalid choice: 100"
        ),
        ("nll", "--data", "d", "--ckpt", "a", "b"): "trajeglish nll: error: unrecognized arguments: b",
        ("evaluate", "--data", "d", "--rollouts", "0"): "trajeglish evaluate: error: argument --rollouts",
    }
    for command, message in usage.items():
        with pytest.raises(SystemExit) as exited:
            main([*command, "--json"])
        captured = capsys.readouterr()
        assert exited.value.code == 2 and captured.err.startswith(message) and captured.err.count("\n") == 1
        shown = json.loads(captured.out)
        assert shown["type"] == "UsageError" and message.split("error: ")[1] in shown["error"]
    assert main(["tokenizer", "eval", "--data", str(tmp_path / "none"), "--quiet"]) == 2
    assert capsys.readouterr().err.startswith("trajeglish tokenizer eval: error: ")


def test_tokenizer_fit_and_eval_commands(tmp_path, capsys) -> None:
    from trajeglish_env.scenario_io import save_scenarios
    from trajeglish_env.sources.highway import generate_scene
    from trajeglish_env.tokenizer.vocabulary import MotionVocabulary

    save_scenarios(tmp_path / "d" / "a.scn.npz", [generate_scene("two-way", s) for s in range(5)])
    out = tmp_path / "vocab.npz"
    args = [
        "tokenizer",
        "fit",
        "--data",
        str(tmp_path / "d"),
        "--vocab",
        "128",
        "--out",
        str(out),
        "--trials",
        "2",
    ]
    assert main([*args, "--json", "--quiet"]) == 0
    fit = _json(capsys)
    vocab = MotionVocabulary.load(out)
    assert vocab.size == 128 and fit["vocab_size"] == 128
    assert fit["heldout"]["mean_cm"] < 10.0
    args = [
        "tokenizer",
        "eval",
        "--data",
        str(tmp_path / "d"),
        "--vocab",
        "128",
        "--out",
        str(tmp_path / "e"),
    ]
    assert main([*args, "--trials", "1", "--json", "--quiet"]) == 0
    table = json.dumps(_json(capsys))
    for method in ("k-disks", "k-means", "xyh-grid", "xy-grid"):
        assert method in table
    # too few scenes to hold any out: one line naming the count and the way out, not zip()'s complaint
    save_scenarios(tmp_path / "few" / "a.scn.npz", [generate_scene("two-way", s) for s in range(3)])
    assert main([*args[:3], str(tmp_path / "few"), *args[4:], "--trials", "1", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "no held-out scenes" in err and "holds 3 scenes" in err and "--fit-data" in err
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("TRAJEGLISH_TRACEBACK", "1")  # the traceback of bad input, when asked for: still exit 2
        assert main([*args[:3], str(tmp_path / "few"), *args[4:], "--trials", "1", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "Traceback" in err and "ValueError: " in err and "no held-out scenes" in err


def test_rollout_and_nll_commands_with_the_shipped_model(tmp_path, capsys) -> None:
    from trajeglish_env.sources.highway import generate_scene

    path = save_scenario(tmp_path / "d" / "s.scn.npz", generate_scene("two-way", 11))
    out = tmp_path / "r.gif"
    args = ["rollout", "--scenario", str(path), "--horizon", "6", "--out", str(out), "--json"]
    assert main(args) == 0
    shown = _json(capsys)
    assert shown["horizon"] == 6 and shown["guard"] and shown["green_rule"] and out.stat().st_size > 1000
    assert shown["road_ahead"] == 5.0
    assert main([*args, "--road-ahead", "0"]) == 0 and _json(capsys)["road_ahead"] == 0.0  # one-step rule
    with pytest.raises(SystemExit) as exited:  # a one-line usage error, not a traceback
        main([*args, "--road-ahead", "-1"])
    assert exited.value.code == 2 and "--road-ahead" in capsys.readouterr().err
    assert shown["step_change"] == 0.5 and shown["stall_steps"] == 10
    assert main([*args, "--stall-steps", "0"]) == 0 and _json(capsys)["stall_steps"] == 0
    # a guard rule with the guard off changed nothing, silently: refused, naming the flags
    assert main([*args, "--guard", "off", "--no-green-rule", "--step-change", "1"]) == 2
    assert "--no-green-rule, --step-change: the guard's rules, but --guard off" in capsys.readouterr().err
    assert main([*args, "--guard", "off"]) == 0  # the model alone
    alone = _json(capsys)
    assert not alone["guard"] and alone["green_rule"] is None and alone["road_ahead"] is None
    assert alone["step_change"] is None and alone["stall_steps"] is None  # guard settings
    # a picture shows where the rollout ends, not the logged current step: guard on and off differ there
    pictures = [tmp_path / "on.png", tmp_path / "off.png"]
    for picture, guard in zip(pictures, ("on", "off"), strict=True):
        assert main([*args[:-3], "--out", str(picture), "--guard", guard, "--quiet"]) == 0
    capsys.readouterr()
    assert pictures[0].read_bytes() != pictures[1].read_bytes()
    nll_args = ["nll", "--data", str(tmp_path / "d"), "--windows", "4", "--cache-dtype", "bfloat16"]
    assert main([*nll_args, "--compute-dtype", "bfloat16", "--json", "--quiet"]) == 0
    result = _json(capsys)
    model = result["models"]["trajeglish"]
    assert model["tokens"] > 0 and 0 < model["nll"] < result["unigram_nll"] + 5
    bf16 = model["through_cache"]["bfloat16"]
    assert bf16["tokens"] == model["tokens"] and abs(bf16["reference_nll"] - model["nll"]) < 1e-5
    assert abs(bf16["nll"] - model["nll"]) < 0.01
    # the linear layers multiplying in bfloat16 too: other logits, the same NLL within 0.01 nats
    both = model["through_cache_by_compute"]["bfloat16"]["bfloat16"]
    assert both["tokens"] == model["tokens"] and abs(both["nll"] - model["nll"]) < 0.01
    assert both["max_logit_diff"] > bf16["max_logit_diff"] > 0
    assert (
        main(["rollout", "--scenario", str(path), "--out", str(out), "--ckpt", str(tmp_path / "no.pt")]) == 2
    )
    assert "no.pt: no such checkpoint file" in capsys.readouterr().err
