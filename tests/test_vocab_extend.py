"""Extending a trained model's vocabulary (``tokenizer.extend``): the shipped templates keep their ids,
the added ones keep every motion of the env's limits within 5 cm, and a model that takes them on starts
as the trained model was (each old token's probability, shared by its copies); ``train --init CKPT
--vocab EXTENDED`` fine-tunes it, and a vocabulary that does not extend the checkpoint's is refused."""

from __future__ import annotations

import dataclasses
import json
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import bundle_scene, small_scenes, straight_road_scene, tiny_checkpoint, tiny_config
from test_tokenizer_coverage import _envelope_tracks, _max_error, _random_envelope_tracks

from trajeglish_env.checkpoint import (
    Checkpoint,
    CheckpointError,
    check_init,
    load_checkpoint,
    load_into,
    save_checkpoint,
)
from trajeglish_env.cli import main
from trajeglish_env.env.actions import bicycle_step
from trajeglish_env.geometry import to_global, wrap_angle
from trajeglish_env.kinematics import VehicleLimits, bicycle_local_step
from trajeglish_env.model import TrajeglishModel
from trajeglish_env.sampler import guard as guard_module
from trajeglish_env.sampler.config import SamplingConfig
from trajeglish_env.sampler.engine import RolloutEngine
from trajeglish_env.scenario import AgentKind
from trajeglish_env.scenario_io import save_scenarios
from trajeglish_env.tokenizer.coverage import DEFAULT_ENVELOPES, stress_error
from trajeglish_env.tokenizer.data import TrajectorySet
from trajeglish_env.tokenizer.discretization import evaluate_vocabulary
from trajeglish_env.tokenizer.extend import embedding_sources, extend_vocabulary, extension_report
from trajeglish_env.tokenizer.tokenize import tokenize
from trajeglish_env.tokenizer.vocabulary import MotionVocabulary, load_default_tokenizer
from trajeglish_env.training.train import TrainConfig, train


@pytest.fixture(scope="module")
def shipped() -> MotionVocabulary:
    return load_default_tokenizer()


@pytest.fixture(scope="module")
def extended(shipped: MotionVocabulary) -> MotionVocabulary:
    return extend_vocabulary(shipped, 2048)


def test_the_shipped_templates_keep_their_ids(shipped: MotionVocabulary, extended: MotionVocabulary) -> None:
    assert extended.size == 2048 and extended.method == shipped.method
    assert np.array_equal(extended.templates[:, :384], shipped.templates)
    report = extension_report(extended)
    assert report["base_size"] == 384
    assert (report["vehicle"]["cover"], report["vehicle"]["bicycle"]) == (1321, 618)  # 703 + the bicycle's
    for kind in AgentKind:
        row = report[kind.name.lower()]
        assert row["cover"] + row["catch_up"] + row["fill"] == 2048 - 384
    sources = embedding_sources(shipped, extended)
    assert np.array_equal(sources[:, :384], np.tile(np.arange(384), (3, 1)))
    assert sources[:, 384:].max() < 384
    fastest = int(np.argmax(shipped.templates[0, :, 0]))  # 3.04 m a step: what 40 m/s templates copy
    assert sources[0, 384 + int(np.argmax(extended.templates[0, 384:, 0]))] == fastest


def _bicycle_tracks(count: int, seed: int, hold: bool) -> tuple[np.ndarray, np.ndarray]:
    """Held-out tracks of the env's continuous action (``bicycle_step``): random start speeds, car lengths
    of 4-5.5 m, one random action held (``hold``) or a new one every step."""
    rng = np.random.default_rng(seed)
    limits = VehicleLimits()
    tracks, lengths = [], rng.uniform(4.0, 5.5, count)
    for length in lengths:
        xyh, speed = np.zeros(3), np.array(rng.uniform(0, 40))
        states, held = [xyh], rng.uniform(-1, 1, 2)
        for _ in range(50):
            action = held if hold else rng.uniform(-1, 1, 2)
            xyh, speed = bicycle_step(xyh, speed, action, np.array(length), limits, 0.1)
            states.append(xyh)
        tracks.append(np.stack(states))
    return np.stack(tracks), lengths


def _worst(vocab: MotionVocabulary, xyh: np.ndarray, lengths: np.ndarray) -> float:
    size = np.stack([lengths, np.full(len(lengths), 2.0)], 1)
    return float(
        np.nanmax(tokenize(vocab, xyh, np.ones(xyh.shape[:2], bool), size, np.zeros(len(xyh), int)).error)
    )


def test_every_motion_of_the_limits_tokenizes_within_5cm(
    shipped: MotionVocabulary, extended: MotionVocabulary
) -> None:
    """Held-out tracks (not those the catch-up followed). Measured: unicycle stress tracks 3.2 cm, 200
    random envelope tracks 4.0 cm, the env's bicycle with held / random actions 4.4 / 4.0 cm; the shipped
    vocabulary: 67 m (it tops out at 30.4 m/s); the unicycle cover alone (V = 1152): bicycle tracks 17 cm."""
    for kind in AgentKind:
        entry = extended.metadata["coverage"][kind.name.lower()]
        assert entry["stress_max_error_m"] <= 0.05, (kind, entry)
    vehicle = dataclasses.replace(DEFAULT_ENVELOPES[AgentKind.VEHICLE], radius=0.03)
    assert stress_error(extended, AgentKind.VEHICLE, 0.1, vehicle) < 0.05
    random_tracks = _random_envelope_tracks(60, seed=11)
    assert max(_max_error(extended, x) for x in random_tracks) < 0.05
    assert max(_max_error(shipped, x) for x in random_tracks) > 10.0
    for name, xyh in _envelope_tracks().items():  # 40 m/s, braking from 40, reversing, tight turns
        assert _max_error(extended, xyh) < 0.05, name
    for hold in (True, False):
        xyh, lengths = _bicycle_tracks(40, seed=3, hold=hold)
        assert _worst(extended, xyh, lengths) < 0.05, hold
        assert _worst(shipped, xyh, lengths) > 1.0, hold


def test_the_tokenizers_bicycle_is_the_envs() -> None:
    rng = np.random.default_rng(0)
    xyh = rng.normal(size=(64, 3))
    speed, action, length = rng.uniform(0, 40, 64), rng.uniform(-1, 1, (64, 2)), rng.uniform(3, 6, 64)
    limits = VehicleLimits()
    want, _ = bicycle_step(xyh, speed, action, length, limits, 0.1)
    accel = np.where(action[:, 0] >= 0, action[:, 0] * limits.max_accel, action[:, 0] * limits.max_brake)
    local = bicycle_local_step(speed, accel, action[:, 1], length, limits, 0.1)
    got = to_global(xyh, local)
    np.testing.assert_allclose(got[:, :2], want[:, :2], atol=1e-9)
    np.testing.assert_allclose(wrap_angle(got[:, 2] - want[:, 2]), 0.0, atol=1e-9)


def test_real_tracks_tokenize_closer(shipped: MotionVocabulary, extended: MotionVocabulary) -> None:
    data = TrajectorySet.from_scenarios(small_scenes())
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # drift warnings name the tracks; the shares are asserted
        before, after = (evaluate_vocabulary(v, data, collisions=False) for v in (shipped, extended))
    assert after["by_kind"]["vehicle"]["mean_cm"] < 0.85 * before["by_kind"]["vehicle"]["mean_cm"]
    assert (
        after["drift"]["per_class"]["vehicle"]["drift_share"]
        < before["drift"]["per_class"]["vehicle"]["drift_share"]
    )


def test_too_small_an_extension_says_what_size_it_needs(shipped: MotionVocabulary) -> None:
    with pytest.raises(ValueError, match="class 'vehicle' needs 1321 templates.*at least 1705"):
        extend_vocabulary(shipped, 1700)
    with pytest.raises(ValueError, match="cover_radius"):
        extend_vocabulary(shipped, 2048, cover_radius=2.0)


def _tiny_extension(size: int = 384) -> tuple[MotionVocabulary, MotionVocabulary]:
    base = tiny_checkpoint().vocabulary  # a grid of templates
    with pytest.warns(UserWarning, match="class 'vehicle''s stress tracks lag up to"):  # a 12 cm cover
        return base, extend_vocabulary(base, size, cover_radius=0.12)


def test_the_guards_lazy_passes_draw_what_the_full_mask_draws_in_a_larger_vocabulary(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A vocabulary of more than 384 tokens gets a fourth lazy pass (384 candidates) before all of them."""
    ckpt = tiny_checkpoint()
    base, ext = _tiny_extension(512)
    model = TrajeglishModel(dataclasses.replace(ckpt.config, vocab_size=ext.size, token_bias=True)).eval()
    load_into(model, ckpt, ext)
    extended_ckpt = Checkpoint(model=model, vocabulary=ext, training={})
    sc = bundle_scene("highway-roundabout-999001")
    active = sc.valid[:, sc.current_index].copy()
    config = SamplingConfig(temperature=1.0, guard=True, seed=5)
    passes: list[int] = []
    original = guard_module.SamplingGuard._lazy_draw

    def counted(self, pairs, sel, probs, cdf, k, *rest):  # noqa: ANN001, ANN202
        passes.append(k)
        return original(self, pairs, sel, probs, cdf, k, *rest)

    monkeypatch.setattr(guard_module.SamplingGuard, "_lazy_draw", counted)
    lazy = RolloutEngine(extended_ckpt, sc, 2, 12, active, config=config)
    lazy.run()
    monkeypatch.setattr(guard_module, "LAZY_CANDIDATES", ())  # every candidate of every agent checked
    full = RolloutEngine(extended_ckpt, sc, 2, 12, active, config=config)
    full.run()
    assert np.array_equal(lazy.tokens, full.tokens)
    assert 384 in passes and lazy.guard.stats.full < lazy.guard.stats.guarded


def test_an_extended_model_starts_as_the_trained_one() -> None:
    """Summed over each old token's copies, the extended model's probabilities are the trained model's."""
    from test_model import random_scene

    ckpt = tiny_checkpoint()
    base, ext = _tiny_extension()
    cfg = dataclasses.replace(ckpt.config, vocab_size=ext.size, token_bias=True)
    check_init(ckpt, cfg, ext)
    model = TrajeglishModel(cfg).eval()
    load_into(model, ckpt, ext)
    scene, tokens = random_scene(ckpt.config, b=2)
    sources = torch.from_numpy(embedding_sources(base, ext))
    with torch.no_grad():
        want = ckpt.model(scene, tokens).softmax(-1)  # [B,T,A,V]
        probs = model(scene, tokens).softmax(-1)  # [B,T,A,384]
    kind = scene.agent_kind[:, None, :, None].expand(*probs.shape[:-1], 1)
    groups = sources[kind.clamp(0, 2), torch.arange(ext.size)]  # each token's old token, per agent's class
    got = torch.zeros_like(want).scatter_add_(-1, groups, probs)
    torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-6)
    assert (probs[..., base.size :] > 0).all()  # the added tokens can be drawn


def test_init_takes_an_extension_and_nothing_else(tmp_path: Path) -> None:
    torch.manual_seed(0)
    base, ext = _tiny_extension()
    start = save_checkpoint(tmp_path / "start.pt", TrajeglishModel(tiny_config()), base)
    ckpt = load_checkpoint(start)
    scenes = tmp_path / "scenes"
    save_scenarios(scenes / "a.scn.npz", [straight_road_scene(5, 40, seed=s) for s in range(3)])
    cfg = dataclasses.replace(tiny_config(), vocab_size=ext.size, token_bias=True)
    quick = TrainConfig(steps=2, batch_size=2, warmup_steps=1, val_fraction=0.0, num_workers=0)
    result = train(scenes, tmp_path / "run", cfg, quick, ext, progress=False, init=start)
    tuned = load_checkpoint(result["checkpoint"])
    assert tuned.config.vocab_size == 384 and tuned.config.token_bias
    assert tuned.vocabulary.equals(ext)
    n = base.size
    old = ckpt.model.token.weight.view(3, n, -1)
    torch.testing.assert_close(tuned.model.token.weight.view(3, 384, -1)[:, :n], old, atol=1e-2, rtol=0)
    shifted = MotionVocabulary(ext.templates + 0.01 * (np.arange(ext.size) < n)[None, :, None])
    with pytest.raises(CheckpointError, match="vocabulary differs.*tokenizer extend"):
        check_init(ckpt, cfg, shifted)  # the old templates must be kept as they are
    with pytest.raises(CheckpointError, match="vocab_size"):
        check_init(ckpt, dataclasses.replace(tiny_config(), vocab_size=384), base)


def test_extend_command_writes_the_vocabulary_and_compares_on_held_out_scenes(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], extended: MotionVocabulary
) -> None:
    scenes = tmp_path / "scenes"
    save_scenarios(scenes / "a.scn.npz", small_scenes()[:1])
    out = tmp_path / "ext.npz"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        main(["tokenizer", "extend", "--out", str(out), "--data", str(scenes), "--json"])
    result = json.loads(capsys.readouterr().out)
    assert result["extension"]["size"] == 2048 and result["extension"]["vehicle"]["within_5cm"]
    assert (
        result["heldout"]["extended"]["templates"] == 2048 and result["heldout"]["base"]["templates"] == 384
    )
    assert MotionVocabulary.load(out).equals(extended)  # deterministic: the fixture's, byte for byte
    assert main(["tokenizer", "extend", "--out", str(out), "--size", "384"]) == 2
    assert "an extension needs more than the base's 384 templates" in capsys.readouterr().err


def test_extend_refuses_to_write_over_the_shipped_assets_or_its_base(tmp_path, capsys) -> None:
    """docs/vocabulary.md's example wrote `--reading-out trajeglish_env/assets/trajeglish_small.pt`: 65 s
    later the shipped model was replaced (same weights, another sha256, provenance rewritten)."""
    from trajeglish_env.checkpoint import pretrained_path
    from trajeglish_env.cli import main

    shipped = pretrained_path()
    before = shipped.stat().st_mtime_ns
    args = ["tokenizer", "extend", "--size", "400", "--out", str(tmp_path / "v.npz")]
    assert main([*args, "--reading-out", str(shipped)]) == 2
    assert "refusing to write into the package's shipped assets" in capsys.readouterr().err
    assert main(["tokenizer", "extend", "--size", "400", "--out", str(shipped.parent / "v.npz")]) == 2
    base = tmp_path / "base.pt"
    assert main([*args, "--base", str(base), "--reading-out", str(base)]) == 2
    assert "that is --base itself" in capsys.readouterr().err
    assert shipped.stat().st_mtime_ns == before and not (shipped.parent / "v.npz").exists()
