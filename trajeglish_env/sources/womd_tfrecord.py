"""TFRecord framing and CRC-32C for reading Waymo Open Motion Dataset files without TensorFlow.

A TFRecord file is a sequence of records, each framed as
``uint64 length (LE) | uint32 masked crc32c(length bytes) | data | uint32 masked crc32c(data)``.
Both checksums are verified. CRC-32C is computed in NumPy: the data is cut into equal chunks whose
CRCs advance together one byte column at a time, then the chunk CRCs are folded with a precomputed
"append L zero bytes" linear map (CRCs are linear over GF(2)). A 1 MB record takes a few milliseconds.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from functools import lru_cache
from pathlib import Path

import numpy as np

CRC32C_POLY = 0x82F63B78  # Castagnoli polynomial, bit-reflected
_MASK_DELTA = 0xA282EAD8  # TFRecord's checksum masking constant
_HEADER_BYTES = 12  # uint64 length + uint32 masked crc of the length
_FOOTER_BYTES = 4  # uint32 masked crc of the data
_SCALAR_LIMIT = 2048  # below this many bytes the plain table loop is faster than the vectorised one


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
    path: str | os.PathLike[str], *, check_data_crc: bool = True
) -> Iterator[tuple[int, bytes]]:
    """Yield ``(record_index, data)`` for each record of a TFRecord file, verifying both checksums.

    Raises :class:`TFRecordFramingError` (a :class:`WomdFormatError`) naming the file, the record and its
    byte offset on a truncated or corrupt record, after yielding the good records before it.
    ``check_data_crc=False`` skips the data checksum (the length checksum is always verified).
    """
    path = Path(path)
    with open(path, "rb") as fh:
        size = os.fstat(fh.fileno()).st_size
        index = 0
        while True:
            start = fh.tell()
            header = fh.read(_HEADER_BYTES)
            if not header:
                return
            if len(header) < _HEADER_BYTES:
                raise _framing_error(
                    path, index, start, f"truncated header: {len(header)} of {_HEADER_BYTES} bytes"
                )
            length = int.from_bytes(header[:8], "little")
            if masked_crc32c(header[:8]) != int.from_bytes(header[8:12], "little"):
                raise _framing_error(
                    path, index, start, "length checksum mismatch (corrupt file or not a TFRecord file)"
                )
            left = size - start - _HEADER_BYTES
            if length + _FOOTER_BYTES > left:
                raise _framing_error(
                    path,
                    index,
                    start,
                    f"truncated: the record needs {length + _FOOTER_BYTES} bytes but only {left} are left",
                )
            data = fh.read(length)
            footer = fh.read(_FOOTER_BYTES)
            if len(data) != length or len(footer) != _FOOTER_BYTES:
                raise _framing_error(
                    path, index, start, "truncated while reading (file changed during the read?)"
                )
            if check_data_crc and masked_crc32c(data) != int.from_bytes(footer, "little"):
                raise _framing_error(
                    path, index, start, f"data checksum mismatch over {length} bytes (corrupt record)"
                )
            yield index, data
            index += 1
