"""Batched simulation: a scene simulated among many gives exactly what it gives alone (engine rows, the
Gymnasium vector env, the batched parallel env and the SB3 VecEnv), and chunked decoding is exact."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from helpers import bundle_scene, tiny
from stable_baselines3 import PPO
from stable_baselines3.common.vec_env import DummyVecEnv

from trajeglish_env.env import EgoEnv, RewardConfig, TrajeglishNPC, parallel_env
from trajeglish_env.env.sb3 import SB3VecEnv
from trajeglish_env.env.scenes import load_bundle
from trajeglish_env.env.vector import BatchedEgoEnv, BatchedParallelEnv, auto_threads
from trajeglish_env.model.layers import (
    MIN_GEMM_ROWS,
    Attention,
    Linear,
    bucket_rows,
    invariant_linear,
    linear_compute,
)
from trajeglish_env.model.masks import teacher_inputs
from trajeglish_env.sampler import windows as windows_module
from trajeglish_env.sampler.config import SamplingConfig, native_bfloat16
from trajeglish_env.sampler.engine import BatchEngine, RowSpec, _row_blocks
from trajeglish_env.sampler.sampling import counter_uniform

SCENES = [
    "highway-merge-999000",
    "sumo-random-999000-0-0",
    "highway-exit-999001",
    "highway-roundabout-999001",
]
KEEP_GOING = RewardConfig(terminate_on_collision=False, terminate_on_offroad=False, terminate_on_goal=False)


def full_control(name: str, horizon: int = 12) -> RowSpec:
    sc = bundle_scene(name)
    return RowSpec(sc, horizon, sc.valid[:, sc.current_index].copy())


def run_rows(
    specs: list[RowSpec],
    seeds: list[int],
    dtype: torch.dtype,
    restart: tuple | None = None,
    compute: str = "float32",
) -> BatchEngine:
    """Run one engine with a row per spec; ``restart = (step, row, spec, seed)`` restarts a row mid-run."""
    # guarded rows: tests/test_guard.py
    config = SamplingConfig(temperature=1.0, guard=False, compute_dtype=compute)
    engine = BatchEngine(tiny(), len(specs), config, cache_dtype=dtype)
    for row, (spec, seed) in enumerate(zip(specs, seeds, strict=True)):
        engine.start_rows([row], spec, [seed])
    k = 0
    while engine.stepping.any():
        if restart is not None and k == restart[0]:
            engine.start_rows([restart[1]], restart[2], [restart[3]])
        engine.step()
        k += 1
    return engine


def row_view(engine: BatchEngine, row: int, spec: RowSpec) -> tuple[np.ndarray, np.ndarray]:
    n, T = spec.scenario.num_agents, spec.scenario.current_index + 1 + spec.horizon
    return engine.tokens[row, :n, : T - 1].copy(), engine.xyh[row, :n, :T].copy()


@pytest.mark.parametrize(
    ("dtype", "compute"),
    [(torch.float32, "float32"), (torch.bfloat16, "float32"), (torch.bfloat16, "bfloat16")],
)
def test_engine_rows_of_different_scenes_equal_their_solo_runs(
    dtype: torch.dtype, compute: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(windows_module, "ROW_BLOCK", 2)  # windows of the batch built in blocks of 2 rows
    specs = [full_control(name) for name in SCENES]
    seeds = [11, 12, 13, 14]
    solo = [
        row_view(run_rows([spec], [seed], dtype, compute=compute), 0, spec)
        for spec, seed in zip(specs, seeds, strict=True)
    ]
    # the same rows in another order, beside a duplicate of scene 0 with another seed
    order = [2, 0, 3, 1]
    rows, row_seeds = [specs[i] for i in order] + [specs[0]], [seeds[i] for i in order] + [99]
    batch = run_rows(rows, row_seeds, dtype, compute=compute)
    for row, i in enumerate(order):
        tokens, xyh = row_view(batch, row, specs[i])
        assert np.array_equal(tokens, solo[i][0]), f"{SCENES[i]}: tokens differ in the batch"
        assert np.array_equal(xyh, solo[i][1])
    assert (solo[1][0][:, 10:] >= 0).sum() > 100  # the 29-agent scene really sampled (several contexts)
    other, _ = row_view(batch, 4, specs[0])
    assert not np.array_equal(other, solo[0][0])  # another seed, another rollout


def test_row_blocks_split_runs_of_consecutive_rows() -> None:
    blocks = _row_blocks(np.array([0, 1, 2, 3, 4, 7, 9, 10]), 2)
    assert blocks == [slice(0, 2), slice(2, 4), slice(4, 5), slice(5, 6), slice(6, 8)]
    assert _row_blocks(np.array([5]), 8) == [slice(0, 1)]


def test_engine_row_restarted_mid_run_equals_a_fresh_run() -> None:
    specs = [full_control(SCENES[0], 20), full_control(SCENES[1], 20)]
    late = full_control(SCENES[2], 6)
    engine = run_rows(specs, [1, 2], torch.float32, restart=(5, 0, late, 7))
    fresh = run_rows([late], [7], torch.float32)
    assert np.array_equal(row_view(engine, 0, late)[0], row_view(fresh, 0, late)[0])
    untouched = run_rows([specs[1]], [2], torch.float32)
    assert np.array_equal(row_view(engine, 1, specs[1])[0], row_view(untouched, 0, specs[1])[0])


def test_chunked_decoding_equals_the_full_forward_pass() -> None:
    """decode_at with per-row positions and chunk lengths gives the teacher-forced logits."""
    model = tiny().model
    cfg = model.cfg
    a, t, b = cfg.max_agents, cfg.steps, 3
    g = torch.Generator().manual_seed(0)
    from trajeglish_env.model.network import SceneInputs

    scene = SceneInputs(
        agent_xyh=torch.randn(b, a, 3, generator=g) * 10,
        agent_size=torch.rand(b, a, 2, generator=g) + 1,
        agent_kind=torch.randint(0, 3, (b, a), generator=g),
        agent_mask=torch.ones(b, a, dtype=torch.bool),
        map_points=torch.randn(b, cfg.max_polylines, cfg.points_per_polyline, 2, generator=g) * 20,
        map_point_mask=torch.ones(b, cfg.max_polylines, cfg.points_per_polyline, dtype=torch.bool),
        map_kind=torch.randint(0, 20, (b, cfg.max_polylines), generator=g),
        map_mask=torch.ones(b, cfg.max_polylines, dtype=torch.bool),
        map_signal=torch.zeros(b, cfg.max_polylines, dtype=torch.long),
    )
    tokens = torch.randint(0, cfg.vocab_size, (b, a, t), generator=g)
    with torch.no_grad():
        full = model(scene, tokens).reshape(b, t * a, -1)  # [B, positions, V]
    ids = model.global_ids(tokens, scene.agent_kind[:, :, None]).transpose(1, 2).reshape(b, -1)
    carried, own = teacher_inputs(cfg.variant, ids, a)
    cache = model.empty_cache(b, torch.float32)
    agents = model.encode_into(cache, scene)
    rng = np.random.default_rng(0)
    done = np.zeros(b, dtype=np.int64)
    while (done < t * a).any():
        count = np.minimum(rng.integers(0, 5, b), t * a - done)  # rows advance by 0-4 positions per call
        n = max(1, int(count.max()))
        pos = np.minimum(done[:, None] + np.arange(n), t * a - 1)
        idx = torch.from_numpy(pos)
        hidden = model.decode_at(cache, agents, carried.gather(1, idx), own.gather(1, idx), done, count)
        for row in range(b):
            if count[row]:
                kind = scene.agent_kind[row, pos[row, : count[row]] % a]
                with torch.no_grad():
                    got = model.class_logits(hidden[row, : count[row]], kind)
                np.testing.assert_allclose(got, full[row, done[row] : done[row] + count[row]], atol=2e-5)
        done += count


def test_linear_layers_multiply_in_the_compute_dtype_at_inference_only() -> None:
    """Inside linear_compute(bfloat16) a Linear rounds inputs and weight to bfloat16 (float32 bias), per row
    whatever the rows beside it; with gradients on, or outside, it is the float32 layer; a changed weight
    (a training step) is converted again."""
    torch.manual_seed(0)
    layer = Linear(48, 64)
    x = torch.randn(200, 48)
    want = torch.nn.functional.linear(x.bfloat16(), layer.weight.bfloat16()).float() + layer.bias
    with torch.no_grad():
        plain = layer(x)
        with linear_compute(torch.bfloat16):
            fast = layer(x)
            alone = torch.cat([layer(x[i : i + 1]) for i in range(5)])
            with torch.enable_grad():
                trained = layer(x)
        assert torch.equal(layer(x), plain)
    assert torch.equal(fast, want) and torch.equal(alone, fast[:5]) and fast.dtype == torch.float32
    assert not torch.equal(fast, plain) and (fast - plain).abs().max() < 0.05
    assert torch.equal(trained.detach(), plain) and trained.requires_grad
    with torch.no_grad():
        layer.weight.mul_(2.0)
        with linear_compute(torch.bfloat16):
            doubled = layer(x)
    want = torch.nn.functional.linear(x.bfloat16(), layer.weight.bfloat16()).float() + layer.bias
    assert torch.equal(doubled, want)
    with torch.no_grad(), linear_compute(torch.bfloat16):  # a bfloat16 input: the same float32 result
        assert torch.equal(layer(x.bfloat16()), doubled) and layer(x.bfloat16()).dtype == torch.float32


def test_reduced_precision_rows_are_padded_to_few_buckets_without_changing_a_row() -> None:
    """Inside linear_compute(bfloat16) the rows are padded to buckets (oneDNN compiles a kernel per
    shape): every count of rows 1 .. 300 gives each row the numbers it has among 300, 1 .. 1,024 rows meet
    at most 41 shapes, and no bucket pads more than 1/8 beyond 32 rows."""
    torch.manual_seed(2)
    layer = Linear(48, 64)
    x = torch.randn(300, 48)
    with torch.no_grad(), linear_compute(torch.bfloat16):
        full = layer(x)
        for rows in range(1, 301):
            assert torch.equal(layer(x[:rows]), full[:rows]), rows
    buckets = [bucket_rows(r) for r in range(1, 1025)]
    assert len(set(buckets)) <= 41 and all(b >= r for r, b in zip(range(1, 1025), buckets, strict=True))
    assert all(b * 8 <= r * 9 for r, b in zip(range(33, 1025), buckets[32:], strict=True))
    assert bucket_rows(33) == 36 and bucket_rows(1000) == 1024 and bucket_rows(5) == MIN_GEMM_ROWS


def test_attention_over_a_bfloat16_cache_feeds_its_output_projection_without_a_round_trip() -> None:
    """With bfloat16 keys/values and bfloat16 linear layers, attention's output goes to the output
    projection in bfloat16: the very numbers of the float32 round trip (widening then rounding is exact)."""
    torch.manual_seed(1)
    attn = Attention(64, 4).eval()
    x, context = torch.randn(3, 7, 64), torch.randn(3, 11, 64)
    with torch.no_grad(), linear_compute(torch.bfloat16):
        k, v = (t.bfloat16() for t in attn.keys_values(context))
        got = attn.attend(x, k, v, None)
        q = attn.split(attn.q(x)).bfloat16()
        y = torch.nn.functional.scaled_dot_product_attention(q, k, v).float()  # the round trip
        want = attn.out(y.transpose(1, 2).reshape(3, 7, 64))
    assert got.dtype == torch.float32 and torch.equal(got, want)


def test_compute_dtype_is_validated_and_resolved() -> None:
    with pytest.raises(ValueError, match="compute_dtype must be one of"):
        SamplingConfig(compute_dtype="float16")
    assert SamplingConfig(compute_dtype="float32").torch_compute_dtype() == torch.float32
    assert SamplingConfig(compute_dtype="bfloat16").torch_compute_dtype() == torch.bfloat16
    auto = SamplingConfig().torch_compute_dtype()
    assert auto == (torch.bfloat16 if native_bfloat16() else torch.float32)
    assert SamplingConfig(compute_dtype="bfloat16").torch_compute_dtype("meta") == torch.float32


def test_auto_compute_dtype_is_float32_for_one_row(monkeypatch: pytest.MonkeyPatch) -> None:
    """On a CPU with native bfloat16, "auto" multiplies in float32 for a single row (a single env, one
    rollout: its small matrices pay more for the casts than the products save) and in bfloat16 from 2 rows
    on; an engine resolves it for its rows, split rollouts and split envs for all of theirs."""
    from trajeglish_env.env.shards import prepared_config
    from trajeglish_env.sampler import config as config_module
    from trajeglish_env.sampler import rollouts as rollouts_module

    monkeypatch.setattr(config_module, "native_bfloat16", lambda: True)
    auto = SamplingConfig()
    assert config_module.AUTO_BFLOAT16_ROWS == 2
    assert auto.torch_compute_dtype(rows=1) == torch.float32
    assert auto.torch_compute_dtype(rows=2) == auto.torch_compute_dtype(rows=8) == torch.bfloat16
    assert auto.torch_compute_dtype() == torch.bfloat16
    assert auto.torch_compute_dtype("meta", rows=64) == torch.float32  # not a CPU: float32
    assert auto.for_rows(1).compute_dtype == "float32" and auto.for_rows(None).compute_dtype == "bfloat16"
    fixed = SamplingConfig(compute_dtype="bfloat16")
    assert fixed.for_rows(1) is fixed and fixed.torch_compute_dtype(rows=1) == torch.bfloat16
    ckpt = tiny()
    assert BatchEngine(ckpt, 1, auto)._compute_dtype == torch.float32
    assert BatchEngine(ckpt, 2, auto)._compute_dtype == torch.bfloat16
    seen: list[str] = []
    sample = lambda job, first, count: seen.append(job[-1].compute_dtype)  # noqa: E731
    monkeypatch.setattr(rollouts_module, "_sample", sample)
    for rollouts in (1, 4):
        rollouts_module.rollout(ckpt, bundle_scene("highway-merge-999000"), rollouts, 2, config=auto)
    assert seen == ["float32", "bfloat16"]  # the chunks of a split take the dtype of all the rollouts
    for scenes, want in ((1, "float32"), (4, "bfloat16")):
        npc = prepared_config(None, {"npc": TrajeglishNPC(ckpt)}, "test", scenes).npc
        assert npc.sampling.compute_dtype == want


def test_invariant_linear_and_counter_uniform() -> None:
    w, bias = torch.randn(64, 48), torch.randn(64)
    x = torch.randn(200, 48)
    with torch.no_grad():
        together = invariant_linear(x, w, bias)
        alone = torch.cat([invariant_linear(x[i : i + 1], w, bias) for i in range(7)])
    assert torch.equal(together[:7], alone) and MIN_GEMM_ROWS >= 16
    u = counter_uniform(np.full(4, 3, np.uint64), np.array([0, 0, 1, 1]), np.array([0, 1, 0, 1]))
    assert len(np.unique(u)) == 4 and ((u >= 0) & (u < 1)).all()
    assert np.array_equal(
        u[2:], counter_uniform(np.full(2, 3, np.uint64), np.array([1, 1]), np.array([0, 1]))
    )


def ego_actions(steps: int, n: int) -> list[np.ndarray]:
    rng = np.random.default_rng(0)
    return [rng.uniform(-1, 1, (n, 2)).astype(np.float32) for _ in range(steps)]


@pytest.mark.parametrize("npc", ["tiny", "idm", "idm-bev"])
def test_batched_ego_env_equals_separate_envs_with_autoreset(npc: str) -> None:
    # float32: under "auto" a single env multiplies in float32 and a batch in bfloat16 (same distribution,
    # other draws) on CPUs with native bfloat16; the env logic is what is compared here (bev: the rasters of
    # all scenes come from one geometry pass)
    spec = TrajeglishNPC(tiny(), SamplingConfig(compute_dtype="float32")) if npc == "tiny" else "idm"
    kw = {"npc": spec, "max_cycles": 7, "observation": "bev" if npc.endswith("bev") else "vector"}
    venv = BatchedEgoEnv(3, **kw)
    obs, info = venv.reset(seed=5)
    assert obs.shape == (3, *venv.single_observation_space.shape) and venv.observation_space.contains(obs)
    actions = ego_actions(16, 3)
    batched = [venv.step(a) for a in actions]
    assert sum(int((r[2] | r[3]).sum()) for r in batched) >= 6  # every scene ended and restarted
    for i in range(3):
        env = EgoEnv(**kw)
        o, inf = env.reset(seed=5 + i)
        assert np.array_equal(o, obs[i]) and inf["scenario_id"] == info["scenario_id"][i]
        for a, (b_obs, b_rew, b_term, b_trunc, b_info) in zip(actions, batched, strict=True):
            o, r, term, trunc, inf = env.step(a[i])
            assert (r, term, trunc) == (b_rew[i], b_term[i], b_trunc[i])
            if term or trunc:
                assert np.array_equal(o, b_info["final_obs"][i]) and b_info["_final_obs"][i]
                o, _ = env.reset()
            assert np.array_equal(o, b_obs[i])


def test_batched_parallel_env_equals_separate_parallel_envs() -> None:
    kw = {"npc": TrajeglishNPC(tiny()), "external": "all", "max_cycles": 5}
    penv = BatchedParallelEnv(2, **kw)
    obs, _ = penv.reset(seed=[3, 4], options={"scene": SCENES[0]})
    refs = [parallel_env(**kw) for _ in range(2)]
    ref_obs = [r.reset(seed=s, options={"scene": SCENES[0]})[0] for r, s in zip(refs, [3, 4], strict=True)]
    for got, want in zip(obs, ref_obs, strict=True):
        assert got.keys() == want.keys() and all(np.array_equal(got[a], want[a]) for a in got)
    for step in range(7):
        actions = [{a: penv.action_space(a).sample() for a in agents} for agents in penv.agents]
        out = penv.step(actions)
        for i, ref in enumerate(refs):
            if not ref.agents:
                assert out[0][i] == {}  # a finished scene stays empty until it is reset
                continue
            want = ref.step(actions[i])
            for k in range(4):
                assert out[k][i].keys() == want[k].keys()
            assert all(np.array_equal(out[0][i][a], want[0][a]) for a in want[0])
            assert out[1][i] == pytest.approx(dict(want[1]))
        if step == 5:
            assert penv.agents == [[], []]
            obs, _ = penv.reset_scenes([1], seed=8)
            ref_obs = refs[1].reset(seed=8)[0]
            assert obs[0].keys() == ref_obs.keys() and penv.agents[1]


def test_sb3_vec_env_equals_dummy_vec_env_and_trains() -> None:
    kw = {"npc": TrajeglishNPC(tiny()), "max_cycles": 6}
    vec = SB3VecEnv(3, **kw)
    ref = DummyVecEnv([lambda: EgoEnv(**kw) for _ in range(3)])
    vec.seed(21)
    ref.seed(21)
    assert np.array_equal(vec.reset(), ref.reset())
    for a in ego_actions(10, 3):
        got, want = vec.step(a), ref.step(a)
        assert (
            np.array_equal(got[0], want[0])
            and np.allclose(got[1], want[1])
            and np.array_equal(got[2], want[2])
        )
        for i in np.flatnonzero(got[2]):
            assert np.array_equal(got[3][i]["terminal_observation"], want[3][i]["terminal_observation"])
            assert got[3][i]["TimeLimit.truncated"] == want[3][i]["TimeLimit.truncated"]
    assert vec.get_attr("agent") == ref.get_attr("agent")
    for name in ("observation_space", "action_space", "spec"):  # what SB3's own vector envs give
        assert vec.get_attr(name) == ref.get_attr(name), name
    assert all(isinstance(g, np.random.Generator) for g in vec.get_attr("np_random"))
    model = PPO("MlpPolicy", vec, n_steps=16, batch_size=24, n_epochs=1, seed=0, device="cpu")
    model.learn(48)
    assert model.num_timesteps >= 48


def test_batched_envs_refuse_bad_inputs() -> None:
    with pytest.raises(ValueError, match="positive integer"):
        BatchedEgoEnv(0, npc="idm")
    with pytest.raises(ValueError, match="torch_threads"):
        BatchedEgoEnv(2, npc="idm", torch_threads="many")
    venv = BatchedEgoEnv(2, npc="idm", max_cycles=3)
    with pytest.raises(ValueError, match="expected 2 seeds"):
        venv.reset(seed=[1, 2, 3])
    venv.reset(seed=0)
    with pytest.raises(ValueError, match=r"expected actions of shape \(2, 2\) .*got \(3, 2\)"):
        venv.step(np.zeros((3, 2), np.float32))
    with pytest.raises(ValueError, match=r"expected actions of shape \(2, 2\) .*got \(2,\)"):
        venv.step(np.zeros(2, np.float32))  # one action for the batch, read as a scalar per scene
    with pytest.raises(ValueError, match=r"step: scene 1 \(.*\): agent .*must be a finite array"):
        venv.step(np.array([[0.0, 0.0], [np.nan, 0.0]], np.float32))  # the scene is named
    # a bad action of the second scene: refused before the first scene's action is applied
    before = [venv.core.sim(i).driver.xyh.copy() for i in range(2)]
    with pytest.raises(ValueError, match=f"agent {venv.envs[1].agent}: action .* outside the action space"):
        venv.step(np.array([[0.5, 0.0], [3.0, 0.0]], np.float32))
    assert all(np.array_equal(b, venv.core.sim(i).driver.xyh) for i, b in enumerate(before))
    obs, *_ = venv.step(np.zeros((2, 2), np.float32))  # and it steps on normally
    alone = EgoEnv(npc="idm", max_cycles=3)
    alone.reset(seed=1)
    assert np.array_equal(alone.step(np.zeros(2, np.float32))[0], obs[1])
    penv = BatchedParallelEnv(2, npc="idm", external="all")
    penv.reset(seed=0)
    with pytest.raises(KeyError, match="scene 0 has no action"):
        penv.step([{}, {}])
    with pytest.raises(ValueError, match="out of range"):
        penv.reset_scenes([2])
    assert auto_threads(1, cores=2) == 2 and auto_threads(1, cores=1) == 1 and auto_threads(128) >= 1
    assert len(load_bundle()) == 20


def test_batched_render_follows_the_engine_when_a_bigger_scene_grows_its_arrays() -> None:
    scenes = [bundle_scene(SCENES[0]), bundle_scene(SCENES[1])]  # the second has more agents: the arrays grow
    venv = BatchedEgoEnv(2, scenes, render_mode="rgb_array", npc=TrajeglishNPC(tiny()), max_cycles=4)
    venv.envs[0].reset(seed=0, options={"scene": 0})
    venv.envs[1].reset(seed=0, options={"scene": 0})
    before = venv.render()
    venv.envs[1].reset(seed=1, options={"scene": 1})
    venv.step(np.zeros((2, 2), np.float32))
    after = venv.render()
    assert all(f.dtype == np.uint8 and f.ndim == 3 for f in before + after)
    assert venv.core.batch.rows.engine.N == scenes[1].num_agents and not np.array_equal(before[0], after[0])


def test_the_readme_loop_drives_several_agents_per_scene_with_one_sb3_model() -> None:
    """README "Several learned agents in one scene": one model's batched forward pass drives every
    external agent of every scene; scenes whose agents have all finished restart."""
    from policies import SB3Policy
    from trajeglish_env.env import RandomAgents

    class Constant:
        def predict(self, obs, deterministic=True):
            return np.tile(np.array([0.2, 0.0], np.float32), (len(obs), 1)), None

    policy = SB3Policy(Constant(), deterministic=False)
    spec = RandomAgents(4, with_sdc=True, at_most=True)
    penv = BatchedParallelEnv(3, npc="constant_velocity", external=spec, max_cycles=4)
    obs, _ = penv.reset(seed=0)
    restarts = transitions = 0
    for _ in range(12):
        obs, rewards, terms, truncs, infos = penv.step([policy.act_many(o) for o in obs])
        transitions += sum(len(r) for r in rewards)
        ended = [i for i, agents in enumerate(penv.agents) if not agents]
        if ended:
            fresh, _ = penv.reset_scenes(ended)
            restarts += len(ended)
            for i, o in zip(ended, fresh, strict=True):
                obs[i] = o
    assert restarts >= 6 and transitions > 12 * 3


def test_the_parallel_step_builds_each_observation_once() -> None:
    """The stock wrapper called ``last()`` before every agent's action: an observation built and thrown
    away per agent (a 35-agent scene observed 70 times a step)."""
    import trajeglish_env

    env = trajeglish_env.parallel_env(npc="replay", external="all")
    env.reset(seed=0, options={"scene": "sumo-random-999000-0-0"})
    raw = env.unwrapped
    calls = []
    real = raw.batch.observe
    raw.batch.observe = lambda scenes, agents: calls.append(len(agents)) or real(scenes, agents)
    live = len(env.agents)
    obs, *_ = env.step({a: np.zeros(2, np.float32) for a in env.agents})
    assert sum(calls) == len(obs) <= live and len(calls) == 1
    raw.batch.observe = real
    assert all(np.array_equal(raw.observe(a), obs[a]) for a in obs)  # each one, alone, the same
    with pytest.raises(TypeError, match="expected a dict agent name -> action, got list"):
        env.step([np.zeros(2)] * 3)
