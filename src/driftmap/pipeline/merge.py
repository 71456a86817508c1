"""``driftmap merge``: several stores of the same place (sessions) -> one merged store whose pose graph holds every
session's trajectory and the loops between them (issue 26, first slice).

Stages, each reusing what ``build`` does:

1. **Check the sources** (opened read-only; nothing is ever written to them): at least two, no store twice (the same
   folder, a link to it or a copy: the same store uuid), one sensor kind and the same kind of intrinsics in all.
2. **Keyframes per session** on its head revision: :func:`~driftmap.registration.loops.select_keyframes` and
   :func:`~driftmap.pipeline.loop_closure.keyframe_clouds` with the loop-closure settings ``build`` uses for the
   first session's sensor (:func:`~driftmap.pipeline.loop_closure.loop_config_for`).
3. **Loops between sessions** (:mod:`driftmap.pipeline.merge_loops`): place-descriptor candidates only, verified with
   ``build``'s gates, a consensus check per session pair; sessions not connected to session 0 are reported and left
   out (never forced in). If no session connects, nothing is written and the error says so.
4. **The merged store** (``out``, a new store): every frame of each connected session in session order, its points
   untouched, with a new id ``session * SESSION_ID_STRIDE + source frame id`` and a provenance naming the session,
   the source store (path, uuid, head revision), the source frame id and the frame's own provenance
   (:func:`frame_origin` reads it back); the stamps are the frames' own. Revision 0 holds each session's head poses,
   each in its own world frame.
5. **One pose graph** over all sessions (:func:`~driftmap.pipeline.loop_closure.optimize_calibrated`): per session the
   head's relative poses between keyframes (``odometry_edges`` with the trajectory's relative poses, information from
   the keyframe registrations, else ``fallback_information``; ``build.odometry_edges = "registration"``: the
   keyframe registrations themselves, both edge groups calibrated), the consistent inter-session loops (Cauchy kernel and
   the loops' information calibration, as in ``build``), session 0's first keyframe fixed. The optimised keyframe
   poses, with every other frame following its session's keyframes (the store's propagation rule, applied per
   session), are revision 1 (source ``loop_closure``, note ``merge of N sessions ...``).
"""

from __future__ import annotations

import dataclasses
import fnmatch
import json
import logging
import os
import secrets
import shutil
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import parse_qsl, quote, urlencode

import numpy as np
from numpy.typing import NDArray

from driftmap import geometry
from driftmap.errors import ConfigError, MergeError, StoreError
from driftmap.frame import Frame, PoseEstimate, PoseSource, Provenance, SensorKind
from driftmap.pipeline.build_config import BuildConfig, BuildResult, ProgressCallback
from driftmap.pipeline.loop_closure import (
    EdgeGroup,
    keyframe_clouds,
    loop_config_for,
    odometry_edges,
    optimize_calibrated,
)
from driftmap.pipeline.merge_loops import (
    MIN_CONSISTENT_LOOPS,
    PairLoops,
    connected_sessions,
    drop_graph_rejected,
    find_pair_loops,
)
from driftmap.pipeline.resume import recorded_odometry
from driftmap.pipeline.same_recording import frame_readings, refuse_same_recording
from driftmap.preprocess.scene import sample_positions
from driftmap.registration.loops import Keyframe, LoopClosureConfig, select_keyframes
from driftmap.registration.odometry import OdometryConfig
from driftmap.store.frame_store import FrameStore
from driftmap.store.guards import refuse_inside_store
from driftmap.store.layout import BUILD_SOURCE_FILE, MERGE_SUMMARY_FILE, SESSION_ID_STRIDE
from driftmap.store.lock import writer_alive
from driftmap.store.manifest import read_manifest
from driftmap.store.propagation import propagate_correction
from driftmap.store.unmerged import unmerged_sessions
from driftmap.volume.defaults import lidar_max_range, lidar_max_range_from_frames

__all__ = ["MERGE_SUMMARY_FILE", "MERGE_URI_SCHEME", "MIN_CONSISTENT_LOOPS", "SESSION_ID_STRIDE", "FrameOrigin",
           "MergeResult", "SessionReport", "copy_frames", "frame_origin", "keyframe_range", "merge_stores",
           "odometry_config", "record_graph_verdicts", "session_frame_ids", "session_keyframes", "session_of",
           "lost_per_session", "recorded_session_stores", "sessions_left_unmerged", "source_losses", "store_sessions"]

logger = logging.getLogger(__name__)

MERGE_URI_SCHEME = "driftmap-merge"
"""The scheme of a merged frame's ``provenance.source_uri`` (:func:`frame_origin`)."""


@dataclass(frozen=True)
class FrameOrigin:
    """Where a frame of a merged store came from."""

    session: int
    store: str
    """the source store's folder (absolute) when it was merged"""
    store_uuid: str
    revision: int
    """the source store's head revision, whose pose the frame got in revision 0"""
    frame_id: int
    """the frame's id in the source store"""
    source_uri: str | None = None
    """the frame's own provenance in the source store (data set file, log and topic), if it had one"""
    index: int | None = None

    @property
    def reading(self) -> tuple[str | None, int | None]:
        """(source URI, index) the frame was read from before the merge."""
        return self.source_uri, self.index


def frame_origin(provenance: Provenance | dict | None) -> FrameOrigin | None:
    """The session and source of a merged store's frame from its provenance (a :class:`Provenance` or the stored
    ``provenance`` dict of ``FrameStore.frame_info``); None for a frame that was not merged."""
    if provenance is None:
        return None
    uri = provenance["source_uri"] if isinstance(provenance, dict) else provenance.source_uri
    prefix = f"{MERGE_URI_SCHEME}:"
    if not uri.startswith(prefix):
        return None
    q = dict(parse_qsl(uri[len(prefix):], keep_blank_values=True))
    return FrameOrigin(session=int(q["session"]), store=q["store"], store_uuid=q["uuid"], revision=int(q["revision"]),
                       frame_id=int(q["frame_id"]), source_uri=q.get("origin"),
                       index=int(q["origin_index"]) if "origin_index" in q else None)


def store_sessions(store: FrameStore) -> dict[int, list[int]]:
    """The sessions of a merged store: ``{session: [frame ids in store order]}`` from each frame's provenance
    (:func:`frame_origin`); ``{}`` for a store that no merge made."""
    sessions: dict[int, list[int]] = {}
    for fid in store.frame_ids:
        origin = frame_origin(store.frame_info(int(fid)).get("provenance"))
        if origin is None:
            return {}
        sessions.setdefault(origin.session, []).append(int(fid))
    return sessions


def sessions_left_unmerged(store: FrameStore, revision: int | None = None) -> str | None:
    """What a merged store whose merge revision (or an append's) was lost to damage shows in ``revision`` (default:
    the head), and what to do (hostile trial 19 W6); None when it shows every session merged. See
    :func:`driftmap.store.unmerged.unmerged_sessions`."""
    found = unmerged_sessions(store, revision)
    return None if found is None else str(found)


def session_frame_ids(store: FrameStore, session: int) -> list[int]:
    """The frame ids of ``session`` in a merged store; :class:`ConfigError` naming the store when it is not a merged
    one or has no such session (``export --session``)."""
    sessions = store_sessions(store)
    lost = lost_per_session(store)
    if session not in sessions and session in lost:  # hostile trial 21 W7: "not a merged store" after the loss
        raise ConfigError(f"--session {session}: every frame of session {session} of {store.path} ({lost[session]}) "
                          f"was lost to damage (`driftmap recover` declared them; `driftmap info` lists the loss); "
                          + (f"it holds sessions {', '.join(map(str, sorted(sessions)))}" if sessions else
                             "it holds no frames"))
    if not sessions:
        raise ConfigError(f"--session {session}: {store.path} is not a merged store (driftmap merge makes one): it "
                          f"has no sessions")
    if session not in sessions:
        raise ConfigError(f"--session {session}: {store.path} holds sessions {', '.join(map(str, sorted(sessions)))}")
    return sessions[session]


def lost_per_session(store: FrameStore) -> dict[int, int]:
    """How many frames of each session of a merged store were lost to damage (``driftmap recover`` declared them);
    ``{}`` for a store no merge made or one that lost none."""
    if not store.loss.frame_ids or not (store.path / MERGE_SUMMARY_FILE).is_file():
        return {}
    k, n = np.unique(np.asarray(store.loss.frame_ids, dtype=np.int64) // SESSION_ID_STRIDE, return_counts=True)
    return {int(a): int(b) for a, b in zip(k, n, strict=True)}


def recorded_session_stores(store: FrameStore) -> dict[int, str]:
    """The source store of each session as the merge summary records it (``{}`` when it cannot be read): what
    names a session none of whose frames is left."""
    try:
        summary = json.loads((store.path / MERGE_SUMMARY_FILE).read_text())
        rows = summary.get("sessions", []) if isinstance(summary, dict) else []
        return {int(r["session"]): str(r["store"]) for r in rows if isinstance(r, dict) and "session" in r}
    except (OSError, ValueError, TypeError, KeyError):
        return {}


def source_losses(k: int, path: Path, store: FrameStore) -> int:
    """How many frames the source store of session ``k`` declares lost to damage, with a warning when any: a merge
    takes what is left, and the session's record keeps the count (``frames_lost_in_source``)."""
    lost = len(store.loss.frame_ids)
    if lost:
        logger.warning("session %d (%s) declares %d frames lost to damage (`driftmap recover`; `driftmap info` lists "
                       "them); its %d stored frames are merged, the lost ones cannot be", k, path, lost, len(store))
    return lost


def session_of(frame_id: int) -> tuple[int, int]:
    """``(session, source frame id)`` of a merged store's frame id."""
    return int(frame_id) // SESSION_ID_STRIDE, int(frame_id) % SESSION_ID_STRIDE


def _merged_provenance(session: int, store: Path, uuid: str, revision: int, frame: Frame) -> Provenance:
    fields = {"session": session, "store": str(store), "uuid": uuid, "revision": revision, "frame_id": frame.frame_id}
    if frame.provenance is not None:
        fields |= {"origin": frame.provenance.source_uri, "origin_index": frame.provenance.index}
    return Provenance(f"{MERGE_URI_SCHEME}:{urlencode(fields, quote_via=quote)}", frame.frame_id)


@dataclass
class SessionReport:
    """One source store in the merge."""

    session: int
    store: str
    store_uuid: str
    head_revision: int
    head_source: str
    n_frames: int
    n_keyframes: int = 0
    connected: bool = False
    reason: str = ""
    """why a session is not connected"""
    frame_id_offset: int = 0
    T_merged_session: list[float] | None = None
    """where the session's own world frame lies in the merged one after optimisation (its first keyframe's
    correction, 16 numbers row-major); None when not connected"""
    frames_lost_in_source: int = 0
    """frames the source store itself declares lost to damage (``driftmap recover``): they are not in the merge
    (hostile trial 22 W7: a recovered, cut log merged without a word)"""


@dataclass
class MergeResult:
    out: str
    sessions: list[SessionReport]
    pairs: list[dict[str, Any]]
    """per pair of sessions: loops tried / verified / accepted, connected, the reason if not, each loop's record"""
    not_connected: list[int]
    revision_id: int | None
    n_frames: int
    graph_error_before: float | None = None
    graph_error_after: float | None = None
    loops_rejected_by_graph: int = 0
    information_scale: dict[str, float] = field(default_factory=dict)
    max_session0_shift_m: float | None = None
    """how far the merge moved a frame of session 0 (its own trajectory bends to fit the others)"""
    loop_closure_config: dict[str, Any] | None = None
    keyframe_max_range_m: float | None = None
    """the one range every session's keyframe clouds are cut at (an append cuts the new sessions' alike)"""
    volume_defaults: dict[str, Any] | None = None
    """LiDAR: what the merged store's volumetric layers take when ``volume.max_range_m`` is not set
    (:func:`volume_defaults`: ``max_range_m``, ``source`` and ``per_session``); None for a depth camera"""
    seconds_per_stage: dict[str, float] = field(default_factory=dict)
    appends: list[dict[str, Any]] = field(default_factory=list)
    """one record per ``merge --append`` since (:class:`driftmap.pipeline.merge_append.AppendResult`)"""

    @property
    def frames_per_session(self) -> dict[int, int]:
        return {s.session: s.n_frames for s in self.sessions if s.connected}

    def to_json(self) -> dict[str, Any]:
        return dataclasses.asdict(self) | {"frames_per_session": self.frames_per_session}


class _HeadView:
    """A source store as :func:`keyframe_clouds` reads it, with its head revision in the place of revision 0 (the
    sessions are merged with their best poses)."""

    def __init__(self, store: FrameStore) -> None:
        self._store = store
        self.ledger = store.ledger
        self.frame_ids = store.frame_ids
        self._head = store.poses(store.head)

    def poses(self, revision: int | None = None) -> NDArray[np.float64]:
        return self._head

    def frame(self, frame_id: int, revision: int | None = None) -> Frame:
        return self._store.frame(frame_id)


def merge_stores(stores: Sequence[str | Path], out: str | Path, *, config: BuildConfig | None = None,
                 progress: ProgressCallback | None = None) -> MergeResult:
    """Merge the sessions in ``stores`` (session k = ``stores[k]``) into a new store ``out``; see the module
    docstring. ``config``: the ``[build]`` settings (loop closure, pose graph) as ``build`` reads them.

    Raises :class:`ConfigError` for unusable input (fewer than two stores, a store twice, different sensors or
    intrinsics kinds, ``out`` existing or inside a source) and :class:`~driftmap.errors.MergeError` when no session connects to
    session 0 (nothing is written then). Sessions that do not connect while others do are reported in the result."""
    config = config or BuildConfig()
    tick = progress or (lambda stage, done, total: None)
    stages: dict[str, float] = {}
    paths = [Path(p) for p in stores]
    out = Path(out)
    _remove_abandoned_scratch(out)  # first: an --out refused below must not keep a killed merge's scratch forever
    _check_paths(paths, out)
    sources: list[FrameStore] = []
    try:
        for p in paths:
            sources.append(FrameStore.open(p, "r"))
        uuids = _check_sessions(paths, sources)
        return _merge(paths, sources, uuids, out, config, tick, stages)
    finally:
        for s in sources:
            s.close()


SCRATCH_MIN_AGE_S = 60.0
"""A merge's scratch folder this old whose writer is gone was left by a merge that was killed."""


def _scratch_dirs(out: Path) -> list[Path]:
    """The hidden folders merges into ``out`` write before renaming them to ``out`` (``.OUT.merge-XXXXXXXX``)."""
    try:
        return sorted(out.parent.glob(f".{out.name}.merge-*"))
    except OSError:
        return []


SCRATCH_FILES = ("store.json", "writer.lock", MERGE_SUMMARY_FILE, "segment-*.mcap", ".*.tmp*")
"""What a merge's scratch folder holds (a frame store being written, and atomic writes' temporary files): a folder of
that name holding anything else is not removed."""


def _is_merge_scratch(folder: Path) -> bool:
    """``folder`` holds a frame store being written by a merge and nothing else (no sub-folder, no other file)."""
    try:
        entries = list(folder.iterdir())
    except OSError:
        return False
    names = {e.name for e in entries}
    if "store.json" not in names and "writer.lock" not in names:
        return False
    return all(not e.is_symlink() and e.is_file() and any(fnmatch.fnmatchcase(e.name, p) for p in SCRATCH_FILES)
               for e in entries)


def _remove_abandoned_scratch(out: Path) -> None:
    """Remove the scratch folders of merges into ``out`` that were killed (no process holds their writer lock and they
    are older than :data:`SCRATCH_MIN_AGE_S`): a SIGKILL leaves one behind, nothing else ever uses it. A folder of
    that name that holds anything but a store being written (:func:`_is_merge_scratch`) is left alone, with a
    warning."""
    for folder in _scratch_dirs(out):
        try:
            age_s = time.time() - folder.stat().st_mtime
        except OSError:
            continue
        if folder.is_symlink() or not folder.is_dir() or age_s < SCRATCH_MIN_AGE_S or writer_alive(folder):
            continue
        if not _is_merge_scratch(folder):
            logger.warning("%s: named like a merge's scratch folder but holds other files: left alone", folder)
            continue
        shutil.rmtree(folder, ignore_errors=True)
        logger.warning("%s: removed the scratch folder of an earlier merge into %s that did not finish (killed?)",
                       folder, out)


def _check_paths(paths: list[Path], out: Path) -> None:
    if len(paths) < 2:
        raise ConfigError(f"merge needs at least two stores (sessions), got {len(paths)}")
    resolved = [p.resolve() for p in paths]
    for i in range(len(paths)):
        for j in range(i):
            linked = paths[i].exists() and paths[j].exists() and os.path.samefile(paths[i], paths[j])
            if resolved[i] == resolved[j] or linked:
                raise ConfigError(f"{paths[j]} and {paths[i]}: the same store twice (sessions {j} and {i}); "
                                  f"give each session once")
    refuse_inside_store(out, "--out", output_is_store=True)
    target = out.resolve()
    for p, r in zip(paths, resolved, strict=True):
        if target == r or r.is_relative_to(target) or target.is_relative_to(r):
            raise ConfigError(f"--out {out}: is (or holds, or lies inside) the source store {p}; write the merged "
                              f"store elsewhere (the sources are never modified)")
    for p in paths:  # the log folder a source was built from: the next build of it would read the merge as a frame
        try:
            logged = json.loads((p / BUILD_SOURCE_FILE).read_text()).get("path")
        except (OSError, ValueError, AttributeError):
            continue
        if isinstance(logged, str) and Path(logged).is_dir() and Path(logged).resolve() in target.parents:
            raise ConfigError(f"--out {out}: is inside the log folder {logged} the source store {p} was built from; "
                              f"the next read of that folder would take it for a frame: write it elsewhere")
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise ConfigError(f"--out {out}: exists; merge writes a new store (to add sessions to a merged store, "
                          f"give it first with --append instead of --out): choose another --out")


def refuse_partial_head(path: Path, source: FrameStore, what: str) -> None:
    """A session is merged with every frame it stores, at its head's poses: a source whose head does not place them
    all (a rollback that left frames out, a resume or append after it) is refused, naming the way out; it gave those
    frames the poses of a revision the head does not hold beside its own (hostile trial 18 B4: a 1.41 m seam)."""
    placed = source.members(source.head)
    if len(placed) == len(source):
        return
    out = np.setdiff1d(np.asarray(source.frame_ids, np.int64), placed)
    full = [r.revision_id for r in source.revisions if len(source.members(r.revision_id)) == len(source)]
    stand_in = source.head in source.loss.revision_ids
    head = ("the stand-in for a revision lost to damage" if stand_in else
            source.ledger.revision(source.head).source.value)
    # a stand-in's head keeps the correction of the revision before it: a resume of the store's own log places the
    # frames left out with it, a rollback would drop it (hostile trial 20 W3)
    resume = (f"run the `build --resume` that stored them again (it places them with the head's correction), or "
              if stand_in and not (path / MERGE_SUMMARY_FILE).is_file() else "")
    raise ConfigError(f"{path}: its head (revision {source.head}, {head}) "
                      f"places {len(placed)} of the {len(source)} frames it stores ({len(out)} left out, "
                      f"{int(out.min())}..{int(out.max())}); {what} takes every stored frame of a session: {resume}roll "
                      f"it back to a revision that places them all (`driftmap rollback {path} --to {full[-1]}`), or "
                      f"build the frames the map should hold into a store of their own (`build --frames`)")


def _check_sessions(paths: list[Path], sources: list[FrameStore]) -> list[str]:
    """Every store has frames and a uuid of its own; the sensor kind and the intrinsics kind agree with session 0's.
    Returns the uuids."""
    uuids = []
    for k, (p, s) in enumerate(zip(paths, sources, strict=True)):
        if len(s) == 0:
            raise StoreError(f"{p}: the store has no frames; nothing to merge (session {k})")
        if (p / MERGE_SUMMARY_FILE).is_file() or store_sessions(s):
            raise ConfigError(f"{p}: is a merged store (session {k}); a merged store as a source of a new merge is "
                              f"refused: append the new sessions to it in place with `driftmap merge {p} NEW_STORE "
                              f"[NEW_STORE ...] --append` (a new revision; the older ones are kept)")
        if int(s.frame_ids.max()) >= SESSION_ID_STRIDE or int(s.frame_ids.min()) < 0:
            raise ConfigError(f"{p}: frame ids {int(s.frame_ids.min())}..{int(s.frame_ids.max())} are outside "
                              f"0..{SESSION_ID_STRIDE - 1}, which a merged store keeps per session")
        refuse_partial_head(p, s, "merge")
        uuid = str(read_manifest(p)["store_uuid"])
        if uuid in uuids:
            j = uuids.index(uuid)
            raise ConfigError(f"{paths[j]} and {p}: the same store twice (store uuid {uuid}: one is a copy of the "
                              f"other; sessions {j} and {k}); give each session once")
        uuids.append(uuid)
    first = [s.frame(int(s.frame_ids[0])) for s in sources]
    f0 = first[0]
    for k in range(1, len(sources)):
        f = first[k]
        if f.sensor_kind is not f0.sensor_kind:
            raise ConfigError(f"{paths[0]} and {paths[k]}: different sensors (sensor_kind {f0.sensor_kind.value} vs "
                              f"{f.sensor_kind.value}); merge sessions of one sensor kind")
        if (f0.intrinsics is None) != (f.intrinsics is None):
            kind = {True: "none", False: "pinhole"}
            raise ConfigError(f"{paths[0]} and {paths[k]}: different intrinsics "
                              f"(intrinsics {kind[f0.intrinsics is None]} "
                              f"vs {kind[f.intrinsics is None]}); merge sessions of one sensor kind")
        if f.sensor_name != f0.sensor_name:
            logger.warning("%s and %s: sensor names differ (%r, %r); merging them as one %s", paths[0], paths[k],
                           f0.sensor_name, f.sensor_name, f0.sensor_kind.value)
    refuse_same_recording([(f"{p} (session {k})", frame_readings(s)) for k, (p, s) in enumerate(zip(paths, sources))])
    return uuids


def odometry_config(store: FrameStore, config: BuildConfig) -> OdometryConfig:
    """The odometry settings loop closure scales its lengths with (``build``'s rule: the config's, the store's
    recorded ones, else the defaults for its frames)."""
    if config.odometry is not None:
        return config.odometry
    recorded = recorded_odometry(store)
    if recorded is not None:
        return recorded
    sample = [store.frame(int(store.frame_ids[k])) for k in sample_positions(len(store))]
    return OdometryConfig.for_frames(sample, log=False)


def volume_defaults(paths: list[Path], sources: list[FrameStore], connected: list[int]) -> dict[str, Any] | None:
    """What the volumetric layers of the merged store need and a merged store cannot tell by itself (it has no
    ``build_summary.json``): for LiDAR sessions, each connected session's default max range
    (:func:`driftmap.volume.defaults.lidar_max_range`: the odometry range its store records; a session built with
    given poses records none: the range our odometry's defaults take for its frames,
    :func:`~driftmap.volume.defaults.lidar_max_range_from_frames`), and the one the merged store takes: **session
    0's**, as the merge takes session 0's loop-closure settings (one range for every session's rays). Sessions whose
    range differs from it by more than 10 % are logged. None for a depth camera (its range follows from its noise)."""
    first = sources[0].frame(int(sources[0].frame_ids[0]))
    if first.sensor_kind is not SensorKind.LIDAR:
        return None
    per_session = []
    for k in connected:
        value, how = lidar_max_range(sources[k])
        if value is None:  # built with given poses: the range our odometry would have taken for its frames
            value, how = lidar_max_range_from_frames(sources[k]), "frames"
        per_session.append({"session": k, "store": str(paths[k].resolve()), "max_range_m": value, "source": how})
    chosen = per_session[0]
    for row in per_session[1:]:
        if chosen["max_range_m"] and row["max_range_m"] and abs(row["max_range_m"] / chosen["max_range_m"] - 1) > 0.1:
            logger.warning("%s: its LiDAR max range %.2f m (%s) differs from session 0's %.2f m; the merged store's "
                           "volumetric layers take session 0's (set volume.max_range_m to choose another)",
                           row["store"], row["max_range_m"], row["source"], chosen["max_range_m"])
    return {"max_range_m": chosen["max_range_m"], "source": f"session 0 ({chosen['source']})",
            "per_session": per_session}


def keyframe_range(lc: LoopClosureConfig, odometry_cfg: OdometryConfig) -> float | None:
    """The one range every session's keyframe clouds are cut at: the place descriptors (D2 and range histograms)
    compare only clouds cut alike."""
    return lc.max_range_m if lc.max_range_m is not None else odometry_cfg.max_range_m


def session_keyframes(k: int, store: FrameStore, lc: LoopClosureConfig, max_range_m: float | None,
                      tick: ProgressCallback) -> list[Keyframe]:
    """The keyframes of session ``k`` (a source store) on its head revision, with their merged frame ids."""
    view = _HeadView(store)
    key_rows = select_keyframes(view.poses(), lc)
    kfs = keyframe_clouds(view, lc, key_rows, max_range_m,  # type: ignore[arg-type]
                          lambda s, d, t: tick(f"keyframes, session {k}", d, t))
    offset = k * SESSION_ID_STRIDE
    return [dataclasses.replace(kf, frame_id=offset + kf.frame_id) for kf in kfs]


def _merge(paths: list[Path], sources: list[FrameStore], uuids: list[str], out: Path, config: BuildConfig,
           tick: ProgressCallback, stages: dict[str, float]) -> MergeResult:
    t0 = time.perf_counter()
    odometry_cfg = odometry_config(sources[0], config)
    lc = loop_config_for(sources[0], config, odometry_cfg)
    for k in range(1, len(sources)):
        lc_k = loop_config_for(sources[k], config, odometry_config(sources[k], config))
        if lc_k != lc:
            logger.warning("%s: its own loop-closure settings differ from session 0's; the merge uses session 0's",
                           paths[k])
    max_range_m = keyframe_range(lc, odometry_cfg)
    keyframes = [session_keyframes(k, s, lc, max_range_m, tick) for k, s in enumerate(sources)]
    stages["keyframes"] = time.perf_counter() - t0
    reports = [SessionReport(k, str(p.resolve()), uuids[k], s.head, s.ledger.revision(s.head).source.value, len(s),
                             n_keyframes=len(keyframes[k]), frame_id_offset=k * SESSION_ID_STRIDE,
                             frames_lost_in_source=source_losses(k, p, s))
               for k, (p, s) in enumerate(zip(paths, sources, strict=True))]

    t1 = time.perf_counter()
    pairs: list[PairLoops] = []
    for j in range(1, len(sources)):
        for i in range(j):
            stage = f"loops, sessions {i}-{j}"
            pairs.append(find_pair_loops(i, j, keyframes[i], keyframes[j], lc, lambda d, t, s=stage: tick(s, d, t)))
    stages["loops between sessions"] = time.perf_counter() - t1
    while True:  # again without the pairs whose agreeing loops the pose graph rejected (drop_graph_rejected)
        connected, T_align = connected_sessions(len(sources), pairs)
        not_connected = [k for k in range(len(sources)) if k not in connected]
        for k, report in enumerate(reports):
            report.connected = k in connected
            report.reason = "" if report.connected else "; ".join(
                f"with session {p.session_a if p.session_b == k else p.session_b}: "
                f"{p.why_not_connected() or 'connected only to sessions not connected to session 0'}"
                for p in pairs if k in (p.session_a, p.session_b))
        for k in not_connected:
            logger.warning("session %d (%s) is not connected to session 0: %s; it is left out of the merged store", k,
                           paths[k], reports[k].reason)
        if not_connected and len(connected) == 1:
            raise MergeError(
                f"no session could be connected to session 0 ({paths[0]}): "
                + "; ".join(f"session {k} ({paths[k]}): {reports[k].reason}" for k in not_connected)
                + f"; nothing was written. Are they stores of the same place? (a session needs at least "
                  f"{MIN_CONSISTENT_LOOPS} agreeing loops with another)")
        result = MergeResult(out=str(out), sessions=reports, pairs=[p.summary() for p in pairs],
                             not_connected=not_connected,
                             revision_id=None, n_frames=0, loop_closure_config=lc.model_dump(mode="json"),
                             keyframe_max_range_m=max_range_m,
                             volume_defaults=volume_defaults(paths, sources, connected), seconds_per_stage=stages)
        opt_poses, covariances, note, rejected = _optimise(connected, keyframes, T_align, pairs, lc, config, result,
                                                           tick, stages)
        if not drop_graph_rejected([p for p in pairs if p.session_a in connected and p.session_b in connected],
                                   rejected):
            break
    t3 = time.perf_counter()
    scratch_dir = out.parent / f".{out.name}.merge-{secrets.token_hex(4)}"  # renamed to ``out`` when complete
    try:
        merged = FrameStore.create(scratch_dir)
        try:
            _copy_frames(merged, connected, paths, sources, uuids, tick)
            stages["frames"] = time.perf_counter() - t3
            t4 = time.perf_counter()
            poses = _propagated(merged, connected, opt_poses)
            revision = merged.add_revision(poses, source=PoseSource.LOOP_CLOSURE, propagate=False,
                                           covariances=covariances, note=note)
            result.revision_id = revision.revision_id
            result.n_frames = len(merged)
            d = merged.diff(0, revision.revision_id)
            in_s0 = d.frame_ids < SESSION_ID_STRIDE
            result.max_session0_shift_m = float(d.translation_m[in_s0].max()) if in_s0.any() else None
            for k in connected:
                first = keyframes[k][0]
                moved = opt_poses[first.frame_id] @ geometry.invert(first.T_world_sensor)
                reports[k].T_merged_session = [float(v) for v in moved.ravel()]
            stages["correction"] = time.perf_counter() - t4
        except BaseException:
            merged.abandon()  # removed below: no "left open ... recover" warning for it
            raise
        merged.close()
        (scratch_dir / MERGE_SUMMARY_FILE).write_text(json.dumps(result.to_json(), indent=2, default=str) + "\n")
        if out.is_dir():  # an empty folder given as --out (checked empty before anything ran)
            out.rmdir()
        os.replace(scratch_dir, out)
    except BaseException as exc:
        shutil.rmtree(scratch_dir, ignore_errors=True)
        if isinstance(exc, OSError):  # a full disk, a quota: nothing half-written is left to look like a merge
            raise MergeError(f"{getattr(exc, 'filename', None) or out}: writing the merged store failed "
                             f"({exc.strerror or type(exc).__name__}); nothing was written to {out} and the sources "
                             f"are untouched: free space (or write elsewhere) and run the merge again") from exc
        raise
    logger.info("merged %d sessions (%d frames) into %s: revision %s", len(connected), result.n_frames, out,
                result.revision_id)
    return result


def _optimise(connected: list[int], keyframes: list[list[Keyframe]], T_align: dict[int, NDArray[np.float64]],
              pairs: list[PairLoops], lc: LoopClosureConfig, config: BuildConfig, result: MergeResult,
              tick: ProgressCallback,
              stages: dict[str, float]) -> tuple[dict[int, NDArray[np.float64]], dict, str, set[tuple[int, int]]]:
    """One pose graph over the connected sessions: their keyframes placed by the loops' alignment, each session's
    odometry edges (the head's relative poses), the consistent loops between connected sessions. Also returns the
    loops the graph rejected (``(a, b)`` frame ids)."""
    t = time.perf_counter()
    from_trajectory = config.odometry_edges != "registration"  # auto: the head's relative poses (module docstring)
    nodes: list[Keyframe] = []
    edges = []
    for k in connected:
        nodes += [dataclasses.replace(kf, T_world_sensor=T_align[k] @ kf.T_world_sensor) for kf in keyframes[k]]
        edges += odometry_edges(keyframes[k], lc, config, from_trajectory,
                                lambda s, d, n, k=k: tick(f"odometry edges, session {k}", d, n))
    stages["odometry edges"] = time.perf_counter() - t
    loops = [c for p in pairs if p.session_a in connected and p.session_b in connected for c in p.consistent]
    edges += [(EdgeGroup.LOOP, c.a, c.b, c.T_a_b, c.result.information_6x6) for c in loops if c.result is not None]
    t = time.perf_counter()
    scratch = BuildResult(store=result.out, n_frames=0, n_frames_new=0, mean_invalid_fraction=None,
                          pose_source=PoseSource.LOOP_CLOSURE.value, odometry_fps=None)
    opt = optimize_calibrated(nodes, edges, config, scratch, calibrate_odometry=not from_trajectory)
    stages["pose graph"] = time.perf_counter() - t
    result.graph_error_before, result.graph_error_after = opt.initial_error, opt.final_error
    result.information_scale = scratch.information_scale
    rejected = record_graph_verdicts(result, opt)
    origins = ", ".join(f"session {k}: {result.sessions[k].store} revision {result.sessions[k].head_revision}"
                        for k in connected)
    note = (f"merge of {len(connected)} sessions ({origins}); {len(loops)} loops between sessions, graph error "
            f"{opt.initial_error:.3g} -> {opt.final_error:.3g}")
    return dict(opt.poses), dict(opt.covariances or {}), note, rejected


def record_graph_verdicts(result: Any, opt: Any) -> set[tuple[int, int]]:
    """The pose graph's verdict on each accepted loop of ``result.pairs`` (``graph_chi2``, ``graph_weight``,
    ``kept_by_graph``) and ``result.loops_rejected_by_graph``, with a warning when it rejected any (a merge's
    :class:`MergeResult` or an append's result; ``opt`` the optimisation). Returns the rejected loops' ``(a, b)``."""
    verdict = {(r.key_from, r.key_to): r for r in opt.loop_residuals}
    for p in result.pairs:
        for rec in p["loops"]:
            r = verdict.get((rec["a"], rec["b"]))
            if rec["accepted"] and r is not None:
                rec |= {"graph_chi2": r.chi2, "graph_weight": r.weight, "kept_by_graph": r.accepted}
    result.loops_rejected_by_graph = sum(not r.accepted for r in opt.loop_residuals)
    if result.loops_rejected_by_graph:
        logger.warning("%d of %d loops between sessions rejected by the pose graph (chi2 > %.1f)",
                       result.loops_rejected_by_graph, len(opt.loop_residuals), opt.chi2_threshold)
    return {(r.key_from, r.key_to) for r in opt.loop_residuals if not r.accepted}


def copy_frames(merged: FrameStore, connected: Sequence[int], paths: Any, sources: Any, uuids: Any,
                 tick: ProgressCallback) -> None:
    """Every frame of the connected sessions, in session order, with its merged id, its session's head pose as its
    revision-0 pose and the merge provenance (its points, stamp, intrinsics, quality and tracking as stored).
    ``paths``, ``sources``, ``uuids``: indexed by session (lists, or dicts for an append). A frame already in
    ``merged`` with the same stamp (an interrupted append run again) is skipped."""
    total = sum(len(sources[k]) for k in connected)
    done = 0
    for k in connected:
        src, offset = sources[k], k * SESSION_ID_STRIDE
        head = src.head
        head_source = src.ledger.revision(head).source
        store_path = paths[k].resolve()
        for fid, T in zip(src.frame_ids.tolist(), src.poses(head), strict=True):
            if offset + int(fid) in merged:
                if int(merged.ledger.stamps_ns[np.searchsorted(merged.frame_ids, offset + int(fid))]) != \
                        int(src.ledger.stamps_ns[np.searchsorted(src.frame_ids, int(fid))]):
                    raise StoreError(f"{merged.path}: frame {offset + int(fid)} is stored with another stamp than "
                                     f"frame {fid} of {paths[k]} (session {k}); not the same session")
                done += 1
                continue
            frame = src.frame(int(fid))
            merged.append(dataclasses.replace(
                frame, frame_id=offset + int(fid),
                pose=PoseEstimate(T, revision=0, source=head_source, world_frame=frame.pose.world_frame),
                provenance=_merged_provenance(k, store_path, uuids[k], head, frame)))
            done += 1
            tick("frames", done, total)


_copy_frames = copy_frames
"""the name the merge calls (a failure injected there is a write failure of the merged store: tests/test_merge.py)"""


def _propagated(merged: FrameStore, connected: list[int],
                key_poses: dict[int, NDArray[np.float64]]) -> dict[int, NDArray[np.float64]]:
    """The optimised keyframe poses and, per session, every other frame following its session's keyframes by the
    store's propagation rule (:func:`~driftmap.store.propagation.propagate_correction`). Per session: the ledger's own
    propagation orders all frames by stamp, which would interpolate between sessions whose stamps interleave."""
    ids, stamps, rev0 = merged.frame_ids, merged.ledger.stamps_ns, merged.poses(0)
    out = dict(key_poses)
    for k in connected:
        rows = np.flatnonzero(ids // SESSION_ID_STRIDE == k)
        key_ids = np.array(sorted(f for f in key_poses if f // SESSION_ID_STRIDE == k), dtype=np.int64)
        if len(key_ids) == len(rows):
            continue
        prop_ids, prop_poses = propagate_correction(ids[rows], stamps[rows], rev0[rows], key_ids,
                                                    np.array([key_poses[int(f)] for f in key_ids]))
        out.update(zip(prop_ids.tolist(), prop_poses, strict=True))
    return out
