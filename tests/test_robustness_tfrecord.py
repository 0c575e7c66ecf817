"""Issue 17, bug 6: TFRecord conversion keeps the good records before a bad tail and reports the tail; an
empty input is an error (exit 2 from the command line), never a 0-scene shard.

The records are small synthetic WOMD scenes framed here, so these tests need no shared data.
"""

from __future__ import annotations

import gzip
import importlib.util
import json
import os
import struct
from pathlib import Path

import numpy as np
import pytest
from helpers import REPO

from trajeglish_env.cli import main
from trajeglish_env.scenario_io import load_scenarios
from trajeglish_env.sources.womd import (
    TFRecordFramingError,
    WomdFormatError,
    parse_scenario,
    read_good_records,
    read_tfrecord,
    read_womd,
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


# ------------------------------------------------------------------------------------- audit fixes
def _convert(paths, out, **kwargs):
    return convert_womd([Path(p) for p in paths], out, progress=False, **kwargs)


def test_an_input_replaced_by_a_complete_file_is_converted_again(tmp_path, capsys, two_records):
    path = tmp_path / "grow.tfrecord"
    path.write_bytes(two_records + _frame(_scenario_record("third"))[:40])  # an interrupted copy
    out = tmp_path / "out"
    first = _convert([path], out)
    assert first["converted"] == [str(path)] and first["scenes"] == 2 and first["bad_tails"], first
    again = _convert([path], out)  # unchanged, but converted with a bad tail: converted again
    assert again["converted"] == [str(path)], f"{path}: an input with a bad tail must be converted again"
    path.write_bytes(two_records + _frame(_scenario_record("third")))  # the copy completed in place
    report = _convert([path], out)
    assert report["converted"] == [str(path)] and report["skipped"] == [], (
        f"{path} changed since it was converted: expected it converted again, got {report}"
    )
    ids = [s.scenario_id for s in load_scenarios(out / "grow.scn.npz")]
    assert ids == ["first", "second", "third"], f"{out / 'grow.scn.npz'}: expected 3 scenes, got {ids}"
    assert report["bad_tails"] == [] and report["reconverted"][0]["file"] == str(path)
    resumed = _convert([path], out)  # unchanged and complete: skipped (resumable runs)
    assert resumed["skipped"] == [str(path)] and resumed["converted"] == [], resumed
    capsys.readouterr()


def test_an_input_rewritten_with_the_same_size_but_a_new_mtime_is_converted_again(tmp_path, two_records):
    path = tmp_path / "same.tfrecord"
    path.write_bytes(two_records)
    out = tmp_path / "out"
    assert _convert([path], out)["converted"] == [str(path)]
    assert _convert([path], out)["skipped"] == [str(path)]
    path.write_bytes(_frame(_scenario_record("first")) + _frame(_scenario_record("sEcond")))
    assert path.stat().st_size == len(two_records)  # same size, other content
    stat = path.stat()
    os.utime(path, ns=(stat.st_atime_ns, stat.st_mtime_ns + 1_000_000_000))
    report = _convert([path], out)
    assert report["converted"] == [str(path)], f"{path}: new mtime, expected a new conversion, got {report}"
    ids = [s.scenario_id for s in load_scenarios(out / "same.scn.npz")]
    assert ids == ["first", "sEcond"], f"{out / 'same.scn.npz'}: expected the new scenes, got {ids}"


def test_a_corrupt_record_in_the_middle_is_skipped_and_the_rest_is_read(tmp_path, capsys):
    frames = [_frame(_scenario_record(name)) for name in ("first", "second", "third")]
    raw = bytearray(b"".join(frames))
    raw[len(frames[0]) + 12 + 20] ^= 0x40  # a byte of record 1's data: its data CRC fails, framing intact
    path = tmp_path / "mid.tfrecord"
    path.write_bytes(bytes(raw))
    bad: list = []
    scenes, tail = read_good_records(path, bad_records=bad)
    ids = [s.scenario_id for s in scenes]
    assert ids == ["first", "third"] and tail is None, f"{path}: expected records 0 and 2 kept, got {ids}"
    assert [(b.record, b.offset) for b in bad] == [(1, len(frames[0]))]
    report = _convert([path], tmp_path / "out")
    assert report["scenes"] == 2 and report["bad_tails"] == [], f"{path}: expected 2 scenes, got {report}"
    (entry,) = report["bad_records"]
    assert entry["file"] == str(path) and entry["record"] == 1 and entry["byte_offset"] == len(frames[0])
    assert "data checksum mismatch" in entry["error"]
    err = capsys.readouterr().err
    assert f"{path}: skipped corrupt record 1 (byte offset {len(frames[0])})" in err, err
    with pytest.raises(TFRecordFramingError, match=r"mid\.tfrecord: record 1 .*data checksum mismatch"):
        list(read_tfrecord(path))  # the plain reader stays strict


def test_a_gzip_compressed_tfrecord_is_read_transparently(tmp_path, two_records):
    path = tmp_path / "zipped.tfrecord"
    path.write_bytes(gzip.compress(two_records))
    ids = [s.scenario_id for s in read_womd(path)]
    assert ids == ["first", "second"], f"{path}: gzip-compressed TFRecord: expected 2 scenes, got {ids}"
    report = _convert([path], tmp_path / "out")
    assert report["scenes"] == 2 and report["failed"] == [], f"{path}: expected 2 scenes, got {report}"
    cut = tmp_path / "cut.tfrecord"
    cut.write_bytes(gzip.compress(two_records)[:-20])  # an interrupted download of the .gz
    with pytest.raises(TFRecordFramingError, match=r"cut\.tfrecord: record \d .*gzip"):
        list(read_tfrecord(cut))
    plain = tmp_path / "plain.tfrecord"  # a plain record whose length's first bytes are gzip's 1f 8b
    plain.write_bytes(_frame(b"x" * 0x8B1F))
    assert plain.read_bytes()[:2] == b"\x1f\x8b"
    assert list(read_tfrecord(plain)) == [(0, b"x" * 0x8B1F)], f"{plain}: a plain TFRecord read as gzip"


def test_read_womd_on_an_empty_file_is_an_error(tmp_path):
    empty = tmp_path / "empty.tfrecord"
    empty.write_bytes(b"")
    with pytest.raises(WomdFormatError, match=r"empty\.tfrecord: no records \(empty file"):
        list(read_womd(empty))
    with pytest.raises(WomdFormatError, match=r"empty\.tfrecord: no records \(empty file"):
        read_good_records(empty)


def test_the_same_input_twice_is_converted_once(tmp_path, capsys, two_records):
    path = tmp_path / "dup.tfrecord"
    path.write_bytes(two_records)
    (tmp_path / "sub").mkdir()
    link = tmp_path / "link.tfrecord"
    link.symlink_to(path)
    spellings = [path, path, tmp_path / "sub" / ".." / "dup.tfrecord"]
    for i, inputs in enumerate((spellings, [path, link])):
        report = _convert(inputs, tmp_path / f"out{i}", workers=2)
        assert report["converted"] == [str(path)] and report["scenes"] == 2, (
            f"{inputs}: the same file listed twice must be converted once, got {report}"
        )
        assert [d["file"] for d in report["duplicates"]] == [str(p) for p in inputs[1:]]
        assert all(d["same_as"] == str(path) for d in report["duplicates"])
    assert "is the same file as" in capsys.readouterr().err


def test_a_repeated_input_is_named_as_it_was_given(tmp_path, capsys, monkeypatch, two_records):
    """``convert-womd bad/copy.tfrecord ./bad/copy.tfrecord`` said "bad/copy.tfrecord is the same file as
    bad/copy.tfrecord" (both read back through Path, which drops the "./")."""
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "copy.tfrecord").write_bytes(two_records)
    monkeypatch.chdir(tmp_path)
    argv = ["convert-womd", "bad/copy.tfrecord", "./bad/copy.tfrecord", "bad/copy.tfrecord", "--out", "o"]
    assert main([*argv, "--json", "--quiet"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["converted"] == ["bad/copy.tfrecord"] and report["duplicates"] == [
        {"file": "./bad/copy.tfrecord", "same_as": "bad/copy.tfrecord"},
        {"file": "bad/copy.tfrecord", "same_as": "bad/copy.tfrecord"},
    ]
    assert main(argv) == 0  # the notes on stderr (the outputs are there: skipped this time)
    err = capsys.readouterr().err
    assert "./bad/copy.tfrecord is the same file as bad/copy.tfrecord: converted once" in err
    assert "note: bad/copy.tfrecord is given again: converted once" in err


def test_a_ragged_track_is_named():
    proto = ScenarioProto.FromString(_scenario_record("ragged"))
    del proto.tracks[1].states[-1]
    with pytest.raises(WomdFormatError, match=r"track 11 \(index 1\) has 10 states; the others have 11"):
        parse_scenario(proto.SerializeToString(), origin="r.tfrecord: record 0")


def _womd_scene():
    spec = importlib.util.spec_from_file_location("example_womd_scene", REPO / "examples" / "womd_scene.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_womd_scene_example_names_a_bad_file_and_picks_a_scene_by_index(tmp_path, capsys, two_records):
    example = _womd_scene()
    for name, content in (("empty", b""), ("corrupt", b"\x00" * 40)):
        bad = tmp_path / f"{name}.tfrecord"
        bad.write_bytes(content)
        with pytest.raises(SystemExit) as exit_info:
            example.main(["--tfrecord", str(bad), "--npc", "idm"])
        assert exit_info.value.code == 2, f"{bad}: expected exit 2, got {exit_info.value.code}"
        lines = capsys.readouterr().err.strip().splitlines()
        assert len(lines) == 1 and str(bad) in lines[0] and "error" in lines[0], lines
    path = tmp_path / "two.tfrecord"
    path.write_bytes(two_records)
    assert example.load_scene(path, 1).scenario_id == "second"
    with pytest.raises(SystemExit) as exit_info:
        example.main(["--tfrecord", str(path), "--index", "2"])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip()
    assert f"{path} holds 2 scenario(s); --index 2 is out of range" in err, err
