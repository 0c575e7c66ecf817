"""Tokenizer fitting: k-disks, the paper's baselines, borrowing, file format, directory fit/eval and the
shipped asset."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest

from trajeglish_env.scenario import AgentKind, Scenario
from trajeglish_env.scenario_io import save_scenarios
from trajeglish_env.tokenizer import (
    MotionVocabulary,
    VocabularyError,
    evaluate_directory,
    fit_from_directory,
    fit_vocabulary,
    load_default_tokenizer,
    tokenize,
)
from trajeglish_env.tokenizer.baselines import kmeans_templates, xy_grid_templates, xyh_grid_templates
from trajeglish_env.tokenizer.collisions import boxes_overlap, collision_flags
from trajeglish_env.tokenizer.data import TrajectorySet
from trajeglish_env.tokenizer.discretization import evaluate_vocabulary
from trajeglish_env.tokenizer.distance import corner_distance
from trajeglish_env.tokenizer.kdisks import default_epsilon, sample_kdisks
from trajeglish_env.tokenizer.synthetic import synthetic_trajectories

UNIT = np.array([1.0, 1.0])


def _scenes(
    count: int,
    agents: int,
    steps: int,
    seed: int,
    kinds: tuple[AgentKind, ...],
    max_speed: float | None = None,
) -> list[Scenario]:
    rng = np.random.default_rng(seed)
    out = []
    for i in range(count):
        xyh, valid, size, kind = synthetic_trajectories(agents, steps, rng, kinds=kinds, max_speed=max_speed)
        out.append(
            Scenario.from_arrays(xyh, valid, size, kind, scenario_id=f"syn{seed}-{i}", source="synthetic")
        )
    return out


@pytest.fixture(scope="module")
def vehicle_set() -> TrajectorySet:
    return TrajectorySet.from_scenarios(_scenes(40, 25, 50, 0, (AgentKind.VEHICLE,), max_speed=12.0))


# ---------------------------------------------------------------- baselines
@pytest.mark.parametrize(("v", "n_xy", "n_h"), [(128, 6, 4), (256, 7, 6), (384, 8, 7), (512, 9, 8)])
def test_xyh_grid_shapes(v: int, n_xy: int, n_h: int) -> None:
    grid = xyh_grid_templates(v)
    assert grid.shape == (n_xy * n_xy * n_h, 3)
    for axis, (lo, hi), n in zip(
        range(3), [(-0.3, 3.5), (-0.2, 0.2), (-0.1, 0.1)], [n_xy, n_xy, n_h], strict=True
    ):
        np.testing.assert_allclose(np.unique(grid[:, axis]), np.linspace(lo, hi, n), atol=1e-12)


@pytest.mark.parametrize(("v", "n"), [(128, 12), (256, 16), (384, 20), (512, 23)])
def test_xy_grid_takes_heading_of_nearest_transition(v: int, n: int) -> None:
    transitions = np.array([[0.0, 0.0, 0.05], [3.0, 0.1, -0.07], [1.5, -0.15, 0.02]])
    grid = xy_grid_templates(v, transitions)
    assert grid.shape == (n * n, 3)
    near = np.argmin(((grid[:, None, :2] - transitions[None, :, :2]) ** 2).sum(-1), 1)
    np.testing.assert_array_equal(grid[:, 2], transitions[near, 2])
    with pytest.raises(ValueError, match="vocabulary sizes"):
        xy_grid_templates(300, transitions)


def test_kmeans_is_deterministic_and_sized(vehicle_set: TrajectorySet) -> None:
    trans = vehicle_set.transitions(AgentKind.VEHICLE)[:5000]
    a = kmeans_templates(trans, 64, np.random.default_rng(3), iterations=10)
    b = kmeans_templates(trans, 64, np.random.default_rng(3), iterations=10)
    assert a.shape == (64, 3) and np.array_equal(a, b)
    assert np.abs(a[:, 2]).max() <= np.pi


# ---------------------------------------------------------------- k-disks
def test_kdisks_templates_are_epsilon_apart(vehicle_set: TrajectorySet) -> None:
    trans = vehicle_set.transitions(AgentKind.VEHICLE)
    eps = default_epsilon(128)
    assert eps == 0.035 and default_epsilon(512) == 0.030
    templates = sample_kdisks(trans, 128, eps, np.random.default_rng(0))
    assert templates.shape == (128, 3)
    d = corner_distance(templates[:, None], templates[None], UNIT)
    np.fill_diagonal(d, np.inf)
    assert d.min() > eps
    # Every template is an observed transition.
    assert np.isin(templates.view([("", float)] * 3), trans.view([("", float)] * 3)).all()
    again = sample_kdisks(trans, 128, eps, np.random.default_rng(0))
    assert np.array_equal(templates, again)


def test_kdisks_with_little_data_shrinks_epsilon_or_fails() -> None:
    rng = np.random.default_rng(1)
    few = rng.normal(0, 0.01, (40, 3))  # all within a few cm: covered by one 3.5 cm disk or so
    templates = sample_kdisks(few, 30, 0.035, rng)
    assert len(np.unique(templates, axis=0)) == 30
    with pytest.raises(ValueError, match="only 40 distinct transitions"):
        sample_kdisks(few, 41, 0.035, rng)


# ---------------------------------------------------------------- method comparison and borrowing
def test_error_ordering_kdisks_best(vehicle_set: TrajectorySet) -> None:
    fit, heldout = vehicle_set.split()
    errors = {}
    for method in ("xyh-grid", "xy-grid", "k-means", "k-disks"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            vocab = fit_vocabulary(method, 128, fit, heldout, seed=0, trials=2, coverage=False)
        errors[method] = evaluate_vocabulary(vocab, heldout, collisions=False)["mean_cm"]
    assert errors["k-disks"] == min(errors.values()), errors
    assert errors["k-disks"] < 0.6 * min(v for k, v in errors.items() if k != "k-disks"), errors


def test_class_without_data_borrows_vehicle_templates(vehicle_set: TrajectorySet) -> None:
    with pytest.warns(UserWarning) as record:
        vocab = fit_vocabulary(
            "k-disks", 128, vehicle_set, None, seed=0, trials=1, epsilon_scales=(1.0,), coverage=False
        )
    messages = sorted(str(w.message) for w in record)
    assert len(messages) == 2 and "class 'cyclist' has only 0 transitions" in messages[0]
    assert (
        "class 'pedestrian' has only 0 transitions" in messages[1]
        and "uses the vehicle templates" in messages[1]
    )
    assert vocab.metadata["borrowed"] == {"pedestrian": "vehicle", "cyclist": "vehicle"}
    assert vocab.metadata["epsilon_m"] == {"vehicle": 0.035}  # exactly the paper's procedure
    np.testing.assert_array_equal(vocab.for_kind(AgentKind.CYCLIST), vocab.for_kind(AgentKind.VEHICLE))
    tiny = vehicle_set.select_scenes(np.arange(vehicle_set.num_scenes) < 1)
    with pytest.raises(ValueError, match="vehicle class has .* transitions"):
        fit_vocabulary("k-disks", 384, tiny)


# ---------------------------------------------------------------- file format
def test_vocabulary_save_load_and_state(tmp_path: Path) -> None:
    templates = np.random.default_rng(0).normal(size=(3, 16, 3))
    vocab = MotionVocabulary(templates, method="k-disks", metadata={"seed": 3, "borrowed": {}})
    path = vocab.save(tmp_path / "tok.npz")
    loaded = MotionVocabulary.load(path)
    assert loaded.equals(vocab) and loaded.size == 16
    state = vocab.to_state()
    assert MotionVocabulary.from_state(state).equals(vocab)
    assert all(isinstance(v, (np.ndarray, str, int)) for v in state.values())
    with pytest.raises(VocabularyError, match="version 99 is not supported"):
        MotionVocabulary.from_state({**state, "version": 99}, where="ckpt.pt")
    broken = tmp_path / "broken.npz"
    broken.write_bytes(path.read_bytes()[:100])
    with pytest.raises(VocabularyError, match=f"{broken}: not a readable tokenizer file"):
        MotionVocabulary.load(broken)
    other = tmp_path / "other.npz"
    np.savez(other, templates=templates)
    with pytest.raises(VocabularyError, match="lacks"):
        MotionVocabulary.load(other)
    with pytest.raises(VocabularyError, match=r"templates must be an array \[3 classes, V, 3"):
        MotionVocabulary(templates[:2])
    bad = templates.copy()
    bad[1, 4, 0] = np.nan
    with pytest.raises(VocabularyError, match="template 4 of class pedestrian is not finite"):
        MotionVocabulary(bad)


def test_shipped_default_tokenizer() -> None:
    vocab = load_default_tokenizer()
    assert vocab.size == 384 and vocab.method == "k-disks" and vocab.templates.shape == (3, 384, 3)
    assert "data" in vocab.metadata and "fit_transitions" in vocab.metadata
    assert vocab.metadata["borrowed"] == {}  # every class was fitted on its own data
    # A parked vehicle is represented exactly (the zero transition is the most common one) and a vehicle
    # driving straight at 10 m/s stays within a few centimetres (templates are >= 3.5 cm apart).
    for speed, worst in ((0.0, 1e-12), (1.0, 0.05)):
        xyh = np.zeros((1, 30, 3))
        xyh[0, :, 0] = np.arange(30) * speed
        tok = tokenize(vocab, xyh, np.ones((1, 30), bool), np.array([[4.5, 2.0]]), np.zeros(1, int))
        assert np.nanmax(tok.error) <= worst


# ---------------------------------------------------------------- collisions
def test_boxes_overlap_cases() -> None:
    a = np.array([[0.0, 0.0, 0.0]] * 4)
    b = np.array([[4.4, 0.0, 0.0], [4.6, 0.0, 0.0], [0.0, 2.1, 0.0], [4.5, 4.5, np.pi / 4]])
    size = np.tile([4.5, 2.0], (4, 1))
    np.testing.assert_array_equal(boxes_overlap(a, size, b, size), [True, False, False, False])
    xyh = np.zeros((3, 2, 3))
    xyh[1, :, 0] = [1.0, 10.0]
    xyh[2, :, 0] = [20.0, 10.5]
    flags = collision_flags(xyh, np.ones((3, 2), bool), size[:3], np.array([0, 0, 0]))
    np.testing.assert_array_equal(flags, [[True, False], [True, True], [False, True]])
    assert not collision_flags(xyh, np.ones((3, 2), bool), size[:3], np.array([0, 1, 2])).any()


# ---------------------------------------------------------------- directory fit / eval (CLI back ends)
def test_fit_and_evaluate_directory(tmp_path: Path) -> None:
    data = tmp_path / "scenes"
    scenes = _scenes(16, 30, 40, 5, tuple(AgentKind), max_speed=12.0)
    save_scenarios(data / "a.scn.npz", scenes[:8])
    save_scenarios(data / "b.scn.npz", scenes[8:])
    result = fit_from_directory(data, vocab_size=128, seed=1, out=tmp_path / "tok.npz", trials=1)
    json.dumps(result)
    assert result["templates"] == 128 and Path(result["out"]).is_file()
    assert result["heldout"]["mean_cm"] > 0 and result["borrowed"] == {}
    vocab = MotionVocabulary.load(result["out"])
    assert vocab.metadata["data"] == [str(data)]
    summary = evaluate_directory(
        data,
        vocab_sizes=(128,),
        methods=("xyh-grid", "k-disks"),
        out_dir=tmp_path / "ev",
        trials=1,
        heldout_every=2,
        coverage=False,  # the paper's procedure (coverage: tests/test_tokenizer_coverage.py)
    )
    json.dumps(summary)
    assert set(summary["table_cm"]) == {"xyh-grid", "k-disks"}
    assert summary["table_cm"]["k-disks"]["128"] < summary["table_cm"]["xyh-grid"]["128"]
    assert Path(summary["plot"]).is_file()
    res = summary["results"][1]
    assert set(res["frac_above_cm"]) == {"2", "5", "10"}
    # boxes overlapping in the seeded synthetic tracks, before and after tokenization (the same pairs)
    assert res["collision_rate"] == {"raw": 0.00292, "tokenized": 0.00292}
    assert len(res["error_vs_length"]["mean_cm"]) == 39
