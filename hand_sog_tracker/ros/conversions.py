"""Conversion between ROS messages and the core's NumPy values.

Input side (duck-typed through :class:`ImageLike` / :class:`CameraInfoLike`, so
the same functions take rclpy messages and rosbags records):

* :func:`image_to_depth_mm` - ``sensor_msgs/Image`` to a float32 depth map in mm.
* :func:`camera_info_to_intrinsics` - ``sensor_msgs/CameraInfo`` to :class:`Intrinsics`.

Output side (rclpy messages; units converted from mm to metres):
:func:`joint_state_msg`, :func:`pose_msg`, :func:`fingertip_markers`,
:func:`delete_all_markers`, :func:`bgr_to_image_msg` (the debug image drawn by
:func:`hand_sog_tracker.core.overlay.draw_overlay`) and :func:`diagnostic_array`.
"""

from __future__ import annotations

import array
from typing import Any, Mapping, Protocol, Sequence

import numpy as np
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Point, PoseStamped
from numpy.typing import NDArray
from sensor_msgs.msg import Image, JointState
from std_msgs.msg import ColorRGBA, Header
from visualization_msgs.msg import Marker, MarkerArray

from hand_sog_tracker.core.hand_model import FINGERS, JOINT_NAMES, N_PARAMS
from hand_sog_tracker.core.kinematics import global_rotation
from hand_sog_tracker.core.types import Intrinsics
from hand_sog_tracker.errors import DepthImageError, InputError, IntrinsicsError

__all__ = [
    "ImageLike",
    "CameraInfoLike",
    "DEPTH_ENCODINGS",
    "image_to_depth_mm",
    "camera_info_to_intrinsics",
    "rotation_to_quaternion",
    "stamp_to_ns",
    "SKELETON_BONES",
    "joint_state_msg",
    "pose_msg",
    "fingertip_markers",
    "delete_all_markers",
    "bgr_to_image_msg",
    "diagnostic_array",
]


class ImageLike(Protocol):
    """The fields of ``sensor_msgs/Image`` this module reads (rclpy message or rosbags record)."""

    height: int
    width: int
    encoding: str
    is_bigendian: int
    step: int
    data: Any  # bytes, bytearray, memoryview, array.array('B'), list[int] or uint8 ndarray


class RegionOfInterestLike(Protocol):
    """The fields of ``sensor_msgs/RegionOfInterest``."""

    x_offset: int
    y_offset: int
    height: int
    width: int


class CameraInfoLike(Protocol):
    """The fields of ``sensor_msgs/CameraInfo`` this module reads."""

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
            raise DepthImageError(f"image data array.array must hold bytes, got typecode {data.typecode!r}")
        return np.frombuffer(data, dtype=np.uint8)
    try:
        return np.asarray(data, dtype=np.uint8).reshape(-1)
    except (TypeError, ValueError, OverflowError) as err:
        raise DepthImageError(f"image data is not a byte sequence: {err}") from err


def image_to_depth_mm(msg: ImageLike) -> NDArray[np.float32]:
    """Convert a depth ``sensor_msgs/Image`` to millimetres.

    Parameters
    ----------
    msg : ImageLike
        ``16UC1`` / ``mono16`` (mm, 0 = invalid) or ``32FC1`` (metres; NaN,
        Inf, 0 and negative values are invalid).  ``step`` (row padding) and
        ``is_bigendian`` are honoured.

    Returns
    -------
    array, shape (H, W), float32, mm
        A new array; invalid pixels are 0.

    Raises
    ------
    DepthImageError
        Unknown encoding, zero size, ``step < width * bytes_per_pixel`` or
        ``data`` shorter than the image needs.
    """
    enc = str(msg.encoding)
    spec = DEPTH_ENCODINGS.get(enc.upper())
    if spec is None:
        raise DepthImageError(
            f"unsupported depth encoding {enc!r} (expected one of 16UC1, mono16, 32FC1)"
        )
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    if h <= 0 or w <= 0:
        raise DepthImageError(f"depth image has zero size ({w}x{h})")
    dtype = np.dtype(spec[0])
    if msg.is_bigendian:
        dtype = dtype.newbyteorder(">")
    bpp = dtype.itemsize
    if step < w * bpp:
        raise DepthImageError(f"step {step} is smaller than width * {bpp} bytes = {w * bpp} ({enc})")
    buf = _as_bytes(msg.data)
    needed = step * (h - 1) + w * bpp  # the last row's padding may be absent
    if buf.size < needed:
        raise DepthImageError(
            f"depth image data is truncated: {buf.size} bytes, need {step * h} "
            f"({h} rows of step {step})"
        )
    view = np.ndarray(shape=(h, w), dtype=dtype, buffer=buf, offset=0, strides=(step, bpp))
    depth = view.astype(np.float32)  # native byte order, contiguous copy
    scale = spec[1]
    if scale is not None:
        with np.errstate(invalid="ignore", over="ignore"):
            depth *= np.float32(scale)
            depth[~(np.isfinite(depth) & (depth > 0.0))] = 0.0
    return depth


def camera_info_to_intrinsics(msg: CameraInfoLike) -> Intrinsics:
    """Pinhole intrinsics of the published (binned) image from ``sensor_msgs/CameraInfo``.

    Binning is honoured like ``image_geometry``: ``fx, cx`` are divided by
    ``binning_x``, ``fy, cy`` by ``binning_y`` and the image size is
    ``width // binning_x`` by ``height // binning_y`` (0 and 1 mean no binning).
    A region of interest other than the full image is rejected: the camera
    would publish a crop this node does not expect.

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
        non-positive focal lengths, zero image size, or a partial ROI.
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
    return Intrinsics(fx=fx, fy=fy, cx=cx, cy=cy, width=width // bx, height=height // by)


def stamp_to_ns(stamp: Any) -> int:
    """``builtin_interfaces/Time`` (``sec``, ``nanosec``) to integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def rotation_to_quaternion(rot: NDArray[np.float64]) -> NDArray[np.float64]:
    """Unit quaternion ``(x, y, z, w)`` of a rotation matrix, shape (3, 3), with ``w >= 0``.

    Uses the numerically stable branch on the largest diagonal term (Shepperd).
    """
    m = np.asarray(rot, dtype=np.float64)
    if m.shape != (3, 3):
        raise InputError(f"rotation must have shape (3, 3), got {m.shape}")
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0.0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = np.array([(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s])
    elif m[0, 0] >= m[1, 1] and m[0, 0] >= m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = np.array([0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s])
    elif m[1, 1] >= m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = np.array([(m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s])
    else:
        s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = np.array([(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s])
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def _check_pose(pose: NDArray[np.float64]) -> NDArray[np.float64]:
    p = np.asarray(pose, dtype=np.float64)
    if p.shape != (N_PARAMS,):
        raise InputError(f"pose must have shape ({N_PARAMS},), got {p.shape}")
    return p


def joint_state_msg(header: Header, pose: NDArray[np.float64]) -> JointState:
    """``sensor_msgs/JointState`` with the 20 joint angles (rad) of ``pose`` (26,).

    Names are :data:`hand_model.JOINT_NAMES` in pose-vector order.
    """
    p = _check_pose(pose)
    return JointState(header=header, name=list(JOINT_NAMES), position=p[6:].tolist())


def pose_msg(header: Header, pose: NDArray[np.float64]) -> PoseStamped:
    """Wrist (root) pose: ``pose[:3]`` mm converted to metres and the global rotation.

    The orientation is :func:`kinematics.global_rotation` of the pose, i.e.
    the hand frame of a right hand (x radial, y along the middle finger, z out
    of the palm).  A left hand is the mirror image of that frame
    (``R @ diag(-1, 1, 1)`` is not a rotation), so the same ``R`` is published.
    """
    p = _check_pose(pose)
    q = rotation_to_quaternion(global_rotation(p))
    msg = PoseStamped(header=header)
    msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = (float(v) / 1000.0 for v in p[:3])
    msg.pose.orientation.x, msg.pose.orientation.y, msg.pose.orientation.z, msg.pose.orientation.w = (
        float(v) for v in q
    )
    return msg


#: Bones of the 21-point skeleton (:func:`kinematics.skeleton_points`): wrist to each
#: chain's first joint, then along each chain to its tip.
SKELETON_BONES: tuple[tuple[int, int], ...] = tuple(
    pair
    for c in range(5)
    for pair in ((0, 1 + 4 * c), (1 + 4 * c, 2 + 4 * c), (2 + 4 * c, 3 + 4 * c), (3 + 4 * c, 4 + 4 * c))
)

#: Marker colours (RGBA) of thumb .. little.
FINGER_RGBA: tuple[tuple[float, float, float, float], ...] = (
    (1.0, 0.2, 0.2, 1.0),
    (1.0, 0.8, 0.1, 1.0),
    (0.2, 0.9, 0.2, 1.0),
    (0.2, 0.6, 1.0, 1.0),
    (0.8, 0.3, 1.0, 1.0),
)


def _point_m(p_mm: NDArray[np.float64]) -> Point:
    return Point(x=float(p_mm[0]) / 1000.0, y=float(p_mm[1]) / 1000.0, z=float(p_mm[2]) / 1000.0)


def fingertip_markers(
    header: Header,
    fingertips_mm: NDArray[np.float64],
    skeleton_mm: NDArray[np.float64] | None = None,
    tip_radii_mm: Sequence[float] | NDArray[np.float64] | None = None,
) -> MarkerArray:
    """Fingertip spheres and the skeleton as RViz markers (metres).

    Parameters
    ----------
    header : std_msgs/Header
        Stamp and frame of the input image.
    fingertips_mm : array, shape (5, 3), mm
        Thumb .. little; become ``ns="fingertips"`` SPHERE markers, ids 0-4.
    skeleton_mm : array, shape (21, 3), mm, optional
        Becomes one ``ns="skeleton"`` LINE_LIST marker (id 0) along :data:`SKELETON_BONES`.
    tip_radii_mm : array, shape (5,), mm, optional
        Sphere radii; 8 mm when omitted.
    """
    tips = np.asarray(fingertips_mm, dtype=np.float64)
    if tips.shape != (5, 3):
        raise InputError(f"fingertips must have shape (5, 3), got {tips.shape}")
    radii = np.full(5, 8.0) if tip_radii_mm is None else np.asarray(tip_radii_mm, dtype=np.float64)
    out = MarkerArray()
    for i in range(5):
        m = Marker(header=header, ns="fingertips", id=i, type=Marker.SPHERE, action=Marker.ADD)
        m.pose.position = _point_m(tips[i])
        m.pose.orientation.w = 1.0
        d = 2.0 * float(radii[i]) / 1000.0
        m.scale.x = m.scale.y = m.scale.z = d
        r, g, b, a = FINGER_RGBA[i]
        m.color = ColorRGBA(r=r, g=g, b=b, a=a)
        m.text = FINGERS[i]
        out.markers.append(m)
    if skeleton_mm is not None:
        sk = np.asarray(skeleton_mm, dtype=np.float64)
        if sk.shape != (21, 3):
            raise InputError(f"skeleton must have shape (21, 3), got {sk.shape}")
        line = Marker(header=header, ns="skeleton", id=0, type=Marker.LINE_LIST, action=Marker.ADD)
        line.pose.orientation.w = 1.0
        line.scale.x = 0.004
        line.color = ColorRGBA(r=0.9, g=0.9, b=0.9, a=1.0)
        line.points = [_point_m(sk[j]) for bone in SKELETON_BONES for j in bone]
        out.markers.append(line)
    return out


def delete_all_markers(header: Header) -> MarkerArray:
    """A MarkerArray holding one DELETEALL marker (clears fingertips and skeleton)."""
    return MarkerArray(markers=[Marker(header=header, action=Marker.DELETEALL)])


def bgr_to_image_msg(header: Header, bgr: NDArray[np.uint8]) -> Image:
    """``sensor_msgs/Image`` (``bgr8``) from an (H, W, 3) uint8 array."""
    a = np.ascontiguousarray(bgr, dtype=np.uint8)
    if a.ndim != 3 or a.shape[2] != 3:
        raise InputError(f"BGR image must have shape (H, W, 3), got {a.shape}")
    h, w, _ = a.shape
    return Image(header=header, height=h, width=w, encoding="bgr8", is_bigendian=0, step=3 * w, data=a.tobytes())


def diagnostic_array(
    stamp: Time,
    name: str,
    hardware_id: str,
    level: bytes,
    message: str,
    values: Mapping[str, Any],
) -> DiagnosticArray:
    """One-status ``diagnostic_msgs/DiagnosticArray``.

    Parameters
    ----------
    stamp : builtin_interfaces/Time
    name, hardware_id, message : str
    level : bytes
        ``DiagnosticStatus.OK``, ``WARN``, ``ERROR`` or ``STALE``.
    values : mapping
        Key/value pairs; floats are formatted with 3 decimals.
    """
    kv = [KeyValue(key=str(k), value=(f"{v:.3f}" if isinstance(v, float) else str(v))) for k, v in values.items()]
    status = DiagnosticStatus(level=level, name=name, message=message, hardware_id=hardware_id, values=kv)
    arr = DiagnosticArray(status=[status])
    arr.header.stamp = stamp
    return arr
