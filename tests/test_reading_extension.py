"""Reading extensions (``checkpoint_reading``): a trained model reads a finer vocabulary than it draws. It
draws its own tokens with the same logits, reads every added token as the old template it was copied from,
tracks an external agent at the env's 40 m/s within 5 cm where its own vocabulary falls metres behind,
and trains (``--init``) as the extended model of its base; ``tokenizer extend --reading-out`` writes it."""

from __future__ import annotations

import dataclasses
import json
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import straight_road_scene, tiny_checkpoint
from test_model import random_scene

from trajeglish_env.checkpoint import (
    CheckpointError,
    load_checkpoint,
    load_into,
    load_pretrained,
    save_checkpoint,
)
from trajeglish_env.checkpoint_reading import drawn_base, is_reading, reading_extension, training_start
from trajeglish_env.cli import main
from trajeglish_env.model import TrajeglishModel
from trajeglish_env.model.config import ModelConfig
from trajeglish_env.sampler.config import SamplingConfig
from trajeglish_env.sampler.engine import RolloutEngine
from trajeglish_env.scenario_io import save_scenarios
from trajeglish_env.tokenizer.extend import embedding_sources, extend_vocabulary
from trajeglish_env.training.train import TrainConfig, train


@pytest.fixture(scope="module")
def tiny_pair():  # noqa: ANN201
    """A tiny model, its 12 cm extension to 384 tokens, and the reading extension."""
    base = tiny_checkpoint()
    with pytest.warns(UserWarning, match="stress tracks lag up to"):  # a coarse cover: fast to build
        ext = extend_vocabulary(base.vocabulary, 384, cover_radius=0.12)
    return base, ext, reading_extension(base, ext)


def test_it_draws_its_own_tokens_with_the_same_logits_and_reads_copies_as_their_sources(tiny_pair) -> None:  # noqa: ANN001
    base, ext, reading = tiny_pair
    assert is_reading(reading) and not is_reading(base)
    assert (reading.config.vocab_size, reading.config.drawn) == (384, base.config.vocab_size)
    scene, tokens = random_scene(base.config, b=2)  # tokens of the base vocabulary
    sources = embedding_sources(base.vocabulary, ext)  # [K, 384]: the base token each token copies
    copy_of = np.tile(np.arange(base.vocabulary.size), (3, 1))  # per class: an added copy of each token
    for k in range(3):
        added = np.arange(base.vocabulary.size, ext.size)
        copy_of[k, sources[k, added]] = added  # (the last copy of each where several share a source)
    kind = scene.agent_kind[:, :, None].expand_as(tokens).clamp(0, 2).numpy()
    copies = torch.from_numpy(np.where(tokens.numpy() >= 0, copy_of[kind, tokens.clamp(min=0).numpy()], -1))
    assert (copies >= base.vocabulary.size).any()
    with torch.no_grad():
        want = base.model(scene, tokens)
        torch.testing.assert_close(reading.model(scene, tokens), want, rtol=0, atol=1e-6)
        torch.testing.assert_close(reading.model(scene, copies), want, rtol=0, atol=1e-6)
        hidden = torch.randn(5, base.config.d_model)
        kinds = np.array([0, 1, 2, 0, 2])
        torch.testing.assert_close(
            reading.model.class_logits_by_kind(hidden, kinds), base.model.class_logits_by_kind(hidden, kinds)
        )
        # an added token as a target counts as the token it was copied from
        loss, n = reading.model.loss(scene, tokens, copies)
        base_loss, base_n = base.model.loss(scene, tokens, tokens)
    assert n == base_n and abs(loss.item() - base_loss.item()) < 1e-5


def test_it_saves_loads_and_gives_back_its_base(tiny_pair, tmp_path: Path) -> None:  # noqa: ANN001
    base, ext, reading = tiny_pair
    path = save_checkpoint(tmp_path / "r.pt", reading.model, reading.vocabulary, reading.training)
    loaded = load_checkpoint(path)
    assert loaded.config == reading.config and loaded.training["reading_extension"]["read_tokens"] == 384
    back = drawn_base(loaded)
    assert back.config == base.config and np.array_equal(back.vocabulary.templates, base.vocabulary.templates)
    for (name, a), (other, b) in zip(
        back.model.state_dict().items(), base.model.state_dict().items(), strict=True
    ):
        assert name == other and torch.equal(a, b), name
    assert drawn_base(base) is base
    with pytest.raises(CheckpointError, match="reads an extended vocabulary already"):
        reading_extension(loaded, ext)
    with pytest.raises(CheckpointError, match="does not extend the checkpoint's"):
        reading_extension(base, dataclasses.replace(ext, templates=ext.templates + 0.01))
    payload = torch.load(path, weights_only=True)
    payload["state_dict"]["token_source"][1, 200] = base.config.vocab_size  # not a drawn token
    torch.save(payload, tmp_path / "bad.pt")
    with pytest.raises(CheckpointError, match="bad.pt: token_source must map every token to one of the 144"):
        load_checkpoint(tmp_path / "bad.pt")
    with pytest.raises(ValueError, match=r"drawn_size must be in \[0, vocab_size 128\], got 200"):
        ModelConfig(vocab_size=128, drawn_size=200)


def test_training_from_it_learns_to_draw_every_token_it_reads(tiny_pair, tmp_path: Path, capsys) -> None:  # noqa: ANN001
    base, ext, reading = tiny_pair
    start = save_checkpoint(tmp_path / "r.pt", reading.model, reading.vocabulary, reading.training)
    assert training_start(base, None) == (base, None)
    scenes = tmp_path / "scenes"
    save_scenarios(scenes / "a.scn.npz", [straight_road_scene(5, 40, seed=s) for s in range(3)])
    quick = TrainConfig(steps=2, batch_size=2, warmup_steps=1, val_fraction=0.0, num_workers=0)
    # its own config, as a fine-tune passes it: the run draws every token it reads
    result = train(scenes, tmp_path / "run", reading.config, quick, None, progress=False, init=start)
    tuned = load_checkpoint(result["checkpoint"])
    assert tuned.config.drawn == tuned.config.vocab_size == 384 and tuned.config.token_bias
    assert tuned.vocabulary.equals(ext)
    assert (
        main(
            [
                "train",
                "--data",
                str(scenes),
                "--out",
                str(tmp_path / "cli"),
                "--init",
                str(start),
                "--steps",
                "1",
                "--batch-size",
                "2",
                "--workers",
                "0",
                "--json",
            ]
        )
        == 0
    )
    assert load_checkpoint(tmp_path / "cli" / "model.pt").config == tuned.config
    err = capsys.readouterr().err  # what the fine-tune changes is said, and that no scene was held out
    assert "reads 384 tokens and draws 144: this run learns to draw all 384" in err and "--vocab" in err
    assert "train: warning: no validation scenes" in err
    # NLLs over different token counts are flagged as not comparable
    from trajeglish_env.training.density import evaluate_nll

    with pytest.warns(UserWarning, match="models draw different token counts"):
        shown = evaluate_nll({"reading": reading, "tuned": tuned}, scenes, windows=2)
    assert (
        shown["models"]["reading"]["drawn_tokens"] == 144 and shown["models"]["tuned"]["drawn_tokens"] == 384
    )


def test_the_shipped_model_tracks_an_ego_at_40_m_s_within_5_cm() -> None:
    """The shipped model reads 2,048 tokens: an external agent at the env's top speed stays within 5 cm of
    its tokenized state; the 384 tokens it draws fall metres behind (and say so)."""
    shipped = load_pretrained()
    assert is_reading(shipped) and shipped.config.drawn == 384 and shipped.config.vocab_size == 2048
    sc = straight_road_scene(4, 60)
    xyh = sc.xyh.copy()
    xyh[0, :, 0] = -40.0 + 40.0 * np.arange(sc.num_steps) * 0.1  # the sdc at 40 m/s behind the others
    sc = dataclasses.replace(sc, xyh=xyh)
    external = np.zeros(sc.num_agents, bool)
    external[0] = True
    controlled = ~external & sc.valid[:, sc.current_index]  # (the last agent enters late)
    errors = {}
    for name, ckpt in (("reading", shipped), ("base", drawn_base(shipped))):
        engine = RolloutEngine(ckpt, sc, 1, 40, controlled, external, config=SamplingConfig(seed=0))
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            for _ in range(30):
                while (agent := engine.advance()) is not None:
                    engine.supply(agent, sc.xyh[agent, engine.t + 1][None])
        t = int(engine.now[0])
        errors[name] = float(np.abs(engine.mxyh[0, 0, t, :2] - sc.xyh[0, t, :2]).max())
        errors[name + "_warned"] = any("faster than its templates" in str(w.message) for w in caught)
    assert errors["reading"] < 0.05 and not errors["reading_warned"]
    assert errors["base"] > 1.0 and errors["base_warned"]


def test_extend_command_writes_the_reading_checkpoint(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    base = tiny_checkpoint()
    start = save_checkpoint(tmp_path / "tiny.pt", base.model, base.vocabulary)
    out, reading = tmp_path / "ext.npz", tmp_path / "reading.pt"
    args = ["tokenizer", "extend", "--size", "384", "--cover-radius", "0.12", "--reading-out", str(reading)]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert main([*args, "--base", str(start), "--out", str(out), "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["reading_out"] == str(reading)
    loaded = load_checkpoint(reading)
    assert loaded.config.drawn == 144 and loaded.config.vocab_size == 384
    assert main([*args, "--base", str(out), "--out", str(tmp_path / "x.npz")]) == 2
    assert "--reading-out needs --base to be a checkpoint" in capsys.readouterr().err


def test_nll_scores_a_reading_model_beside_a_model_drawing_all_it_reads(
    tiny_pair,  # noqa: ANN001
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """Targets beyond the drawn tokens count as their source; each model's unigram is fitted on its own
    tokens (the first model's name tokens the reading one cannot draw), so its figures are the ones it
    gets alone."""
    base, ext, reading = tiny_pair
    full = TrajeglishModel(dataclasses.replace(base.config, vocab_size=ext.size, token_bias=True)).eval()
    load_into(full, base, ext)  # the extension a training run starts from: draws all 384
    scenes = tmp_path / "scenes"
    save_scenarios(scenes / "a.scn.npz", [straight_road_scene(5, 40, seed=s) for s in range(2)])
    first = save_checkpoint(tmp_path / "full.pt", full, ext)
    second = save_checkpoint(tmp_path / "reading.pt", reading.model, reading.vocabulary)
    args = ["nll", "--data", str(scenes), "--unigram-data", str(scenes), "--windows", "4", "--json"]
    assert main([*args, "--quiet", "--ckpt", f"full={first}", "--ckpt", f"reading={second}"]) == 0
    models = json.loads(capsys.readouterr().out)["models"]
    for name in ("full", "reading"):
        assert models[name]["tokens"] > 0 and 0 < models[name]["nll"] < models[name]["unigram_nll"] + 5
    assert main([*args, "--quiet", "--ckpt", f"reading={second}"]) == 0  # alone: the same figures
    assert json.loads(capsys.readouterr().out)["models"]["reading"] == models["reading"]
