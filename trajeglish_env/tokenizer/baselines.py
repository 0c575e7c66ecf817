"""Baseline template sets from the paper's appendix "Tokenization Analysis": two grids and k-means.

- ``(x,y,h)``-grid: the product of evenly spaced dx, dy, dh values.
- ``(x,y)``-grid: evenly spaced dx, dy; each template's heading is that of the data transition whose
  location is closest to the template's.
- k-means: Lloyd's algorithm on the (dx, dy) of transitions, seeded with k-means++; a template's heading is
  the circular mean heading of its cluster.
The grids use the paper's value counts, so their template counts (144/294/448/648 and 144/256/400/529)
differ slightly from the nominal vocabulary size; evaluations report both.
"""

from __future__ import annotations

import numpy as np

from trajeglish_env.tokenizer.nearest import thin_matmul

X_RANGE = (-0.3, 3.5)
Y_RANGE = (-0.2, 0.2)
H_RANGE = (-0.1, 0.1)
# Nominal V -> (values for x and y, values for h).
XYH_GRID_COUNTS = {128: (6, 4), 256: (7, 6), 384: (8, 7), 512: (9, 8)}
# Nominal V -> values for x and y.
XY_GRID_COUNTS = {128: 12, 256: 16, 384: 20, 512: 23}


def _counts(table: dict, vocab_size: int, name: str):  # type: ignore[no-untyped-def]
    if vocab_size not in table:
        raise ValueError(f"{name}: the paper defines vocabulary sizes {sorted(table)}, got {vocab_size}")
    return table[vocab_size]


def xyh_grid_templates(vocab_size: int) -> np.ndarray:
    """The ``(x,y,h)``-grid for nominal ``vocab_size``: ``[n_xy * n_xy * n_h, 3]``, x slowest, h fastest."""
    n_xy, n_h = _counts(XYH_GRID_COUNTS, vocab_size, "xyh-grid")
    x, y, h = np.meshgrid(
        np.linspace(*X_RANGE, n_xy), np.linspace(*Y_RANGE, n_xy), np.linspace(*H_RANGE, n_h), indexing="ij"
    )
    return np.stack([x.ravel(), y.ravel(), h.ravel()], 1)


def xy_grid_templates(vocab_size: int, transitions: np.ndarray, chunk: int = 8192) -> np.ndarray:
    """The ``(x,y)``-grid ``[n * n, 3]``; headings from the transitions ``[M,3]`` nearest in location."""
    n = _counts(XY_GRID_COUNTS, vocab_size, "xy-grid")
    if len(transitions) == 0:
        raise ValueError("xy-grid: needs at least one transition to choose headings")
    x, y = np.meshgrid(np.linspace(*X_RANGE, n), np.linspace(*Y_RANGE, n), indexing="ij")
    grid = np.stack([x.ravel(), y.ravel()], 1)
    weights = np.concatenate([-2.0 * grid.T, np.ones((1, len(grid)))])  # |p|^2 - 2 p.g (+|g|^2, constant)
    best_key = np.full(len(grid), np.inf)
    best_h = np.zeros(len(grid))
    buffer = np.empty((min(chunk, len(transitions)), len(grid)))
    for start in range(0, len(transitions), chunk):
        part = transitions[start : start + chunk]
        rows = np.concatenate([part[:, :2], (part[:, :2] ** 2).sum(1, keepdims=True)], 1)
        key = thin_matmul(rows, weights, buffer)
        j = key.argmin(0)
        value = key[j, np.arange(len(grid))]
        better = value < best_key
        best_key[better], best_h[better] = value[better], part[j[better], 2]
    return np.concatenate([grid, best_h[:, None]], 1)


def _kmeans_pp(points: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
    """k-means++ seeding: indices of ``k`` initial centres among ``points [M,2]``."""
    picks = [int(rng.integers(len(points)))]
    d2 = ((points - points[picks[0]]) ** 2).sum(1)
    for _ in range(1, k):
        total = d2.sum()
        idx = (
            int(rng.integers(len(points)))
            if total <= 0
            else int(np.searchsorted(np.cumsum(d2), rng.random() * total))
        )
        idx = min(idx, len(points) - 1)
        picks.append(idx)
        d2 = np.minimum(d2, ((points - points[idx]) ** 2).sum(1))
    return np.asarray(picks)


def _assign(points: np.ndarray, centers: np.ndarray, chunk: int = 8192) -> np.ndarray:
    """Index of the nearest centre (squared L2) for each point."""
    out = np.empty(len(points), dtype=np.int64)
    weights = np.concatenate([-2.0 * centers.T, (centers**2).sum(1)[None]])  # [3,k]: -2 p.c + |c|^2
    padded = np.concatenate([points, np.ones((len(points), 1))], 1)
    buffer = np.empty((min(chunk, len(points)), len(centers)))
    for start in range(0, len(points), chunk):
        out[start : start + chunk] = thin_matmul(padded[start : start + chunk], weights, buffer).argmin(1)
    return out


def kmeans_templates(
    transitions: np.ndarray, vocab_size: int, rng: np.random.Generator, iterations: int = 30
) -> np.ndarray:
    """Templates ``[vocab_size, 3]`` by k-means (k-means++ seeding, Lloyd) on the (dx, dy) of ``transitions``.

    A cluster that becomes empty keeps its previous centre and heading.
    """
    transitions = np.asarray(transitions, dtype=np.float64)
    if len(transitions) < vocab_size:
        raise ValueError(f"k-means: {len(transitions)} transitions cannot make {vocab_size} clusters")
    points = transitions[:, :2]
    seeds = _kmeans_pp(points, vocab_size, rng)
    centers = points[seeds].copy()
    heading = transitions[seeds, 2].copy()
    for _ in range(iterations):
        label = _assign(points, centers)
        count = np.bincount(label, minlength=vocab_size)
        filled = count > 0
        sums = np.stack([np.bincount(label, weights=points[:, i], minlength=vocab_size) for i in range(2)], 1)
        new = centers.copy()
        new[filled] = sums[filled] / count[filled, None]
        moved = np.abs(new - centers).max()
        centers = new
        if moved < 1e-7:
            break
    label = _assign(points, centers)
    filled = np.bincount(label, minlength=vocab_size) > 0
    sin = np.bincount(label, weights=np.sin(transitions[:, 2]), minlength=vocab_size)
    cos = np.bincount(label, weights=np.cos(transitions[:, 2]), minlength=vocab_size)
    heading[filled] = np.arctan2(sin[filled], cos[filled])
    return np.concatenate([centers, heading[:, None]], 1)
