"""Tokenizer coverage (issue 15, item 5): a vocabulary fitted with the motion-envelope cover follows every
motion the env's vehicle limits allow within 5 cm; the shipped one does not (documented gap); drift
warnings for held-out tracks and for external agents of the env."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from helpers import straight_road_scene
from test_tokenizer_fit import _scenes

from trajeglish_env.checkpoint import Checkpoint
from trajeglish_env.model import TrajeglishModel, preset
from trajeglish_env.scenario import AgentKind
from trajeglish_env.tokenizer import MotionVocabulary, fit_vocabulary, load_default_tokenizer, tokenize
from trajeglish_env.tokenizer.coverage import (
    DEFAULT_ENVELOPES,
    Envelope,
    envelope_cover,
    envelope_error,
    envelope_transitions,
    stress_error,
    stress_tracks,
    unicycle_step,
)
from trajeglish_env.tokenizer.data import TrajectorySet
from trajeglish_env.tokenizer.discretization import evaluate_vocabulary

DT = 0.1
CAR = np.array([4.8, 2.0])
VEHICLE = DEFAULT_ENVELOPES[AgentKind.VEHICLE]
FULL = {"min_data_share": 0.02}  # the whole envelope at its 4.5 cm radius (374 of 384 vehicle templates)


def _track(speed: np.ndarray, curvature: np.ndarray | float) -> np.ndarray:
    """``xyh [T,3]`` of a unicycle with ``speed [T]`` (m/s) and ``curvature`` (1/m) from the origin."""
    curvature = np.broadcast_to(curvature, speed.shape)
    steps = unicycle_step(speed[:-1], np.diff(speed) / DT, curvature[:-1], DT)
    xyh = np.zeros((len(speed), 3))
    for t, (dx, dy, dh) in enumerate(steps):
        x, y, h = xyh[t]
        xyh[t + 1] = [x + dx * np.cos(h) - dy * np.sin(h), y + dx * np.sin(h) + dy * np.cos(h), h + dh]
    return xyh


def _envelope_tracks() -> dict[str, np.ndarray]:
    """The motions of the issue: 40 m/s straight, 40 m/s braking to a stop, reversing at 3 m/s, a tight turn
    at low speed and lateral-accel-limited curves at high speed (5 s each)."""
    t = np.arange(50)
    tight = VEHICLE.min_turn_radius
    return {
        "40 m/s straight": _track(np.full(50, 40.0), 0.0),
        "40 m/s braking to a stop": _track(np.maximum(40.0 - 8.0 * DT * t, 0.0), 0.0),
        "reversing at 3 m/s": _track(np.full(50, -3.0), 0.02),
        "tight turn at 5 m/s": _track(np.full(50, 5.0), 1.0 / tight),
        "8 m/s^2 curve at 30 m/s": _track(np.full(50, 30.0), -8.0 / 30.0**2),
        "8 m/s^2 curve at 40 m/s": _track(np.full(50, 40.0), 8.0 / 40.0**2),
        "accelerating 0 to 10 m/s in a turn": _track(np.minimum(4.0 * DT * t, 10.0), 1.0 / 12.5),
    }


def _max_error(vocab: MotionVocabulary, xyh: np.ndarray) -> float:
    tok = tokenize(vocab, xyh[None], np.ones((1, len(xyh)), bool), CAR[None], np.zeros(1, np.int64))
    return float(np.nanmax(tok.error))


@pytest.fixture(scope="module")
def small_fit() -> TrajectorySet:
    return TrajectorySet.from_scenarios(_scenes(20, 25, 40, 0, (AgentKind.VEHICLE,), max_speed=12.0))


@pytest.fixture(scope="module")
def covered(small_fit: TrajectorySet) -> MotionVocabulary:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the other classes borrow the vehicle templates
        return fit_vocabulary("k-disks", 384, small_fit, seed=0, trials=1, epsilon_scales=(1.0,), **FULL)


def test_envelope_cover_reaches_every_envelope_transition() -> None:
    for kind, env in DEFAULT_ENVELOPES.items():
        cover = envelope_cover(kind, DT)
        assert len(cover) < 384
        assert envelope_error(cover, kind, DT) <= env.radius + 1e-9
    points = envelope_transitions(VEHICLE, DT)
    assert points[:, 0].max() > 4.0 - 1e-6 and points[:, 0].min() < -0.4 + 1e-6  # 40 m/s and reversing
    with pytest.raises(ValueError, match="min_speed"):
        Envelope(1.0, 10.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0)
    with pytest.raises(ValueError, match="dt must be > 0"):
        envelope_transitions(VEHICLE, 0.0)


@pytest.fixture(scope="module")
def fine(small_fit: TrajectorySet) -> MotionVocabulary:
    """The recipe that meets the 5 cm target: V = 1024, the vehicle cover within 3 cm, a fifth for data."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the other classes borrow the vehicle templates
        return fit_vocabulary(
            "k-disks", 1024, small_fit, seed=0, trials=1, epsilon_scales=(1.0,), min_data_share=0.2,
            cover_radius=0.03,
        )  # fmt: skip


@pytest.mark.parametrize("name", list(_envelope_tracks()))
def test_fine_vocabulary_follows_envelope_motions_within_5cm(fine: MotionVocabulary, name: str) -> None:
    """Issue 15's target: a greedy tokenizer's error is not bounded by the cover's one-step radius (a
    state that lags at a limit is tokenized from off the envelope surface), so the cover is made within
    3 cm, and the lattice's catch-up band keeps the lag from growing (measured: 2.6-4.0 cm)."""
    cov = fine.metadata["coverage"]["vehicle"]
    assert fine.size == 1024 and cov["radius_m"] == 0.03 and cov["envelope"]["radius"] == 0.03
    assert cov["max_error_m"] <= 0.03 and 600 < cov["templates"] <= 1024 - 0.2 * 1024
    assert _max_error(fine, _envelope_tracks()[name]) < 0.05


def test_full_cover_at_384_tokens_stays_near_5cm(covered: MotionVocabulary, small_fit: TrajectorySet) -> None:
    """At V = 384 the cover's 4.5 cm radius leaves too little room: six of the seven tracks within 5 cm,
    braking from 40 m/s to a stop ends at 5.1 cm."""
    assert covered.size == 384
    cov = covered.metadata["coverage"]["vehicle"]
    assert cov["max_error_m"] <= 0.045 and cov["envelope"]["max_speed"] == 40.0 and cov["templates"] < 384
    errors = {name: _max_error(covered, xyh) for name, xyh in _envelope_tracks().items()}
    assert max(errors.values()) < 0.055 and sum(e < 0.05 for e in errors.values()) >= 6, errors
    with pytest.raises(ValueError, match="cover_radius"):
        fit_vocabulary("k-disks", 384, small_fit, cover_radius=0.001)


def _random_envelope_tracks(count: int, seed: int) -> list[np.ndarray]:
    """Held-out tracks inside the vehicle envelope (not :func:`stress_tracks`'s grid): a random start speed,
    speed change of up to 8 m/s^2 (reversing ones keep their speed) and a random share of the turn limit."""
    rng = np.random.default_rng(seed)
    tracks = []
    for _ in range(count):
        v0 = rng.uniform(VEHICLE.min_speed, VEHICLE.max_speed)
        speed = np.full(50, v0) if v0 < 0 else np.clip(v0 + rng.uniform(-8, 8) * DT * np.arange(50), 0, 40)
        mean = np.maximum(np.abs(speed), 1e-3)
        limit = np.minimum(1.0 / VEHICLE.min_turn_radius, VEHICLE.max_lateral_accel / mean**2)
        tracks.append(_track(speed, rng.uniform(-1, 1) * limit))
    return tracks


def test_tokenized_tracks_do_not_drift_away_at_the_limits(
    small_fit: TrajectorySet, covered: MotionVocabulary, fine: MotionVocabulary
) -> None:
    """Envelope tracks stay near their tokenized states: the lattice's catch-up band (templates a little
    faster and turning a little harder than the limits). Without it, tracks accelerating through a curve
    at the lateral limit fell metres behind (measured: up to 2.9 m with the full cover, 2.1 m at the
    default share on these tracks; stress tracks 2.1 m and 11.6 m)."""
    tracks = _random_envelope_tracks(60, seed=7)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        default = fit_vocabulary("k-disks", 384, small_fit, seed=0, trials=1, epsilon_scales=(1.0,))
    full = covered
    worst = {
        name: max(_max_error(v, x) for x in tracks) for name, v in (("default", default), ("full", full))
    }
    assert worst["full"] < 0.07 and worst["default"] < 0.11, worst  # measured 6.8 and 10.1 cm
    for vocab, bound in ((full, 0.075), (default, 0.3)):  # measured 7.1 and 26.8 cm
        stress = vocab.metadata["coverage"]["vehicle"]["stress_max_error_m"]
        assert stress < bound
        assert stress == pytest.approx(stress_error(vocab, AgentKind.VEHICLE, DT), abs=1e-5)
    shipped = load_default_tokenizer()
    assert max(_max_error(shipped, x) for x in tracks[:20]) > 5.0  # no 40 m/s, no reversing: metres behind
    xyh = stress_tracks(VEHICLE, DT)
    assert xyh.shape[1:] == (50, 3) and np.isfinite(xyh).all()
    # the family reaches both speed limits and both turn directions
    step = np.linalg.norm(np.diff(xyh[..., :2], axis=1), axis=-1).max(1)
    assert step.max() == pytest.approx(4.0, abs=0.01) and np.diff(xyh[..., 2], axis=1).min() < 0


def test_shipped_vocabulary_cannot_follow_40_mps() -> None:
    """Documents the gap of the shipped vocabulary (templates up to ~3.04 m a step, no reversing)."""
    shipped = load_default_tokenizer()
    tracks = _envelope_tracks()
    assert _max_error(shipped, tracks["40 m/s straight"]) > 0.05
    assert envelope_error(shipped.for_kind(AgentKind.VEHICLE), AgentKind.VEHICLE, DT) > 0.5


def test_default_share_leaves_half_for_data(small_fit: TrajectorySet) -> None:
    with pytest.warns(UserWarning, match="class 'vehicle' needs more than 192 of 384 templates"):
        vocab = fit_vocabulary("k-disks", 384, small_fit, seed=0, trials=1, epsilon_scales=(1.0,))
    cov = vocab.metadata["coverage"]["vehicle"]
    assert cov["templates"] <= 192 and 0.045 < cov["radius_m"] < 0.07 and cov["max_error_m"] < 0.07
    # one step within 7 cm; along 5 s at 40 m/s the coarser cover lags a little (measured 5.7 cm; 37.5 cm
    # before the lattice reached past the speed limit; shipped: 47 m)
    assert _max_error(vocab, _envelope_tracks()["40 m/s straight"]) < 0.08
    with pytest.raises(ValueError, match="min_data_share"):
        fit_vocabulary("k-disks", 384, small_fit, trials=1, epsilon_scales=(1.0,), min_data_share=1.0)


def test_fitting_with_coverage_is_deterministic(small_fit: TrajectorySet, covered: MotionVocabulary) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        again = fit_vocabulary("k-disks", 384, small_fit, seed=0, trials=1, epsilon_scales=(1.0,), **FULL)
        plain = fit_vocabulary(
            "k-disks", 384, small_fit, seed=0, trials=1, epsilon_scales=(1.0,), coverage=False
        )
    np.testing.assert_array_equal(again.templates, covered.templates)
    assert again.metadata == covered.metadata
    assert "coverage" not in plain.metadata
    assert _max_error(plain, _envelope_tracks()["40 m/s straight"]) > 0.05


def test_drift_warning_names_the_track(covered: MotionVocabulary) -> None:
    fast = _scenes(2, 3, 30, 5, (AgentKind.VEHICLE,))
    for sc in fast:  # agent 1 of every scene drives at 40 m/s
        sc.xyh[1] = _track(np.full(sc.num_steps, 40.0), 0.0) + [*sc.xyh[1, 0, :2], 0.0]
    data = TrajectorySet.from_scenarios(fast)
    shipped = load_default_tokenizer()
    with pytest.warns(UserWarning, match=r"tokenizer drift: .*scene \d agent 1 \(\d+\.\d+ m\)"):
        report = evaluate_vocabulary(shipped, data, collisions=False)
    drift = report["drift"]["per_class"]["vehicle"]
    assert drift["max_cm"] > 5 and drift["drift_share"] >= 2 / 6
    assert report["envelope_max_cm"]["vehicle"] > 50
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        calm = evaluate_vocabulary(covered, data, collisions=False, drift_tolerance=0.5)
    assert calm["drift"]["tracks_drifting"] == 0


def test_env_warns_once_when_an_external_agent_outruns_the_shipped_vocabulary() -> None:
    import torch

    from trajeglish_env.sampler.config import SamplingConfig
    from trajeglish_env.sampler.engine import RolloutEngine

    vocab = load_default_tokenizer()
    torch.manual_seed(0)
    model = TrajeglishModel(preset("tiny", vocab_size=vocab.size, variant="trajeglish")).eval()
    ckpt = Checkpoint(model=model, vocabulary=vocab, training={})
    scene = straight_road_scene(4, 30)
    external = np.zeros(scene.num_agents, bool)
    external[scene.sdc] = True
    active = scene.valid[:, scene.current_index]
    engine = RolloutEngine(ckpt, scene, 1, 6, active & ~external, external, config=SamplingConfig(seed=1))
    ego = scene.xyh[scene.sdc, engine.t].copy()
    with pytest.warns(
        UserWarning,
        match=rf"external agent vehicle_{scene.track_id[scene.sdc]} of scene .*\d+\.\d\d m from its true",
    ) as rec:
        for _ in range(5):
            while (agent := engine.advance()) is not None:
                ego = ego + [4.0 * np.cos(ego[2]), 4.0 * np.sin(ego[2]), 0.0]  # 40 m/s
                engine.supply(agent, ego[None])
    assert sum("external agent" in str(w.message) for w in rec) == 1  # once per episode and agent
