"""Traffic signals as model input (``ModelConfig.signal_input``): the map chunks of a signal-controlled
lane carry its state at the window's first step, in training windows and in the sampler's windows alike;
a checkpoint extended with the input starts as it was; only that extension is accepted by ``--init``."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import straight_road_scene, tiny_checkpoint, tiny_config

from trajeglish_env.checkpoint import CheckpointError, check_init, load_checkpoint, load_into, save_checkpoint
from trajeglish_env.model import TrajeglishModel
from trajeglish_env.model.map_chunks import chunk_map, nearest_chunks, signal_classes
from trajeglish_env.sampler.config import SamplingConfig
from trajeglish_env.sampler.engine import RolloutEngine
from trajeglish_env.scenario import Scenario, SignalState
from trajeglish_env.scenario_io import save_scenarios
from trajeglish_env.training.dataset import WindowConfig, make_window
from trajeglish_env.training.train import TrainConfig, train

sumo = pytest.importorskip("trajeglish_env.sources.sumo")


@pytest.fixture(scope="module")
def grid_scene() -> Scenario:
    """A SUMO grid scene with traffic lights (their states change during the scene)."""
    try:
        run = sumo.simulate_shard(("grid",), 3, 0, 4)
    except sumo.SumoNotAvailableError as error:
        pytest.skip(str(error))
    scenes = [s for s in sumo.cut_scenes(run, 3, 0, 4) if len(s.signal_lane_id)]
    assert scenes, "the grid network has traffic lights"
    return max(scenes, key=lambda s: len(np.unique(s.signal_state)))


def test_chunks_of_a_controlled_lane_carry_its_signal(grid_scene: Scenario) -> None:
    sc = grid_scene
    chunks = chunk_map(sc, 20)
    lane_of = {int(i): j for j, i in reversed(list(enumerate(sc.signal_lane_id.tolist())))}
    controlled = np.isin(sc.map_id[chunks.polyline], sc.signal_lane_id)
    assert controlled.any() and (chunks.signal[~controlled] == -1).all()
    want = [lane_of[int(i)] for i in sc.map_id[chunks.polyline[controlled]]]
    assert np.array_equal(chunks.signal[controlled], want)
    seen = set()
    for t in range(sc.num_steps):
        got = signal_classes(sc, chunks, t)
        state = sc.signal_state[t, chunks.signal[controlled]]
        stop = np.isin(state, [SignalState.STOP, SignalState.ARROW_STOP, SignalState.FLASHING_STOP])
        go = np.isin(state, [SignalState.GO, SignalState.ARROW_GO])
        assert (got[~controlled] == 0).all()
        assert (got[controlled][stop] == 1).all() and (got[controlled][go] == 3).all()
        seen |= set(np.unique(got[controlled]).tolist())
    assert {1, 3} <= seen  # red and green both occur in the scene
    assert np.array_equal(signal_classes(sc, chunks, 10_000), signal_classes(sc, chunks, sc.num_steps - 1))
    plain = straight_road_scene(4, 20)
    assert not signal_classes(plain, chunk_map(plain, 20), 3).any()  # a scene without signals


def test_training_windows_carry_the_signals_of_their_first_step(grid_scene: Scenario) -> None:
    cfg = WindowConfig(max_agents=8, steps=16, max_polylines=64, points_per_polyline=20)
    chunks = chunk_map(grid_scene, cfg.points_per_polyline)
    found = 0
    for seed in range(6):
        w = make_window(grid_scene, cfg, np.random.default_rng(seed))
        signal = signal_classes(grid_scene, chunks, int(w["start"]))
        *_, want = nearest_chunks(chunks, w["frame"], cfg.max_polylines, cfg.map_radius, signal)
        assert np.array_equal(w["map_signal"], want)
        found += int((w["map_signal"] > 0).sum())
    assert found > 0


def extended(ckpt_model: TrajeglishModel) -> TrajeglishModel:
    """A copy of a model with the signal input added (its weights loaded as ``train --init`` does)."""
    model = TrajeglishModel(dataclasses.replace(ckpt_model.cfg, signal_input=True)).eval()
    ckpt = tiny_checkpoint()
    load_into(model, dataclasses.replace(ckpt, model=ckpt_model))
    return model


def test_a_model_extended_with_the_signal_input_starts_as_it_was() -> None:
    from test_model import random_scene

    base = tiny_checkpoint().model
    model = extended(base)
    scene, tokens = random_scene(base.cfg, b=2)
    assert scene.map_signal.any()
    with torch.no_grad():
        torch.testing.assert_close(model(scene, tokens), base(scene, tokens), rtol=0, atol=0)
        model.encoder.polylines.signal.weight[1:] = torch.randn(3, base.cfg.d_model)
        red = dataclasses.replace(scene, map_signal=torch.ones_like(scene.map_signal))
        green = dataclasses.replace(scene, map_signal=torch.full_like(scene.map_signal, 3))
        none = dataclasses.replace(scene, map_signal=torch.zeros_like(scene.map_signal))
        assert (model(red, tokens) - model(green, tokens)).abs().max() > 1e-3
        torch.testing.assert_close(model(none, tokens), base(none, tokens), rtol=0, atol=0)  # class 0: none
    assert model.encoder.polylines.signal.weight[0].abs().max() == 0


def test_sampler_windows_read_the_signals_only_with_the_input(
    grid_scene: Scenario, monkeypatch: pytest.MonkeyPatch
) -> None:
    import trajeglish_env.sampler.windows as windows

    seen: dict[bool, list[torch.Tensor]] = {True: [], False: []}
    engines: list[RolloutEngine] = []
    steps: list[tuple[int, int]] = []  # (step the signals were read at, the engine's step then)

    def classes_at(sc, chunks, step):  # noqa: ANN001, ANN202
        steps.append((step, int(engines[-1].now[0])))
        return signal_classes(sc, chunks, step)

    monkeypatch.setattr(windows, "signal_classes", classes_at)
    for flag in (False, True):
        ckpt = tiny_checkpoint()
        model = extended(ckpt.model) if flag else ckpt.model
        original = model.encode_into

        def record(cache, scene, original=original, flag=flag):  # noqa: ANN001, ANN202
            seen[flag].append(scene.map_signal.clone())
            return original(cache, scene)

        model.encode_into = record  # type: ignore[method-assign]
        engines.append(
            RolloutEngine(
                dataclasses.replace(ckpt, model=model),
                grid_scene,
                1,
                20,
                grid_scene.valid[:, grid_scene.current_index].copy(),
                config=SamplingConfig(seed=0, guard=False),
            )
        )
        engines[-1].run()
    assert seen[False] and all(not s.any() for s in seen[False])
    assert any(s.any() for s in seen[True])
    # read at each window's first step (as training reads them), once per rebuild, not at the present step
    prime = engines[-1].prime
    assert len({now for _, now in steps}) >= 3
    assert all(step == now - prime for step, now in steps), (steps, prime)


def test_init_accepts_adding_the_signal_input_and_nothing_else(tmp_path: Path) -> None:
    torch.manual_seed(0)
    vocabulary = tiny_checkpoint().vocabulary
    start = save_checkpoint(tmp_path / "start.pt", TrajeglishModel(tiny_config()), vocabulary)
    ckpt = load_checkpoint(start)
    with_input = dataclasses.replace(tiny_config(), signal_input=True)
    check_init(ckpt, with_input, ckpt.vocabulary)  # adding the input is fine
    scenes = tmp_path / "scenes"
    save_scenarios(scenes / "a.scn.npz", [straight_road_scene(5, 40, seed=s) for s in range(3)])
    quick = TrainConfig(steps=1, batch_size=2, lr=1e-12, warmup_steps=1, val_fraction=0.0, num_workers=0)
    result = train(scenes, tmp_path / "run", with_input, quick, ckpt.vocabulary, progress=False, init=start)
    tuned = load_checkpoint(result["checkpoint"])
    assert tuned.config.signal_input and not ckpt.config.signal_input
    for name, value in ckpt.model.state_dict().items():  # every old weight carried over
        torch.testing.assert_close(tuned.model.state_dict()[name], value, rtol=1e-6, atol=1e-9)
    with pytest.raises(CheckpointError, match="signal_input True \\(checkpoint\\) vs False"):
        check_init(tuned, tiny_config(), ckpt.vocabulary)  # removing it is not
    with pytest.raises(CheckpointError, match="d_model"):
        check_init(ckpt, dataclasses.replace(with_input, d_model=64), ckpt.vocabulary)
    with pytest.raises(TypeError, match="signal_input must be a bool"):
        dataclasses.replace(tiny_config(), signal_input=1)


@pytest.mark.parametrize("scale", [1.0, 25.0])
def test_the_signal_embedding_learns_at_its_own_rate(
    grid_scene: Scenario, tmp_path: Path, scale: float
) -> None:
    """One AdamW step moves each element by about lr (its first update is m / sqrt(v) = +-1): the signal
    embedding by ``lr * signal_lr_scale``, the others by ``lr``; class 0 (no signal) stays zero."""
    save_scenarios(tmp_path / "grid.scn.npz", [grid_scene])
    base = dataclasses.replace(tiny_config(), max_polylines=64)
    cfg = dataclasses.replace(base, signal_input=True)
    lr = 1e-4
    quick = TrainConfig(
        steps=1, batch_size=4, lr=lr, warmup_steps=1, val_fraction=0.0, num_workers=0, signal_lr_scale=scale
    )
    start = save_checkpoint(tmp_path / "start.pt", TrajeglishModel(base), tiny_checkpoint().vocabulary)
    result = train(tmp_path / "grid.scn.npz", tmp_path / "run", cfg, quick, progress=False, init=start)
    weights = load_checkpoint(result["checkpoint"]).model.encoder.polylines.signal.weight.detach()
    assert weights[0].abs().max() == 0
    moved = weights[1:].abs().amax(1)
    assert (moved > 0).any()  # the windows saw signals
    torch.testing.assert_close(moved[moved > 0].max(), torch.tensor(lr * scale), rtol=0.02, atol=0)
    with pytest.raises(ValueError, match="signal_lr_scale must be > 0"):
        TrainConfig(signal_lr_scale=0.0)


def test_nll_reports_what_the_signals_are_worth(grid_scene: Scenario, tmp_path: Path) -> None:
    from trajeglish_env.training.density import evaluate_nll

    save_scenarios(tmp_path / "grid.scn.npz", [grid_scene])
    ckpt = tiny_checkpoint()
    model = extended(ckpt.model)
    with_input = dataclasses.replace(ckpt, model=model)
    result = evaluate_nll({"plain": ckpt, "signals": with_input}, tmp_path, windows=8)
    assert "without_signals" not in result["models"]["plain"]
    off = result["models"]["signals"]["without_signals"]
    assert off["nll"] == pytest.approx(result["models"]["signals"]["nll"], abs=1e-6)  # zero embedding: unused
    assert off["red_windows"]["tokens"] > 0
    with torch.no_grad():
        model.encoder.polylines.signal.weight[1:] = 3 * torch.randn(3, model.cfg.d_model)
    moved = evaluate_nll({"signals": with_input}, tmp_path, windows=8)["models"]["signals"]
    assert abs(moved["nll"] - moved["without_signals"]["nll"]) > 1e-3
    assert moved["without_signals"]["nll"] == pytest.approx(off["nll"], abs=1e-6)  # signals off: as before
