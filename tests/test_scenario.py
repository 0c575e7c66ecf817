"""The Scenario data model and its on-disk format."""

from __future__ import annotations

import dataclasses
import zipfile

import numpy as np
import pytest
from helpers import straight_road_scene

from trajeglish_env import (
    Scenario,
    ScenarioError,
    load_scenario,
    load_scenarios,
    save_scenario,
    save_scenarios,
)
from trajeglish_env.scenario import AgentKind, MapKind


def test_from_arrays_builds_ragged_map(straight_scene: Scenario) -> None:
    assert straight_scene.num_agents == 6 and straight_scene.num_steps == 91
    assert straight_scene.num_polylines == 5
    assert straight_scene.map_offsets.tolist() == [0, 450, 900, 1350, 1800, 2250]
    np.testing.assert_array_equal(straight_scene.polyline(1)[:, 1], 3.5)
    assert len(straight_scene.polylines(frozenset({MapKind.ROAD_EDGE_BOUNDARY}))) == 2
    assert straight_scene.agent_index(103) == 3
    with pytest.raises(KeyError, match="track_id 999"):
        straight_scene.agent_index(999)


def test_speed_is_finite_difference(straight_scene: Scenario) -> None:
    v = straight_scene.speed()
    dx = straight_scene.xyh[0, 1, 0] - straight_scene.xyh[0, 0, 0]
    assert v[0, 5] == pytest.approx(dx / 0.1)
    assert v[-1, 19] == 0.0  # not valid before step 20


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("xyh", np.zeros((6, 91, 2)), "field 'xyh': expected a 3-d array with last dimension 3"),
        ("valid", np.ones((6, 90), dtype=bool), "field 'valid': expected shape"),
        (
            "size",
            np.tile([4.5, -2.0], (6, 1)),
            "field 'size': agent 0: length and width must be finite and > 0",
        ),
        ("kind", np.full(6, 7, dtype=np.int8), "field 'kind': values must be AgentKind"),
        ("track_id", np.zeros(6, dtype=np.int64), "field 'track_id': ids must be unique"),
        ("sdc", 6, "field 'sdc': index 6 out of range for 6 agents"),
        ("current_index", 91, "field 'current_index': 91 out of range for 91 steps"),
        ("map_offsets", np.array([0, 10, 5, 1350, 1800, 2250]), "field 'map_offsets'"),
        ("map_kind", np.zeros(4, dtype=np.int8), "field 'map_kind': expected 5 entries"),
        ("dt", 0.0, "field 'dt': must be a positive number"),
        ("tracks_to_predict", np.array([9]), "field 'tracks_to_predict'"),
    ],
)
def test_validate_names_the_field(straight_scene: Scenario, field: str, value: object, message: str) -> None:
    bad = dataclasses.replace(straight_scene, **{field: value})
    with pytest.raises(ScenarioError, match=message.replace("(", r"\(").replace(")", r"\)")):
        bad.validate()


def test_validate_rejects_nan_only_where_valid(straight_scene: Scenario) -> None:
    xyh = straight_scene.xyh.copy()
    xyh[5, 3] = np.nan  # agent 5 is invalid before step 20: allowed
    dataclasses.replace(straight_scene, xyh=xyh).validate()
    xyh[2, 40, 1] = np.inf
    with pytest.raises(ScenarioError, match="non-finite value at valid agent 2 step 40"):
        dataclasses.replace(straight_scene, xyh=xyh).validate()


def test_round_trip_is_exact(tmp_path, straight_scene: Scenario) -> None:
    scenes = [straight_scene, straight_road_scene(num_agents=3, seed=7)]
    with_signals = dataclasses.replace(
        scenes[1],
        signal_lane_id=np.array([0, 1]),
        signal_xy=np.array([[10.0, 0.0], [10.0, 3.5]]),
        signal_state=np.tile(np.array([[4, 6]], dtype=np.int8), (91, 1)),
        tracks_to_predict=np.array([1, 2]),
    )
    path = save_scenarios(tmp_path / "a.scn.npz", [scenes[0], with_signals])
    loaded = load_scenarios(path)
    assert len(loaded) == 2
    assert loaded[0].equals(scenes[0]) and loaded[1].equals(with_signals)
    assert not loaded[0].equals(with_signals)
    assert loaded[1].signal_state.dtype == np.int8 and loaded[0].signal_state is None
    assert load_scenario(path, 1).scenario_id == "straight-7"
    with pytest.raises(IndexError, match="holds 2"):
        load_scenario(path, 2)
    assert not list(tmp_path.glob(".*tmp*"))  # no temporary file left behind


def test_truncated_and_foreign_files_fail_clearly(tmp_path, straight_scene: Scenario) -> None:
    path = save_scenario(tmp_path / "s.scn.npz", straight_scene)
    data = path.read_bytes()
    cut = tmp_path / "cut.scn.npz"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(ScenarioError, match="cut.scn.npz: not a readable scenario file"):
        load_scenarios(cut)
    foreign = tmp_path / "foreign.scn.npz"
    np.savez(foreign, x=np.zeros(3))
    with pytest.raises(ScenarioError, match="not a trajeglish_env scenario file"):
        load_scenarios(foreign)
    with pytest.raises(FileNotFoundError, match="missing.scn.npz"):
        load_scenarios(tmp_path / "missing.scn.npz")


def test_unknown_version_is_refused(tmp_path, straight_scene: Scenario) -> None:
    path = save_scenario(tmp_path / "s.scn.npz", straight_scene)
    with np.load(path) as d:
        items = {k: d[k] for k in d.files}
    items["__version__"] = np.array(99)
    future = tmp_path / "future.scn.npz"
    np.savez_compressed(future, **items)
    with pytest.raises(ScenarioError, match="version 99 is not supported"):
        load_scenarios(future)
    assert zipfile.is_zipfile(future)


def test_failed_write_keeps_previous_file(tmp_path, straight_scene: Scenario) -> None:
    path = save_scenario(tmp_path / "s.scn.npz", straight_scene)
    before = path.read_bytes()
    broken = dataclasses.replace(straight_scene, kind=np.full(6, 9, dtype=np.int8))
    with pytest.raises(ScenarioError):
        save_scenario(path, broken)
    assert path.read_bytes() == before


def test_with_agents_keeps_sdc_and_remaps_indices(straight_scene: Scenario) -> None:
    sub = dataclasses.replace(straight_scene, tracks_to_predict=np.array([2, 4])).with_agents(
        np.array([4, 0, 1])
    )
    assert sub.sdc == 1 and sub.track_id.tolist() == [104, 100, 101]
    assert sub.tracks_to_predict.tolist() == [0]
    assert sub.kind[2] == AgentKind.CYCLIST
    with pytest.raises(ScenarioError, match="sdc"):
        straight_scene.with_agents(np.array([1, 2]))


def test_from_arrays_checks_the_raw_values_before_casting() -> None:
    """A kind of 256 became 0 and 1.7 became 1, a validity of 0.5 True, an sdc of 1.5 agent 1, a polyline
    kind of 257 a freeway lane, and [P, 3] points were reshaped into other points, all silently."""
    xyh, valid, size = np.zeros((2, 5, 3)), np.ones((2, 5), bool), np.ones((2, 2))
    cases = (
        (
            {"kind": np.array([0, 256])},
            r"field 'kind': expected whole numbers in \[0, 2\], got 256 at agent 1",
        ),
        ({"kind": np.array([0.0, 1.7])}, r"field 'kind': expected whole numbers in \[0, 2\], got 1.7"),
        ({"kind": [0, 1], "valid": np.full((2, 5), 0.5)}, "field 'valid': expected booleans"),
        ({"kind": [0, 1], "sdc": 1.5}, r"field 'sdc': expected whole numbers >= 0, got 1.5"),
        (
            {"kind": [0, 1], "polylines": [np.zeros((3, 3))], "polyline_kinds": [1]},
            r"polylines\[0\]: expected",
        ),
        (
            {"kind": [0, 1], "polylines": [np.zeros((3, 2))], "polyline_kinds": [257]},
            "field 'polyline_kinds': expected",
        ),
    )
    for kw, message in cases:
        args = {"xyh": xyh, "valid": kw.pop("valid", valid), "size": size, "current_index": 1}
        with pytest.raises(ScenarioError, match=message):
            Scenario.from_arrays(**args, **kw)
    ok = Scenario.from_arrays(
        xyh,
        valid.astype(int),
        size,
        np.array([0, 1], np.int64),
        sdc=np.int64(1),
        polylines=[np.zeros(2), np.zeros((3, 2))],
        polyline_kinds=[1, 2],
        current_index=1,
    )
    assert ok.sdc == 1 and ok.valid.dtype == bool and ok.num_polylines == 2


def test_from_arrays_errors_name_the_scene_the_agent_and_its_track_id() -> None:
    """A kind of 7 said ``kind: expected whole numbers in [0, 2], got np.int64(7)`` (no agent, no track id,
    no scene), and a scene without an id was ``scenario: field 'size': ...``."""
    xyh, valid, size = np.zeros((2, 5, 3)), np.ones((2, 5), bool), np.ones((2, 2))
    whole = r"^scenario 'a1': field 'kind': expected whole numbers in \[0, 2\], got 7"
    with pytest.raises(ScenarioError, match=whole + r" at agent 1 \(track_id 101\)$"):
        Scenario.from_arrays(xyh, valid, size, np.array([0, 7]), track_id=[100, 101], scenario_id="a1")
    with pytest.raises(
        ScenarioError, match=r"^scenario <no id>: field 'kind': .* got 7 at agent 1 \(track_id 1\)$"
    ):
        Scenario.from_arrays(xyh, valid, size, np.array([0, 7]))
    with pytest.raises(ScenarioError, match=r"^scenario <no id>: field 'size': agent 0: "):
        Scenario.from_arrays(xyh, valid, np.array([[4.5, 0.0], [4.5, 2.0]]), [0, 0])
    with pytest.raises(
        ScenarioError, match=r"field 'polyline_kinds': .* got 257 at polyline 0 \(map_id 40\)$"
    ):
        Scenario.from_arrays(
            xyh, valid, size, [0, 0], polylines=[np.zeros((3, 2))], polyline_kinds=[257], polyline_ids=[40]
        )
