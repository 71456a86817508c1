"""The frame source of a ROS log: :class:`RosLogSource` reads one PointCloud2 or depth Image topic of an MCAP file,
ROS 1 bag or rosbag2 folder (:mod:`driftmap.sources.ros`), composing the log's reader
(:mod:`~driftmap.sources.ros.containers`), the topic choice and CameraInfo (:mod:`~driftmap.sources.ros.topics`),
message decoding (:mod:`~driftmap.sources.ros.messages`), poses (:mod:`~driftmap.sources.ros.poses`) and the
export metadata (:mod:`~driftmap.sources.ros.provenance`)."""

from __future__ import annotations

import logging
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from driftmap.errors import DepthError, DepthScaleError, GeometryError, SourceError
from driftmap.frame import Frame, FrameQuality, PoseEstimate, PoseSource, Provenance, SensorKind
from driftmap.preprocess.depth import DEFAULT_MAX_DEPTH_M, DEFAULT_MIN_DEPTH_M, InvalidFractionMonitor, depth_frame
from driftmap.sources.base import FrameSource
from driftmap.sources.point_fields import PointTimeReference
from driftmap.sources.ros.backend import RawMessage
from driftmap.sources.ros.containers import open_backend
from driftmap.sources.ros.messages import RawMeasurement, depth_image_array, pointcloud2_array, pointcloud2_points
from driftmap.sources.ros.msgtypes import (
    DEPTH_ENCODINGS,
    EXPORT_METADATA_NAME,
    IMAGE,
    StampSource,
    header_stamp_ns,
    message_fields,
    stamp_ns_of,
)
from driftmap.sources.ros.poses import SensorPoses, load_pose_topic
from driftmap.sources.ros.provenance import export_entry, parse_origin, provenance_uri
from driftmap.sources.ros.topics import (
    CameraInfo,
    CameraInfoTrack,
    FirstMessages,
    choose_camera_info,
    choose_sensor_topic,
)
from driftmap.sources.stamps import check_stamp_ns
from driftmap.sources.tf import normalize_frame

logger = logging.getLogger(__name__)


class RosLogSource(FrameSource):
    """Frames of one PointCloud2 or depth Image topic of an MCAP file, ROS 1 bag or rosbag2 folder.

    Options:
        topic: the sensor topic; required when the log has several PointCloud2 / depth Image topics.
        stamp: :class:`StampSource` (``HEADER`` default, or ``LOG``) for frames and pose samples alike.
        start_ns, end_ns: keep frames with ``start_ns <= stamp < end_ns`` (by the chosen stamp).
        pose_from_tf: ``(world_frame, base_frame)``: pose of ``base_frame`` in ``world_frame`` from the TF
            tree at each frame's stamp (SE(3) interpolation), composed with the TF path to the sensor.
        pose_from_odometry: a ``nav_msgs/Odometry`` topic (``header.frame_id`` is the world frame,
            ``child_frame_id`` the body) interpolated at each frame's stamp.
        base_frame: the frame ``T_base_sensor`` is relative to; default: the pose input's body frame, else
            the sensor's own frame (identity extrinsics, TF not read).
        camera_info_topic: the CameraInfo topic to pair with (default: found by namespace and frame_id).
        min_depth_m, max_depth_m: valid depth range for Image topics.
        pixel_stride: keep every n-th pixel of depth images in both directions (see ``depth_frame``).
        point_time: :class:`PointTimeReference` of float per-point time fields.
        ignore_distortion: accept CameraInfo with non-zero distortion (frames are flagged).
        use_export_metadata: apply the ``driftmap.export`` metadata of MCAP files written by driftmap.
        frames, lenient: as in :class:`~driftmap.sources.base.FrameSource`.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        format: str | None = None,
        topic: str | None = None,
        stamp: StampSource | str = StampSource.HEADER,
        start_ns: int | None = None,
        end_ns: int | None = None,
        pose_from_tf: tuple[str, str] | None = None,
        pose_from_odometry: str | None = None,
        base_frame: str | None = None,
        camera_info_topic: str | None = None,
        min_depth_m: float = DEFAULT_MIN_DEPTH_M,
        max_depth_m: float = DEFAULT_MAX_DEPTH_M,
        pixel_stride: int = 1,
        point_time: PointTimeReference | str = PointTimeReference.AUTO,
        ignore_distortion: bool = False,
        use_export_metadata: bool = True,
        frames: str | slice | None = None,
        lenient: bool = False,
    ):
        super().__init__(str(path), frames=frames, lenient=lenient)
        self.path = Path(path)
        self.stamp = StampSource(stamp)
        self.point_time = PointTimeReference(point_time)
        self.start_ns, self.end_ns = start_ns, end_ns
        self.min_depth_m, self.max_depth_m = min_depth_m, max_depth_m
        self.pixel_stride = int(pixel_stride)
        self.ignore_distortion = ignore_distortion
        if pose_from_tf is not None and pose_from_odometry is not None:
            raise SourceError(f"{path}: give pose_from_tf or pose_from_odometry, not both")
        if pose_from_tf is not None and (
            len(pose_from_tf) != 2 or not all(isinstance(f, str) and f for f in pose_from_tf)
        ):
            raise SourceError(f"{path}: pose_from_tf must be (world_frame, base_frame), got {pose_from_tf!r}")
        self._backend = open_backend(self.path, format, lenient=lenient)
        try:
            self._setup(topic, pose_from_tf, pose_from_odometry, base_frame, camera_info_topic, use_export_metadata)
        except BaseException:
            self._backend.close()
            raise

    def _setup(
        self,
        topic: str | None,
        pose_from_tf: tuple[str, str] | None,
        pose_from_odometry: str | None,
        base_frame: str | None,
        camera_info_topic: str | None,
        use_export_metadata: bool,
    ) -> None:
        """Choose the topic and its CameraInfo, read the export metadata and the TF the options need."""
        self.format_name = self._backend.format_name
        self._topics = self._backend.topics()
        first_message = FirstMessages(self._backend, self._topics)
        self.topic = choose_sensor_topic(self.path, self._topics, first_message, topic)
        info = self._topics[self.topic]
        self.msgtype = info.msgtype
        self.reads_depth_images = self.msgtype == IMAGE
        """the topic is a depth image topic (``build`` applies ``build.pixel_stride`` to it as to a data set's)"""
        if self.pixel_stride != 1 and self.msgtype != IMAGE:
            raise SourceError(f"{self.path}: pixel_stride applies to depth images; {self.topic} is a {self.msgtype}")
        self._backend.check_decodable(self.topic)
        self._log_times: NDArray[np.int64] | None = None
        self._members: NDArray[np.int64] | None = None
        self._header_stamps: NDArray[np.int64] | None = None
        self._monitor = InvalidFractionMonitor()

        first = first_message(self.topic)
        if first is None:
            raise SourceError(f"{self.path}: topic {self.topic} has no messages")
        with message_fields(f"{self.path}: {self.topic} message 0"):
            self.first_sensor_frame = normalize_frame(first.header.frame_id)
            encoding = str(first.encoding) if self.msgtype == IMAGE else None
        if encoding is not None and encoding not in DEPTH_ENCODINGS:
            raise SourceError(
                f"{self.path}: topic {self.topic} is a {encoding!r} image, not a depth image "
                f"(expected {', '.join(DEPTH_ENCODINGS)})"
            )

        # driftmap export metadata (MCAP written by export_mcap)
        self._export: dict[str, Any] | None = self._export_entry() if use_export_metadata else None
        if (
            self._export is not None
            and pose_from_tf is None
            and pose_from_odometry is None
            and any(s != PoseSource.NONE.value for s in self._export.get("pose_sources", []))
        ):
            pose_from_tf = (self._export["world_frame"], self._export["base_frame"])
        if self._export is not None and self._export.get("point_time"):
            self.point_time = PointTimeReference(self._export["point_time"])

        self.camera_info_topic = choose_camera_info(
            self.path, self._topics, first_message, camera_info_topic,
            sensor_topic=self.topic, sensor_frame=self.first_sensor_frame, msgtype=self.msgtype,
        )
        self._camera_info = CameraInfoTrack(self._backend, self.camera_info_topic,
                                            ignore_distortion=self.ignore_distortion)
        self._setup_poses(pose_from_tf, pose_from_odometry, base_frame)

    def _setup_poses(self, pose_from_tf: tuple[str, str] | None, pose_from_odometry: str | None,
                     base_frame: str | None) -> None:
        """Poses and extrinsics (:class:`~driftmap.sources.ros.poses.SensorPoses`): reads the odometry topic and
        the TF the options need."""
        self.pose_from_tf = pose_from_tf
        self.pose_from_odometry = pose_from_odometry
        self._poses = SensorPoses(
            self._backend,
            self._topics,
            topic=self.topic,
            sensor_frame=self.first_sensor_frame,
            stamp=self.stamp,
            pose_from_tf=pose_from_tf,
            pose_from_odometry=pose_from_odometry,
            base_frame=base_frame,
            default_base_frame=(self._export or {}).get("base_frame") or self.first_sensor_frame,
            export=self._export,
        )
        self.world_frame: str | None = self._poses.world_frame
        self.pose_body_frame: str | None = self._poses.body_frame
        self.base_frame: str = self._poses.base_frame

    def export_origin(self) -> dict[str, Any] | None:
        """The data set an MCAP written by ``driftmap convert`` was read from (``{"format", "path",
        "options"}``), if it says so (:mod:`driftmap.export.mcap`)."""
        return parse_origin(self._backend.metadata().get(EXPORT_METADATA_NAME) or {})

    def _export_entry(self) -> dict[str, Any] | None:
        record = self._backend.metadata().get(EXPORT_METADATA_NAME)
        return export_entry(self.path, record, self.topic, self._topics[self.topic].count)

    # ---- index bookkeeping
    def log_times(self) -> NDArray[np.int64]:
        """Log time of every message on the topic (from the MCAP message index where there is one)."""
        if self._log_times is None:
            self._log_times = self._backend.log_times(self.topic)
        return self._log_times

    def header_stamps(self) -> NDArray[np.int64]:
        """``header.stamp`` of every message on the topic (decodes every message once; cached)."""
        if self._header_stamps is None:
            with message_fields(f"{self.path}: {self.topic}"):
                self._header_stamps = np.fromiter(
                    (stamp_ns_of(self._backend.decode(raw).header.stamp) for raw in self._backend.stream([self.topic])),
                    dtype=np.int64,
                )
        return self._header_stamps

    def _stamps(self) -> NDArray[np.int64]:
        return self.log_times() if self.stamp is StampSource.LOG else self.header_stamps()

    def _member_indices(self) -> NDArray[np.int64] | None:
        if self.start_ns is None and self.end_ns is None:
            return None
        if self._members is None:
            stamps = self._stamps()
            keep = np.ones(len(stamps), dtype=bool)
            if self.start_ns is not None:
                keep &= stamps >= self.start_ns
            if self.end_ns is not None:
                keep &= stamps < self.end_ns
            self._members = np.flatnonzero(keep).astype(np.int64)
        return self._members

    def _count(self) -> int:
        members = self._member_indices()
        if members is not None:
            return len(members)
        count = self._topics[self.topic].count
        return int(count) if count is not None else len(self.log_times())

    def _message_index(self, index: int) -> int:
        members = self._member_indices()
        return int(members[index]) if members is not None else int(index)

    def _frame_id(self, index: int) -> int:
        m = self._message_index(index)
        if self._export is not None:
            return int(self._export["frame_ids"][m])
        return m

    def _stamp_ns(self, index: int) -> int | None:
        m = self._message_index(index)
        if self.stamp is StampSource.LOG:
            return int(self.log_times()[m])
        return int(self._header_stamps[m]) if self._header_stamps is not None else None

    # ---- decoding
    def _measure(self, raw: RawMessage, m: int, info: CameraInfo | None) -> RawMeasurement:
        """Message ``m`` decoded to arrays (no back-projection); its fields checked (:func:`message_fields`)."""
        with message_fields(f"{self.path}: {self.topic} message {m}"):
            return self._measure_fields(raw, m, info)

    def _measure_fields(self, raw: RawMessage, m: int, info: CameraInfo | None) -> RawMeasurement:
        msg = self._backend.decode(raw)
        what = f"{self.path}: {self.topic} message {m}"
        sensor_frame = normalize_frame(msg.header.frame_id)
        if self.stamp is StampSource.HEADER:
            stamp_ns = header_stamp_ns(msg.header.stamp, what)
        else:
            stamp_ns = check_stamp_ns(raw.log_time_ns, f"{what}: log time")
        if info is None and self.camera_info_topic is not None:
            info = self._camera_info.at(raw.log_time_ns)
        intrinsics, flags = None, ()
        if info is not None:
            info_frame, intrinsics, flags = info
            if info_frame != sensor_frame:
                if self.msgtype == IMAGE:
                    raise SourceError(
                        f"{what}: frame_id {sensor_frame!r} but CameraInfo on {self.camera_info_topic} "
                        f"has frame_id {info_frame!r}"
                    )
                intrinsics, flags = None, ()
        if self.msgtype == IMAGE:
            if intrinsics is None:
                raise SourceError(f"{what}: depth image (frame_id {sensor_frame!r}) has no CameraInfo")
            depth, scale = depth_image_array(msg, what)
            if (depth.shape[1], depth.shape[0]) != (intrinsics.width, intrinsics.height):
                raise SourceError(
                    f"{what}: image is {depth.shape[1]}x{depth.shape[0]} but CameraInfo on "
                    f"{self.camera_info_topic} says {intrinsics.width}x{intrinsics.height}"
                )
            return RawMeasurement(
                m, stamp_ns, raw.log_time_ns, sensor_frame, depth, scale, None, None, intrinsics, flags, raw.size_bytes
            )
        cloud = pointcloud2_array(msg, what)
        return RawMeasurement(
            m, stamp_ns, raw.log_time_ns, sensor_frame, None, None, cloud, msg, intrinsics, flags, raw.size_bytes
        )

    def _to_frame(self, raw: RawMeasurement, uri: str | None = None) -> Frame:
        """The :class:`Frame` of a measurement; ``uri`` is :func:`provenance_uri` of this source, when the
        caller has it already (it resolves the path on the file system)."""
        m = raw.message_index
        frame_id = int(self._export["frame_ids"][m]) if self._export is not None else m
        pose, T_base_sensor = self._poses.pose(m, raw.stamp_ns, raw.sensor_frame)
        if uri is None:
            uri = provenance_uri(self.path, self.topic, self.stamp)
        provenance = Provenance(uri, m)
        sensor_name = (self._export or {}).get("sensor_name") or self.topic.strip("/")
        if raw.depth is not None:
            assert raw.intrinsics is not None
            return depth_frame(
                raw.depth,
                raw.intrinsics,
                frame_id=frame_id,
                stamp_ns=raw.stamp_ns,
                pose=pose,
                sensor_name=sensor_name,
                sensor_frame=raw.sensor_frame,
                T_base_sensor=T_base_sensor,
                depth_scale=raw.depth_scale or 1000.0,
                min_depth_m=self.min_depth_m,
                max_depth_m=self.max_depth_m,
                provenance=provenance,
                monitor=self._monitor,
                pixel_stride=self.pixel_stride,
                base_frame=self.base_frame,
                flags=tuple(raw.flags),
            )
        return self._cloud_frame(raw, frame_id, pose, T_base_sensor, sensor_name, provenance)

    def _cloud_frame(self, raw: RawMeasurement, frame_id: int, pose: PoseEstimate, T_base_sensor: NDArray[np.float64],
                     sensor_name: str, provenance: Provenance) -> Frame:
        """The :class:`Frame` of a PointCloud2 measurement: its finite points and their attributes."""
        m = raw.message_index
        what = f"{self.path}: {self.topic} message {m}"
        with message_fields(what):
            cloud = pointcloud2_points(raw.cloud_msg, raw.stamp_ns, what=what, point_time=self.point_time,
                                       warned=self._warned)
        flags = list(raw.flags)
        non_finite = cloud.invalid_counts.get("nan", 0) + cloud.invalid_counts.get("inf", 0)
        if non_finite and getattr(raw.cloud_msg, "is_dense", False):
            flags.append(f"is_dense_but_nonfinite: {non_finite} points with NaN/inf")
        kind = SensorKind.DEPTH_CAMERA if raw.intrinsics is not None else SensorKind.LIDAR
        export = self._export or {}
        if export.get("sensor_kind"):
            kind = SensorKind(export["sensor_kind"])
        n_measurements, invalid_counts = cloud.n_measurements, dict(cloud.invalid_counts)
        pixels = 0 if raw.intrinsics is None else int(raw.intrinsics.width) * int(raw.intrinsics.height)
        if kind is SensorKind.DEPTH_CAMERA and pixels > n_measurements and getattr(raw.cloud_msg, "height", 1) == 1:
            # an unorganised cloud of a depth camera (convert writes the valid pixels only): the pixels without a
            # point are invalid ones, not none (hostile trial 25 W3: "invalid-pixel fraction 0.000")
            invalid_counts["no_point"] = invalid_counts.get("no_point", 0) + pixels - n_measurements
            n_measurements = pixels
        return Frame(
            frame_id=frame_id,
            stamp_ns=raw.stamp_ns,
            sensor_name=sensor_name,
            sensor_kind=kind,
            points_sensor=cloud.points,
            pose=pose,
            T_base_sensor=T_base_sensor,
            attributes=cloud.attributes,
            intrinsics=raw.intrinsics,
            depth_scale=export.get("depth_scale"),
            quality=FrameQuality(n_measurements, len(cloud.points), invalid_counts, tuple(flags)),
            provenance=provenance,
            sensor_frame=raw.sensor_frame,
            base_frame=self.base_frame,
        )

    # ---- FrameSource
    def _load(self, index: int) -> Frame:
        m = self._message_index(index)
        raw = self._backend.fetch(self.topic, m, self.log_times())
        return self._to_frame(self._measure(raw, m, None))

    def _selected_messages(self) -> list[int]:
        return [self._message_index(i) for i in self._indices()]

    def _iterate(self, build: bool) -> Iterator[Any]:
        wanted = self._selected_messages()
        if not wanted:
            return
        start_ns, k = None, 0
        if wanted[0] > 0:
            times = self.log_times()
            start_ns = int(times[wanted[0]])
            k = int(np.searchsorted(times, start_ns, side="left"))
        topics = [self.topic] + ([self.camera_info_topic] if self.camera_info_topic else [])
        pos = 0
        uri = provenance_uri(self.path, self.topic, self.stamp) if build else None
        info_raw: RawMessage | None = None
        info_cache: tuple[RawMessage, CameraInfo] | None = None
        previous: tuple[int, int] | None = None  # (message index, stamp) of the last frame given out
        k -= 1
        for raw in self._backend.stream(topics, start_ns):
            if raw.topic != self.topic:
                info_raw = raw
                continue
            k += 1
            if k < wanted[pos]:
                continue
            try:
                info = None
                if info_raw is not None:
                    if info_cache is None or info_cache[0] is not info_raw:
                        info_cache = (info_raw, self._camera_info.decode(info_raw))
                    info = info_cache[1]
                measurement = self._measure(raw, k, info)
                if previous is not None and measurement.stamp_ns <= previous[1]:
                    kind = "duplicate" if measurement.stamp_ns == previous[1] else "non-monotonic"
                    raise SourceError(
                        f"{self.path}: topic {self.topic}: {kind} {self.stamp.value} stamps: message {k} has "
                        f"{measurement.stamp_ns} ns, message {previous[0]} before it has {previous[1]} ns"
                    )
                item = self._to_frame(measurement, uri) if build else measurement
            except (SourceError, DepthError, GeometryError) as exc:
                if not self.lenient or isinstance(exc, DepthScaleError):  # a wrong scale is wrong for every frame
                    raise
                logger.warning("%s: skipping message %d of %s: %s", self.path, k, self.topic, exc)
                self.skipped.append((k, str(exc)))
            else:
                previous = (k, measurement.stamp_ns)
                yield item
            pos += 1
            if pos == len(wanted):
                return

    def __iter__(self) -> Iterator[Frame]:
        """Frames in log order; stamps must increase strictly (else :class:`SourceError` naming both message
        indices, or the later frame is skipped in lenient mode)."""
        return self._iterate(build=True)

    def iter_raw(self) -> Iterator[RawMeasurement]:
        """Decode only: the selected messages as numpy arrays with their stamps and intrinsics, without
        back-projection, point filtering or pose lookups (the same checks on stamps as :meth:`__iter__`)."""
        return self._iterate(build=False)

    def describe(self) -> dict[str, Any]:
        out = super().describe()
        out.update(
            format=self.format_name,
            topic=self.topic,
            msgtype=self.msgtype,
            stamp=self.stamp.value,
            camera_info_topic=self.camera_info_topic,
            base_frame=self.base_frame,
            sensor_frame=self.first_sensor_frame,
            pose_from_tf=list(self.pose_from_tf) if self.pose_from_tf else None,
            pose_from_odometry=self.pose_from_odometry,
            damage=getattr(self._backend, "damage", None),
        )
        return out

    def ground_truth(self):  # type: ignore[override]
        """Ground truth written by :func:`~driftmap.export.mcap.export_mcap` (``PoseStamped`` on the
        sensor's ground-truth topic), else ``None``."""
        from driftmap.trajectory import Trajectory

        topic = (self._export or {}).get("ground_truth_topic")
        if not topic or topic not in self._topics:
            return None
        series = load_pose_topic(self._backend, topic, stamp=StampSource.HEADER)
        ids = self._export.get("ground_truth_frame_ids") if self._export else None
        frame_ids = np.asarray(ids, dtype=np.int64) if ids is not None and len(ids) == len(series) else None
        return Trajectory(np.array(series.stamps_ns), np.array(series.T_parent_child), frame_ids)

    def close(self) -> None:
        self._backend.close()

    def __enter__(self) -> RosLogSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
