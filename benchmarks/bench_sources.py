"""Reading a ROS 2 depth-camera log: ``RosLogSource`` vs the plain ``mcap`` reader + ``mcap_ros2`` decoder.

100 real 7-Scenes depth images (spread over the sequence) are written to a temporary MCAP as
``sensor_msgs/msg/Image`` ``16UC1`` + ``sensor_msgs/msg/CameraInfo`` per image (1 MiB chunks, the
``mcap_ros2`` default), once uncompressed and once zstd-compressed. One timed item is a whole pass over the
file, opening included (summary, topic discovery and CameraInfo pairing for ours); times are reported per
frame.

* ``ros_mcap_decode`` / ``ros_mcap_decode_zstd`` -- ours: ``RosLogSource(path).iter_raw()`` (decode the
  CDR messages, pair every image with its CameraInfo, (height, width) uint16 arrays, stamps, intrinsics; no
  back-projection). Anchor: ``make_reader(...).iter_decoded_messages`` over the same two topics plus
  ``np.frombuffer(...).reshape`` of each image. Target: ours <= 1.2x.
* ``ros_mcap_frames`` -- ours: ``list(RosLogSource(path))`` (full :class:`Frame` objects: validation,
  back-projection, quality, invalid-fraction monitor). Anchor: the plain reader + ``driftmap.backproject``
  of each decoded image. The difference to ``ros_mcap_decode`` is the back-projection cost, reported in
  ``details``.
"""

from __future__ import annotations

import logging
import tempfile
from pathlib import Path

import numpy as np
from _harness import check, time_per_item
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from PIL import Image

from driftmap import PinholeIntrinsics, backproject
from driftmap.datasets import ENV_VAR, shared_datasets_dir
from driftmap.export.depth_log import write_depth_image_mcap
from driftmap.sources.ros import RosLogSource

SCENE = "7scenes-redkitchen"
INTRINSICS = PinholeIntrinsics(fx=585.0, fy=585.0, cx=320.0, cy=240.0, width=640, height=480)
N_FRAMES = 100
TOPIC = "/camera/depth/image_raw"
INFO_TOPIC = "/camera/depth/camera_info"
STAMP0_NS = 1_700_000_000_000_000_000
PERIOD_NS = 33_333_333
TARGET_RATIO = 1.2
REPEATS, QUICK_REPEATS = 15, 3


def load_depths(n: int) -> tuple[list[str], list[np.ndarray]]:
    folder = shared_datasets_dir() / SCENE
    paths = sorted(folder.glob("frame-*.depth.png"))
    if not paths:
        raise FileNotFoundError(f"no frame-*.depth.png in {folder} (set {ENV_VAR} to the shared data-set folder)")
    picks = np.linspace(0, len(paths) - 1, min(n, len(paths))).round().astype(int)
    names, depths = [], []
    for i in picks:
        with Image.open(paths[i]) as im:
            depths.append(np.array(im).astype(np.uint16, copy=False))
        names.append(paths[i].name)
    return names, depths


def plain_decode(path: Path) -> list[tuple[int, np.ndarray, list[float]]]:
    """The anchor: mcap reader + ROS 2 decoder, images as (height, width) uint16 views."""
    out = []
    K: list[float] = []
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _, channel, _, msg in reader.iter_decoded_messages(topics=[TOPIC, INFO_TOPIC]):
            if channel.topic == INFO_TOPIC:
                K = msg.k
                continue
            stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
            out.append((stamp, np.frombuffer(msg.data, dtype="<u2").reshape(msg.height, msg.width), K))
    return out


def plain_frames(path: Path) -> list:
    results = []
    intrinsics: dict[tuple, PinholeIntrinsics] = {}
    for _, depth, K in plain_decode(path):
        key = tuple(K)
        if key not in intrinsics:
            intrinsics[key] = PinholeIntrinsics(K[0], K[4], K[2], K[5], depth.shape[1], depth.shape[0])
        results.append(backproject(depth, intrinsics[key]))
    return results


def ours_decode(path: Path) -> list:
    return list(RosLogSource(path).iter_raw())


def ours_frames(path: Path) -> list:
    return list(RosLogSource(path))


def per_frame(timing: dict, n: int) -> dict:
    """A pass timing -> per-frame timing (same ratios)."""
    out = dict(timing)
    for key in ("median_s", "min_s", "max_s"):
        out[key] = timing[key] / n
    out["samples_s"] = [s / n for s in timing["samples_s"]]
    out["page_faults_per_item"] = timing["page_faults_per_item"] / n
    out["items"] = n
    return out


def run(quick: bool = False) -> list[dict]:
    names, depths = load_depths(N_FRAMES)
    stamps = [STAMP0_NS + k * PERIOD_NS for k in range(len(depths))]
    repeats = QUICK_REPEATS if quick else REPEATS
    driftmap_logger = logging.getLogger("driftmap")
    level = driftmap_logger.level
    driftmap_logger.setLevel(logging.ERROR)  # the invalid-fraction monitor warns about frame jumps
    results = []
    try:
        with tempfile.TemporaryDirectory(prefix="driftmap-bench-") as tmp:
            files = {}
            for compression in ("none", "zstd"):
                path = Path(tmp) / f"depth_{compression}.mcap"
                write_depth_image_mcap(
                    path,
                    depths,
                    stamps,
                    INTRINSICS,
                    topic=TOPIC,
                    camera_info_topic=INFO_TOPIC,
                    compression=compression,
                    chunk_size=1024 * 1024,
                )
                files[compression] = path
            payload_bytes = sum(d.nbytes for d in depths)

            # correctness (untimed): same images, stamps and intrinsics as the plain reader and the PNGs
            for path in files.values():
                ours = ours_decode(path)
                plain = plain_decode(path)
                check(len(ours) == len(plain) == len(depths), f"{path.name}: {len(ours)} vs {len(plain)} frames")
                for raw, (stamp, image, K), depth in zip(ours, plain, depths, strict=True):
                    check(raw.stamp_ns == stamp, f"{path.name}: stamp {raw.stamp_ns} != {stamp}")
                    check(
                        np.array_equal(raw.depth, image) and np.array_equal(raw.depth, depth),
                        f"{path.name}: message {raw.message_index}: depth differs from the plain reader / PNG",
                    )
                    check(
                        raw.intrinsics == INTRINSICS and list(raw.intrinsics.K.ravel()) == list(K),
                        f"{path.name}: intrinsics {raw.intrinsics} != CameraInfo K {K}",
                    )
            frames = ours_frames(files["none"])
            for frame, depth, name in zip(frames, depths, names, strict=True):
                ref = backproject(depth, INTRINSICS)
                check(frame.points_sensor.tobytes() == ref.points.tobytes(), f"{name}: points differ from backproject")

            def entry(name: str, description: str, timings: dict, ours_key: str, path: Path, extra: dict) -> dict:
                timings = {k: per_frame(v, len(depths)) for k, v in timings.items()}
                ours = timings.pop(ours_key)
                rates = {
                    k: {
                        "frames_per_s": 1.0 / t["median_s"],
                        "payload_MB_per_s": payload_bytes / len(depths) / t["median_s"] / 1e6,
                        "file_MB_per_s": path.stat().st_size / len(depths) / t["median_s"] / 1e6,
                    }
                    for k, t in {"ours": ours, **timings}.items()
                }
                return {
                    "name": name,
                    "description": description,
                    "unit": "frame",
                    "ours": ours,
                    "anchors": timings,
                    "target_ratio": TARGET_RATIO,
                    "check": (
                        f"{len(depths)} frames: ours gives the same uint16 images, stamps and intrinsics as the "
                        f"plain mcap reader + ROS 2 decoder and as the PNGs; full frames equal "
                        f"driftmap.backproject of the PNGs bit for bit"
                    ),
                    "details": {
                        "file_bytes": path.stat().st_size,
                        "payload_bytes": payload_bytes,
                        "rates": rates,
                        "frames": names,
                        **extra,
                    },
                }

            decode_medians = {}
            for compression, bench_name in (("none", "ros_mcap_decode"), ("zstd", "ros_mcap_decode_zstd")):
                path = files[compression]
                timings = time_per_item(
                    {"driftmap_iter_raw": ours_decode, "mcap_ros2_plain": plain_decode}, [path], repeats=repeats
                )
                results.append(
                    entry(
                        bench_name,
                        f"open + decode a 640x480 16UC1 Image + CameraInfo MCAP ({compression} chunks), per frame",
                        timings,
                        "driftmap_iter_raw",
                        path,
                        {"compression": compression},
                    )
                )
                decode_medians[compression] = results[-1]["ours"]["median_s"]
            path = files["none"]
            timings = time_per_item(
                {"driftmap_frames": ours_frames, "mcap_ros2_plain+backproject": plain_frames},
                [path],
                repeats=max(repeats // 2, 3),
            )
            bench = entry(
                "ros_mcap_frames",
                "open + decode + validate + back-project (full Frames) from the uncompressed MCAP, per frame",
                timings,
                "driftmap_frames",
                path,
                {"compression": "none"},
            )
            bench["details"]["backprojection_s_per_frame"] = bench["ours"]["median_s"] - decode_medians["none"]
            results.append(bench)
    finally:
        driftmap_logger.setLevel(level)
    return results
