"""Issue 17, bug 6: TFRecord conversion keeps the good records before a bad tail and reports the tail; an
empty input is an error (exit 2 from the command line), never a 0-scene shard.

The records are small synthetic WOMD scenes framed here, so these tests need no shared data.
"""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np
import pytest

from trajeglish_env.cli import main
from trajeglish_env.scenario_io import load_scenarios
from trajeglish_env.sources.womd import (
    TFRecordFramingError,
    WomdFormatError,
    read_good_records,
)
from trajeglish_env.sources.womd_convert import convert_womd
from trajeglish_env.sources.womd_proto import ScenarioProto
from trajeglish_env.sources.womd_tfrecord import masked_crc32c


def _scenario_record(name: str, steps: int = 11) -> bytes:
    """A serialized WOMD Scenario: two vehicles driving along one lane for ``steps`` steps."""
    proto = ScenarioProto(scenario_id=name, sdc_track_index=0, current_time_index=steps - 1)
    proto.timestamps_seconds.extend(0.1 * np.arange(steps))
    for track, y in ((10, 0.0), (11, 3.5)):
        t = proto.tracks.add(id=track, object_type=1)
        for step in range(steps):
            t.states.add(center_x=float(step), center_y=y, length=4.5, width=2.0, heading=0.0, valid=True)
    lane = proto.map_features.add(id=1)
    lane.lane.type = 2
    for x in range(-5, 20):
        lane.lane.polyline.add(x=float(x), y=0.0)
    return proto.SerializeToString()


def _frame(data: bytes) -> bytes:
    """One TFRecord record: length, its masked CRC, the data and its masked CRC."""
    length = struct.pack("<Q", len(data))
    return length + struct.pack("<I", masked_crc32c(length)) + data + struct.pack("<I", masked_crc32c(data))


@pytest.fixture
def two_records() -> bytes:
    return _frame(_scenario_record("first")) + _frame(_scenario_record("second"))


@pytest.mark.parametrize(
    ("tail", "problem"),
    [
        (b"abc", "truncated header: 3 of 12 bytes"),
        (b"\x00" * 16, "length checksum mismatch"),
        ("half", "truncated: the record needs"),
    ],
    ids=["garbage-bytes", "zeros", "half-record"],
)
def test_a_bad_tail_keeps_the_good_records_and_is_reported(tmp_path, capsys, two_records, tail, problem):
    tail_bytes = _frame(_scenario_record("third"))[:40] if tail == "half" else tail
    path = tmp_path / "part.tfrecord"
    path.write_bytes(two_records + tail_bytes)
    scenes, bad = read_good_records(path)
    assert [s.scenario_id for s in scenes] == ["first", "second"]
    assert isinstance(bad, TFRecordFramingError) and bad.record == 2 and bad.offset == len(two_records)

    out = tmp_path / "out"
    report = convert_womd([path], out, progress=False)
    assert report["converted"] == [str(path)] and report["failed"] == [] and report["scenes"] == 2
    (entry,) = report["bad_tails"]
    assert entry["file"] == str(path) and entry["records_kept"] == 2
    assert entry["byte_offset"] == len(two_records) and problem in entry["error"]
    warning = capsys.readouterr().err.strip()
    assert warning.startswith(f"convert-womd: warning: {path}: kept 2 good record(s)")
    assert f"from byte offset {len(two_records)}" in warning and problem in warning
    assert [s.scenario_id for s in load_scenarios(out / "part.scn.npz")] == ["first", "second"]


def test_the_cli_converts_the_good_records_and_lists_the_tail_in_json(tmp_path, capsys, two_records):
    path = tmp_path / "part.tfrecord"
    path.write_bytes(two_records + b"xyz")
    assert main(["convert-womd", str(path), "--out", str(tmp_path / "o"), "--json", "--quiet"]) == 0
    captured = capsys.readouterr()
    result = json.loads(captured.out)
    assert result["scenes"] == 2 and result["bad_tails"][0]["byte_offset"] == len(two_records)
    assert "part.tfrecord: kept 2 good record(s)" in captured.err


def test_a_bad_first_record_still_fails_the_file(tmp_path, two_records):
    path = tmp_path / "cut.tfrecord"
    path.write_bytes(two_records[:100])
    with pytest.raises(TFRecordFramingError, match=r"cut\.tfrecord: record 0 \(byte offset 0\)"):
        read_good_records(path)
    report = convert_womd([path], tmp_path / "out", progress=False)
    assert report["converted"] == [] and "record 0" in report["failed"][0]["error"]
    assert not (tmp_path / "out" / "cut.scn.npz").exists()


def test_an_empty_input_is_an_error_before_anything_is_converted(tmp_path, capsys, two_records):
    good = tmp_path / "good.tfrecord"
    good.write_bytes(two_records)
    empty = tmp_path / "empty.tfrecord"
    empty.write_bytes(b"")
    with pytest.raises(WomdFormatError, match=r"empty\.tfrecord: empty file"):
        convert_womd([good, empty], tmp_path / "out", progress=False)
    assert not (tmp_path / "out").exists()  # no 0-scene shard, and the good input waits for a fixed run
    assert main(["convert-womd", str(good), str(empty), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    message = f"{empty}: empty file (a WOMD TFRecord file holds at least one record)"
    assert captured.err.strip().splitlines() == [f"trajeglish convert-womd: error: {message}"]


def test_a_missing_input_is_one_line_on_stderr_and_exit_2(tmp_path, capsys):
    missing = Path(tmp_path / "missing.tfrecord")
    assert main(["convert-womd", str(missing), "--out", str(tmp_path / "out")]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err.strip().splitlines() == [
        f"trajeglish convert-womd: error: {missing}: no such WOMD TFRecord file"
    ]
    assert main(["convert-womd", str(tmp_path), "--out", str(tmp_path / "out")]) == 2
    assert "not a regular file" in capsys.readouterr().err
