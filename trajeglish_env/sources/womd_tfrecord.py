"""TFRecord framing and CRC-32C for reading Waymo Open Motion Dataset files without TensorFlow.

A TFRecord file is a sequence of records, each framed as
``uint64 length (LE) | uint32 masked crc32c(length bytes) | data | uint32 masked crc32c(data)``.
Both checksums are verified; a gzip-compressed file (TensorFlow's ``GZIP`` option) is read through
:mod:`gzip`. CRC-32C is computed in NumPy: the data is cut into equal chunks whose
CRCs advance together one byte column at a time, then the chunk CRCs are folded with a precomputed
"append L zero bytes" linear map (CRCs are linear over GF(2)). A 1 MB record takes a few milliseconds.
"""

from __future__ import annotations

import gzip
import os
import zlib
from collections.abc import Iterator
from functools import lru_cache
from pathlib import Path
from typing import BinaryIO

import numpy as np

CRC32C_POLY = 0x82F63B78  # Castagnoli polynomial, bit-reflected
_MASK_DELTA = 0xA282EAD8  # TFRecord's checksum masking constant
_HEADER_BYTES = 12  # uint64 length + uint32 masked crc of the length
_FOOTER_BYTES = 4  # uint32 masked crc of the data
_SCALAR_LIMIT = 2048  # below this many bytes the plain table loop is faster than the vectorised one
_GZIP_MAGIC = b"\x1f\x8b"  # a TFRecord written with TensorFlow's GZIP compression option
_GZIP_PIECE = 1 << 24  # bytes decompressed per read of a gzip-compressed record
_GZIP_NOTE = " (gzip-compressed file: offsets are in the decompressed data)"


class WomdFormatError(ValueError):
    """A WOMD input is malformed (TFRecord framing, checksum or Scenario content); names file and record."""


def _make_table() -> np.ndarray:
    crc = np.arange(256, dtype=np.uint32)
    for _ in range(8):
        crc = np.where(crc & 1, (crc >> 1) ^ np.uint32(CRC32C_POLY), crc >> 1).astype(np.uint32)
    return crc


_TABLE = _make_table()
_TABLE_LIST = [int(v) for v in _TABLE]


def _crc_update_scalar(state: int, data: bytes | memoryview) -> int:
    table = _TABLE_LIST
    for byte in bytes(data):
        state = (state >> 8) ^ table[(state ^ byte) & 0xFF]
    return state


@lru_cache(maxsize=32)
def _zero_shift_tables(length: int) -> tuple[list[int], list[int], list[int], list[int]]:
    """Byte-indexed tables of the linear map "CRC register after ``length`` more zero bytes"."""
    basis = np.left_shift(np.uint32(1), np.arange(32, dtype=np.uint32))  # images of the 32 unit vectors
    for _ in range(length):
        basis = (basis >> np.uint32(8)) ^ _TABLE[basis & np.uint32(0xFF)]
    bits = ((np.arange(256)[:, None] >> np.arange(8)[None, :]) & 1).astype(bool)  # [256, 8]
    tables = []
    for b in range(4):
        cols = np.where(bits, basis[None, 8 * b : 8 * b + 8], np.uint32(0))
        tables.append([int(v) for v in np.bitwise_xor.reduce(cols, axis=1)])
    return tables[0], tables[1], tables[2], tables[3]


def crc32c(data: bytes | bytearray | memoryview) -> int:
    """CRC-32C (Castagnoli) of ``data``, as used by TFRecord; vectorised for large inputs."""
    view = memoryview(data).cast("B")
    n = len(view)
    if n < _SCALAR_LIMIT:
        return _crc_update_scalar(0xFFFFFFFF, view) ^ 0xFFFFFFFF
    # The initial register 0xFFFFFFFF equals XOR-ing 0xFF into the first four bytes and starting from 0;
    # leading zero bytes leave a zero register unchanged, so the data may be left-padded to a full grid.
    chunks = max(1, int(np.sqrt(n)))
    length = -(-n // chunks)
    grid = np.zeros(chunks * length, dtype=np.uint8)
    grid[-n:] = np.frombuffer(view, dtype=np.uint8)
    grid[-n : -n + 4] ^= 0xFF
    columns = np.ascontiguousarray(grid.reshape(chunks, length).T).astype(np.uint32)  # [length, chunks]
    state = np.zeros(chunks, dtype=np.uint32)
    mask = np.uint32(0xFF)
    eight = np.uint32(8)
    for column in columns:
        state = (state >> eight) ^ _TABLE[(state ^ column) & mask]
    t0, t1, t2, t3 = _zero_shift_tables(length)
    acc = 0
    for chunk_crc in state.tolist():
        acc = t0[acc & 0xFF] ^ t1[(acc >> 8) & 0xFF] ^ t2[(acc >> 16) & 0xFF] ^ t3[acc >> 24] ^ chunk_crc
    return acc ^ 0xFFFFFFFF


def masked_crc32c(data: bytes | bytearray | memoryview) -> int:
    """TFRecord's masked CRC-32C: rotate right by 15 bits and add a constant (mod 2**32)."""
    crc = crc32c(data)
    return (((crc >> 15) | (crc << 17)) + _MASK_DELTA) & 0xFFFFFFFF


class TFRecordFramingError(WomdFormatError):
    """Record ``record`` of a TFRecord file, starting at byte ``offset``, is truncated or corrupt; the
    records before it are intact (a reader may keep them and report the bad tail)."""

    def __init__(self, path: Path, record: int, offset: int, problem: str):
        super().__init__(f"{path}: record {record} (byte offset {offset}): {problem}")
        self.path, self.record, self.offset, self.problem = path, record, offset, problem


def _framing_error(path: Path, index: int, offset: int, problem: str) -> TFRecordFramingError:
    """The error of record ``index`` at byte ``offset``, naming the file."""
    return TFRecordFramingError(path, index, offset, problem)


def read_tfrecord(
    path: str | os.PathLike[str],
    *,
    check_data_crc: bool = True,
    bad_records: list[TFRecordFramingError] | None = None,
) -> Iterator[tuple[int, bytes]]:
    """Yield ``(record_index, data)`` for each record of a TFRecord file, verifying both checksums.

    Raises :class:`TFRecordFramingError` (a :class:`WomdFormatError`) naming the file, the record and its
    byte offset on a truncated or corrupt record, after yielding the good records before it.
    ``check_data_crc=False`` skips the data checksum (the length checksum is always verified). With a
    ``bad_records`` list, a record whose data checksum fails while its framing is intact (length checksum
    right, the whole record present) is appended to it as an error and skipped, and reading goes on; the
    indices of the later records still count it. A gzip-compressed file (TensorFlow's ``GZIP`` option,
    first bytes ``1f 8b``) is decompressed on the fly; its byte offsets are those of the decompressed data.
    """
    path = Path(path)
    with open(path, "rb") as fh:
        head = fh.read(_HEADER_BYTES)
        plain = len(head) == _HEADER_BYTES and masked_crc32c(head[:8]) == int.from_bytes(head[8:], "little")
        if head[:2] == _GZIP_MAGIC and not plain:  # a record length may start with 1f 8b: its CRC decides
            fh.seek(0)
            with gzip.GzipFile(fileobj=fh, mode="rb") as stream:
                yield from _records(path, stream, None, check_data_crc, bad_records)
            return
        fh.seek(0)
        yield from _records(path, fh, os.fstat(fh.fileno()).st_size, check_data_crc, bad_records)


def _read(path: Path, fh: BinaryIO, n: int, index: int, start: int, compressed: bool) -> bytes:
    """Up to ``n`` bytes of ``fh`` (fewer at its end); a broken gzip stream is a framing error."""
    if not compressed:
        return fh.read(n)
    parts = []
    try:
        while n > 0:  # in pieces: a huge length must not allocate before the data is there
            part = fh.read(min(n, _GZIP_PIECE))
            if not part:
                break
            parts.append(part)
            n -= len(part)
    except (EOFError, OSError, zlib.error) as exc:  # truncated download (EOFError), bad deflate data or CRC
        raise _framing_error(
            path, index, start, f"truncated or corrupt gzip stream: {exc}{_GZIP_NOTE}"
        ) from exc
    return b"".join(parts)


def _records(
    path: Path,
    fh: BinaryIO,
    size: int | None,
    check_data_crc: bool,
    bad_records: list[TFRecordFramingError] | None,
) -> Iterator[tuple[int, bytes]]:
    """The records of an open (plain, ``size`` bytes, or decompressed, ``size`` None) TFRecord stream."""
    compressed = size is None
    note = _GZIP_NOTE if compressed else ""
    index = start = 0
    while True:
        header = _read(path, fh, _HEADER_BYTES, index, start, compressed)
        if not header:
            return
        if len(header) < _HEADER_BYTES:
            raise _framing_error(
                path, index, start, f"truncated header: {len(header)} of {_HEADER_BYTES} bytes{note}"
            )
        length = int.from_bytes(header[:8], "little")
        if masked_crc32c(header[:8]) != int.from_bytes(header[8:12], "little"):
            raise _framing_error(
                path, index, start, f"length checksum mismatch (corrupt file or not a TFRecord file){note}"
            )
        left = None if size is None else size - start - _HEADER_BYTES
        if left is not None and length + _FOOTER_BYTES > left:
            raise _framing_error(
                path,
                index,
                start,
                f"truncated: the record needs {length + _FOOTER_BYTES} bytes but only {left} are left",
            )
        data = _read(path, fh, length, index, start, compressed)
        footer = _read(path, fh, _FOOTER_BYTES, index, start, compressed)
        if len(data) != length or len(footer) != _FOOTER_BYTES:
            got = len(data) + len(footer)
            problem = (
                f"truncated: the record needs {length + _FOOTER_BYTES} bytes but only {got} are left{note}"
                if compressed
                else "truncated while reading (file changed during the read?)"
            )
            raise _framing_error(path, index, start, problem)
        if check_data_crc and masked_crc32c(data) != int.from_bytes(footer, "little"):
            error = _framing_error(
                path, index, start, f"data checksum mismatch over {length} bytes (corrupt record){note}"
            )
            if bad_records is None:
                raise error
            bad_records.append(error)  # the framing is intact: the next record starts right after it
        else:
            yield index, data
        index += 1
        start += _HEADER_BYTES + length + _FOOTER_BYTES
