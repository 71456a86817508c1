"""The sessions of a store in the viewer (:mod:`driftmap.viewer`): for ``--color session``, which session each frame
belongs to (a merged store's, :func:`driftmap.pipeline.merge.store_sessions`; one session for a store that no merge
made), each session's colour (:data:`~driftmap.render.SESSION_PALETTE_RGB`) and the legend; for ``--color state
--latest-state``, a merged store's latest-state layers (:func:`latest_state_of`)."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from driftmap.render import SESSION_PALETTE_RGB, session_color_rgb, session_color_text

from driftmap.errors import ConfigError

if TYPE_CHECKING:
    from driftmap.store.frame_store import FrameStore
    from driftmap.volume import VolumeLayers

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class SessionColor:
    """One session of a store in ``--color session``: its colour, its frames and where they came from."""

    session: int
    rgb: tuple[int, int, int]
    n_frames: int
    source_store: str | None
    """The store the session was merged from (``driftmap merge``); None for a store that no merge made (one session)."""
    n_points_shown: int = 0
    """Points of the picture that came from this session's frames."""

    @property
    def color_text(self) -> str:
        """``#rrggbb (name)``."""
        return session_color_text(self.session)


def store_session_ids(store: FrameStore) -> tuple[NDArray[np.int64], list[tuple[int, int, str | None]]]:
    """The session of each of ``store.frame_ids`` and ``(session, frames, source store)`` per session: a merged
    store's sessions (:func:`driftmap.pipeline.merge.store_sessions`), else one session 0 holding every frame."""
    from driftmap.pipeline.merge import frame_origin, store_sessions

    sessions = store_sessions(store)
    frame_ids = np.asarray(store.frame_ids, np.int64)
    if not sessions:
        logger.info("view: %s is not a merged store: one session, one colour", store.path)
        return np.zeros(len(frame_ids), np.int64), [(0, len(frame_ids), None)]
    per_frame = np.empty(len(frame_ids), np.int64)
    rows: list[tuple[int, int, str | None]] = []
    for k, ids in sorted(sessions.items()):
        per_frame[np.searchsorted(frame_ids, np.asarray(ids, np.int64))] = k
        origin = frame_origin(store.frame_info(int(ids[0])).get("provenance"))
        rows.append((k, len(ids), None if origin is None else origin.store))
    if len(sessions) > len(SESSION_PALETTE_RGB):
        logger.warning("view: %d sessions but %d session colours: colours repeat (session k has colour k %% %d)",
                       len(sessions), len(SESSION_PALETTE_RGB), len(SESSION_PALETTE_RGB))
    return per_frame, rows


def session_colours(store: FrameStore, frame_ids: NDArray[np.int64]) -> tuple[NDArray[np.float64], NDArray[np.uint8],
                                                                               tuple[SessionColor, ...]]:
    """Colour ``session``: the session of each shown point (its frame's), its colour and the legend."""
    per_frame, rows = store_session_ids(store)
    point_sessions = per_frame[np.searchsorted(store.frame_ids, frame_ids)]
    palette = np.asarray(SESSION_PALETTE_RGB, np.uint8)
    colors = palette[point_sessions % len(palette)]
    legend = tuple(SessionColor(k, session_color_rgb(k), n, src, int(np.count_nonzero(point_sessions == k)))
                   for k, n, src in rows)
    for entry in legend:
        logger.info("view: session %d %s: %d frames, %d points shown", entry.session, entry.color_text, entry.n_frames,
                    entry.n_points_shown)
    return point_sessions.astype(np.float64), colors, legend


def latest_state_of(store: FrameStore, revision: int, voxel_size_m: float | None, color: str = "state") -> VolumeLayers:
    """A merged store's latest-state layers of ``revision`` (:func:`driftmap.volume.sessions.latest_state_layers`: each
    voxel as the newest session that observed it saw it) for ``--color state``; :class:`ConfigError` for another
    colour and for a store of one session (its layers are its latest state already)."""
    from driftmap.pipeline.merge import store_sessions
    from driftmap.volume import VolumeConfig
    from driftmap.volume.sessions import latest_state_layers

    if color != "state":
        raise ConfigError(f"--latest-state applies to --color state (the volumetric layers), not --color {color}")

    sessions = store_sessions(store)
    if len(sessions) < 2:
        raise ConfigError(f"{store.path} holds one session (no store that driftmap merge made): its layers are its "
                          f"latest state already; leave --latest-state out")
    state = latest_state_layers(store, sessions, revision, VolumeConfig(voxel_size_m=voxel_size_m))
    logger.info("view: latest-state layers of %d sessions, voxels decided per session %s", len(state.order),
                state.voxels_per_session())
    return state.layers
