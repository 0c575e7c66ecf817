"""Map chunk selection skips chunks whose bounding circle lies beyond the selection radius: the chunks chosen
and their order are exactly those of measuring every chunk (the shared WOMD city map, generated scenes)."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import womd_tfrecord

from trajeglish_env.model import map_chunks
from trajeglish_env.model.map_chunks import MapChunks, chunk_map, nearest_chunks
from trajeglish_env.sources.highway import generate_scene
from trajeglish_env.sources.womd import read_womd


def every_chunk_d2(
    chunks: MapChunks, anchors: np.ndarray, radius: float = np.inf, keep: int | None = None
) -> np.ndarray:
    """The reference: every chunk's distance measured."""
    d2 = ((chunks.points[:, :, None, :] - anchors[None, None]) ** 2).sum(-1).min(-1)
    return np.where(chunks.mask, d2, np.inf).min(-1)


@pytest.fixture(scope="module")
def womd():  # type: ignore[no-untyped-def]
    return next(read_womd(womd_tfrecord()))


def test_bounding_circles_hold_every_real_point(womd) -> None:  # type: ignore[no-untyped-def]
    chunks = chunk_map(womd, 20)
    centre, radius = chunks.bounds
    d = np.hypot(*(chunks.points - centre[:, None]).transpose(2, 0, 1))
    assert (np.where(chunks.mask, d, 0) <= radius[:, None] + 1e-9).all()
    assert chunks.num_chunks > 1000  # a city map: many chunks are far from any one window


@pytest.mark.parametrize("source", ["womd", "highway"])
def test_selection_equals_measuring_every_chunk(womd, source: str, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    scenes = [womd] if source == "womd" else [generate_scene(k, 3) for k in ("roundabout", "intersection")]
    rng = np.random.default_rng(0)
    for sc in scenes:
        chunks = chunk_map(sc, 20)
        live = sc.xyh[sc.valid]
        skipped = 0
        for _ in range(12):
            at = live[rng.integers(len(live))]
            anchors = live[rng.integers(len(live), size=rng.integers(1, 25)), :2] + rng.normal(0, 30, (1, 2))
            for radius in (20.0, 100.0):
                fast = map_chunks._nearest_d2(chunks, anchors, radius)
                full = every_chunk_d2(chunks, anchors)
                within = full <= radius * radius
                np.testing.assert_array_equal(fast[within], full[within])
                assert (fast[~within] > radius * radius).all()
                for keep in (8, 64, 256):  # the nearest `keep` are measured, whatever lies beyond
                    some = map_chunks._nearest_d2(chunks, anchors, radius, keep)
                    kth = np.sort(full)[min(keep, len(full)) - 1]
                    nearest = full <= min(kth, radius * radius)  # ties with the keep-th included
                    np.testing.assert_array_equal(some[nearest], full[nearest])
                    assert (np.isinf(some) | (some == full)).all()
                    skipped += int(np.isinf(some).sum() - np.isinf(full).sum())
                    got = nearest_chunks(chunks, at, keep, radius, None, anchors)
                    with monkeypatch.context() as m:
                        m.setattr(map_chunks, "_nearest_d2", every_chunk_d2)
                        want = nearest_chunks(chunks, at, keep, radius, None, anchors)
                    for a, b in zip(got, want, strict=True):
                        np.testing.assert_array_equal(a, b)
        if source == "womd":
            assert skipped > 0.5 * 72 * chunks.num_chunks  # most of the city map is never measured
