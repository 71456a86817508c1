"""``driftmap build``: frames from any source -> validated -> odometry (or given poses) -> stored with the
pose that produced them (revision 0) -> keyframes, verified loop closures -> GTSAM pose graph -> a new
ledger revision (``loop_closure``) -> the map re-transformed through the store's ``apply``.

Library code: progress goes to a callback, numbers into :class:`BuildResult`; the CLI prints.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from driftmap import geometry
from driftmap.config import DepthConfig
from driftmap.errors import ConfigError, DriftmapError, NoPointsError, SourceError, StoreError
from driftmap.frame import Frame, PoseEstimate, PoseSource, SensorKind
from driftmap.pipeline.build_config import (
    DEFAULT_POSES_MAX_DT_NS,
    BuildConfig,
    BuildResult,
    ProgressCallback,
    tracking_summary,
)
from driftmap.pipeline.build_poses import (
    check_first_frame_poses,
    log_ground_truth_lookup,
    no_pose_message,
    pose_file_lookup,
)
from driftmap.pipeline.given_poses import check_given_poses
from driftmap.pipeline.loop_closure import check_place_descriptor, close_loops, flagged_rows
from driftmap.pipeline.resume import (
    check_recorded_source,
    check_resume_settings,
    check_stored_frames,
    describe_poses,
    poses_record,
    recorded_odometry,
    remove_new_store,
    source_record,
)
from driftmap.pipeline.source_options import (
    SOURCE_OPTION_FLAGS,
    check_source_options,
    detect_format,
    open_build_source,
    show_source_option,
    source_params,
)
from driftmap.preprocess.scene import lidar_frames, sample_positions, scene_reach
from driftmap.registration.odometry import GicpMapOdometry, KissOdometry, OdometryConfig, make_odometry
from driftmap.sources.base import FrameSource
from driftmap.store.frame_store import FrameStore
from driftmap.store.layout import BUILD_CONFIG_FILE, BUILD_SOURCE_FILE, BUILD_SUMMARY_FILE, MANIFEST, MERGE_SUMMARY_FILE
from driftmap.store.propagation import propagate_correction
from driftmap.store.values import preview

__all__ = [  # the names other modules and users take from here (several live in the sibling modules now)
    "BUILD_SOURCE_FILE", "DEFAULT_POSES_MAX_DT_NS", "SOURCE_OPTION_FLAGS", "BuildConfig", "BuildResult",
    "ProgressCallback", "build", "check_source_options", "detect_format", "flagged_rows", "show_source_option",
    "source_params", "tracking_summary",
]

logger = logging.getLogger(__name__)


def build(
    source: str | Path,
    out: str | Path,
    *,
    format: str | None = None,
    config: BuildConfig | None = None,
    poses_file: str | Path | None = None,
    poses_from_source: bool = False,
    loop_closure: bool = True,
    frames: str | None = None,
    resume: bool = False,
    progress: ProgressCallback | None = None,
    inject_wrong_loop: tuple[int, int, np.ndarray] | None = None,
    kitti_frame: str = "auto",
    calib_file: str | Path | None = None,
    poses_max_dt_ns: int = DEFAULT_POSES_MAX_DT_NS,
    depth: DepthConfig | None = None,
    source_options: dict[str, Any] | None = None,
) -> BuildResult:
    """Build (or ``resume``) a store from a source. See the module docstring for the stages.

    ``source_options``: which stream of the source to read (``sensor``, ``topic``, ``pose_from_tf``,
    ``pose_from_odometry``, ``lenient``: the command line's ``SOURCE_OPTION_FLAGS``); one the format does not take
    is a :class:`ConfigError` naming the flag; they are recorded, and ``--resume`` must give the same.
    ``depth``: how a depth-image source reads its images (:class:`driftmap.config.DepthConfig`; None or unset
    fields: the source's own defaults). A set option the format does not take is a :class:`ConfigError`.
    ``--resume`` refuses a different source, pose mode (odometry / ``poses_file`` / ``poses_from_source``, and
    another ``poses_file``) or depth options than the store was built with (``build_source.json``).

    ``kitti_frame`` / ``calib_file``: the frame of a KITTI ``poses_file`` (``auto`` | ``velodyne`` | ``cam0``)
    and the calibration for ``cam0``; see :func:`driftmap.sources.kitti.kitti_rows_as_velodyne`.
    ``poses_max_dt_ns``: a TUM ``poses_file`` row is a frame's pose when it is the nearest within this (20 ms,
    as TUM's ``associate.py``).

    ``inject_wrong_loop=(frame_a, frame_b, T_a_b)`` adds a deliberately wrong loop measurement (for testing
    the robust back end); it is reported like any other loop.
    """
    config = config or BuildConfig()
    _check_pose_arguments(poses_file, poses_from_source, kitti_frame, calib_file, poses_max_dt_ns)
    tick = progress or (lambda stage, done, total: None)
    stages: dict[str, float] = {}
    out = Path(out)
    store_exists = (out / MANIFEST).exists()
    if store_exists and not resume:
        raise StoreError(f"{out}: a store exists already; use --resume to continue it or choose another --out")
    depth_options = (depth or DepthConfig()).source_options()
    source_options = {k: v for k, v in (source_options or {}).items() if v is not None and v is not False}
    src = open_build_source(source, format, frames, config, poses_from_source, depth_options, source_options)
    if config.depth_scale_error != 1.0 or config.focal_length_error != 1.0:
        logger.warning("build: frames perturbed on purpose (depth scale x%g, focal length x%g); recorded in build_config.json",
                       config.depth_scale_error, config.focal_length_error)
    record = source_record(source, src, poses_record(poses_file, poses_from_source, kitti_frame, calib_file),
                            depth_options, source_options)
    # inputs are checked before a store is created or opened for appending: a pose file that cannot be read
    # leaves nothing behind
    pose_of = pose_file_lookup(poses_file, src, kitti_frame, calib_file, poses_max_dt_ns) if poses_file is not None else None
    pose_of_source = PoseSource.EXTERNAL_FILE
    if poses_from_source and (ground_truth := log_ground_truth_lookup(src, Path(source), format)) is not None:
        pose_of, pose_of_source = ground_truth, PoseSource.GROUND_TRUTH
    new_store = not (resume and store_exists)
    if resume and new_store:  # a mistyped --out must not pass for a resume (hostile trial 18)
        logger.warning("--resume: %s %s, so there is nothing to resume: building a new store there", out,
                       "holds no store" if out.exists() else "does not exist")
    out_existed, new_dirs = out.exists(), [p for p in (out, *out.parents) if not p.exists()]  # what create() makes
    store, recorded = _open_store(out, new_store, src, record, pose_of, poses_from_source)
    try:
        if recorded is None or set(record) - set(recorded):
            # a new store, or one whose record predates some fields (checked above): write the full record
            (out / BUILD_SOURCE_FILE).write_text(json.dumps({**record, **(recorded or {})}, indent=2) + "\n")
        return _build(src, store, config, pose_of, poses_from_source, loop_closure, tick, stages, inject_wrong_loop,
                      source_record=record, pose_of_source=pose_of_source)
    except BaseException as exc:
        n_stored = len(store)
        store.close()
        what = "interrupted" if isinstance(exc, KeyboardInterrupt) else "failed"
        if new_store and (n_stored == 0 or isinstance(exc, NoPointsError)):
            remove_new_store(out, out_existed, new_dirs)
        elif n_stored:
            logger.warning("build %s with %d frames stored; %s is kept (continue it with --resume)", what, n_stored, out)
        raise
    finally:
        store.close()


def _check_pose_arguments(poses_file: str | Path | None, poses_from_source: bool, kitti_frame: str,
                          calib_file: str | Path | None, poses_max_dt_ns: int) -> None:
    """The pose options agree with each other (before anything is read)."""
    if poses_max_dt_ns < 0:
        raise ConfigError(f"the stamp tolerance of --poses must be >= 0, got {poses_max_dt_ns} ns")
    if poses_file is not None and poses_from_source:
        raise ConfigError("give either --poses FILE or --poses-from-source, not both")
    if poses_file is None and (kitti_frame != "auto" or calib_file is not None):
        raise ConfigError("--kitti-frame / --calib describe a KITTI --poses FILE; give one")


def _open_store(out: Path, new_store: bool, src: FrameSource, record: dict[str, Any],
                pose_of: Callable[[Frame], np.ndarray] | None,
                poses_from_source: bool) -> tuple[FrameStore, dict[str, Any] | None]:
    """A new store (after the first frame's pose is checked), or the store to resume with what it recorded of its
    source (checked against this run's: same source, pose mode, options and the frames already stored)."""
    if new_store:
        check_first_frame_poses(src, pose_of, poses_from_source)
        return FrameStore.create(out), None
    if (out / MERGE_SUMMARY_FILE).exists():  # trial 17 W9: it said a frame order was wrong
        raise ConfigError(f"{out}: is a merged store (`driftmap merge` made it): --resume continues a store `build` "
                          f"made; add a session to it with `driftmap merge {out} OTHER_STORE --append`")
    recorded = check_recorded_source(out, record)
    store = FrameStore.open(out, "a")
    for event in store.recovery_events:
        logger.warning("resume: %s", event)
    try:
        if recorded is None:
            check_stored_frames(store, src, record)
        check_resume_settings(store, src, recorded, record)
    except BaseException:
        store.close()
        raise
    return store, recorded


def _carry_head_correction(store: FrameStore, head: int, existing: set[int]) -> None:
    """``--resume`` on a store whose head is a correction (revision ``head``, not revision 0): the frames just added
    have only revision-0 poses, which the head would place beside its corrected ones (a seam; hostile trial 16 B3). A
    new revision keeps the head's poses of the frames it places and carries its correction on to the others (as
    ``correct`` does for frames its file has no row for): the new frames, and stored frames a rollback left out
    (hostile trial 18 W4), which the resumed log places again."""
    ids = store.frame_ids
    placed = set(store.ledger.members(head, later=False).tolist())
    kept = np.array([int(f) in placed for f in ids])
    poses = np.array(store.poses(head))
    parent = store.ledger.revision(head)
    made_by = parent  # the source of the carried poses: a rollback's are those of the revision it restores, a
    # stand-in's those of the revision before it (hostile trial 20 W4: the carry revision's source read "none")
    lost = set(store.loss.revision_ids)
    while True:
        if made_by.source is PoseSource.ROLLBACK and made_by.restores is not None:
            made_by = store.ledger.revision(made_by.restores)
        elif made_by.revision_id in lost and made_by.parent_id is not None:
            made_by = store.ledger.revision(made_by.parent_id)
        else:
            break
    new_ids = ids[~kept]
    # the head's world-frame correction of the neighbouring old frames, applied to the new frames' revision-0 poses
    prop_ids, prop_poses = propagate_correction(ids, store.ledger.stamps_ns, store.poses(0), ids[kept], poses[kept])
    poses[np.searchsorted(ids, prop_ids)] = prop_poses
    left_out = sorted(set(new_ids.tolist()) & existing)  # stored before this resume
    # (trial 19 W4: the note called every frame the head leaves out "new", also those stored before this resume)
    lost_frames = set(store.loss.frame_ids)
    again = [f for f in new_ids.tolist() if f in lost_frames and f not in existing]  # lost, stored again now
    parts = [f"{len(new_ids) - len(left_out) - len(again)} new frames",
             f"{len(again)} frames stored again after a loss" if again else "",
             f"{len(left_out)} stored frames it leaves out" if left_out else ""]
    carried_to = ", ".join(p for p in parts if p)
    revision = store.add_revision({int(f): poses[k] for k, f in enumerate(ids)}, source=made_by.source, parent=head,
                                  propagate=False,
                                  note=f"resume: revision {head}'s correction carried on to the {carried_to}")
    what = (f"the stand-in for a lost revision, with revision {made_by.revision_id}'s poses "
            f"({made_by.source.value})" if head in lost else f"{parent.source.value}, a correction")
    logger.warning("resume: the store's head was revision %d (%s); the %d frames it does not place "
                   "(%d..%d: %s) would have sat at their uncorrected poses beside it, so revision %d carries that "
                   "correction on to them", head, what, len(new_ids), int(new_ids.min()),
                   int(new_ids.max()), carried_to, revision.revision_id)


def _refuse_a_gap(src: FrameSource, existing: set[int], first_new: int) -> None:
    """``--resume`` tracking on from the last stored frame, with a selection that does not hold it: the first new
    frame must follow it as the stored frames follow each other (at most twice their usual id step). A selection that
    jumps ahead (``--frames=-10:`` after frames 0..24) made the odometry track across 25 missing frames and store the
    new ones 2-5.5 m off, exit 0 (hostile trial 20 B3). A selection that holds the last stored frame is tracked on as
    an uninterrupted build tracks it, whatever its step (hostile trial 21 B1)."""
    ids = np.array(sorted(existing))
    last = int(ids[-1])
    step = int(np.median(np.diff(ids))) if len(ids) > 1 else 1
    if first_new - last <= 2 * max(step, 1):
        return
    raise ConfigError(
        f"{src.uri}: --resume would add frame {first_new} after frame {last}, the last stored one, skipping the "
        f"frames between (the stored frames are {step} apart): the odometry tracks each frame from the one before "
        f"and cannot bridge them. Nothing new was stored. Resume with a selection that holds frame {last} and the "
        f"frames after it (the stored selection's start and step, a later end), or build the later frames into "
        f"another --out")


def _warn_a_wider_step(src: FrameSource, existing: set[int], first_new: int) -> None:
    """``--resume`` through the last stored frame with a step over 4 times the stored frames' own (step 3 after step 1
    stays quiet: the odometry bridges it on the trials' logs): tracked on, as
    an uninterrupted build of the selection tracks it (hostile trial 21 B1), but said: the odometry tracks each frame
    from the one before, and a step it cannot bridge stores the frame off without a flag (hostile trial 22 W1:
    ``--frames 24:60:24`` after frames 0..24 stored frame 48 2.1 m off, exit 0; ``build --frames 0:60:24`` from
    scratch stores frame 24 0.4 m off too)."""
    ids = np.array(sorted(existing))
    if len(ids) < 2:
        return  # no stored step to compare with
    last = int(ids[-1])
    step = max(int(np.median(np.diff(ids))), 1)
    if first_new - last > 4 * step:
        logger.warning("%s: --resume goes on from frame %d to frame %d, %d frames on, while the stored frames are %d "
                       "apart: the odometry tracks each frame from the one before, and a frame it cannot bridge to is "
                       "stored off without a flag; check the trajectory (export --trajectory), or resume with the "
                       "stored step", src.uri, last, first_new, first_new - last, step)


def _warn_a_mixed_step(src: FrameSource, existing: set[int], previous_id: int, first_new: int) -> None:
    """``--resume`` whose selection steps otherwise than the stored frames do: tracked on (trial 21 B1), but the store
    then mixes two frame spacings, which no uninterrupted build of one selection gives (hostile trial 27 W2:
    ``--frames 0:16:2`` after ``0:6`` stored frames 0..6 one apart, then 8..14 two apart, exit 0 without a word)."""
    ids = np.array(sorted(existing))
    if len(ids) < 2:
        return  # no stored step to compare with
    stored_step = max(int(np.median(np.diff(ids))), 1)
    new_step = first_new - previous_id
    if new_step == stored_step:
        return
    logger.warning("%s: --resume adds frame %d %d frame(s) after frame %d, while the stored frames are %d apart: the "
                   "store will mix both spacings, which no uninterrupted build of one --frames selection gives (rates, "
                   "drift per frame and frame-spacing settings read it as one log). Resume with the stored selection's "
                   "start and step for a store like an uninterrupted build's", src.uri, first_new, new_step,
                   previous_id, stored_step)


def _check_image_size(src: FrameSource, stored: Frame, frame: Frame) -> None:
    """``--resume``: the new frames' depth images must be read at the stored frames' size (the same pixel stride):
    else the store mixes point densities (a ROS log's depth topic is read at ``build.pixel_stride`` since hostile
    trial 27's follow-up; a store built before read it at every pixel)."""
    a, b = stored.intrinsics, frame.intrinsics
    if a is None or b is None or (a.width, a.height) == (b.width, b.height):
        return
    raise ConfigError(f"{src.uri}: --resume would store frame {frame.frame_id} as a {b.width}x{b.height} image, while "
                      f"the stored frames (the last: {stored.frame_id}) are {a.width}x{a.height} (another pixel "
                      f"stride: build.pixel_stride, chosen automatically as 2 for images 640 px wide or more); the "
                      f"store would mix two point densities. Nothing new was stored; resume with `[build] "
                      f"pixel_stride = {max(round(int(getattr(src, 'pixel_stride', 1)) * b.width / a.width), 1)}` "
                      f"in --config, or build into another --out")


STORED_POSE_TOLERANCE_M = 1e-6
"""``--resume`` with given poses: a stored frame's pose and the source's may differ by this (m, and rad) at most."""


def _check_stored_pose(src: FrameSource, store: FrameStore, frame: Frame, T_source: np.ndarray) -> None:
    """``--resume`` taking poses from the source or a file: a frame stored before must have the pose the source gives
    it now, else the store would mix two versions of the poses (a ground-truth file edited between the runs)."""
    T_stored = store.poses(0)[int(np.searchsorted(store.frame_ids, frame.frame_id))]
    moved_m = float(np.linalg.norm(T_stored[:3, 3] - T_source[:3, 3]))
    turned = float(np.abs(T_stored[:3, :3] - T_source[:3, :3]).max())
    if moved_m > STORED_POSE_TOLERANCE_M or turned > STORED_POSE_TOLERANCE_M:
        raise SourceError(f"{src.uri}: --resume: frame {frame.frame_id} is stored with another pose than the one the "
                          f"source gives it now ({moved_m:.6g} m apart): the poses changed since the store was built, "
                          f"and resuming would mix both versions; build into a new --out")


def _build(src: FrameSource, store: FrameStore, config: BuildConfig, pose_of: Callable[[Frame], np.ndarray] | None,
           poses_from_source: bool, loop_closure: bool, tick: ProgressCallback, stages: dict[str, float],
           inject_wrong_loop: tuple[int, int, np.ndarray] | None, *,
           source_record: dict[str, Any] | None = None,
           pose_of_source: PoseSource = PoseSource.EXTERNAL_FILE) -> BuildResult:
    existing = {int(i) for i in store.frame_ids}
    last_stored = max(existing) if existing else -1
    head_before = store.head if existing else 0
    poser = _Poser(src, store, config, pose_of, poses_from_source, pose_of_source, existing, tick)
    n_total = len(src)
    invalid: list[float] = []
    n_new = n_pointless = 0
    t_read = t_odom = t_store = 0.0
    t0 = time.perf_counter()
    frame_iter = iter(src)
    done = 0
    previous_id: int | None = None  # the frame the source yielded last (stored before or not)
    while True:
        t_a = time.perf_counter()
        try:
            frame = next(frame_iter)
        except StopIteration:
            break
        t_read += time.perf_counter() - t_a
        done += 1
        if frame.quality is not None:
            invalid.append(frame.quality.invalid_fraction)
        frame = _with_sensor_error(frame, config)
        if done == 1 and loop_closure and frame.sensor_kind is not SensorKind.LIDAR:
            check_place_descriptor(config.loop_closure, frame)  # before anything is stored
        if frame.frame_id in existing:
            if poses_from_source or pose_of is not None:
                _check_stored_pose(src, store, frame, poser.pose(frame)[0])
            tick("frames", done, n_total)
            previous_id = frame.frame_id
            continue
        if existing and poser.source is PoseSource.ODOMETRY and frame.frame_id < last_stored:
            if frame.frame_id in store.loss.frame_ids:  # (hostile trial 20 W1: "not stored", "the selection skipped")
                raise ConfigError(
                    f"{src.uri}: --resume would add frame {frame.frame_id} after frame {last_stored}, the last stored "
                    f"one: frame {frame.frame_id} was stored and lost to damage (`driftmap recover` declared frames "
                    f"{preview(store.loss.frame_ids)} lost). The odometry tracks forward in time from the stored frames "
                    f"and cannot store a frame before them again; the store stays as it is (the lost frames a gap). "
                    f"To have them, build the log into another --out; to add later frames, resume with a selection "
                    f"that starts after frame {last_stored}")
            raise ConfigError(
                f"{src.uri}: --resume would add frame {frame.frame_id} after frame {last_stored}, the last stored one: "
                f"the odometry tracks forward in time from the stored frames and cannot place a frame before them "
                f"(this --frames selection holds frames the stored selection skipped). Frame {frame.frame_id} was not stored; build "
                f"them into another --out, or resume with a selection that starts after frame {last_stored}")
        if existing and n_new == 0 and poser.source is PoseSource.ODOMETRY and previous_id != last_stored:
            # the selection yields the last stored frame and then this one: what an uninterrupted build tracks too
            # (a step, frames --lenient skips, a gap in the log; hostile trial 21 B1). Otherwise it starts past it:
            _refuse_a_gap(src, existing, frame.frame_id)
        elif existing and n_new == 0 and poser.source is PoseSource.ODOMETRY:
            _warn_a_wider_step(src, existing, frame.frame_id)
        if existing and n_new == 0:
            _warn_a_mixed_step(src, existing, last_stored if previous_id is None else previous_id, frame.frame_id)
            _check_image_size(src, store.frame(last_stored), frame)
        t_b = time.perf_counter()
        T, health = poser.pose(frame)
        t_c = time.perf_counter()
        stored = frame.with_pose(PoseEstimate(T, revision=0, source=poser.source, world_frame=frame.pose.world_frame))
        store.append(stored if health is None else dataclasses.replace(stored, tracking=health))
        t_store += time.perf_counter() - t_c
        t_odom += t_c - t_b
        n_new += 1
        n_pointless += frame.n_points == 0
        tick("frames", done, n_total)
    pose_source, odometry, odometry_config, scene = poser.source, poser.odometry, poser.odometry_config, poser.scene
    stages["read+validate"] = t_read
    if poser.retrack_seconds is not None:  # timed within the first new frame's pose: reported on its own
        stages["re-tracking"] = poser.retrack_seconds
        t_odom -= poser.retrack_seconds
    stages["odometry" if pose_source is PoseSource.ODOMETRY else "poses"] = t_odom
    stages["store"] = t_store
    logger.info("stored %d new frames in %.1f s", n_new, time.perf_counter() - t0)
    if src.skipped:
        logger.warning("%d frames skipped (lenient): %s", len(src.skipped), src.skipped[:5])
        if len(store) == 0:
            frame_index, reason = src.skipped[0]
            raise SourceError(f"every frame read was skipped ({len(src.skipped)}; --lenient), so nothing was stored; "
                              f"the first, frame {frame_index}: {reason}")
    if n_new and n_pointless == n_new and n_new == len(store):
        raise NoPointsError(f"none of the {n_new} frames read holds a point (every depth pixel invalid or out of "
                             f"range, or an empty scan), so no store was kept: check the frames (a depth image of "
                             f"zeros, the wrong --depth-scale or --format)")
    result = BuildResult(
        store=str(store.path), n_frames=len(store), n_frames_new=n_new,
        mean_invalid_fraction=float(np.mean(invalid)) if invalid else None,
        pose_source=pose_source.value if n_new else store.ledger.revision(0).source.value,
        odometry_fps=odometry.fps if odometry is not None else None, seconds_per_stage=stages, source=source_record,
        odometry_config=odometry_config, tracking=tracking_summary(store), scene_reach=scene,
    )
    ours = poser.pose_of is None and not poser.poses_from_source  # our odometry's poses (not a file's, not the log's)
    if len(store) >= 2 and not ours:  # also a resume that adds nothing, and a log's own odometry (trial 13)
        t_check = time.perf_counter()
        what = describe_poses((source_record or {}).get("poses", {"mode": "source"}))
        try:
            check = check_given_poses(store)
        except (DriftmapError, RuntimeError, ValueError, np.linalg.LinAlgError) as exc:  # a check, not the build
            logger.warning("%s: not checked against the frames (%s: %s); the frames are stored", what,
                           type(exc).__name__, exc)
            result.given_poses_check = {"consistent": None, "error": f"{type(exc).__name__}: {exc}"}
        else:
            result.given_poses_check = check.to_json()
            if (reason := check.reason(what)) is not None:
                logger.warning("%s", reason)
        stages["given poses check"] = time.perf_counter() - t_check
    if result.tracking["flagged"]:
        logger.warning("odometry: %d of %d frames flagged (tracking lost, poses bridged): %s; loop closure does not "
                       "trust the trajectory across them", len(result.tracking["flagged"]), result.tracking["frames"],
                       ", ".join(f"{f['frame_id']} ({f['status']})" for f in result.tracking["flagged"][:10]))
    if result.tracking["degenerate"]:
        logger.warning("odometry: %d of %d frames degenerate (a direction of motion unconstrained by the scan, bridged "
                       "along it by the motion model): %s", len(result.tracking["degenerate"]),
                       result.tracking["frames"], ", ".join(str(f["frame_id"]) for f in result.tracking["degenerate"][:10]))
    if loop_closure and len(store) >= 2:
        close_loops(store, config, result, tick, stages, inject_wrong_loop,
                     own_odometry=pose_of is None and not poses_from_source)
    left_out = head_before != 0 and len(store.ledger.members(head_before, later=False)) < len(store)
    if (n_new or left_out) and head_before != 0 and store.head == head_before:
        # also when loop closure ran and made no revision (no loop accepted: hostile trial 18 B1, a 1.44 m seam), and
        # when the resume adds no frame but the head leaves stored ones out (a rollback, a revision lost to damage:
        # hostile trial 19 W3), which the resumed log places again
        _carry_head_correction(store, head_before, existing)
    (store.path / BUILD_CONFIG_FILE).write_text(config.model_dump_json(indent=2) + "\n")
    (store.path / BUILD_SUMMARY_FILE).write_text(json.dumps(result.to_json(), indent=2, default=str) + "\n")
    return result


def _scene_sample(src: FrameSource, first: Frame, config: BuildConfig) -> list[Frame]:
    """Frames spread over the log whose reach sets the odometry's lengths (LiDAR; :mod:`driftmap.preprocess.scene`):
    the source's, or only ``first`` (the first frame the odometry registers) when the source's length is unknown.
    Never the stored frames: a resumed build that has no record of its lengths (killed before it wrote
    ``build_summary.json``) chooses them again from the frames the killed build chose them from (its store was empty
    then), so that the re-tracked odometry is the killed build's."""
    if first.sensor_kind is not SensorKind.LIDAR:
        return [first]
    try:
        n = len(src)
    except SourceError:
        n = 0
        logger.warning("%s: the number of frames is unknown, so the LiDAR odometry's lengths come from frame %d alone",
                       src.uri, first.frame_id)
    sample = []
    for k in sample_positions(n):
        try:
            sample.append(_with_sensor_error(src.frame(k), config))
        except SourceError as exc:  # an unreadable frame is skipped (or fails) when the build reaches it
            logger.info("scene reach: frame index %d not sampled (%s)", k, exc)
    return sample or [first]


def _with_sensor_error(frame: Frame, config: BuildConfig) -> Frame:
    """Apply the configured depth-scale / focal-length error (the perturbation harness's build-time part)."""
    if config.depth_scale_error == 1.0 and config.focal_length_error == 1.0:
        return frame
    from driftmap.diagnostics import perturb

    if config.focal_length_error != 1.0:
        if frame.intrinsics is None:
            raise ConfigError(f"frame {frame.frame_id}: focal_length_error needs a depth camera with intrinsics "
                              f"({frame.sensor_kind.value} frames have none)")
        frame = perturb.with_focal_error(frame, config.focal_length_error)
    if config.depth_scale_error != 1.0:
        frame = perturb.with_depth_scale_error(frame, config.depth_scale_error)
    return frame


RETRACK_TOLERANCE = 1e-9
"""``--resume`` with our odometry: a re-tracked stored frame whose pose differs from its stored one by more than this
(m, and rotation-matrix entries) is a disagreement (reported, and the new frames anchored to the stored poses). With
``--threads 1`` they agree to the bit; with more threads the registration's partial sums arrive in varying order."""


class _Poser:
    """The revision-0 pose of each new frame: from the pose file or the log's ground truth (``pose_of``), from the
    source (``--poses-from-source``), or from the odometry, made on the first frame that needs it (its lengths from
    frames spread over the log, or as recorded on ``--resume``).

    ``--resume`` (our odometry, frames stored): the odometry re-tracks every stored frame first, in the store's order
    (:meth:`_retrack`), so that its whole state -- local map, adaptive threshold, motion model, the refinements'
    previous scan, the recent fitness, the lost-frame count -- is the one the interrupted build had when it stopped,
    and the new frames get the poses an uninterrupted build gives them."""

    def __init__(self, src: FrameSource, store: FrameStore, config: BuildConfig,
                 pose_of: Callable[[Frame], np.ndarray] | None, poses_from_source: bool, pose_of_source: PoseSource,
                 existing: set[int], tick: ProgressCallback | None = None) -> None:
        self.src, self.store, self.config, self.existing = src, store, config, existing
        self.pose_of, self.poses_from_source = pose_of, poses_from_source
        self.tick = tick or (lambda stage, done, total: None)
        self.source = pose_of_source if pose_of else PoseSource.ODOMETRY
        self.odometry: KissOdometry | GicpMapOdometry | None = None
        self.odometry_config: dict[str, Any] | None = None
        self.scene: dict[str, Any] | None = None
        self.retrack_seconds: float | None = None
        """How long re-tracking the stored frames took (None: there was none)."""
        self._anchor: np.ndarray | None = None
        """Applied to the odometry's new poses when the re-tracked stored poses disagreed with the stored ones (see
        :meth:`_retrack`); None: they agreed (the odometry's poses are stored as they are)."""

    def pose(self, frame: Frame) -> tuple[np.ndarray, Any]:
        """``(T_world_sensor, tracking health or None)`` of ``frame``."""
        if self.pose_of is not None:
            return self.pose_of(frame), None
        if self.poses_from_source:
            if frame.pose.source is PoseSource.NONE:
                raise SourceError(no_pose_message(self.src, frame.frame_id))
            self.source = frame.pose.source
            return frame.T_world_sensor, None
        if self.odometry is None:
            self.odometry = self._make_odometry(frame)
        step = self.odometry.register(frame)
        if self._anchor is not None:
            return self._anchor @ step.T_world_sensor, step.health
        return step.T_world_sensor, step.health

    def _make_odometry(self, frame: Frame) -> KissOdometry | GicpMapOdometry:
        store, config = self.store, self.config
        cfg = config.odometry or (recorded_odometry(store) if self.existing else None)
        if cfg is None:
            # the frame the odometry starts at: on --resume the first stored one, where the interrupted build started
            first = store.frame(int(store.frame_ids[0])) if self.existing else frame
            sample = _scene_sample(self.src, first, config)
            reach = scene_reach(lidar_frames(sample))
            self.scene = None if reach is None else reach.to_json()
            cfg = OdometryConfig.for_frames(sample)
        if config.num_threads is not None:
            cfg = cfg.model_copy(update={"num_threads": config.num_threads})
        self.odometry_config = cfg.model_dump(mode="json")
        if not self.existing:
            return make_odometry(cfg)
        odometry = make_odometry(cfg, store.poses(0)[0])  # the first stored pose: the origin the build started from
        self._retrack(odometry)
        return odometry

    def _retrack(self, odometry: KissOdometry | GicpMapOdometry) -> None:
        """Register every stored frame again (read back from the store: the frames exactly as the interrupted build
        registered them, after its sensor-error perturbation) in the store's order, writing nothing, and compare the
        poses with the stored revision-0 ones. The stored poses stay the truth of the stored frames. When they
        disagree (beyond :data:`RETRACK_TOLERANCE`: more than one thread, or a store built by another version), a
        warning gives the largest difference, and the new frames' poses are anchored to the last stored frame's stored
        pose (the odometry's motion from it is kept), so that revision 0 has no jump where the build resumed."""
        store = self.store
        ids, stored = store.frame_ids, store.poses(0)
        n = len(ids)
        if "resume_seed_frames" in self.config.model_fields_set:
            logger.info("build.resume_seed_frames is not used: --resume re-tracks every stored frame")
        logger.info("re-tracking %d stored frames for an exact resume", n)
        t0 = time.perf_counter()
        worst_m = worst_entry = worst_deg = 0.0
        worst_id, n_exact = None, 0
        for k, fid in enumerate(ids):
            T = odometry.register(store.frame(int(fid))).T_world_sensor
            if np.array_equal(T, stored[k]):
                n_exact += 1
            else:
                moved_m = float(np.linalg.norm(T[:3, 3] - stored[k][:3, 3]))
                if worst_id is None or moved_m > worst_m:
                    worst_id, worst_m = int(fid), moved_m
                worst_entry = max(worst_entry, float(np.abs(T[:3, :3] - stored[k][:3, :3]).max()))
                worst_deg = max(worst_deg, geometry.rotation_angle_deg(T, stored[k]))
            self.tick("re-tracking", k + 1, n)
        self.retrack_seconds = time.perf_counter() - t0
        if max(worst_m, worst_entry) <= RETRACK_TOLERANCE:
            logger.info("re-tracked %d stored frames in %.1f s: %d poses equal to the bit, the others within %.2g m / "
                        "%.2g deg of the stored ones", n, self.retrack_seconds, n_exact, worst_m, worst_deg)
            return
        threads = odometry.config.num_threads
        why = (f"the registration ran on {threads} threads, whose partial sums arrive in varying order (--threads 1 "
               f"repeats a build to the bit)" if threads > 1 else
               "the stored frames were registered otherwise (another driftmap version or odometry settings?)")
        logger.warning("resume: re-tracking the %d stored frames gave poses up to %.3g m / %.3g deg (frame %s) from "
                       "the stored ones (%d equal to the bit): %s. The stored poses are kept; the new frames continue "
                       "from the last stored frame's stored pose", n, worst_m, worst_deg, worst_id, n_exact, why)
        self._anchor = stored[-1] @ geometry.invert(T)
