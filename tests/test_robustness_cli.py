"""Issue 17, bug 7: every ``trajeglish`` command answers bad input with one line on stderr and exit code 2
(no traceback, nothing written), while unexpected exceptions keep their traceback."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from trajeglish_env.cli import main
from trajeglish_env.scenario_io import save_scenario


def _run(argv: list[str]) -> int:
    """Exit code of the command line (argparse errors leave through SystemExit)."""
    try:
        return main(argv)
    except SystemExit as exc:
        return int(exc.code or 0)


@pytest.fixture
def files(tmp_path: Path, straight_scene) -> dict[str, Path]:
    """A one-scene shard, a plain file, a text file posing as a checkpoint, and a missing path."""
    not_ckpt = tmp_path / "notes.pt"
    not_ckpt.write_text("not a checkpoint\n")  # torch answers this with many lines of advice
    plain = tmp_path / "plain.txt"
    plain.write_text("x")
    return {
        "shard": save_scenario(tmp_path / "data" / "s.scn.npz", straight_scene),
        "plain": plain,
        "not_ckpt": not_ckpt,
        "missing": tmp_path / "missing.tfrecord",
        "tmp": tmp_path,
    }


CASES = [
    (
        "generate-out-is-a-file",
        ["generate", "--scenes", "1", "--out", "{plain}"],
        "--out {plain}: exists and is not a directory",
    ),
    ("generate-workers-0", ["generate", "--scenes", "1", "--out", "{tmp}/g", "--workers", "0"], "--workers"),
    ("generate-scenes-0", ["generate", "--scenes", "0", "--out", "{tmp}/g"], "--scenes"),
    (
        "render-index-past-the-end",
        ["render", "{shard}", "--index", "99", "--out", "{tmp}/x.png"],
        "--index 99: {shard} holds 1 scene(s) (indices 0..0)",
    ),
    ("render-negative-index", ["render", "{shard}", "--index", "-1", "--out", "{tmp}/x.png"], "--index"),
    (
        "train-batch-size-0",
        ["train", "--data", "{tmp}/data", "--out", "{tmp}/run", "--batch-size", "0"],
        "argument --batch-size: expected an integer >= 1, got '0'",
    ),
    (
        "train-steps-0",
        ["train", "--data", "{tmp}/data", "--out", "{tmp}/run", "--steps", "0"],
        "argument --steps: expected an integer >= 1, got '0'",
    ),
    (
        "train-lr-nan",
        ["train", "--data", "{tmp}/data", "--out", "{tmp}/run", "--lr", "nan"],
        "argument --lr: expected a finite number > 0, got 'nan'",
    ),
    (
        "train-interaction-weight-below-1",
        ["train", "--data", "{tmp}/data", "--out", "{tmp}/run", "--interaction-weight", "0.5"],
        "argument --interaction-weight: expected a finite number >= 1, got '0.5'",
    ),
    (
        "train-history-dropout-1",
        ["train", "--data", "{tmp}/data", "--out", "{tmp}/run", "--history-dropout", "1"],
        "argument --history-dropout: expected a number in [0, 1), got '1'",
    ),
    (
        "evaluate-rollouts-0",
        ["evaluate", "--data", "{tmp}/data", "--rollouts", "0", "--out", "{tmp}/ev"],
        "argument --rollouts: expected an integer >= 1, got '0'",
    ),
    (
        "rollout-not-a-checkpoint",
        ["rollout", "--scenario", "{shard}", "--ckpt", "{not_ckpt}", "--out", "{tmp}/r.gif"],
        "{not_ckpt}: not a readable checkpoint (not written by trajeglish, truncated or corrupt?): ",
    ),
    (
        "evaluate-two-unnamed-checkpoints",  # the second replaced the first, silently
        ["evaluate", "--data", "{tmp}/data", "--ckpt", "shipped", "--ckpt", "shipped", "--out", "{tmp}/ev"],
        "--ckpt shipped: the name 'trajeglish' is taken by --ckpt shipped; name each one",
    ),
    (
        "evaluate-unknown-partial",  # a KeyError traceback after every method had run
        ["evaluate", "--data", "{tmp}/data", "--partial", "nope", "--out", "{tmp}/ev"],
        "--partial nope: expected one of the checkpoints ['trajeglish']",
    ),
    (
        "curves-text-suffix",  # a PNG was written into c.txt
        ["curves", "{tmp}/run", "--out", "{tmp}/c.txt"],
        "--out {tmp}/c.txt: expected a .png, .pdf or .svg picture",
    ),
    (
        "rollout-top-p-2",
        ["rollout", "--scenario", "{shard}", "--top-p", "2", "--out", "{tmp}/r.gif"],
        "argument --top-p: expected a number in (0, 1], got '2'",
    ),
    (
        "demo-not-a-checkpoint",
        ["demo", "--checkpoint", "{not_ckpt}", "--out", "{tmp}/demo"],
        "{not_ckpt}: not a readable checkpoint",
    ),
    ("demo-unknown-scene", ["demo", "--scene", "nope", "--ego", "replay", "--out", "{tmp}/d"], "'nope'"),
    (
        "convert-womd-missing-file",
        ["convert-womd", "{missing}", "--out", "{tmp}/w"],
        "{missing}: no such WOMD TFRecord file",
    ),
    ("bench-batches-0", ["bench", "--batches", "0"], "argument --batches"),
    ("scorecard-ckpt-without-name", ["scorecard", "--ckpt", "{not_ckpt}"], "expected NAME=PATH"),
    (
        "scorecard-ckpt-name-taken",
        ["scorecard", "--ckpt", "shipped={not_ckpt}"],
        "the name 'shipped' is taken",
    ),
    ("scorecard-no-checkpoint", ["scorecard", "--no-shipped"], "--no-shipped leaves no checkpoint"),
    (
        "scorecard-not-a-checkpoint",
        ["scorecard", "--ckpt", "c={not_ckpt}"],
        "{not_ckpt}: not a readable checkpoint",
    ),
]


@pytest.mark.parametrize(("argv", "expected"), [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_bad_input_is_one_line_on_stderr_and_exit_2(files, capsys, argv, expected) -> None:
    argv = [a.format(**files) for a in argv]
    assert _run([*argv, "--quiet"]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    (line,) = captured.err.strip().splitlines()
    assert line.startswith(f"trajeglish {argv[0]}: error: ") and expected.format(**files) in line
    assert not (files["tmp"] / "run").exists() and not (files["tmp"] / "g").exists()  # nothing written


def test_json_errors_are_one_object_on_stdout(files, capsys) -> None:
    argv = ["render", str(files["shard"]), "--index", "5", "--out", str(files["tmp"] / "x.png"), "--json"]
    assert _run(argv) == 2
    captured = capsys.readouterr()
    assert json.loads(captured.out) == {
        "error": f"--index 5: {files['shard']} holds 1 scene(s) (indices 0..0)",
        "type": "ValueError",
    }
    assert len(captured.err.strip().splitlines()) == 1


def test_traceback_mode_prints_the_traceback_and_still_exits_2(files, capsys, monkeypatch) -> None:
    """With TRAJEGLISH_TRACEBACK=1 bad input propagated out of main: exit code 1, not the README's 2."""
    monkeypatch.setenv("TRAJEGLISH_TRACEBACK", "1")
    missing = files["tmp"] / "nothere.scn.npz"
    assert _run(["render", str(missing), "--out", str(files["tmp"] / "x.png")]) == 2
    err = capsys.readouterr().err
    assert "Traceback (most recent call last)" in err and f"FileNotFoundError: {missing}" in err
    assert err.strip().splitlines()[-1] == f"trajeglish render: error: {missing}: no such scenario file"


@pytest.mark.parametrize("error", [RuntimeError("boom"), KeyError("boom"), IndexError("boom")])
def test_unexpected_exceptions_keep_their_traceback(files, monkeypatch, error) -> None:
    import trajeglish_env.render

    def broken(*args: object, **kwargs: object) -> None:
        raise error

    monkeypatch.setattr(trajeglish_env.render, "save_render", broken)
    with pytest.raises(type(error), match="boom"):
        main(["render", str(files["shard"]), "--out", str(files["tmp"] / "x.png")])


def test_a_bare_array_as_a_tokenizer_file_is_a_clear_error(tmp_path: Path) -> None:
    from trajeglish_env.tokenizer.vocabulary import MotionVocabulary, VocabularyError

    np.save(tmp_path / "v.npy", np.zeros(3))
    with pytest.raises(VocabularyError, match="v.npy: not a readable tokenizer file .*single array"):
        MotionVocabulary.load(tmp_path / "v.npy")


def test_a_text_file_or_a_pickled_npz_gets_no_advice_to_load_it_unsafely(tmp_path: Path, capsys) -> None:
    """A text file or a foreign .npz of pickled objects given as a scenario shard, a vocabulary, log
    details or a checkpoint: NumPy's "you can load it unsafely using the allow_pickle= keyword argument"
    (or torch's "pop from empty list") stood in the message."""
    from trajeglish_env.checkpoint import CheckpointError, load_checkpoint
    from trajeglish_env.metrics.log_details_io import load_log_details
    from trajeglish_env.scenario import ScenarioError
    from trajeglish_env.scenario_io import load_scenarios
    from trajeglish_env.tokenizer.vocabulary import MotionVocabulary, VocabularyError

    text = tmp_path / "notes.scn.npz"
    text.write_text("this is not a scenario file\n")
    pickled = tmp_path / "foreign.npz"
    np.savez(pickled, a=np.array([{"x": 1}], dtype=object))
    plain = "not a NumPy .npz archive written by trajeglish (it holds pickled objects or is not an archive)"
    loads = [
        (load_scenarios, ScenarioError, "scenario file"),
        (MotionVocabulary.load, VocabularyError, "tokenizer file"),
        (load_log_details, ValueError, "log-details file"),
    ]
    for load, error, what in loads:
        with pytest.raises(error) as err:
            load(text)
        assert str(err.value) == f"{text}: not a readable {what} (truncated or corrupt?): {plain}"
        with pytest.raises(error, match="foreign.npz: ") as err:
            load(pickled)
        assert "allow_pickle" not in str(err.value)
    with pytest.raises(VocabularyError, match=f"foreign.npz: not a readable tokenizer file .*{plain[:30]}"):
        MotionVocabulary.load(pickled)  # no header read first: its arrays are read, the pickled one fails
    with pytest.raises(
        CheckpointError, match=r"notes.scn.npz: not a readable checkpoint .*: not a zip archive$"
    ):
        load_checkpoint(text)
    with pytest.raises(CheckpointError, match="foreign.npz: a NumPy .npz archive, not a model checkpoint"):
        load_checkpoint(pickled)
    assert _run(["render", str(text), "--out", str(tmp_path / "x.png"), "--quiet"]) == 2
    assert f"{text}: not a readable scenario file (truncated or corrupt?): {plain}" in capsys.readouterr().err


def test_files_of_the_wrong_kind_are_named_with_what_was_expected(tmp_path: Path, capsys) -> None:
    """A checkpoint given as a vocabulary, a vocabulary with a text version, a binary metrics.csv, and a
    scorecard part that is JSON but no object (tracebacks or unnamed errors before)."""
    from helpers import tiny

    from trajeglish_env.checkpoint import save_checkpoint
    from trajeglish_env.tokenizer.vocabulary import MotionVocabulary, VocabularyError

    ckpt = tiny()
    save_checkpoint(tmp_path / "model.pt", ckpt.model, ckpt.vocabulary)
    with pytest.raises(VocabularyError, match=r"model.pt: not a readable tokenizer file .*a checkpoint\?"):
        MotionVocabulary.load(tmp_path / "model.pt")
    # ... and the other way round: a vocabulary or a scene shard given as a checkpoint
    from trajeglish_env.checkpoint import CheckpointError, load_checkpoint

    with pytest.raises(
        CheckpointError, match=r"tokenizer_v384.npz: a motion vocabulary .* pass it as --vocab"
    ):
        load_checkpoint(Path(__file__).parents[1] / "trajeglish_env/assets/tokenizer_v384.npz")
    with pytest.raises(CheckpointError, match=r"scenes_bundle.scn.npz: a scenario shard, not a model"):
        load_checkpoint(Path(__file__).parents[1] / "trajeglish_env/assets/scenes_bundle.scn.npz")
    import trajeglish_env

    with pytest.raises(ValueError, match=r"a checkpoint\? pass npc=TrajeglishNPC\('runs/x/model.pt'\)"):
        trajeglish_env.env(npc="runs/x/model.pt")
    state = ckpt.vocabulary.to_state()
    with pytest.raises(VocabularyError, match=r"here: tokenizer version 'v2' is not a number"):
        MotionVocabulary.from_state({**state, "version": "v2"}, where="here")
    run = tmp_path / "run"
    run.mkdir()
    (run / "metrics.csv").write_bytes(b"step,val_nll\n\x80\x81\xff\n")
    assert _run(["curves", f"a={run}", "--out", str(tmp_path / "c.png"), "--quiet"]) == 2
    assert "metrics.csv: not a text metrics file" in capsys.readouterr().err


def test_a_ranks_own_error_is_named_and_stdout_keeps_one_object(capsys, monkeypatch) -> None:
    """Under torchrun every rank printed the error (two JSON objects on stdout); then rank > 0 printed
    nothing, though an error may be its own (a shard only it reads)."""
    monkeypatch.setenv("RANK", "1")
    assert _run(["train", "--data", "/nonexistent", "--out", "/tmp/never", "--json"]) == 2
    out, err = capsys.readouterr()
    assert out == "" and "trajeglish train [rank 1]: error: /nonexistent" in err
    monkeypatch.setenv("RANK", "0")
    assert _run(["train", "--data", "/nonexistent", "--out", "/tmp/never", "--json"]) == 2
    out, err = capsys.readouterr()
    assert json.loads(out)["type"] == "FileNotFoundError"
    assert err.startswith("trajeglish train: error: /nonexistent")


def test_a_demo_of_an_unknown_scene_names_the_flag_and_makes_no_folder(tmp_path: Path, capsys) -> None:
    """`demo --scene nope` made its --out folder before refusing; `--scene 999` did not name the flag."""
    for scene in ("nope", "999"):
        assert _run(["demo", "--scene", scene, "--out", str(tmp_path / "d")]) == 2
        assert f"--scene {scene}: " in capsys.readouterr().err
    assert not (tmp_path / "d").exists()


def test_train_resume_of_a_folder_without_a_run_is_refused_before_anything(files, capsys) -> None:
    """`train --resume` into a folder holding no last.pt (a mistyped --out) started a new full-size run."""
    empty = files["tmp"] / "emptydir"
    empty.mkdir()
    for out in (empty, files["tmp"] / "run"):  # an empty folder, and one that is not there
        argv = ["train", "--data", str(files["tmp"] / "data"), "--out", str(out), "--resume", "--json"]
        assert _run(argv) == 2
        captured = capsys.readouterr()
        message = f"--resume: no run to resume in {out} (no {out / 'last.pt'}); to start a new run there"
        assert json.loads(captured.out)["type"] == "FileNotFoundError"
        (line,) = captured.err.strip().splitlines()
        assert line.startswith(f"trajeglish train: error: {message}") and line.endswith("leave out --resume")
    assert list(empty.iterdir()) == [] and not (files["tmp"] / "run").exists()  # nothing written


def test_tokenizer_outputs_are_checked_before_the_work(files, capsys, monkeypatch) -> None:
    """`tokenizer fit --out DIR` fitted first, then failed with a raw "[Errno 21] Is a directory" naming a
    temporary file; extend's --out / --reading-out likewise, and any output under a plain file."""
    import trajeglish_env.tokenizer.extend as extend_module
    import trajeglish_env.tokenizer.fit as fit_module

    def no_work(*args: object, **kwargs: object) -> None:
        raise AssertionError("the work began before the output was checked")

    for module, name in ((fit_module, "fit_from_directory"), (fit_module, "evaluate_directory")):
        monkeypatch.setattr(module, name, no_work)
    monkeypatch.setattr(extend_module, "extend_vocabulary", no_work)
    tmp, data, plain = files["tmp"], str(files["tmp"] / "data"), files["plain"]
    cases = [
        (["fit", "--data", data, "--out", data], f"--out {data}: is a directory; expected a file to write, "
         f"e.g. {data}/vocab.npz"),
        (["fit", "--data", data, "--out", f"{plain}/v.npz"], f"--out {plain}/v.npz: {plain} is a file, not "
         "a directory"),
        (["eval", "--data", data, "--out", f"{plain}/plots"], f"--out {plain}/plots: {plain} is a file"),
        (["eval", "--data", data, "--out", str(plain)], f"--out {plain}: exists and is not a directory"),
        (["extend", "--out", str(tmp)], f"--out {tmp}: is a directory; expected a file to write, e.g. "
         f"{tmp}/vocab.npz"),
        (["extend", "--out", f"{tmp}/v.npz", "--reading-out", str(tmp)], f"--reading-out {tmp}: is a "
         f"directory; expected a file to write, e.g. {tmp}/model.pt"),
    ]  # fmt: skip
    for argv, expected in cases:
        assert _run(["tokenizer", *argv, "--quiet"]) == 2, argv
        (line,) = capsys.readouterr().err.strip().splitlines()
        assert line.startswith(f"trajeglish tokenizer {argv[0]}: error: {expected}"), (argv, line)
    assert not (tmp / "v.npz").exists()
