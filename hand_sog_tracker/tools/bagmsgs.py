"""The depth-bag convention's topics and message types, and rosbags messages to and from arrays.

Used by :mod:`hand_sog_tracker.tools.bagio` (reading; it re-exports everything here) and
:mod:`hand_sog_tracker.tools.bagwrite` (writing).  No ROS installation needed: the messages
are ``rosbags`` types of ROS 2 Jazzy (:func:`typestore`).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any, Final, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore

from hand_sog_tracker import interface
from hand_sog_tracker.core.types import Intrinsics
from hand_sog_tracker.errors import BagError, InputError
from hand_sog_tracker.interface import stamp_to_ns

__all__ = [
    "DEPTH_TOPIC",
    "INFO_TOPIC",
    "GT_TOPIC",
    "OPTICAL_FRAME",
    "IMAGE_TYPE",
    "COMPRESSED_TYPE",
    "INFO_TYPE",
    "GT_TYPE",
    "BagTopics",
    "typestore",
    "ns_to_stamp",
    "depth_image_msg",
    "compressed_depth_msg",
    "camera_info_msg",
    "points_msg",
    "points_from_msg",
    "fingertips_msg",
    "fingertips_from_msg",
    "describe_error",
]

#: Topics of the bag convention (:mod:`hand_sog_tracker.interface`, absolute names).
DEPTH_TOPIC: Final[str] = interface.BAG_DEPTH_TOPIC
INFO_TOPIC: Final[str] = interface.BAG_INFO_TOPIC
GT_TOPIC: Final[str] = interface.GROUND_TRUTH_TOPIC
OPTICAL_FRAME: Final[str] = "camera_depth_optical_frame"
IMAGE_TYPE: Final[str] = "sensor_msgs/msg/Image"
COMPRESSED_TYPE: Final[str] = "sensor_msgs/msg/CompressedImage"
INFO_TYPE: Final[str] = "sensor_msgs/msg/CameraInfo"
GT_TYPE: Final[str] = "geometry_msgs/msg/PoseArray"

@functools.lru_cache(maxsize=1)
def typestore() -> Typestore:
    """The ROS 2 Jazzy type store used to build and serialise messages."""
    return get_typestore(Stores.ROS2_JAZZY)


@dataclass(frozen=True)
class BagTopics:
    """Topic names of a depth bag (defaults: contract 5)."""

    depth: str = DEPTH_TOPIC
    info: str = INFO_TOPIC
    truth: str = GT_TOPIC


def describe_error(err: BaseException) -> str:
    """``"ExceptionType: message"`` (or just the type) for error messages about a bag."""
    text = str(err).strip()
    return f"{type(err).__name__}: {text}" if text else type(err).__name__


# -- small message helpers ---------------------------------------------------
# stamp_to_ns is :func:`hand_sog_tracker.interface.stamp_to_ns` (imported above).
def ns_to_stamp(ns: int) -> Any:
    """Nanoseconds to a rosbags ``builtin_interfaces/msg/Time``."""
    try:
        return interface.ns_to_stamp(ns, typestore().types["builtin_interfaces/msg/Time"])
    except InputError as err:
        raise BagError(str(err)) from None


def _header(stamp_ns: int, frame_id: str) -> Any:
    Header = typestore().types["std_msgs/msg/Header"]
    return Header(stamp=ns_to_stamp(stamp_ns), frame_id=frame_id)


def depth_image_msg(
    depth_mm: ArrayLike,
    stamp_ns: int,
    frame_id: str = OPTICAL_FRAME,
    encoding: Literal["16UC1", "32FC1"] = "16UC1",
) -> Any:
    """Build a rosbags ``sensor_msgs/msg/Image`` from a depth map.

    Parameters
    ----------
    depth_mm : array, shape (H, W)
        Depth in millimetres; 0, NaN or Inf = invalid.
    stamp_ns : int
        Header stamp, nanoseconds.
    frame_id : str
    encoding : {"16UC1", "32FC1"}
        ``16UC1``: uint16 millimetres (rounded, invalid = 0, clipped to 65535);
        ``32FC1``: float32 **metres** (REP 118), invalid = NaN.
    """
    d = np.asarray(depth_mm, dtype=np.float64)
    if d.ndim != 2:
        raise BagError(f"depth image must be 2-D (H, W), got shape {d.shape}")
    valid = np.isfinite(d) & (d > 0)
    if encoding == "16UC1":
        pix = np.where(valid, np.clip(np.rint(d), 0, 65535), 0).astype("<u2")
    elif encoding == "32FC1":
        pix = np.where(valid, d / 1000.0, np.nan).astype("<f4")
    else:
        raise BagError(f"unsupported depth encoding {encoding!r} (use 16UC1 or 32FC1)")
    Image = typestore().types[IMAGE_TYPE]
    h, w = pix.shape
    return Image(
        header=_header(stamp_ns, frame_id),
        height=h,
        width=w,
        encoding=encoding,
        is_bigendian=0,
        step=w * pix.itemsize,
        data=np.frombuffer(np.ascontiguousarray(pix).tobytes(), dtype=np.uint8),
    )


def compressed_depth_msg(
    depth_mm: ArrayLike,
    stamp_ns: int,
    frame_id: str = OPTICAL_FRAME,
    encoding: Literal["16UC1", "32FC1"] = "16UC1",
    codec: Literal["png", "rvl"] = "png",
) -> Any:
    """A rosbags ``sensor_msgs/msg/CompressedImage`` as compressed_depth_image_transport writes it.

    See :func:`hand_sog_tracker.compressed_depth.encode_compressed_depth` (32FC1 quantises
    inverse depth with the plugin's default parameters).
    """
    from hand_sog_tracker.compressed_depth import encode_compressed_depth
    from hand_sog_tracker.errors import DepthImageError

    try:
        fmt, data = encode_compressed_depth(depth_mm, encoding, codec)
    except DepthImageError as err:
        raise BagError(str(err)) from err
    return typestore().types[COMPRESSED_TYPE](
        header=_header(stamp_ns, frame_id), format=fmt, data=np.frombuffer(data, dtype=np.uint8)
    )


def camera_info_msg(intrinsics: Intrinsics, stamp_ns: int, frame_id: str = OPTICAL_FRAME) -> Any:
    """Build a rosbags ``sensor_msgs/msg/CameraInfo`` (plumb bob, zero distortion)."""
    i = intrinsics
    CameraInfo = typestore().types[INFO_TYPE]
    Roi = typestore().types["sensor_msgs/msg/RegionOfInterest"]
    return CameraInfo(
        header=_header(stamp_ns, frame_id),
        height=i.height,
        width=i.width,
        distortion_model="plumb_bob",
        d=np.zeros(5, dtype=np.float64),
        k=np.array([i.fx, 0.0, i.cx, 0.0, i.fy, i.cy, 0.0, 0.0, 1.0]),
        r=np.eye(3).reshape(-1),
        p=np.array([i.fx, 0.0, i.cx, 0.0, 0.0, i.fy, i.cy, 0.0, 0.0, 0.0, 1.0, 0.0]),
        binning_x=0,
        binning_y=0,
        roi=Roi(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
    )


def points_msg(points_mm: ArrayLike, stamp_ns: int, frame_id: str = OPTICAL_FRAME) -> Any:
    """Points as a rosbags ``geometry_msgs/msg/PoseArray`` (identity orientations).

    Parameters
    ----------
    points_mm : array, shape (n, 3)
        Positions, millimetres (written as metres).
    """
    pts = np.asarray(points_mm, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or not np.all(np.isfinite(pts)):
        raise BagError(f"points must be a finite (n, 3) array, got shape {pts.shape}")
    t = typestore().types
    Pose, Point, Quat = t["geometry_msgs/msg/Pose"], t["geometry_msgs/msg/Point"], t["geometry_msgs/msg/Quaternion"]
    poses = [
        Pose(position=Point(x=float(x), y=float(y), z=float(z)), orientation=Quat(x=0.0, y=0.0, z=0.0, w=1.0))
        for x, y, z in pts / 1000.0
    ]
    return t[GT_TYPE](header=_header(stamp_ns, frame_id), poses=poses)


def fingertips_msg(fingertips_mm: ArrayLike, stamp_ns: int, frame_id: str = OPTICAL_FRAME) -> Any:
    """Ground truth as a rosbags ``geometry_msgs/msg/PoseArray``.

    Parameters
    ----------
    fingertips_mm : array, shape (5, 3)
        Fingertips thumb .. little, millimetres (written as metres).
    """
    tips = np.asarray(fingertips_mm, dtype=np.float64)
    if tips.shape != (5, 3) or not np.all(np.isfinite(tips)):
        raise BagError(f"fingertips must be a finite (5, 3) array, got shape {tips.shape}")
    return points_msg(tips, stamp_ns, frame_id)


def points_from_msg(msg: Any, n: int) -> NDArray[np.float64]:
    """Positions (n, 3) in millimetres from a PoseArray (metres) of exactly ``n`` finite poses.

    Raises
    ------
    BagError
        If the array does not hold exactly ``n`` finite poses.
    """
    poses = list(msg.poses)
    if len(poses) != n:
        raise BagError(
            f"PoseArray at stamp {stamp_to_ns(msg.header.stamp)} ns has {len(poses)} poses, expected {n}"
            + (" (thumb, index, middle, ring, little)" if n == 5 else "")
        )
    pts = np.array([[p.position.x, p.position.y, p.position.z] for p in poses], dtype=np.float64) * 1000.0
    if not np.all(np.isfinite(pts)):
        raise BagError(f"PoseArray at stamp {stamp_to_ns(msg.header.stamp)} ns is not finite")
    return pts.reshape(n, 3)


def fingertips_from_msg(msg: Any) -> NDArray[np.float64]:
    """Fingertips (5, 3) in millimetres from a PoseArray (metres).

    Raises
    ------
    BagError
        If the array does not hold exactly five finite poses.
    """
    poses = list(msg.poses)
    if len(poses) != 5:
        raise BagError(
            f"ground-truth PoseArray at stamp {stamp_to_ns(msg.header.stamp)} ns has "
            f"{len(poses)} poses, expected 5 (thumb, index, middle, ring, little)"
        )
    return points_from_msg(msg, 5)
