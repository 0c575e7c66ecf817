"""WOMD reader: TFRecord framing and CRC-32C, Scenario proto parsing, conversion to shards."""

from __future__ import annotations

import gzip
from pathlib import Path

import numpy as np
import pytest
from helpers import womd_tfrecord

from trajeglish_env.scenario import AgentKind, MapKind, SignalState
from trajeglish_env.scenario_io import load_scenarios
from trajeglish_env.sources.womd import (
    WomdFormatError,
    output_name,
    parse_scenario,
    read_tfrecord,
    read_womd,
)
from trajeglish_env.sources.womd_convert import convert_womd
from trajeglish_env.sources.womd_proto import ScenarioProto
from trajeglish_env.sources.womd_tfrecord import _crc_update_scalar, crc32c, masked_crc32c


@pytest.fixture(scope="module")
def record() -> bytes:
    ((index, data),) = list(read_tfrecord(womd_tfrecord()))
    assert index == 0
    return data


@pytest.fixture(scope="module")
def scene(record: bytes):
    return parse_scenario(record, origin="sample")


def _modified(record: bytes, edit) -> bytes:
    proto = ScenarioProto.FromString(record)
    edit(proto)
    return proto.SerializeToString()


# ------------------------------------------------------------------------------------------ crc + framing
def test_crc32c_matches_published_vectors_and_scalar_reference():
    assert crc32c(b"123456789") == 0xE3069283
    assert crc32c(bytes(32)) == 0x8A9136AA  # RFC 3720 B.4
    assert crc32c(b"\xff" * 32) == 0x62A8AB43
    assert crc32c(b"") == 0
    rng = np.random.default_rng(0)
    for n in (2047, 2048, 2049, 4099, 65_537, 300_001):  # the vectorised path starts at 2048 bytes
        data = rng.integers(0, 256, n, dtype=np.uint8).tobytes()
        assert crc32c(data) == _crc_update_scalar(0xFFFFFFFF, data) ^ 0xFFFFFFFF, n
    assert masked_crc32c(b"") == 0xA282EAD8


def test_sample_record_framing(record: bytes):
    assert len(record) == womd_tfrecord().stat().st_size - 16 == 952_947


def test_truncated_file_names_file_and_record(tmp_path: Path):
    raw = womd_tfrecord().read_bytes()
    cut = tmp_path / "cut.tfrecord"
    cut.write_bytes(raw[: len(raw) // 2])
    with pytest.raises(WomdFormatError, match=r"cut\.tfrecord: record 0 .*truncated"):
        list(read_tfrecord(cut))
    cut.write_bytes(raw[:5])
    with pytest.raises(WomdFormatError, match=r"cut\.tfrecord: record 0 .*truncated header: 5 of 12"):
        list(read_tfrecord(cut))
    two = tmp_path / "two.tfrecord"
    two.write_bytes(raw + raw[:100])
    reader = read_womd(two)
    assert next(reader).scenario_id == "637f20cafde22ff8"
    with pytest.raises(WomdFormatError, match=r"two\.tfrecord: record 1 \(byte offset 952963\).*truncated"):
        next(reader)


def test_flipped_bytes_fail_their_checksum(tmp_path: Path):
    raw = bytearray(womd_tfrecord().read_bytes())
    bad = tmp_path / "flip.tfrecord"
    raw[500_000] ^= 0x01
    bad.write_bytes(bytes(raw))
    with pytest.raises(
        WomdFormatError, match=r"flip\.tfrecord: record 0 .*data checksum mismatch over 952947"
    ):
        list(read_tfrecord(bad))
    assert len(next(read_tfrecord(bad, check_data_crc=False))[1]) == 952_947
    raw[500_000] ^= 0x01
    raw[3] ^= 0x10  # length field
    bad.write_bytes(bytes(raw))
    with pytest.raises(WomdFormatError, match=r"record 0 .*length checksum mismatch"):
        list(read_tfrecord(bad))


# ------------------------------------------------------------------------------------------ conversion
def test_sample_agents(scene):
    assert scene.scenario_id == "637f20cafde22ff8" and scene.source == "womd"
    assert (scene.num_agents, scene.num_steps) == (83, 91)
    assert scene.current_index == 10 and scene.dt == 0.1
    assert scene.sdc == 82 and scene.track_id[82] == 2406
    assert scene.tracks_to_predict.tolist() == [72, 43, 42]
    assert scene.track_id[[72, 43, 42]].tolist() == [2320, 1676, 1675]
    assert scene.kind[[72, 43, 42]].tolist() == [AgentKind.PEDESTRIAN, AgentKind.VEHICLE, AgentKind.VEHICLE]
    assert np.bincount(scene.kind, minlength=3).tolist() == [70, 10, 3]
    assert int(scene.valid.sum()) == 4596 and scene.valid[82].all()
    np.testing.assert_allclose(
        scene.xyh[82, 10], [-7785.9164875775678, -6683.40586769982, -1.54576147], atol=1e-7
    )
    np.testing.assert_allclose(scene.size[82], [5.286, 2.332], atol=1e-6)
    np.testing.assert_allclose(scene.xyh[82, 90], [-7785.91643, -6683.40591, -1.5457232], atol=1e-4)
    assert (scene.xyh[~scene.valid] == 0).all()


def test_sample_map(scene):
    assert scene.num_polylines == 301
    counts = np.bincount(scene.map_kind, minlength=len(MapKind))
    expected = {
        MapKind.LANE_SURFACE_STREET: 198,
        MapKind.LANE_BIKE: 1,
        MapKind.ROAD_LINE_BROKEN_SINGLE_WHITE: 24,
        MapKind.ROAD_LINE_SOLID_SINGLE_WHITE: 18,
        MapKind.ROAD_LINE_SOLID_SINGLE_YELLOW: 17,
        MapKind.ROAD_EDGE_BOUNDARY: 15,
        MapKind.ROAD_EDGE_MEDIAN: 13,
        MapKind.STOP_SIGN: 8,
        MapKind.CROSSWALK: 4,
        MapKind.SPEED_BUMP: 3,
    }
    assert {MapKind(k): int(c) for k, c in enumerate(counts) if c} == expected
    assert len(scene.map_points) == 19_643
    crosswalk = int(np.flatnonzero(scene.map_kind == MapKind.CROSSWALK)[0])
    assert scene.map_id[crosswalk] == 587
    outline = scene.polyline(crosswalk)
    assert len(outline) == 5 and (outline[0] == outline[-1]).all()  # closed polygon
    np.testing.assert_allclose(outline[1], [-7761.94081225, -6694.3552316])
    stops = np.flatnonzero(scene.map_kind == MapKind.STOP_SIGN)
    assert scene.map_id[stops].tolist() == list(range(594, 602))
    assert (np.diff(scene.map_offsets)[stops] == 1).all()
    np.testing.assert_allclose(scene.polyline(int(stops[0]))[0], [-7884.11243404, -6739.49588259])


def test_sample_traffic_signals(scene):
    assert scene.signal_lane_id.tolist() == [431, 432, 443, 445, 446, 447, 448, 449, 450, 455, 456, 457]
    np.testing.assert_allclose(scene.signal_xy[0], [-7811.1817935320987, -6717.7573872755256])
    state = scene.signal_state
    assert state.shape == (91, 12) and state.dtype == np.int8
    assert state[0].tolist() == [0, 0, 4, 4, 0, 0, 4, 4, 0, 1, 1, 0]
    assert state[14, 0] == SignalState.ARROW_STOP and state[49].tolist() == [0] * 12
    assert np.bincount(state.ravel(), minlength=9).tolist() == [540, 228, 0, 0, 324, 0, 0, 0, 0]


def test_track_without_valid_state_is_dropped_and_indices_follow(record: bytes):
    def invalidate_first_track(proto):
        for state in proto.tracks[0].states:
            state.valid = False

    scene = parse_scenario(_modified(record, invalidate_first_track))
    assert scene.num_agents == 82 and scene.sdc == 81 and scene.track_id[81] == 2406
    assert scene.tracks_to_predict.tolist() == [71, 42, 41]


def test_bad_scenarios_raise_errors_naming_origin(record: bytes):
    with pytest.raises(WomdFormatError, match=r"f\.tfrecord: record 7: not a valid WOMD Scenario"):
        parse_scenario(b"\xff\xff\xff", origin="f.tfrecord: record 7")
    with pytest.raises(WomdFormatError, match=r"^here: scenario '637f20cafde22ff8' has no tracks"):
        parse_scenario(_modified(record, lambda p: p.ClearField("tracks")), origin="here")
    with pytest.raises(WomdFormatError, match=r"^here: sdc_track_index 83 out of range for 83 tracks"):
        parse_scenario(_modified(record, lambda p: setattr(p, "sdc_track_index", 83)), origin="here")

    def bad_road_line(proto):
        proto.map_features[
            next(i for i, f in enumerate(proto.map_features) if f.HasField("road_line"))
        ].road_line.type = 9

    with pytest.raises(WomdFormatError, match=r"map feature \d+ \(road_line\): unknown type 9"):
        parse_scenario(_modified(record, bad_road_line))
    with pytest.raises(WomdFormatError, match=r"track 2406: unknown object_type 7"):
        parse_scenario(_modified(record, lambda p: setattr(p.tracks[82], "object_type", 7)))


# ------------------------------------------------------------------------------------------ shards
def test_output_names_are_unique_per_input():
    assert output_name("/d/training.tfrecord-00001-of-01000") == "training-00001-of-01000.scn.npz"
    assert output_name("a/motion.tfrecord") == "motion.scn.npz"
    with pytest.raises(ValueError, match="would both be written"):
        convert_womd([Path("a/x.tfrecord"), Path("b/x.tfrecord")], Path("out"), progress=False)


def test_convert_writes_loadable_shard_and_resumes(tmp_path: Path, scene, capsys):
    out = tmp_path / "out"
    report = convert_womd([womd_tfrecord()], out)
    assert report["converted"] == [str(womd_tfrecord())] and report["failed"] == [] and report["scenes"] == 1
    assert "convert-womd" in capsys.readouterr().err  # progress bar on stderr
    shard = out / "motion_data_one_scenario.scn.npz"
    assert report["outputs"] == [str(shard)]
    (loaded,) = load_scenarios(shard)
    assert loaded.equals(scene)
    again = convert_womd([womd_tfrecord()], out, progress=False)
    assert (
        again["skipped"] == [str(womd_tfrecord())]
        and again["converted"] == []
        and again["scenes_skipped"] == 1
    )


def test_convert_reports_corrupt_input_and_converts_the_rest(tmp_path: Path):
    bad = tmp_path / "broken.tfrecord"
    bad.write_bytes(womd_tfrecord().read_bytes()[:1000])
    out = tmp_path / "out"
    report = convert_womd([bad, womd_tfrecord()], out, progress=False)
    assert report["converted"] == [str(womd_tfrecord())] and report["scenes"] == 1
    (failure,) = report["failed"]
    assert failure["file"] == str(bad)
    assert "broken.tfrecord: record 0" in failure["error"] and "truncated" in failure["error"]
    names = ["motion_data_one_scenario.details.npz", "motion_data_one_scenario.scn.npz"]
    assert sorted(p.name for p in out.iterdir()) == names


# ------------------------------------------------------------------------------------------ audit fixes
def test_real_sample_gzip_and_a_corrupt_middle_record(tmp_path: Path, record: bytes, scene):
    raw = womd_tfrecord().read_bytes()
    zipped = tmp_path / "sample.tfrecord.gz"
    zipped.write_bytes(gzip.compress(raw, compresslevel=1))
    (read,) = list(read_womd(zipped))
    assert read.equals(scene), f"{zipped}: the gzip-compressed sample must read as the plain one"
    flipped = bytearray(raw)
    flipped[500_000] ^= 0x01
    three = tmp_path / "three.tfrecord"
    three.write_bytes(raw + bytes(flipped) + raw)
    report = convert_womd([three], tmp_path / "out", progress=False)
    assert report["scenes"] == 2 and report["bad_tails"] == [], f"{three}: expected records 0 and 2, {report}"
    assert [(b["record"], b["byte_offset"]) for b in report["bad_records"]] == [(1, len(raw))]


def test_ragged_real_track_names_its_id(record: bytes):
    with pytest.raises(WomdFormatError, match=r"track 2406 \(index 82\) has 90 states; the others have 91"):
        parse_scenario(_modified(record, lambda p: p.tracks[82].states.pop()), origin="here")


def test_external_agents_that_start_off_the_road_or_overlapping_are_named_at_reset() -> None:
    """Under external="all" 7 of the shared scene's 50 agents lost their episode at step 1 with a -1 they
    could do nothing about, unnamed (5 parked vehicles off the road, 2 pedestrians overlapping): a reset
    names them, as it names agents without a goal."""
    import trajeglish_env
    from trajeglish_env.sources.womd import read_womd

    sc = next(iter(read_womd(womd_tfrecord())))
    env = trajeglish_env.env(scenes=[sc], npc="replay", external="all")
    with pytest.warns(UserWarning) as caught:
        env.reset(seed=0)
    said = " ".join(str(w.message) for w in caught)
    assert "pedestrian_2313, pedestrian_2320 start overlapping another agent" in said
    assert "vehicle_1594, vehicle_1602, vehicle_1610, vehicle_1611, vehicle_1663 start off the road" in said
