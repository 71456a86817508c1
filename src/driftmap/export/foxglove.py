"""Export one pose revision of a frame store to a single MCAP file that opens in Foxglove: the corrected
map, the corrected trajectory, every frame landing in it during playback, and (optionally) the double
walls the diagnostics found.

Every message is a Foxglove protobuf schema (``foxglove.*``), so the file needs nothing from driftmap to
be read. Topics (see ``docs/export.md`` for the full description):

* ``/map`` -- one ``foxglove.PointCloud`` in ``world``: the fused, voxel-deduplicated world points of the
  revision (:meth:`driftmap.map.view.MapView.fused`); fields ``x y z`` float32, ``n_frames`` float32 (how
  many frames saw the voxel) and ``frame_id`` float32 (the first frame that saw it: colour by it to tell
  layers of different times apart).
* ``/trajectory`` -- one ``foxglove.PosesInFrame`` in ``world`` with every pose of the revision.
* ``/tf`` -- one ``foxglove.FrameTransform`` per frame at its stamp: ``world -> <sensor_frame>@<frame_id>``
  (:func:`driftmap.store.segment.cloud_frame_name`, one coordinate frame per stored frame, as in the
  store's own segments) = the revision's ``T_world_sensor``.
* ``/points`` -- one ``foxglove.PointCloud`` per frame at its stamp in that frame's coordinate frame: the
  sensor-frame points, voxel-downsampled per frame (``x y z`` float32, plus ``intensity`` and
  ``red green blue alpha`` when the frame has them).
* ``/double_walls`` -- one ``foxglove.SceneUpdate`` (only with ``double_walls``): per region a cube
  (thin along the wall normal, as thick as the separation), an arrow from layer A to layer B, a label, and
  metadata (separation, frame spans).
* ``/driftmap/mesh`` -- one ``foxglove.SceneUpdate`` (only with ``volume``): entity ``tsdf_mesh`` with one
  ``TriangleListPrimitive`` in ``world``, the volumetric layers' TSDF mesh (``VolumeLayers.mesh``): its
  vertices (``points``), its triangles as vertex ``indices``, one flat colour; metadata (counts, voxel size).
* ``/driftmap/grid2d`` -- one ``foxglove.Grid`` (only with ``volume`` and ``grid2d_band_m``): the 2-D occupancy
  map of the voxel columns in the height band (:func:`driftmap.volume.export.occupancy_grid2d`, the cells of
  the ``map_server`` export), in ``world`` at z = the band's bottom; one cell per voxel column, rows along +y
  from the grid's corner; fields ``occupancy`` int8 (0 free, 100 occupied, -1 unknown) and ``red green blue
  alpha`` uint8 (free white, occupied black, unknown translucent grey) for the 3D panel's RGBA colour mode.
* a ``driftmap.foxglove_export`` metadata record: driftmap version, store path, revision and its source,
  the data source, voxel sizes.

``color="session"`` (``driftmap export --mcap --color session``; the sessions of a merged store given as
``sessions={session: [frame ids]}``, ``driftmap.pipeline.merge.store_sessions``) colours by session: ``/map`` gains
the fields ``session`` float32 (the session of the voxel's first frame) and ``red green blue alpha`` uint8 (that
session's colour, :data:`driftmap.render.SESSION_PALETTE_RGB`), each frame on ``/points`` carries its session's
colour as ``red green blue alpha`` (in place of the frame's own colours), and the metadata record gains ``color``
and ``sessions``. Without it (``color="frame"``, the default) the file is the same, byte for byte, as before the
option existed.

``/map``, ``/trajectory``, ``/double_walls``, ``/driftmap/mesh`` and ``/driftmap/grid2d`` are the result of the
whole revision; they are logged at
the **first** frame stamp so that Foxglove shows them from the moment the file opens, and the frames of
``/points`` land on them while the file plays. Log time = publish time = the message's stamp.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from foxglove_schemas_protobuf.PosesInFrame_pb2 import PosesInFrame
from mcap.writer import CompressionType
from mcap_protobuf.writer import Writer
from numpy.typing import NDArray

from driftmap import __version__
from driftmap.errors import ConfigError, EmptyStoreExportError, ExportError
from driftmap.export.foxglove_messages import (
    FLOAT32,
    UINT8,
    check_size,
    cloud_message,
    double_wall_scene,
    grid2d_message,
    mesh_scene,
    set_pose,
    set_stamp,
    transform_message,
)
from driftmap.files import atomic_write
from driftmap.frame import PointAttributes
from driftmap.map.view import MapView
from driftmap.preprocess.cloud import voxel_downsample
from driftmap.render import SESSION_PALETTE_RGB, session_color_rgb, session_color_text
from driftmap.store.guards import refuse_inside_store
from driftmap.store.revision import Revision
from driftmap.store.segment import WORLD_FRAME, cloud_frame_name, pack_points

if TYPE_CHECKING:
    import open3d as o3d

    from driftmap.diagnostics.double_wall import DoubleWallRegion, DoubleWallResult
    from driftmap.store.frame_store import FrameStore
    from driftmap.volume.export import Grid2D
    from driftmap.volume.layers import VolumeLayers

logger = logging.getLogger(__name__)

TOPIC_MAP = "/map"
TOPIC_TRAJECTORY = "/trajectory"
TOPIC_TF = "/tf"
TOPIC_POINTS = "/points"
TOPIC_DOUBLE_WALLS = "/double_walls"
TOPIC_MESH = "/driftmap/mesh"
TOPIC_GRID2D = "/driftmap/grid2d"
METADATA_NAME = "driftmap.foxglove_export"
COMPRESSIONS = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}
COLOR_MODES = ("frame", "session")
"""``color=`` of :func:`export_foxglove_mcap` (CLI ``export --mcap --color``): ``frame`` (the default: ``/map``'s
``frame_id`` field, the frames' own colours) or ``session`` (each session of a merged store in its own colour)."""

ProgressCallback = Callable[[str, int, int | None], None]
"""``progress(stage, done, total)``: stages ``"map"`` (0 or 1 of 1) and ``"frames"`` (frames written)."""


@dataclass(frozen=True)
class FoxgloveExportSummary:
    """What :func:`export_foxglove_mcap` wrote."""

    path: Path
    revision: int
    n_frames: int
    n_map_points: int
    n_frame_points: int
    """Points written on ``/points``, all frames together (after per-frame downsampling)."""
    n_double_walls: int
    message_counts: dict[str, int] = field(default_factory=dict)
    n_mesh_vertices: int = 0
    n_mesh_triangles: int = 0
    """Of ``/driftmap/mesh`` (0: no ``volume``, or its mesh is empty and the topic was left out)."""
    grid2d_shape: tuple[int, int] | None = None
    """(cells along x, cells along y) of ``/driftmap/grid2d``; None when it was not written."""
    session_colors: dict[int, tuple[int, int, int]] | None = None
    """``color="session"``: each session's 8-bit RGB colour; None otherwise."""
    map_voxel_size_m: float | None = None
    frame_voxel_size_m: float | None = None
    bytes: int = 0
    seconds: float = 0.0


def _sources(store: FrameStore) -> str:
    """Where the store's frames came from: the distinct folders / logs of their provenance URIs."""
    seen: dict[str, None] = {}
    for fid in store.frame_ids:
        prov = store.frame_info(int(fid)).get("provenance")
        if not prov:
            continue
        uri = str(prov["source_uri"])
        seen["#".join(uri.split("#")[:1]) if "#" in uri else str(Path(uri).parent)] = None
    names = list(seen)
    return "; ".join(names[:10]) + (f"; ... ({len(names)} in all)" if len(names) > 10 else "")


def _regions_of(double_walls: DoubleWallResult | Sequence[DoubleWallRegion] | None) -> list[DoubleWallRegion]:
    if double_walls is None:
        return []
    regions = getattr(double_walls, "regions", double_walls)
    return list(regions)


def frame_cloud_points(store: FrameStore, frame_id: int, voxel_size_m: float | None) -> tuple[NDArray[np.float32], PointAttributes]:
    """The sensor-frame points (and the attributes kept: intensity, colour) written on ``/points`` for a frame."""
    frame = store.frame(int(frame_id))
    attrs = PointAttributes(intensity=frame.attributes.intensity, color_rgb=frame.attributes.color_rgb)
    frame = frame.with_points(frame.points_sensor, attrs)
    if voxel_size_m is not None:
        frame, _ = voxel_downsample(frame, voxel_size_m)
    return frame.points_sensor, frame.attributes


@dataclass
class _Plan:
    """What one export writes, all checked before the file is opened: the revision, the frames in time order and
    their poses, the double-wall regions, and the volume layers' mesh and 2-D grid (None: not written)."""

    revision: Revision
    frame_ids: NDArray[np.int64]
    stamps_ns: NDArray[np.int64]
    poses: NDArray[np.float64]
    order: NDArray[np.int64]
    regions: list[DoubleWallRegion]
    mesh: o3d.geometry.TriangleMesh | None = None
    grid2d: Grid2D | None = None
    frame_sessions: NDArray[np.int64] | None = None
    """``color="session"``: the session of each of ``frame_ids``; None: colour by frame (as before)."""

    def session_rgb(self, k: int) -> tuple[int, int, int]:
        """The colour of frame ``frame_ids[k]``'s session."""
        assert self.frame_sessions is not None
        return session_color_rgb(int(self.frame_sessions[k]))

    @property
    def t0(self) -> int:
        """The first frame stamp: the revision's results are logged at it."""
        return int(self.stamps_ns[self.order[0]])


class _TopicWriter:
    """An MCAP protobuf writer that counts the messages of each topic (the message's sequence number) and logs
    each at its stamp (log time = publish time)."""

    def __init__(self, writer: Writer):
        self.writer = writer
        self.counts: dict[str, int] = {}

    def write(self, topic: str, msg: Any, stamp_ns: int) -> None:
        self.writer.write_message(topic, msg, log_time=int(stamp_ns), publish_time=int(stamp_ns),
                                  sequence=self.counts.get(topic, 0))
        self.counts[topic] = self.counts.get(topic, 0) + 1


def _check_settings(map_voxel_size_m: float | None, frame_voxel_size_m: float | None, compression: str,
                    volume: VolumeLayers | None, grid2d_band_m: tuple[float, float] | None, rev: int) -> CompressionType:
    """The chunk compression; :class:`~driftmap.errors.ConfigError` for a non-positive voxel size, an unknown
    compression, volume layers of another revision or a band without the layers."""
    for name, value in (("map_voxel_size_m", map_voxel_size_m), ("frame_voxel_size_m", frame_voxel_size_m)):
        if value is not None and not (math.isfinite(value) and value > 0):
            raise ConfigError(f"{name} must be positive (or None for every point), got {value}")
    try:
        chunk_compression = COMPRESSIONS[compression]
    except KeyError:
        raise ConfigError(f"compression must be zstd, lz4 or none, got {compression!r}") from None
    if volume is not None and volume.revision != rev:
        raise ConfigError(f"the volume layers are of revision {volume.revision}, the export of revision {rev}: build "
                          f"them for the exported revision (VolumeLayers.from_store(store, {rev}))")
    if grid2d_band_m is not None and volume is None:
        raise ConfigError("grid2d_band_m (--band-m) needs the volume layers (volume=...): the 2-D grid is cut "
                          "from them")
    return chunk_compression


def _check_output(path: Path, overwrite: bool) -> None:
    """Refuse a path inside any store folder (``overwrite`` or not), a directory, or an existing file without
    ``overwrite``."""
    refuse_inside_store(path, "Foxglove MCAP export path")  # any store folder, --overwrite or not
    if path.is_dir():
        raise ExportError(f"{path}: is a directory; give a file name such as {path / 'export.mcap'}")
    if path.exists() and not overwrite:
        raise ExportError(f"{path}: already exists; pass overwrite=True (CLI: --overwrite) to replace it")


def _frame_sessions(store: FrameStore, frame_ids: NDArray[np.int64],
                    sessions: Mapping[int, Sequence[int]] | None) -> NDArray[np.int64]:
    """The session of each of ``frame_ids`` (the frames the exported revision places) for ``color="session"``;
    ``sessions`` None or empty: one session 0 (a store that no merge made). :class:`ConfigError` unless ``sessions``
    holds every one of ``frame_ids`` exactly once and names only frames the store holds; the frames of a session the
    revision does not place (appended after it, or abandoned) are left out (hostile trial 18 B7)."""
    if not sessions:
        logger.info("foxglove export: %s is one session (no sessions given): one colour", store.path)
        return np.zeros(len(frame_ids), np.int64)
    out = np.full(len(frame_ids), -1, np.int64)
    for k, ids in sessions.items():
        if int(k) < 0:
            raise ConfigError(f"sessions: session {k} is negative")
        ids = np.asarray(ids, np.int64)
        unknown = np.setdiff1d(ids, np.asarray(store.frame_ids, np.int64))
        if len(unknown):
            raise ConfigError(f"sessions: session {k} names frame {int(unknown[0])}, which {store.path} does not hold")
        ids = ids[np.isin(ids, frame_ids)]  # the revision's frames of the session
        rows = np.searchsorted(frame_ids, ids)
        if np.any(out[rows] >= 0):
            raise ConfigError(f"sessions: frame {int(frame_ids[rows[out[rows] >= 0][0]])} is in two sessions")
        out[rows] = int(k)
    if np.any(out < 0):
        raise ConfigError(f"sessions: frame {int(frame_ids[np.argmax(out < 0)])} of {store.path} is in no session")
    if len(sessions) > len(SESSION_PALETTE_RGB):
        logger.warning("foxglove export: %d sessions but %d session colours: colours repeat", len(sessions),
                       len(SESSION_PALETTE_RGB))
    return out


def _plan(store: FrameStore, path: Path, revision: Revision,
          double_walls: DoubleWallResult | Sequence[DoubleWallRegion] | None, volume: VolumeLayers | None,
          grid2d_band_m: tuple[float, float] | None, color: str = "frame",
          sessions: Mapping[int, Sequence[int]] | None = None, mesh_weight_threshold: float | None = None) -> _Plan:
    """The frames in time order (frame id breaks ties), their poses in ``revision`` and the volume outputs; an
    empty store, a negative stamp, a band that selects nothing or a mesh too large for a message is refused
    here, before anything is written."""
    rev = revision.revision_id
    placed = store.ledger.member_rows(rev)  # the frames the revision places (not those stored after it)
    frame_ids = np.asarray(store.frame_ids, dtype=np.int64)[placed]
    if len(frame_ids) == 0:
        raise EmptyStoreExportError(f"store {store.path} has no frames in revision {rev}: nothing to export (nothing "
                                    f"written to {path})", store=store.path, revision=rev)
    stamps = np.asarray(store.ledger.stamps_ns, dtype=np.int64)[placed]
    if stamps.min() < 0:
        bad = int(frame_ids[np.argmin(stamps)])
        raise ExportError(f"{store.path}: frame {bad} has a negative stamp ({int(stamps.min())} ns); MCAP log times are unsigned")
    plan = _Plan(revision, frame_ids, stamps, store.poses(rev)[placed], np.lexsort((frame_ids, stamps)),
                 _regions_of(double_walls))
    if color == "session":
        plan.frame_sessions = _frame_sessions(store, frame_ids, sessions)
    if volume is not None:  # computed before anything is written: a bad band writes nothing
        from driftmap.volume.export import occupancy_grid2d, tsdf_mesh

        if grid2d_band_m is not None:
            plan.grid2d = occupancy_grid2d(volume, grid2d_band_m, flag="--band-m")
        plan.mesh = tsdf_mesh(volume, mesh_weight_threshold)
        if len(plan.mesh.triangles) == 0:
            logger.warning("foxglove export: the TSDF mesh of revision %d is empty; %s left out", rev, TOPIC_MESH)
            plan.mesh = None
        else:
            check_size(32 * len(plan.mesh.vertices) + 15 * len(plan.mesh.triangles),
                       f"{TOPIC_MESH} ({len(plan.mesh.triangles):,} triangles)", "use larger volume voxels")
    return plan


def _metadata(store: FrameStore, plan: _Plan, map_voxel_size_m: float | None, frame_voxel_size_m: float | None,
              include_frames: bool, volume: VolumeLayers | None) -> dict[str, str]:
    """The ``driftmap.foxglove_export`` metadata record."""
    rev_info = plan.revision
    return {
        "driftmap_version": __version__,
        "store_path": str(Path(store.path).resolve()),
        "revision": str(rev_info.revision_id),
        "revision_source": rev_info.source.value,
        "revision_parent": "" if rev_info.parent_id is None else str(rev_info.parent_id),
        "revision_note": rev_info.note,
        "head_revision": str(store.head),
        "source": _sources(store),
        "n_frames": str(len(plan.frame_ids)),
        "world_frame": WORLD_FRAME,
        "map_voxel_size_m": "" if map_voxel_size_m is None else f"{map_voxel_size_m:g}",
        "frame_voxel_size_m": "" if frame_voxel_size_m is None else f"{frame_voxel_size_m:g}",
        "topics": ",".join([TOPIC_MAP, TOPIC_TRAJECTORY, TOPIC_TF] + ([TOPIC_POINTS] if include_frames else [])
                           + ([TOPIC_DOUBLE_WALLS] if plan.regions else [])
                           + ([TOPIC_MESH] if plan.mesh is not None else [])
                           + ([TOPIC_GRID2D] if plan.grid2d is not None else [])),
        "volume_voxel_size_m": "" if volume is None else f"{volume.grid.voxel_size_m:g}",
        "grid2d_band_m": "" if plan.grid2d is None else f"{plan.grid2d.band_m[0]:g},{plan.grid2d.band_m[1]:g}",
        **({} if plan.frame_sessions is None else _session_metadata(plan.frame_sessions)),
    }


def _session_metadata(frame_sessions: NDArray[np.int64]) -> dict[str, str]:
    """``color="session"``: ``color`` and ``sessions`` (``K=#rrggbb (name), N frames`` per session, ``;``-joined)."""
    ks, counts = np.unique(frame_sessions, return_counts=True)
    return {"color": "session",
            "sessions": "; ".join(f"{int(k)}={session_color_text(int(k))}, {int(n)} frames" for k, n in zip(ks, counts))}


def _write_map(out: _TopicWriter, store: FrameStore, rev: int, map_voxel_size_m: float | None, t0: int,
               plan: _Plan | None = None) -> int:
    """``/map``: the revision's fused points with, per voxel, the number of frames that saw it and the first of
    them (``color="session"``: also that frame's session and its colour). Returns the number of map points."""
    fused = MapView.from_store(store, rev).fused(map_voxel_size_m)  # the view is released once fused
    if plan is not None and plan.frame_sessions is not None:
        return _write_session_map(out, fused, plan, t0)
    n_map = len(fused.points_world)
    offsets = fused.provenance_offsets
    n_frames_per_voxel = np.diff(offsets).astype(np.float32)
    first_frame = (np.minimum.reduceat(fused.provenance_frame_ids, offsets[:-1]).astype(np.float32)
                   if n_map else np.zeros(0, np.float32))
    map_rows = np.empty((n_map, 5), dtype="<f4")
    map_rows[:, :3] = fused.points_world
    map_rows[:, 3] = n_frames_per_voxel
    map_rows[:, 4] = first_frame
    del fused
    check_size(map_rows.nbytes, f"{TOPIC_MAP} ({n_map:,} points)", "raise map_voxel_size_m")
    map_fields = [{"name": n, "offset": 4 * i, "type": FLOAT32} for i, n in enumerate(("x", "y", "z", "n_frames", "frame_id"))]
    out.write(TOPIC_MAP, cloud_message(WORLD_FRAME, t0, map_rows.tobytes(), 20, map_fields), t0)
    return n_map


_SESSION_MAP_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("n_frames", "<f4"), ("frame_id", "<f4"),
                               ("session", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1"), ("alpha", "u1")])


def _write_session_map(out: _TopicWriter, fused: Any, plan: _Plan, t0: int) -> int:
    """``/map`` of ``color="session"``: the fields of :func:`_write_map`, then ``session`` float32 (the session of
    the voxel's first frame, looked up by its integer id) and ``red green blue alpha`` uint8 (that session's
    colour). Returns the number of map points."""
    assert plan.frame_sessions is not None
    n_map = len(fused.points_world)
    offsets = fused.provenance_offsets
    first = (np.minimum.reduceat(fused.provenance_frame_ids, offsets[:-1]).astype(np.int64)
             if n_map else np.zeros(0, np.int64))
    sessions = plan.frame_sessions[np.searchsorted(plan.frame_ids, first)]
    palette = np.asarray(SESSION_PALETTE_RGB, np.uint8)
    rows = np.empty(n_map, _SESSION_MAP_DTYPE)
    for axis, name in enumerate("xyz"):
        rows[name] = fused.points_world[:, axis]
    rows["n_frames"] = np.diff(offsets)
    rows["frame_id"] = first
    rows["session"] = sessions
    rgb = palette[sessions % len(palette)]
    rows["red"], rows["green"], rows["blue"], rows["alpha"] = rgb[:, 0], rgb[:, 1], rgb[:, 2], 255
    check_size(rows.nbytes, f"{TOPIC_MAP} ({n_map:,} points)", "raise map_voxel_size_m")
    fields = [{"name": name, "offset": _SESSION_MAP_DTYPE.fields[name][1],
               "type": UINT8 if _SESSION_MAP_DTYPE[name] == np.uint8 else FLOAT32} for name in _SESSION_MAP_DTYPE.names]
    out.write(TOPIC_MAP, cloud_message(WORLD_FRAME, t0, rows.tobytes(), _SESSION_MAP_DTYPE.itemsize, fields), t0)
    return n_map


def _write_revision_results(out: _TopicWriter, plan: _Plan, volume: VolumeLayers | None) -> None:
    """``/trajectory``, and ``/double_walls``, ``/driftmap/mesh`` and ``/driftmap/grid2d`` when they are written,
    at the first stamp."""
    t0 = plan.t0
    trajectory = PosesInFrame(frame_id=WORLD_FRAME)
    set_stamp(trajectory, t0)
    for k in plan.order:
        set_pose(trajectory.poses.add(), plan.poses[k])
    out.write(TOPIC_TRAJECTORY, trajectory, t0)
    if plan.regions:
        out.write(TOPIC_DOUBLE_WALLS, double_wall_scene(plan.regions, t0), t0)
    if plan.mesh is not None:
        assert volume is not None
        out.write(TOPIC_MESH, mesh_scene(plan.mesh, t0, metadata={
            "revision": str(plan.revision.revision_id), "voxel_size_m": f"{volume.grid.voxel_size_m:g}",
            "truncation_m": f"{float(volume.config.truncation_m or 0.0):g}"}), t0)
    if plan.grid2d is not None:
        out.write(TOPIC_GRID2D, grid2d_message(plan.grid2d, t0), t0)


def _write_frames(out: _TopicWriter, store: FrameStore, plan: _Plan, include_frames: bool,
                  frame_voxel_size_m: float | None, tick: ProgressCallback) -> int:
    """Every frame at its stamp: ``/tf`` (its pose in the revision), then ``/points`` (its sensor-frame points)
    with ``include_frames``. Returns the number of points written on ``/points``."""
    n_frame_points = 0
    for done, k in enumerate(plan.order, start=1):
        fid, stamp = int(plan.frame_ids[k]), int(plan.stamps_ns[k])
        child = cloud_frame_name(store.frame_info(fid)["sensor_frame"], fid)
        out.write(TOPIC_TF, transform_message(WORLD_FRAME, child, plan.poses[k], stamp), stamp)
        if include_frames:
            points, attrs = frame_cloud_points(store, fid, frame_voxel_size_m)
            if plan.frame_sessions is not None:  # the session's colour in place of the frame's own
                attrs = PointAttributes(intensity=attrs.intensity,
                                        color_rgb=np.tile(np.asarray(plan.session_rgb(k), np.uint8), (len(points), 1)))
            payload, stride, fields = pack_points(points, attrs)
            check_size(len(payload), f"{TOPIC_POINTS} frame {fid}", "set frame_voxel_size_m")
            out.write(TOPIC_POINTS, cloud_message(child, stamp, payload, stride, fields), stamp)
            n_frame_points += len(points)
        tick("frames", done, len(plan.order))
    return n_frame_points


# ---------------------------------------------------------------------------------------------- export


def export_foxglove_mcap(
    store: FrameStore,
    path: str | Path,
    *,
    revision: int | None = None,
    map_voxel_size_m: float | None = 0.02,
    frame_voxel_size_m: float | None = 0.05,
    include_frames: bool = True,
    double_walls: DoubleWallResult | Sequence[DoubleWallRegion] | None = None,
    volume: VolumeLayers | None = None,
    grid2d_band_m: tuple[float, float] | None = None,
    overwrite: bool = False,
    compression: str = "zstd",
    progress: ProgressCallback | None = None,
    color: str = "frame",
    sessions: Mapping[int, Sequence[int]] | None = None,
    mesh_weight_threshold: float | None = None,
) -> FoxgloveExportSummary:
    """Write one revision of ``store`` (default: the head) as a Foxglove-ready MCAP file at ``path``.

    ``map_voxel_size_m`` deduplicates ``/map`` (None: every point of every frame); ``frame_voxel_size_m``
    downsamples each frame on ``/points`` (None: every point); ``include_frames=False`` leaves out
    ``/points`` (``/tf`` is still written). ``double_walls`` (a detector result or its regions) adds
    ``/double_walls``. ``volume`` (the revision's :class:`~driftmap.volume.VolumeLayers`) adds its TSDF mesh
    on ``/driftmap/mesh`` (left out with a warning when the mesh is empty) and, with ``grid2d_band_m =
    (z_min, z_max)`` (metres), the 2-D occupancy grid of that height band on ``/driftmap/grid2d``. An
    existing file at ``path`` is an :class:`ExportError` unless ``overwrite``; a ``path``
    inside any store folder is refused, ``overwrite`` or not (:func:`driftmap.store.refuse_inside_store`). The
    file is written under a temporary name in the same folder (``.<name>.<random>.tmp.mcap``) and renamed into
    place only when complete, so a failed export never leaves a half-written file under the requested name.
    ``compression``: ``zstd`` | ``lz4`` | ``none``. ``color``: ``frame`` (default; the file as it always was) or
    ``session``: each session in its own colour on ``/map`` and ``/points`` (module docstring), the sessions given
    as ``sessions = {session: [frame ids]}`` (every frame of the store exactly once;
    ``driftmap.pipeline.merge.store_sessions`` of a merged store), None or empty: one session, one colour.
    ``mesh_weight_threshold``: the mesh's (``map.mesh_weight_threshold``; None: Open3D's 3).

    Raises :class:`~driftmap.errors.StoreError` for an unknown revision, :class:`~driftmap.errors.ConfigError`
    for a non-positive voxel size or unknown compression, volume layers of another revision, a
    ``grid2d_band_m`` without ``volume`` or a band that selects no observed voxel (naming ``--band-m``);
    :class:`~driftmap.errors.OutputInsideStoreError` for a path inside a store, :class:`EmptyStoreExportError`
    (an :class:`ExportError` and an :class:`~driftmap.errors.EmptyStoreError`) for a store without frames,
    :class:`ExportError` for a negative frame stamp (MCAP log times are unsigned) or an existing output, and
    :class:`~driftmap.errors.OutputWriteError` naming ``path`` when the file cannot be written (a full disk).
    """
    t_start = time.perf_counter()
    path = Path(path)
    rev_info = store.ledger.revision(store.head if revision is None else revision)  # StoreError naming the range
    rev = rev_info.revision_id
    chunk_compression = _check_settings(map_voxel_size_m, frame_voxel_size_m, compression, volume, grid2d_band_m, rev)
    if color not in COLOR_MODES:
        raise ConfigError(f"color must be one of {', '.join(COLOR_MODES)}, got {color!r}")
    if sessions is not None and color != "session":
        raise ConfigError("sessions= colours the export by session: give color='session' with it (CLI: --color session)")
    _check_output(path, overwrite)
    plan = _plan(store, path, rev_info, double_walls, volume, grid2d_band_m, color, sessions, mesh_weight_threshold)
    tick = progress or (lambda stage, done, total: None)
    with atomic_write(path, "Foxglove MCAP export path") as tmp, open(tmp, "wb") as fh:
        out = _TopicWriter(Writer(fh, compression=chunk_compression))
        out.writer.add_metadata(METADATA_NAME, _metadata(store, plan, map_voxel_size_m, frame_voxel_size_m,
                                                         include_frames, volume))
        # the revision's result, logged at the first stamp so that it shows as soon as the file opens
        tick("map", 0, 1)
        n_map = _write_map(out, store, rev, map_voxel_size_m, plan.t0, plan)
        tick("map", 1, 1)
        _write_revision_results(out, plan, volume)
        n_frame_points = _write_frames(out, store, plan, include_frames, frame_voxel_size_m, tick)
        out.writer.finish()
    summary = FoxgloveExportSummary(
        path=path,
        revision=rev,
        n_frames=len(plan.frame_ids),
        n_map_points=n_map,
        n_frame_points=n_frame_points,
        n_double_walls=len(plan.regions),
        message_counts=dict(out.counts),
        n_mesh_vertices=0 if plan.mesh is None else len(plan.mesh.vertices),
        n_mesh_triangles=0 if plan.mesh is None else len(plan.mesh.triangles),
        grid2d_shape=None if plan.grid2d is None else plan.grid2d.shape,
        session_colors=None if plan.frame_sessions is None else {int(k): session_color_rgb(int(k))
                                                                 for k in np.unique(plan.frame_sessions)},
        map_voxel_size_m=map_voxel_size_m,
        frame_voxel_size_m=frame_voxel_size_m,
        bytes=path.stat().st_size,
        seconds=time.perf_counter() - t_start,
    )
    logger.info("foxglove export: %s revision %d, %d frames, %d map points, %d frame points, %.1f MB in %.1f s",
                path, rev, summary.n_frames, n_map, n_frame_points, summary.bytes / 1e6, summary.seconds)
    return summary


__all__ = [
    "COLOR_MODES",
    "METADATA_NAME",
    "TOPIC_DOUBLE_WALLS",
    "TOPIC_GRID2D",
    "TOPIC_MAP",
    "TOPIC_MESH",
    "TOPIC_POINTS",
    "TOPIC_TF",
    "TOPIC_TRAJECTORY",
    "FoxgloveExportSummary",
    "double_wall_scene",
    "export_foxglove_mcap",
    "frame_cloud_points",
    "grid2d_message",
    "mesh_scene",
]
