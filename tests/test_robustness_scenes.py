"""Issue 17, bugs 3-5: the env's scene sources fail with clear errors naming the file, the scene field or
the reset option, instead of raw NumPy/zip errors, IndexErrors deep in the simulator or silent runs."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from helpers import straight_road_scene

import trajeglish_env
from trajeglish_env.env.scenes import UnknownSceneError, scene_index, scene_set
from trajeglish_env.scenario import Scenario, ScenarioError
from trajeglish_env.scenario_io import count_scenarios, load_scenarios, save_scenarios


def _play(scenes: object, steps: int = 5) -> None:
    """Build a replay-NPC env on ``scenes`` and play a few constant actions."""
    env = trajeglish_env.env(scenes=scenes, npc="replay")
    env.reset(seed=0)
    for _ in range(steps):
        if not env.agents:
            break
        _, _, terminated, truncated, _ = env.last()
        env.step(None if terminated or truncated else np.zeros(2, np.float32))


# ------------------------------------------------------------------------ bug 3: broken shards in a directory
@pytest.fixture
def shard_bytes(tmp_path) -> bytes:
    path = save_scenarios(tmp_path / "src" / "good.scn.npz", [straight_road_scene(seed=s) for s in range(2)])
    return path.read_bytes()


@pytest.mark.parametrize(
    ("content", "reason"),
    [
        (lambda raw: raw[: len(raw) // 2], "BadZipFile"),
        (lambda raw: b"", "EOFError"),
        (lambda raw: raw[:30], "truncated or corrupt"),
    ],
    ids=["truncated", "empty", "header-only"],
)
def test_env_on_a_directory_with_a_broken_shard_names_the_file(
    tmp_path, shard_bytes, content, reason
) -> None:
    data = tmp_path / "data"
    data.mkdir()
    (data / "a.scn.npz").write_bytes(shard_bytes)
    (data / "b.scn.npz").write_bytes(content(shard_bytes))
    with pytest.raises(ScenarioError, match=rf"b\.scn\.npz: not a readable scenario file .*{reason}"):
        trajeglish_env.env(scenes=str(data), npc="replay")


def test_a_bare_array_or_an_empty_shard_is_refused_with_the_file_name(tmp_path) -> None:
    data = tmp_path / "data"
    data.mkdir()
    with open(data / "a.scn.npz", "wb") as fh:
        np.save(fh, np.zeros(3))
    with pytest.raises(
        ScenarioError, match=r"a\.scn\.npz: not a trajeglish_env scenario file \(a bare NumPy"
    ):
        trajeglish_env.env(scenes=data, npc="replay")
    (data / "a.scn.npz").unlink()
    save_scenarios(data / "none.scn.npz", [])
    assert count_scenarios(data / "none.scn.npz") == 0
    with pytest.raises(ScenarioError, match=r"data: the scenario files hold no scenes"):
        trajeglish_env.env(scenes=data, npc="replay")


def test_a_damaged_member_fails_when_its_shard_is_read(tmp_path, shard_bytes) -> None:
    raw = bytearray(shard_bytes)
    middle = len(raw) // 2
    raw[middle : middle + 64] = bytes(64)  # the zip directory is intact: counting works, reading does not
    path = tmp_path / "d.scn.npz"
    path.write_bytes(bytes(raw))
    assert count_scenarios(path) == 2
    with pytest.raises(ScenarioError, match=r"d\.scn\.npz: not a readable scenario file"):
        load_scenarios(path)


# ------------------------------------------------------------------ bug 4: user scenes validated at the entry
def _replace_array(scene: Scenario, name: str, edit) -> Scenario:
    """A copy of ``scene`` whose field ``name`` is ``edit`` applied to a copy of the array."""
    value = getattr(scene, name).copy()
    return dataclasses.replace(scene, **{name: edit(value)})


def _set(arr: np.ndarray, index: tuple, value: float) -> np.ndarray:
    arr[index] = value
    return arr


BROKEN = [
    (
        "nan-in-sdc-future",
        "xyh",
        lambda a: _set(a, (0, 60, 0), np.nan),
        r"field 'xyh': non-finite value at valid agent 0 step 60 \(track_id 100\): expected finite x, y, "
        r"heading wherever valid is True, got \[nan",
    ),
    (
        "inf-heading",
        "xyh",
        lambda a: _set(a, (3, 11, 2), np.inf),
        r"field 'xyh': non-finite value at valid agent 3 step 11 \(track_id 103\)",
    ),
    (
        "negative-size",
        "size",
        lambda a: _set(a, (2, 1), -2.0),
        r"field 'size': agent 2: length and width must be finite and > 0 \(m\), got \[4\.5, -2\.0\] "
        r"\(track_id 102\)",
    ),
    ("nan-size", "size", lambda a: _set(a, (4, 0), np.nan), r"field 'size': agent 4: .* \(track_id 104\)"),
    (
        "inf-map-point",
        "map_points",
        lambda a: _set(a, (460, 1), np.inf),
        r"field 'map_points': point 460 \(polyline 1, map_id 1\): expected finite x, y, got \[-40\.0, inf\]",
    ),
    ("int8-valid", "valid", lambda a: a.astype(np.int8), r"field 'valid': expected a bool dtype, got int8"),
    (
        "valid-wrong-shape",
        "valid",
        lambda a: a[:, :1],
        r"field 'valid': expected shape \(6, 91\) \(agents, steps of xyh\), got \(6, 1\)",
    ),
    ("float-kind", "kind", lambda a: a.astype(np.float64), r"field 'kind': expected an integer dtype"),
]


@pytest.mark.parametrize(("field", "edit", "message"), [b[1:] for b in BROKEN], ids=[b[0] for b in BROKEN])
def test_env_validates_a_list_of_user_scenes(straight_scene, field, edit, message) -> None:
    bad = _replace_array(straight_scene, field, edit)
    with pytest.raises(ScenarioError, match=r"^scenes\[1\]: scenario 'straight-0': " + message):
        trajeglish_env.env(scenes=[straight_road_scene(seed=3), bad], npc="replay")
    with pytest.raises(ScenarioError, match=r"^scenes\[0\]: scenario 'straight-0': " + message):
        trajeglish_env.env(scenes=bad, npc="replay")


@pytest.mark.parametrize(
    ("field", "edit", "message"), [b[1:] for b in BROKEN[:3]], ids=[b[0] for b in BROKEN[:3]]
)
def test_rollout_validates_its_scene_before_sampling(straight_scene, field, edit, message) -> None:
    from trajeglish_env.checkpoint import load_pretrained
    from trajeglish_env.sampler import rollout

    bad = _replace_array(straight_scene, field, edit)
    with pytest.raises(ScenarioError, match=r"^scenario 'straight-0': " + message):
        rollout(load_pretrained(), bad, rollouts=1, horizon=3)


class _OwnScenes:
    """A user's duck-typed scene set (``__len__``, ``get``, ``index_of``)."""

    def __init__(self, scenes: list[Scenario]):
        self.scenes = scenes

    def __len__(self) -> int:
        return len(self.scenes)

    def get(self, index: int) -> Scenario:
        return self.scenes[index]

    def index_of(self, name: str) -> int:
        return [s.scenario_id for s in self.scenes].index(name)


def test_scenes_are_validated_once_not_at_every_reset(straight_scene, monkeypatch) -> None:
    calls: list[str] = []
    original = Scenario.validate

    def spy(self: Scenario) -> Scenario:
        calls.append(self.scenario_id)
        return original(self)

    monkeypatch.setattr(Scenario, "validate", spy)
    env = trajeglish_env.env(scenes=[straight_scene], npc="replay")
    own = trajeglish_env.env(scenes=_OwnScenes([straight_scene]), npc="replay")
    assert calls == ["straight-0"] * 2  # the list at construction; the own set on its first get
    for seed in range(3):
        env.reset(seed=seed)
        own.reset(seed=seed)
    assert calls == ["straight-0"] * 2
    bad = _replace_array(straight_scene, "valid", lambda a: a.astype(np.int8))
    with pytest.raises(ScenarioError, match=r"^scenes\.get\(0\): scenario 'straight-0': field 'valid'"):
        trajeglish_env.env(scenes=_OwnScenes([bad]), npc="replay")
    shared = scene_set([straight_scene])
    assert scene_set(shared) is shared  # a batched env's shared set is not wrapped or checked again


def test_valid_user_scenes_still_play(straight_scene) -> None:
    _play([straight_scene, straight_road_scene(seed=4)])
    _play(_OwnScenes([straight_scene]))


# --------------------------------------------------------------------------- bug 5: the "scene" reset option
@pytest.mark.parametrize(
    ("option", "error", "message"),
    [
        (1.5, TypeError, r"'scene' must be a scene index \(int\) or a scenario_id \(str\), got float 1\.5"),
        (1.0, TypeError, r"got float 1\.0"),
        (True, TypeError, r"got bool True"),
        (np.bool_(False), TypeError, r"got bool np\.False_"),
        ([1], TypeError, r"got list \[1\]"),
        (2, ValueError, r"'scene' index 2 out of range: expected 0\.\.1 \(2 scenes\)"),
        (-1, ValueError, r"'scene' index -1 out of range"),
        ("nope", UnknownSceneError, r"no scene with scenario_id 'nope'"),
    ],
)
def test_reset_refuses_a_malformed_scene_option(straight_scene, option, error, message) -> None:
    env = trajeglish_env.env(scenes=[straight_scene, straight_road_scene(seed=5)], npc="replay")
    with pytest.raises(error, match=message) as info:
        env.reset(seed=0, options={"scene": option})
    assert error is UnknownSceneError or str(info.value).startswith("reset options: 'scene' ")


def test_reset_accepts_int_like_indices_and_scenario_ids(straight_scene) -> None:
    scenes = [straight_scene, straight_road_scene(seed=5)]
    env = trajeglish_env.env(scenes=scenes, npc="replay")
    for option in (1, np.int64(1), np.uint8(1), "straight-5"):
        env.reset(seed=0, options={"scene": option})
        assert env.unwrapped.scenario.scenario_id == "straight-5"
    assert scene_index(None, scene_set(scenes)) is None
    unknown = UnknownSceneError("x: no scene with scenario_id 'y'")
    assert isinstance(unknown, KeyError) and isinstance(unknown, ValueError) and str(unknown).startswith("x:")


def test_a_womd_tfrecord_where_scenes_are_expected_says_to_convert_it(tmp_path) -> None:
    """A raw WOMD file (or a folder of them) given as scenes says to run convert-womd (it said "pickled
    data ... load it unsafely", or only "no scenario files")."""
    from helpers import womd_tfrecord

    from trajeglish_env.training.dataset import SceneStore

    folder = tmp_path / "raw"
    folder.mkdir()
    record = folder / "validation.tfrecord-00000-of-00001"
    record.write_bytes(womd_tfrecord().read_bytes())
    with pytest.raises(ScenarioError, match="a WOMD TFRecord file, not a scenario file .* convert-womd"):
        trajeglish_env.env(scenes=str(record))
    with pytest.raises(ValueError, match="there are WOMD TFRecord files, e.g. .*validation.tfrecord-00000"):
        trajeglish_env.env(scenes=str(folder))
    with pytest.raises(FileNotFoundError, match="convert them first, `trajeglish convert-womd FILES"):
        SceneStore(folder)


def test_reset_by_scenario_id_reads_the_ids_once_without_loading_scenes(tmp_path, monkeypatch) -> None:
    """Many shards: a reset by id read every shard in full until it found the id, at every reset."""
    import trajeglish_env.env.scenes as scenes_module

    for k in range(3):
        scene = dataclasses.replace(straight_road_scene(), scenario_id=f"scene-{k}")
        save_scenarios(tmp_path / f"s{k}.scn.npz", [scene])
    files = scenes_module.SceneFiles(tmp_path)
    loaded = []
    real = scenes_module.load_scenarios
    monkeypatch.setattr(scenes_module, "load_scenarios", lambda p: loaded.append(p) or real(p))
    assert [files.index_of(f"scene-{k}") for k in (2, 0, 2)] == [2, 0, 2] and loaded == []
    with pytest.raises(UnknownSceneError, match="no scene with scenario_id 'nope'"):
        files.index_of("nope")
