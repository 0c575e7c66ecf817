"""Per-step box-overlap (collision) flags for agents of one scene, to compare raw and tokenized scenes."""

from __future__ import annotations

import numpy as np

from trajeglish_env.geometry import box_corners


def boxes_overlap(a_xyh: np.ndarray, a_size: np.ndarray, b_xyh: np.ndarray, b_size: np.ndarray) -> np.ndarray:
    """Whether oriented boxes ``a`` and ``b`` (``[...,3]`` states, ``[...,2]`` sizes) overlap (SAT)."""
    ca = box_corners(a_xyh, a_size)  # [...,4,2]
    cb = box_corners(b_xyh, b_size)
    overlap = np.ones(ca.shape[:-2], dtype=bool)
    for heading in (a_xyh[..., 2], b_xyh[..., 2]):
        for axis in (
            np.stack([np.cos(heading), np.sin(heading)], -1),
            np.stack([-np.sin(heading), np.cos(heading)], -1),
        ):
            pa = (ca * axis[..., None, :]).sum(-1)
            pb = (cb * axis[..., None, :]).sum(-1)
            overlap &= (pa.max(-1) > pb.min(-1)) & (pb.max(-1) > pa.min(-1))
    return overlap


def scene_pairs(scene: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """All unordered pairs ``(i, j)``, ``i < j``, of rows that belong to the same scene."""
    if not len(scene):
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    order = np.argsort(scene, kind="stable")
    counts = np.bincount(scene)
    starts = np.r_[0, np.cumsum(counts)[:-1]]
    first, second = [], []
    for start, n in zip(starts, counts, strict=True):  # one block of pairs per scene
        if n > 1:
            i, j = np.triu_indices(n, 1)
            first.append(order[start + i])
            second.append(order[start + j])
    if not first:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    return np.concatenate(first), np.concatenate(second)


def collision_flags(
    xyh: np.ndarray, valid: np.ndarray, size: np.ndarray, scene: np.ndarray, chunk: int = 20000
) -> np.ndarray:
    """``[R,T]`` bool: row ``r`` overlaps some other valid row of its scene at step ``t``."""
    hit = np.zeros(valid.shape, dtype=bool)
    first, second = scene_pairs(scene)
    reach = 0.5 * np.hypot(size[:, 0], size[:, 1])
    for start in range(0, len(first), chunk):
        i, j = first[start : start + chunk], second[start : start + chunk]
        both = valid[i] & valid[j]
        gap = np.hypot(xyh[i, :, 0] - xyh[j, :, 0], xyh[i, :, 1] - xyh[j, :, 1])
        near = both & (gap < (reach[i] + reach[j])[:, None])
        p, t = np.nonzero(near)
        if not len(p):
            continue
        ii, jj = i[p], j[p]
        over = boxes_overlap(xyh[ii, t], size[ii], xyh[jj, t], size[jj])
        hit[ii[over], t[over]] = True
        hit[jj[over], t[over]] = True
    return hit
