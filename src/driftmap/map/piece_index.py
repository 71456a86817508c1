"""The map view's queries see each frame's world points as pieces of ``piece_points`` consecutive points (the map
view's ``QUERY_PIECE_POINTS``) with their own world boxes (:class:`PieceIndex`): a query reads only the pieces its
region overlaps."""

from __future__ import annotations

import numba
import numpy as np
from numpy.typing import NDArray

from driftmap.kernels.points import piece_boxes, piece_boxes_run


def parallel_pass(n_pieces: int, n_points: int, min_points: int) -> bool:
    """Whether a query pass over ``n_points`` in ``n_pieces`` pieces is worth a parallel region (at least
    ``min_points``: the map view's ``QUERY_PARALLEL_POINTS``)."""
    return n_pieces > 1 and n_points >= min_points and numba.get_num_threads() > 1


class PieceIndex:
    """The map's points as pieces of ``piece_points`` consecutive points of one frame, with per-piece
    world boxes (points with a NaN coordinate left out) and whether a piece holds no NaN point. Kept up to date
    lazily by the queries: a frame's pieces are re-measured when its pose differs (bitwise, or is NaN: stale)
    from the pose they were measured under, since a frame's world points change only with its pose."""

    def __init__(self, piece_points: int = 2048) -> None:
        self.piece_points = piece_points
        self.T = np.zeros((0, 4, 4))
        self.first = np.zeros(1, np.int64)  # per frame row: its first piece; first[-1] = the number of pieces
        self.starts = np.zeros(0, np.int64)  # per piece: first and end point (rows of the world array)
        self.stops = np.zeros(0, np.int64)
        self.rows = np.zeros(0, np.int64)  # per piece: its frame row
        self.boxes = np.zeros((0, 6), np.float32)
        self.clean = np.zeros(0, np.bool_)

    @property
    def n_pieces(self) -> int:
        return int(self.first[-1])

    def update(self, n_frames: int, offsets: NDArray[np.int64], T: NDArray[np.float64], world: NDArray[np.float32],
               *, piece_points: int, parallel_min_points: int) -> PieceIndex:
        """Bring the pieces up to date with the view's ``n_frames`` frames (point ``offsets`` per frame row, poses
        ``T``, world points ``world``); pieces of another size than ``piece_points`` are measured again."""
        if self.piece_points != piece_points:
            self.__init__(piece_points)
        m0, m = len(self.T), n_frames
        if m > m0:  # frames added since: their pieces, to be measured below
            size = self.piece_points
            lo, hi = offsets[m0:m], offsets[m0 + 1 : m + 1]
            n = -(-(hi - lo) // size)
            owner = np.repeat(np.arange(m - m0), n)
            first = np.concatenate([[0], np.cumsum(n)[:-1]]).astype(np.int64)
            starts = lo[owner] + (np.arange(int(n.sum())) - first[owner]) * size
            self.first = np.concatenate([self.first[:-1], self.n_pieces + np.concatenate([first, [n.sum()]])])
            self.starts = np.concatenate([self.starts, starts])
            self.stops = np.concatenate([self.stops, np.minimum(starts + size, hi[owner])])
            self.rows = np.concatenate([self.rows, m0 + owner])
            self.boxes = np.concatenate([self.boxes, np.empty((starts.size, 6), np.float32)])
            self.clean = np.concatenate([self.clean, np.zeros(starts.size, np.bool_)])
            self.T = np.concatenate([self.T, np.full((m - m0, 4, 4), np.nan)])
        stale = np.flatnonzero(~np.all(self.T == T, axis=(1, 2)))
        if stale.size:
            n = self.first[stale + 1] - self.first[stale]
            owner = np.repeat(np.arange(stale.size), n)
            sel = self.first[stale][owner] + np.arange(int(n.sum())) - np.concatenate([[0], np.cumsum(n)[:-1]])[owner]
            boxes = np.empty((sel.size, 6), np.float32)
            clean = np.empty(sel.size, np.bool_)
            starts, stops = self.starts[sel], self.stops[sel]
            if parallel_pass(sel.size, int((stops - starts).sum()), parallel_min_points):
                piece_boxes(world, starts, stops, boxes, clean, numba.get_num_threads())
            else:
                piece_boxes_run(world, starts, stops, boxes, clean, 0, sel.size)
            self.boxes[sel] = boxes
            self.clean[sel] = clean
            self.T[stale] = T[stale]
        return self
