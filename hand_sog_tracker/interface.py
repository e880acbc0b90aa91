"""The node's message interface, defined once; imports no ROS package.

Everything a reader or writer of the node's messages needs to agree on lives here, so the node
(:mod:`hand_sog_tracker.ros.node`), its message conversion (:mod:`hand_sog_tracker.ros.conversions`)
and the tools (bag reading, the node harness, replay) use the same names:

* topic names: relative to the node's namespace (:data:`DEPTH_TOPIC` ...), and the absolute
  names recorded in bags (:data:`BAG_DEPTH_TOPIC`, :data:`GROUND_TRUTH_TOPIC` ...);
* the ``hand/fingertips`` marker namespaces and ids;
* the keys of the node's ``/diagnostics`` status;
* header stamps: :func:`stamp_to_ns`, :func:`ns_to_stamp`;
* the input conversions, duck-typed so they take rclpy messages and rosbags records alike:
  :func:`image_to_depth_mm`, :func:`compressed_image_to_depth_mm`,
  :func:`camera_info_to_intrinsics`.

Only NumPy, the core's value types and :mod:`hand_sog_tracker.compressed_depth` are imported:
reading a bag never loads ``rclpy`` or ``sensor_msgs`` (``test/test_interface.py`` checks it).
"""

from __future__ import annotations

import array
from typing import Any, Callable, Final, Protocol, TypeVar

import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.compressed_depth import (
    MAX_IMAGE_PIXELS,
    check_image_size,
    decode_compressed_depth,
    zero_invalid,
)
from hand_sog_tracker.core.types import Intrinsics
from hand_sog_tracker.errors import DepthImageError, InputError, IntrinsicsError

__all__ = [
    "NODE_NAME",
    "DEPTH_TOPIC",
    "COMPRESSED_SUFFIX",
    "COMPRESSED_DEPTH_TOPIC",
    "INFO_TOPIC",
    "JOINTS_TOPIC",
    "POSE_TOPIC",
    "FINGERTIPS_TOPIC",
    "KEYPOINTS_TOPIC",
    "DEBUG_IMAGE_TOPIC",
    "CONFIDENCE_TOPIC",
    "CONFIDENCE_NAMES",
    "DESCRIPTION_TOPIC",
    "DIAGNOSTICS_TOPIC",
    "TF_TOPIC",
    "CALIBRATE_SERVICE",
    "BAG_DEPTH_TOPIC",
    "BAG_INFO_TOPIC",
    "GROUND_TRUTH_TOPIC",
    "FINGERTIPS_NS",
    "SKELETON_NS",
    "SKELETON_MARKER_ID",
    "DIAG_KEYS",
    "DIAG_COUNTER_KEYS",
    "stamp_to_ns",
    "ns_to_stamp",
    "ImageLike",
    "CompressedImageLike",
    "RegionOfInterestLike",
    "CameraInfoLike",
    "DEPTH_ENCODINGS",
    "MAX_IMAGE_PIXELS",
    "FOCAL_PER_SIDE",
    "MAX_FOCAL_RATIO",
    "check_image_size",
    "image_to_depth_mm",
    "compressed_image_to_depth_mm",
    "camera_info_to_intrinsics",
]

#: Name of the node (also the prefix of its ``/diagnostics`` status name).
NODE_NAME: Final[str] = "hand_sog_tracker"

# -- topics, relative to the node's namespace (a namespace or remapping moves them) -----------
#: Depth images in (``sensor_msgs/Image``).
DEPTH_TOPIC: Final[str] = "camera/depth/image_rect_raw"
#: image_transport's compressedDepth sub-topic of an image topic.
COMPRESSED_SUFFIX: Final[str] = "/compressedDepth"
#: Compressed depth images in (``sensor_msgs/CompressedImage``, ``input_transport: compressedDepth``).
COMPRESSED_DEPTH_TOPIC: Final[str] = DEPTH_TOPIC + COMPRESSED_SUFFIX
#: Intrinsics in (``sensor_msgs/CameraInfo``).
INFO_TOPIC: Final[str] = "camera/depth/camera_info"
#: The 20 joint angles (``sensor_msgs/JointState``).
JOINTS_TOPIC: Final[str] = "hand/joint_states"
#: Wrist pose (``geometry_msgs/PoseStamped``).
POSE_TOPIC: Final[str] = "hand/pose"
#: Fingertip and skeleton markers (``visualization_msgs/MarkerArray``).
FINGERTIPS_TOPIC: Final[str] = "hand/fingertips"
#: The 21 keypoints (``geometry_msgs/PoseArray``).
KEYPOINTS_TOPIC: Final[str] = "hand/keypoints"
#: The hand decision of every processed frame (``sensor_msgs/JointState``, names
#: :data:`CONFIDENCE_NAMES`, ``position`` = values in [0, 1]).
CONFIDENCE_TOPIC: Final[str] = "hand/confidence"
#: Entries of a ``hand/confidence`` message: ``present`` (1 = a hand is reported on the other
#: topics, 0 = no hand), ``hand`` (the hand check's confidence), then one per finger (how much
#: of it the data show).
CONFIDENCE_NAMES: Final[tuple[str, ...]] = ("present", "hand", "thumb", "index", "middle", "ring", "little")
#: Depth colour map with the projected model (``sensor_msgs/Image`` bgr8).
DEBUG_IMAGE_TOPIC: Final[str] = "hand/debug_image"
#: URDF of the model in use (``std_msgs/String``, transient local).
DESCRIPTION_TOPIC: Final[str] = "hand/robot_description"
#: Node status at 1 Hz (``diagnostic_msgs/DiagnosticArray``); absolute.
DIAGNOSTICS_TOPIC: Final[str] = "/diagnostics"
#: Wrist and fingertip frames (``tf2_msgs/TFMessage``, with ``publish_tf``); absolute.
TF_TOPIC: Final[str] = "/tf"
#: The calibration service (``std_srvs/Trigger``), private to the node.
CALIBRATE_SERVICE: Final[str] = "~/calibrate"

# -- topics as recorded in bags (default namespace, absolute) ---------------------------------
BAG_DEPTH_TOPIC: Final[str] = "/" + DEPTH_TOPIC
BAG_INFO_TOPIC: Final[str] = "/" + INFO_TOPIC
#: Ground truth of the evaluation bags: a ``geometry_msgs/PoseArray`` of the five fingertips (m),
#: stamped like the depth image it belongs to.
GROUND_TRUTH_TOPIC: Final[str] = "/hand/ground_truth/fingertips"

# -- hand/fingertips markers -------------------------------------------------------------------
#: SPHERE markers of the fingertips; the marker id is the finger (0 thumb .. 4 little).
FINGERTIPS_NS: Final[str] = "fingertips"
#: One LINE_LIST marker of the 21-point skeleton, id :data:`SKELETON_MARKER_ID`.
SKELETON_NS: Final[str] = "skeleton"
SKELETON_MARKER_ID: Final[int] = 0

# -- /diagnostics ---------------------------------------------------------------------------------
#: Keys of the node's diagnostic status values, in the order published.
DIAG_KEYS: Final[tuple[str, ...]] = (
    "input_rate_hz",
    "output_rate_hz",
    "processing_ms",
    "answer_ms",
    "latency_ms",
    "worst_frame_ms",
    "backlog_ms",
    "status",
    "confidence",
    "frames_received",
    "frames_processed",
    "frames_dropped",
    "frames_missed",
    "frames_rejected",
    "frames_cut",
    "last_problem",
)
#: The frame counters among :data:`DIAG_KEYS` (integers since the node started).
DIAG_COUNTER_KEYS: Final[tuple[str, ...]] = (
    "frames_received",
    "frames_processed",
    "frames_dropped",
    "frames_missed",
    "frames_rejected",
)

_StampT = TypeVar("_StampT")


# -- stamps --------------------------------------------------------------------------------------
def stamp_to_ns(stamp: Any) -> int:
    """``builtin_interfaces/Time``-like object (``sec``, ``nanosec``) to integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def ns_to_stamp(ns: int, stamp_type: Callable[..., _StampT]) -> _StampT:
    """Nanoseconds to a ``builtin_interfaces/Time``-like object.

    Parameters
    ----------
    ns : int
        Nanoseconds, >= 0.
    stamp_type : callable
        The message class, called with ``sec=`` and ``nanosec=`` (the rclpy
        ``builtin_interfaces.msg.Time`` or a rosbags type store's).

    Raises
    ------
    InputError
        ``ns`` is negative (``Time.sec`` of a header is unsigned in practice).
    """
    ns = int(ns)
    if ns < 0:
        raise InputError(f"negative time stamp {ns} ns")
    return stamp_type(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


# -- input messages (duck-typed) -----------------------------------------------------------------
class ImageLike(Protocol):
    """The fields of ``sensor_msgs/Image`` read here (rclpy message or rosbags record)."""

    height: int
    width: int
    encoding: str
    is_bigendian: int
    step: int
    data: Any  # bytes, bytearray, memoryview, array.array('B'), list[int] or uint8 ndarray


class CompressedImageLike(Protocol):
    """The fields of ``sensor_msgs/CompressedImage`` read here."""

    format: str
    data: Any


class RegionOfInterestLike(Protocol):
    """The fields of ``sensor_msgs/RegionOfInterest``."""

    x_offset: int
    y_offset: int
    height: int
    width: int


class CameraInfoLike(Protocol):
    """The fields of ``sensor_msgs/CameraInfo`` read here."""

    height: int
    width: int
    k: Any  # 9 numbers, row-major 3x3
    binning_x: int
    binning_y: int
    roi: RegionOfInterestLike


#: Supported depth encodings: name -> (little-endian dtype, metres per unit or None for mm).
DEPTH_ENCODINGS: dict[str, tuple[str, float | None]] = {
    "16UC1": ("<u2", None),
    "MONO16": ("<u2", None),
    "32FC1": ("<f4", 1000.0),
}


#: Plausible focal lengths (px) per pixel of the image's longer side: a horizontal field of view
#: between about 5.7 and 157 degrees (every depth camera lies well inside).
FOCAL_PER_SIDE: Final[tuple[float, float]] = (0.1, 10.0)
#: Largest plausible ratio of the two focal lengths (non-square pixels beyond binning).
MAX_FOCAL_RATIO: Final[float] = 3.0


def _as_bytes(data: Any) -> NDArray[np.uint8]:
    """View the message ``data`` field as a flat uint8 array without copying when possible."""
    if isinstance(data, np.ndarray):
        if data.dtype != np.uint8:
            raise DepthImageError(f"image data array must be uint8, got dtype {data.dtype}")
        return data.reshape(-1)
    if isinstance(data, (bytes, bytearray, memoryview)):
        return np.frombuffer(data, dtype=np.uint8)
    if isinstance(data, array.array):
        if data.itemsize != 1:
            raise DepthImageError(
                f"image data array.array must hold bytes, got typecode {data.typecode!r}"
            )
        return np.frombuffer(data, dtype=np.uint8)
    try:
        return np.asarray(data, dtype=np.uint8).reshape(-1)
    except (TypeError, ValueError, OverflowError) as err:
        raise DepthImageError(f"image data is not a byte sequence: {err}") from err


def image_to_depth_mm(msg: ImageLike, max_pixels: int | None = MAX_IMAGE_PIXELS) -> NDArray[np.float32]:
    """Convert a depth ``sensor_msgs/Image`` to millimetres.

    Parameters
    ----------
    msg : ImageLike
        ``16UC1`` / ``mono16`` (mm, 0 = invalid) or ``32FC1`` (metres; NaN,
        Inf, 0 and negative values are invalid).  ``step`` (row padding) and
        ``is_bigendian`` are honoured.
    max_pixels : int or None
        Larger images are rejected before they are converted (None: no bound).

    Returns
    -------
    array, shape (H, W), float32, mm
        A new array; invalid pixels are 0.

    Raises
    ------
    DepthImageError
        Unknown encoding, zero size, more than ``max_pixels`` pixels,
        ``step < width * bytes_per_pixel`` or ``data`` shorter than the image needs.
    """
    enc = str(msg.encoding)
    spec = DEPTH_ENCODINGS.get(enc.upper())
    if spec is None:
        raise DepthImageError(
            f"unsupported depth encoding {enc!r} (expected one of 16UC1, mono16, 32FC1)"
        )
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    check_image_size(w, h, max_pixels)
    dtype = np.dtype(spec[0])
    if msg.is_bigendian:
        dtype = dtype.newbyteorder(">")
    bpp = dtype.itemsize
    if step < w * bpp:
        raise DepthImageError(
            f"step {step} is smaller than width * {bpp} bytes = {w * bpp} ({enc})"
        )
    buf = _as_bytes(msg.data)
    needed = step * (h - 1) + w * bpp  # the last row's padding may be absent
    if buf.size < needed:
        raise DepthImageError(
            f"depth image data is truncated: {buf.size} bytes, need {step * h} "
            f"({h} rows of step {step})"
        )
    view = np.ndarray(shape=(h, w), dtype=dtype, buffer=buf, offset=0, strides=(step, bpp))
    scale = spec[1]
    if scale is None:
        return view.astype(np.float32)  # native byte order, contiguous copy
    with np.errstate(invalid="ignore", over="ignore"):
        depth = np.multiply(view, np.float32(scale), dtype=np.float32)  # (a new contiguous array)
    return zero_invalid(depth)


def compressed_image_to_depth_mm(
    msg: CompressedImageLike, max_pixels: int | None = MAX_IMAGE_PIXELS
) -> NDArray[np.float32]:
    """Depth in mm from a ``compressedDepth`` ``sensor_msgs/CompressedImage``.

    See :func:`hand_sog_tracker.compressed_depth.decode_compressed_depth` (formats
    ``"16UC1; compressedDepth png"``, ``"32FC1; compressedDepth rvl"`` ...).

    Raises
    ------
    DepthImageError
        Unknown format, bad header, a declared size above ``max_pixels`` (checked before
        decoding), corrupt or truncated payload.
    """
    return decode_compressed_depth(str(msg.format), msg.data, max_pixels)


def camera_info_to_intrinsics(msg: CameraInfoLike) -> Intrinsics:
    """Pinhole intrinsics of the published (binned) image from ``sensor_msgs/CameraInfo``.

    Binning is honoured like ``image_geometry``: ``fx, cx`` are divided by
    ``binning_x``, ``fy, cy`` by ``binning_y`` and the image size is
    ``width // binning_x`` by ``height // binning_y`` (0 and 1 mean no binning).
    A region of interest other than the full image is rejected: the camera
    would publish a crop this node does not expect.  So are implausible intrinsics, which would
    make the tracker's per-frame work meaningless or unbounded: focal lengths outside
    :data:`FOCAL_PER_SIDE` times the image's longer side (e.g. a K for another resolution),
    ``fx / fy`` beyond :data:`MAX_FOCAL_RATIO`, a principal point outside the image.

    Parameters
    ----------
    msg : CameraInfoLike

    Returns
    -------
    Intrinsics
        Pixels, for the image size the camera publishes.

    Raises
    ------
    IntrinsicsError
        ``K`` not 9 finite numbers, all zero (uncalibrated) or with
        non-positive or implausible focal lengths or principal point, zero image size, or a
        partial ROI; the message names the value and the bound.
    """
    try:
        k = np.asarray(msg.k, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as err:
        raise IntrinsicsError(f"CameraInfo K is not numeric: {err}") from err
    if k.shape != (9,):
        raise IntrinsicsError(f"CameraInfo K must have 9 elements, got {k.size}")
    if not np.all(np.isfinite(k)):
        raise IntrinsicsError("CameraInfo K contains NaN or Inf")
    if not np.any(k):
        raise IntrinsicsError("CameraInfo K is all zeros (uncalibrated camera)")
    width, height = int(msg.width), int(msg.height)
    if width <= 0 or height <= 0:
        raise IntrinsicsError(f"CameraInfo has zero image size ({width}x{height})")
    roi = msg.roi
    rx, ry, rw, rh = int(roi.x_offset), int(roi.y_offset), int(roi.width), int(roi.height)
    full_roi = (rx, ry, rw, rh) in ((0, 0, 0, 0), (0, 0, width, height))
    if not full_roi:
        raise IntrinsicsError(
            f"CameraInfo ROI (x={rx}, y={ry}, {rw}x{rh}) is not the full {width}x{height} "
            "image; cropped depth streams are not supported"
        )
    bx = max(int(msg.binning_x), 1)
    by = max(int(msg.binning_y), 1)
    fx, fy, cx, cy = float(k[0]) / bx, float(k[4]) / by, float(k[2]) / bx, float(k[5]) / by
    w, h = width // bx, height // by
    if w <= 0 or h <= 0:
        raise IntrinsicsError(f"CameraInfo binning {bx}x{by} leaves no pixels of the {width}x{height} image")
    side = max(w, h)
    lo, hi = FOCAL_PER_SIDE[0] * side, FOCAL_PER_SIDE[1] * side
    for name, f in (("fx", fx), ("fy", fy)):
        if not lo <= f <= hi:
            raise IntrinsicsError(
                f"CameraInfo focal length {name}={f:.6g} px is implausible for a {w}x{h} image "
                f"(expected {lo:.4g} to {hi:.4g} px, a field of view of 157 to 6 degrees; "
                "K for another resolution or in other units?)"
            )
    if max(fx, fy) > MAX_FOCAL_RATIO * min(fx, fy):
        raise IntrinsicsError(
            f"CameraInfo focal lengths fx={fx:.6g} and fy={fy:.6g} px differ by more than "
            f"{MAX_FOCAL_RATIO:g}x (pixels that far from square: binning not declared?)"
        )
    if not (0.0 <= cx <= w and 0.0 <= cy <= h):
        raise IntrinsicsError(
            f"CameraInfo principal point ({cx:.6g}, {cy:.6g}) px lies outside the {w}x{h} image"
        )
    return Intrinsics(fx=fx, fy=fy, cx=cx, cy=cy, width=w, height=h)
