"""Correction propagation: how the poses given for some frames (keyframes) move the frames between them.

For keyframes ``k`` given new poses ``N_k`` whose parent-revision poses are ``O_k``, the world-frame correction of
a keyframe is ``D_k = N_k @ inv(O_k)``. Frames are ordered by ``(stamp_ns, frame_id)``; a non-keyframe ``f`` (stamp
``t``) takes the keyframe ``a`` just before it and ``b`` just after it in that order. With only one of them it uses
that keyframe's ``D`` (so it keeps its pose relative to that keyframe exactly); with ``t_a == t_b`` it uses
``D_a``; otherwise ``D = interpolate_se3(D_a, D_b, alpha)`` with ``alpha = (t - t_a) / (t_b - t_a)``. Its new pose
is ``D @ O_f``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from driftmap import geometry


def propagate_correction(
    ids: NDArray[np.int64], stamps: NDArray[np.int64], O: NDArray[np.float64], key_ids: NDArray[np.int64],
    key_poses: NDArray[np.float64],
) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """Ids and new poses of every non-keyframe (vectorised; see the module docstring for the rule).

    ``ids`` (sorted) and ``stamps``: every frame; ``O``: their poses in the parent revision; ``key_ids`` (sorted,
    all in ``ids``) and ``key_poses``: the keyframes and their new poses."""
    n = len(ids)
    key_idx = np.searchsorted(ids, key_ids)
    D_key = key_poses @ geometry.invert(O[key_idx])  # world-frame correction of each keyframe
    key_row = np.full(n, -1, dtype=np.intp)
    key_row[key_idx] = np.arange(len(key_idx))

    # neighbouring keyframes in (stamp, frame_id) order, found by forward / backward fill
    order = np.lexsort((ids, stamps))
    is_key = key_row[order] >= 0
    pos = np.arange(n)
    prev_pos = np.maximum.accumulate(np.where(is_key, pos, -1))
    next_pos = np.minimum.accumulate(np.where(is_key, pos, n)[::-1])[::-1]
    prev_key = np.full(n, -1, dtype=np.intp)
    next_key = np.full(n, -1, dtype=np.intp)
    prev_key[order] = np.where(prev_pos >= 0, key_row[order[np.clip(prev_pos, 0, n - 1)]], -1)
    next_key[order] = np.where(next_pos < n, key_row[order[np.clip(next_pos, 0, n - 1)]], -1)

    f = np.flatnonzero(key_row < 0)  # non-keyframes, in frame-id order
    a, b = prev_key[f], next_key[f]
    D = np.empty((len(f), 4, 4))
    only_a, only_b = b < 0, a < 0
    D[only_a] = D_key[a[only_a]]
    D[only_b] = D_key[b[only_b]]
    both = np.flatnonzero((a >= 0) & (b >= 0))
    if both.size:
        ka, kb = a[both], b[both]
        t = stamps[f[both]]
        t_a, t_b = stamps[key_idx[ka]], stamps[key_idx[kb]]
        span = t_b - t_a
        alpha = np.where(span > 0, (t - t_a) / np.where(span > 0, span, 1), 0.0)
        # one relative twist per keyframe interval; identical corrections need no interpolation at all
        pairs, inverse = np.unique(np.stack([ka, kb], axis=1), axis=0, return_inverse=True)
        inverse = inverse.reshape(-1)
        Da, Db = D_key[pairs[:, 0]], D_key[pairs[:, 1]]
        xi = geometry.se3_log(geometry.invert(Da) @ Db)
        xi[np.all(Da == Db, axis=(1, 2))] = 0.0
        D_both = D_key[ka] @ geometry.se3_exp(alpha[:, None] * xi[inverse])
        # exactly on a keyframe's stamp: that keyframe's correction, bit for bit
        at_a, at_b = alpha == 0.0, alpha == 1.0
        D_both[at_a] = D_key[ka[at_a]]
        D_both[at_b] = D_key[kb[at_b]]
        D[both] = D_both
    new = D @ O[f]
    new[:, 3] = (0.0, 0.0, 0.0, 1.0)
    return ids[f], new
