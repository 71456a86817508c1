"""Poses from a ROS log: the TF tree (``/tf``, ``/tf_static``), pose topics (``nav_msgs/Odometry``,
``PoseStamped``, ``PoseWithCovarianceStamped``, ``TransformStamped``) and, for a sensor topic, each frame's pose
estimate and ``T_base_sensor`` (:class:`SensorPoses`)."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from driftmap.errors import ConfigError, SourceError, TfError
from driftmap.frame import PoseEstimate, PoseSource
from driftmap.sources.ros.backend import Backend, TopicInfo
from driftmap.sources.ros.containers import open_backend
from driftmap.sources.ros.msgtypes import (
    ODOMETRY,
    POSE_TYPES,
    POSE_WITH_COVARIANCE_STAMPED,
    TF_MESSAGE,
    TOPIC_TF,
    TOPIC_TF_STATIC,
    TRANSFORM_STAMPED,
    StampSource,
    message_fields,
    stamp_ns_of,
)
from driftmap.sources.tf import TfBuffer, TransformSeries, normalize_frame, transforms_from_tum

logger = logging.getLogger(__name__)


def transform_msg_matrix(transform: Any) -> NDArray[np.float64]:
    """``geometry_msgs/Transform`` -> 4x4."""
    t, q = transform.translation, transform.rotation
    return transforms_from_tum([t.x, t.y, t.z], [q.x, q.y, q.z, q.w])[0]


def pose_msg_matrix(pose: Any) -> NDArray[np.float64]:
    """``geometry_msgs/Pose`` -> 4x4."""
    p, q = pose.position, pose.orientation
    return transforms_from_tum([p.x, p.y, p.z], [q.x, q.y, q.z, q.w])[0]


def load_tf(
    backend: Backend,
    *,
    stamp: StampSource = StampSource.HEADER,
    static_only: bool = False,
    buffer: TfBuffer | None = None,
    topics: Sequence[str] = (TOPIC_TF, TOPIC_TF_STATIC),
) -> TfBuffer:
    """Fill a :class:`TfBuffer` from the ``tf2_msgs/TFMessage`` topics of a log (``/tf_static`` as static
    edges). With ``stamp=LOG`` dynamic samples are keyed by the message's log time instead of each
    transform's ``header.stamp``."""
    buffer = TfBuffer() if buffer is None else buffer
    available = backend.topics()
    for topic in topics:
        is_static = topic == TOPIC_TF_STATIC
        if is_static is False and static_only:
            continue
        info = available.get(topic)
        if info is None:
            continue
        if info.msgtype != TF_MESSAGE:
            raise SourceError(f"{backend.path}: topic {topic} has type {info.msgtype}, expected {TF_MESSAGE}")
        samples: dict[tuple[str, str], tuple[list[int], list[list[float]], list[list[float]]]] = {}
        parent_of: dict[str, tuple[str, str]] = {}  # child -> (parent, where it was first given)
        for raw in backend.stream([topic]):
            msg = backend.decode(raw)
            where = f"{backend.path}: {topic} message logged at {raw.log_time_ns} ns"
            with message_fields(where):
                for tr in msg.transforms:
                    parent, child = normalize_frame(tr.header.frame_id), normalize_frame(tr.child_frame_id)
                    header_ns = stamp_ns_of(tr.header.stamp)
                    if child not in parent_of:
                        buffer.check_edge(parent, child, f"{where} (stamp {header_ns} ns)")  # against other TF topics
                        parent_of[child] = (parent, f"the message logged at {raw.log_time_ns} ns")
                    elif parent_of[child][0] != parent:
                        first_parent, first_where = parent_of[child]
                        raise TfError(
                            f"{where} (stamp {header_ns} ns): frame {child!r} has two parents, {first_parent!r} "
                            f"(since {first_where}) and {parent!r} (a TF tree gives every frame one parent)"
                        )
                    t, q = tr.transform.translation, tr.transform.rotation
                    entry = samples.setdefault((parent, child), ([], [], []))
                    entry[0].append(header_ns if stamp is StampSource.HEADER else raw.log_time_ns)
                    entry[1].append([float(t.x), float(t.y), float(t.z)])
                    entry[2].append([float(q.x), float(q.y), float(q.z), float(q.w)])
        for (parent, child), (stamps, trans, quats) in samples.items():
            what = f"{backend.path}: {topic} {parent} -> {child}"
            T = transforms_from_tum(trans, quats, what=what, stamps_ns=stamps)
            try:
                if is_static:
                    buffer.add_static(parent, child, T[-1])  # the last one published wins, as in tf2
                else:
                    buffer.add_samples(parent, child, stamps, T)
            except TfError as exc:  # already checked per message; kept so that no TF error loses the file
                raise TfError(f"{what}: {exc}") from None
    return buffer


def read_tf(path: str | Path, *, format: str | None = None, stamp: StampSource = StampSource.HEADER) -> TfBuffer:
    """The TF tree of a log (``/tf`` and ``/tf_static``)."""
    backend = open_backend(path, format)
    try:
        return load_tf(backend, stamp=StampSource(stamp))
    finally:
        backend.close()


def load_pose_topic(
    backend: Backend, topic: str, *, stamp: StampSource = StampSource.HEADER, child_frame: str | None = None
) -> TransformSeries:
    """A pose topic as ``T_parent_child`` samples: ``nav_msgs/Odometry`` (``header.frame_id`` ->
    ``child_frame_id``), ``PoseStamped`` / ``PoseWithCovarianceStamped`` (``header.frame_id`` ->
    ``child_frame``, default the topic name) or ``TransformStamped``."""
    info = backend.topics().get(topic)
    if info is None:
        raise SourceError(f"{backend.path}: no topic {topic} (topics: {', '.join(sorted(backend.topics()))})")
    if info.msgtype not in POSE_TYPES:
        raise SourceError(
            f"{backend.path}: topic {topic} has type {info.msgtype}; expected one of {', '.join(POSE_TYPES)}"
        )
    stamps, trans, quats = [], [], []
    parents, children = set(), set()
    for raw in backend.stream([topic]):
        msg = backend.decode(raw)
        with message_fields(f"{backend.path}: {topic} message logged at {raw.log_time_ns} ns"):
            if info.msgtype == TRANSFORM_STAMPED:
                t, q = msg.transform.translation, msg.transform.rotation
                translation = [float(t.x), float(t.y), float(t.z)]
                children.add(normalize_frame(msg.child_frame_id))
            else:
                pose = msg.pose.pose if info.msgtype in (ODOMETRY, POSE_WITH_COVARIANCE_STAMPED) else msg.pose
                p, q = pose.position, pose.orientation
                translation = [float(p.x), float(p.y), float(p.z)]
                if info.msgtype == ODOMETRY:
                    children.add(normalize_frame(msg.child_frame_id))
            quats.append([float(q.x), float(q.y), float(q.z), float(q.w)])
            trans.append(translation)
            parents.add(normalize_frame(msg.header.frame_id))
            stamps.append(stamp_ns_of(msg.header.stamp) if stamp is StampSource.HEADER else raw.log_time_ns)
    if not stamps:
        raise SourceError(f"{backend.path}: topic {topic} has no messages")
    if len(parents) > 1 or len(children) > 1:
        raise SourceError(
            f"{backend.path}: topic {topic} changes frames (parents {sorted(parents)}, children {sorted(children)})"
        )
    child = children.pop() if children else (child_frame or topic.strip("/"))
    T = transforms_from_tum(trans, quats, what=f"{backend.path}: {topic}", stamps_ns=stamps)
    series = TransformSeries.from_samples(parents.pop(), child, stamps, T, what=f"{backend.path}#{topic}")
    if len(series) < len(stamps):
        logger.warning(
            "%s: topic %s has %d messages with repeated stamps (the last one is kept)",
            backend.path,
            topic,
            len(stamps) - len(series),
        )
    return series


def read_pose_topic(
    path: str | Path,
    topic: str,
    *,
    format: str | None = None,
    stamp: StampSource = StampSource.HEADER,
    child_frame: str | None = None,
) -> TransformSeries:
    """Odometry / PoseStamped / PoseWithCovarianceStamped / TransformStamped samples of a log topic."""
    backend = open_backend(path, format)
    try:
        return load_pose_topic(backend, topic, stamp=StampSource(stamp), child_frame=child_frame)
    finally:
        backend.close()


class SensorPoses:
    """Where the frames of one sensor topic are: ``T_base_sensor`` from the TF tree, and the pose estimate of the
    pose input -- ``/tf`` (``pose_from_tf=(world_frame, body_frame)``, SE(3) interpolation) or a
    ``nav_msgs/Odometry`` topic (``pose_from_odometry``) -- at each frame's stamp, composed with the TF path from
    its body frame to the sensor.

    ``base_frame``: the frame ``T_base_sensor`` is relative to; ``None``: the pose input's body frame, else
    ``default_base_frame``. ``export``: the ``driftmap.export`` entry of the topic, whose per-frame pose sources
    are restored. Made when the source opens: reads the TF the options need and checks that the frames connect.
    """

    def __init__(
        self,
        backend: Backend,
        topics: dict[str, TopicInfo],
        *,
        topic: str,
        sensor_frame: str,
        stamp: StampSource,
        pose_from_tf: tuple[str, str] | None,
        pose_from_odometry: str | None,
        base_frame: str | None,
        default_base_frame: str,
        export: dict[str, Any] | None,
    ):
        self.path = backend.path
        self.topic = topic
        self.first_sensor_frame = sensor_frame
        self.stamp = stamp
        self.pose_from_tf = pose_from_tf
        self.export = export
        self.odometry: TransformSeries | None = None
        self.tf: TfBuffer | None = None
        self.world_frame: str | None = None
        body: str | None = None
        if pose_from_odometry is not None:
            odom_info = topics.get(pose_from_odometry)
            if odom_info is not None and odom_info.msgtype != ODOMETRY:
                raise SourceError(
                    f"{self.path}: pose_from_odometry topic {pose_from_odometry} has type "
                    f"{odom_info.msgtype}, expected {ODOMETRY}"
                )
            self.odometry = load_pose_topic(backend, pose_from_odometry, stamp=stamp)
            self.world_frame, body = self.odometry.parent_frame, self.odometry.child_frame
        elif pose_from_tf is not None:
            self.world_frame, body = normalize_frame(pose_from_tf[0]), normalize_frame(pose_from_tf[1])
            self._check_pose_from_tf_frames(self.world_frame, body)
        self.body_frame = body
        """The frame the pose input gives the pose of (``None`` without a pose input)."""
        self.base_frame = normalize_frame(base_frame if base_frame is not None else body or default_base_frame)
        self._no_pose_estimate: PoseEstimate | None = None
        self._read_tf(backend)
        if pose_from_tf is not None:
            self._check_world_frame_place()

    def _flag(self) -> str:
        assert self.pose_from_tf is not None
        return f"--pose-from-tf {self.pose_from_tf[0]},{self.pose_from_tf[1]} (pose_from_tf)"

    def _check_pose_from_tf_frames(self, world: str, body: str) -> None:
        """A world frame equal to the body or the sensor frame makes no pose: every pose would be the identity."""
        if world == body:
            raise ConfigError(
                f"{self.path}: {self._flag()}: the world frame and the child frame are both {world!r}, which makes "
                f"no pose (every pose would be the identity); give PARENT,CHILD as the fixed world frame and the "
                f"moving frame, e.g. odom,base_link"
            )
        if world == self.first_sensor_frame:
            raise ConfigError(
                f"{self.path}: {self._flag()}: the world frame {world!r} is the frame of the sensor topic "
                f"{self.topic} itself, so every pose would be the identity; PARENT must be a fixed frame such as "
                f"odom or map (PARENT,CHILD swapped?)"
            )

    def _check_world_frame_place(self) -> None:
        """Refuse a world frame that lies below the body or the sensor frame in the TF tree: it moves with the sensor,
        so the "pose" is a constant extrinsic (the usual cause: PARENT and CHILD swapped); warn when the whole path
        from the world frame to the sensor is static (every frame then gets the same pose)."""
        tf, world, body = self.tf, self.world_frame, self.body_frame
        if tf is None or world is None or body is None:
            return
        chain, frame = [world], world
        while (parent := tf.parent(frame)) is not None and parent not in chain:
            chain.append(parent)
            frame = parent
        for moving, what in ((body, "the child frame"), (self.first_sensor_frame, "the sensor frame")):
            if moving in chain[1:]:
                path = " -> ".join(reversed(chain[: chain.index(moving) + 1]))
                raise ConfigError(
                    f"{self.path}: {self._flag()}: the world frame {world!r} lies below {what} {moving!r} in the TF "
                    f"tree ({path}), so it moves with the sensor and gives no pose; PARENT must be a fixed frame "
                    f"above it (did you mean --pose-from-tf {body},{world}?)"
                )
        try:
            static = tf.is_static(world, self.first_sensor_frame)
        except TfError:
            return
        if static:
            logger.warning(
                "%s: %s: every edge from %r to the sensor frame %r is static (/tf_static), so every frame of %s "
                "gets the same pose; is %r really the fixed world frame?",
                self.path, self._flag(), world, self.first_sensor_frame, self.topic, world,
            )

    def _read_tf(self, backend: Backend) -> None:
        """Read the TF the options need and check that the frames are connected (errors name both frames).

        Only ``/tf_static`` is read when static extrinsics are all that is needed; ``/tf`` is read for
        ``pose_from_tf`` or when the extrinsics chain has a dynamic edge.
        """
        pairs = [(self.base_frame, self.first_sensor_frame)]
        if self.body_frame is not None:
            pairs.append((self.body_frame, self.first_sensor_frame))
            if self.pose_from_tf is not None:
                pairs.append((self.world_frame, self.body_frame))
        pairs = [(t, s) for t, s in pairs if t != s]
        if not pairs:
            return
        dynamic_read = self.pose_from_tf is not None
        self.tf = load_tf(backend, stamp=self.stamp, static_only=not dynamic_read)
        for target, source in pairs:
            try:
                self.tf.time_range_ns(target, source)  # raises on unknown frames, no path, no common time
                continue
            except TfError as exc:
                problem: TfError = exc
            if not dynamic_read:
                load_tf(backend, stamp=self.stamp, buffer=self.tf, topics=(TOPIC_TF,))
                dynamic_read = True
                try:
                    self.tf.time_range_ns(target, source)
                    continue
                except TfError as exc:
                    problem = exc
            raise SourceError(
                f"{self.path}: no TF path from {target!r} to {source!r} (sensor topic {self.topic}): {problem}"
            ) from None

    def _no_pose(self) -> PoseEstimate:
        """The identity ``PoseSource.NONE`` estimate of frames without a pose input. Made (and validated) once
        per source: a PoseEstimate is immutable (frozen, read-only matrix), so frames can share it."""
        if self._no_pose_estimate is None:
            self._no_pose_estimate = PoseEstimate(np.eye(4), source=PoseSource.NONE)
        return self._no_pose_estimate

    def pose(self, m: int, stamp_ns: int, sensor_frame: str) -> tuple[PoseEstimate, NDArray[np.float64]]:
        """The pose estimate ``T_world_sensor`` and ``T_base_sensor`` of message ``m``."""
        try:
            return self._pose(m, stamp_ns, sensor_frame)
        except TfError as exc:
            changed = ""
            if sensor_frame != self.first_sensor_frame:
                changed = f", frame_id {sensor_frame!r} (changed from {self.first_sensor_frame!r})"
            raise TfError(f"{self.path}: {self.topic} message {m} (stamp {stamp_ns} ns{changed}): {exc}") from None

    def _pose(self, m: int, stamp_ns: int, sensor_frame: str) -> tuple[PoseEstimate, NDArray[np.float64]]:
        tf = self.tf
        if self.base_frame == sensor_frame:
            T_base_sensor = np.eye(4)
        elif tf is not None:
            T_base_sensor = tf.lookup(self.base_frame, sensor_frame, stamp_ns)
        else:  # the sensor frame changed mid-log to one TF was not read for
            raise SourceError(
                f"{self.path}: {self.topic} message {m}: no TF path from {self.base_frame!r} to "
                f"{sensor_frame!r} (frame_id changed from {self.first_sensor_frame!r})"
            )
        recorded = None
        if self.export is not None:
            recorded = PoseSource(self.export["pose_sources"][m])
            if recorded is PoseSource.NONE:
                return self._no_pose(), T_base_sensor
        if self.odometry is None and self.pose_from_tf is None:
            return self._no_pose(), T_base_sensor
        body = self.body_frame
        assert body is not None and self.world_frame is not None
        if self.odometry is not None:
            T_world_body = self.odometry.at(stamp_ns)
            source = PoseSource.ODOMETRY
        else:
            assert tf is not None
            T_world_body = tf.lookup(self.world_frame, body, stamp_ns)
            source = PoseSource.LOG
        if body == self.base_frame:
            T_body_sensor = T_base_sensor
        elif body == sensor_frame:
            T_body_sensor = np.eye(4)
        else:
            assert tf is not None
            T_body_sensor = tf.lookup(body, sensor_frame, stamp_ns)
        pose = PoseEstimate(
            T_world_body @ T_body_sensor, revision=0, source=recorded or source, world_frame=self.world_frame
        )
        return pose, T_base_sensor
