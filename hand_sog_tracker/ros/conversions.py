"""Conversion between ROS messages and the core's NumPy values.

Input side (duck-typed through :class:`ImageLike` / :class:`CameraInfoLike`, so
the same functions take rclpy messages and rosbags records; defined in the ROS-free
:mod:`hand_sog_tracker.interface` and re-exported here):

* :func:`image_to_depth_mm` - ``sensor_msgs/Image`` to a float32 depth map in mm.
* :func:`camera_info_to_intrinsics` - ``sensor_msgs/CameraInfo`` to :class:`Intrinsics`.

* :func:`compressed_image_to_depth_mm` - ``sensor_msgs/CompressedImage`` from the
  ``compressedDepth`` transport to mm (decoding in :mod:`hand_sog_tracker.compressed_depth`).

Output side (rclpy messages; units converted from mm to metres):
:func:`joint_state_msg`, :func:`pose_msg`, :func:`keypoints_msg`, :func:`hand_transforms`,
:func:`fingertip_markers`,
:func:`delete_all_markers`, :func:`bgr_to_image_msg` (the debug image drawn by
:func:`hand_sog_tracker.core.overlay.draw_overlay`) and :func:`diagnostic_array`.
"""

from __future__ import annotations

import struct
from typing import Any, Mapping, Sequence

import numpy as np
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Point, Pose, PoseArray, PoseStamped, TransformStamped
from numpy.typing import NDArray
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import Image, JointState
from std_msgs.msg import ColorRGBA, Header
from visualization_msgs.msg import Marker, MarkerArray

from hand_sog_tracker.core.hand_model import FINGERS, JOINT_NAMES, JOINTS, N_PARAMS
from hand_sog_tracker.core.kinematics import SKELETON_CHAINS, global_rotation
from hand_sog_tracker.core.rotations import quaternion_from_matrix
from hand_sog_tracker.core.urdf import WRIST_JOINT_NAMES, WRIST_LINK
from hand_sog_tracker.errors import InputError

# The input side is pure NumPy on duck-typed messages: it lives in the ROS-free interface module
# (so bag tools can use it without sensor_msgs) and is re-exported here.
from hand_sog_tracker.interface import (
    CONFIDENCE_NAMES,
    DEPTH_ENCODINGS,
    FINGERTIPS_NS,
    SKELETON_MARKER_ID,
    SKELETON_NS,
    CameraInfoLike,
    CompressedImageLike,
    ImageLike,
    camera_info_to_intrinsics,
    compressed_image_to_depth_mm,
    image_to_depth_mm,
    stamp_to_ns,
)

#: Kept under its old name: the quaternion of a rotation matrix (3, 3), ``(x, y, z, w)``
#: (:func:`hand_sog_tracker.core.rotations.quaternion_from_matrix`).
rotation_to_quaternion = quaternion_from_matrix

__all__ = [
    "confidence_msg",
    "ImageLike",
    "CameraInfoLike",
    "DEPTH_ENCODINGS",
    "image_to_depth_mm",
    "CompressedImageLike",
    "compressed_image_to_depth_mm",
    "camera_info_to_intrinsics",
    "rotation_to_quaternion",
    "stamp_to_ns",
    "SKELETON_BONES",
    "joint_state_msg",
    "pose_msg",
    "KEYPOINT_NAMES",
    "keypoints_mm",
    "keypoints_msg",
    "TF_TIP_FRAMES",
    "hand_transforms",
    "fingertip_markers",
    "SerialisedMarkers",
    "delete_all_markers",
    "bgr_to_image_msg",
    "diagnostic_array",
]


def _check_pose(pose: NDArray[np.float64]) -> NDArray[np.float64]:
    p = np.asarray(pose, dtype=np.float64)
    if p.shape != (N_PARAMS,):
        raise InputError(f"pose must have shape ({N_PARAMS},), got {p.shape}")
    return p


def joint_state_msg(header: Header, pose: NDArray[np.float64], wrist_joints: bool = False) -> JointState:
    """``sensor_msgs/JointState`` with the 20 joint angles (rad) of ``pose`` (26,).

    Names are :data:`hand_model.JOINT_NAMES` in pose-vector order.  With ``wrist_joints``
    the six virtual joints of :data:`hand_sog_tracker.core.urdf.WRIST_JOINT_NAMES` follow
    (``hand_tx, hand_ty, hand_tz`` in metres, ``hand_rz, hand_rx, hand_ry`` in radians, so
    that ``R = Rz Rx Ry`` as in the pose vector).
    """
    p = _check_pose(pose)
    names, values = list(JOINT_NAMES), p[JOINTS].tolist()
    if wrist_joints:
        names += list(WRIST_JOINT_NAMES)
        values += [float(p[0]) / 1000.0, float(p[1]) / 1000.0, float(p[2]) / 1000.0]
        values += [float(p[5]), float(p[3]), float(p[4])]
    return JointState(header=header, name=names, position=values)


def pose_msg(header: Header, pose: NDArray[np.float64]) -> PoseStamped:
    """Wrist (root) pose: ``pose[:3]`` mm converted to metres and the global rotation.

    The orientation is :func:`kinematics.global_rotation` of the pose, i.e.
    the hand frame of a right hand (x radial, y along the middle finger, z out
    of the palm).  A left hand is the mirror image of that frame
    (``R @ diag(-1, 1, 1)`` is not a rotation), so the same ``R`` is published.
    """
    p = _check_pose(pose)
    q = quaternion_from_matrix(global_rotation(p))
    msg = PoseStamped(header=header)
    msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = (float(v) / 1000.0 for v in p[:3])
    msg.pose.orientation.x, msg.pose.orientation.y, msg.pose.orientation.z, msg.pose.orientation.w = (
        float(v) for v in q
    )
    return msg


#: The 21 keypoints of ``hand/keypoints`` in MediaPipe Hands' landmark order.
KEYPOINT_NAMES: tuple[str, ...] = ("wrist",) + tuple(
    f"{f}_{j}"
    for f, joints in zip(
        FINGERS,
        [("cmc", "mcp", "ip", "tip")] + [("mcp", "pip", "dip", "tip")] * 4,
    )
    for j in joints
)


def keypoints_mm(skeleton_mm: NDArray[np.float64], fingertips_mm: NDArray[np.float64]) -> NDArray[np.float64]:
    """The 21 keypoints (MediaPipe order), shape (21, 3), mm.

    :func:`kinematics.skeleton_points` already lists the wrist, then per chain (thumb ..
    little) its three joints and its segment end, which is MediaPipe's order (0 wrist, 1-4
    thumb CMC, MCP, IP, TIP, 5-8 index MCP, PIP, DIP, TIP, ... 17-20 little).  The TIP
    keypoints (4, 8, 12, 16, 20) are the fingertips the tracker reports
    (:func:`kinematics.fingertips`, the centre of the fingertip sphere, as on
    ``hand/fingertips``) instead of the bone ends.
    """
    sk = np.asarray(skeleton_mm, dtype=np.float64)
    tips = np.asarray(fingertips_mm, dtype=np.float64)
    if sk.shape != (21, 3) or tips.shape != (5, 3):
        raise InputError(f"need skeleton (21, 3) and fingertips (5, 3), got {sk.shape} and {tips.shape}")
    out = sk.copy()
    out[4::4] = tips
    return out


def confidence_msg(header: Header, present: bool, confidence: float, fingers: NDArray[np.float64]) -> JointState:
    """``hand/confidence``: the frame's hand decision as a ``sensor_msgs/JointState``.

    ``name`` = :data:`~hand_sog_tracker.interface.CONFIDENCE_NAMES`, ``position`` = present
    (1.0 or 0.0), the hand confidence and the five finger confidences (each in [0, 1]);
    ``velocity`` and ``effort`` empty.
    """
    values = [1.0 if present else 0.0, float(confidence)] + [float(f) for f in np.asarray(fingers).reshape(5)]
    return JointState(header=header, name=list(CONFIDENCE_NAMES), position=values)


def keypoints_msg(header: Header, skeleton_mm: NDArray[np.float64], fingertips_mm: NDArray[np.float64]) -> PoseArray:
    """``geometry_msgs/PoseArray`` of the 21 keypoints (metres, identity orientations); see :func:`keypoints_mm`."""
    pts = (keypoints_mm(skeleton_mm, fingertips_mm) / 1000.0).tolist()
    poses = []
    for x, y, z in pts:
        p = Pose()
        p.position.x, p.position.y, p.position.z = x, y, z
        p.orientation.w = 1.0
        poses.append(p)
    return PoseArray(header=header, poses=poses)


#: TF child frames of the fingertips (thumb .. little).  They coincide with the URDF's
#: ``<finger>_tip`` links but are named differently, so the node and a robot_state_publisher
#: never both publish the same frame.
TF_TIP_FRAMES: tuple[str, ...] = tuple(f"{f}_fingertip" for f in FINGERS)


def hand_transforms(
    header: Header, pose: NDArray[np.float64], fingertips_mm: NDArray[np.float64], prefix: str = ""
) -> list[TransformStamped]:
    """TF frames of the hand: the wrist in the image frame and the five fingertips in the wrist frame.

    ``<prefix>hand_wrist`` has the position and orientation of ``hand/pose``;
    ``<prefix><finger>_fingertip`` (:data:`TF_TIP_FRAMES`) has identity rotation and the
    fingertip position expressed in the wrist frame (for a left hand the wrist frame is the
    rotation of ``hand/pose``, and tips are placed where the tracker reports them).

    Returns
    -------
    list of geometry_msgs/TransformStamped
        Six transforms, all with ``header.stamp``.
    """
    p = _check_pose(pose)
    tips = np.asarray(fingertips_mm, dtype=np.float64)
    if tips.shape != (5, 3):
        raise InputError(f"fingertips must have shape (5, 3), got {tips.shape}")
    rot = global_rotation(p)
    q = quaternion_from_matrix(rot)
    wrist = TransformStamped()
    wrist.header.stamp = header.stamp
    wrist.header.frame_id = header.frame_id
    wrist.child_frame_id = prefix + WRIST_LINK
    t = wrist.transform
    t.translation.x, t.translation.y, t.translation.z = (float(v) / 1000.0 for v in p[:3])
    t.rotation.x, t.rotation.y, t.rotation.z, t.rotation.w = (float(v) for v in q)
    out = [wrist]
    local = (tips - p[:3]) @ rot / 1000.0  # R^T (tip - t), metres
    for name, xyz in zip(TF_TIP_FRAMES, local):
        tf = TransformStamped()
        tf.header.stamp = header.stamp
        tf.header.frame_id = prefix + WRIST_LINK
        tf.child_frame_id = prefix + name
        tf.transform.translation.x, tf.transform.translation.y, tf.transform.translation.z = (float(v) for v in xyz)
        tf.transform.rotation.w = 1.0
        out.append(tf)
    return out


#: Bones of the 21-point skeleton (:func:`kinematics.skeleton_points`): wrist to each
#: chain's first joint, then along each chain to its tip.
SKELETON_BONES: tuple[tuple[int, int], ...] = tuple(
    pair for chain in SKELETON_CHAINS for pair in zip(chain[:-1], chain[1:])
)

#: Marker colours (RGBA) of thumb .. little.
FINGER_RGBA: tuple[tuple[float, float, float, float], ...] = (
    (1.0, 0.2, 0.2, 1.0),
    (1.0, 0.8, 0.1, 1.0),
    (0.2, 0.9, 0.2, 1.0),
    (0.2, 0.6, 1.0, 1.0),
    (0.8, 0.3, 1.0, 1.0),
)


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
    tips_m = (tips / 1000.0).tolist()
    diameters = (2.0 * radii / 1000.0).tolist()
    out = MarkerArray()
    for i in range(5):
        m = Marker(header=header, ns=FINGERTIPS_NS, id=i, type=Marker.SPHERE, action=Marker.ADD)
        x, y, z = tips_m[i]
        m.pose.position = Point(x=x, y=y, z=z)
        m.pose.orientation.w = 1.0
        d = diameters[i]
        m.scale.x = m.scale.y = m.scale.z = d
        r, g, b, a = FINGER_RGBA[i]
        m.color = ColorRGBA(r=r, g=g, b=b, a=a)
        m.text = FINGERS[i]
        out.markers.append(m)
    if skeleton_mm is not None:
        sk = np.asarray(skeleton_mm, dtype=np.float64)
        if sk.shape != (21, 3):
            raise InputError(f"skeleton must have shape (21, 3), got {sk.shape}")
        line = Marker(header=header, ns=SKELETON_NS, id=SKELETON_MARKER_ID, type=Marker.LINE_LIST, action=Marker.ADD)
        line.pose.orientation.w = 1.0
        line.scale.x = 0.004
        line.color = ColorRGBA(r=0.9, g=0.9, b=0.9, a=1.0)
        sk_m = (sk / 1000.0).tolist()
        line.points = [Point(x=sk_m[j][0], y=sk_m[j][1], z=sk_m[j][2]) for bone in SKELETON_BONES for j in bone]
        out.markers.append(line)
    return out


class SerialisedMarkers:
    """:func:`fingertip_markers`, every marker with ``lifetime_s``, as the MarkerArray's CDR bytes
    (``Publisher.publish`` takes them): the message is built and serialised once per frame id and
    tip radii; a frame writes its stamp, fingertips and skeleton into a copy of those bytes (what
    ``serialize_message`` gives, padding aside, without building the message: doc/design/speed.md).
    Where the template's fields lie is found from sentinel values and checked by deserialising a
    frame written into it; a template that fails the check is not used (the message path is)."""

    #: Sentinels of the template: a stamp (sec, nanosec), fingertips and skeleton (mm) of distinct
    #: values, each of no zero bytes in metres (a whole number's 4 zero bytes beside an int32 0 and
    #: padding matched an old one), and the values of the check.
    _STAMP = (0x5A5A5A5A, 0x3C3C3C3C)
    _TIPS_MM = np.pi * 1e6 + 1e3 * np.arange(15.0).reshape(5, 3)
    _SKELETON_MM = np.e * 1e6 + 1e3 * np.arange(63.0).reshape(21, 3)
    _CHECK_TIPS_MM = np.linspace(-500.0, 900.0, 15).reshape(5, 3)
    _CHECK_SKELETON_MM = np.linspace(-700.0, 600.0, 63).reshape(21, 3)
    _BONE_ROWS = np.array([j for bone in SKELETON_BONES for j in bone])

    def __init__(self, lifetime_s: float) -> None:
        self.lifetime = (int(lifetime_s), int(lifetime_s % 1 * 1e9))
        self._key: tuple[str, bytes] | None = None
        self._template: NDArray[np.uint8] | None = None
        self._stamp_at = self._tips_at = np.zeros((0, 8), np.int64)
        self._points_at = 0

    def message(
        self, header: Header, fingertips_mm: NDArray[np.float64], skeleton_mm: NDArray[np.float64] | None,
        tip_radii_mm: NDArray[np.float64],
    ) -> MarkerArray:
        """The message the bytes serialise: :func:`fingertip_markers` with the lifetime."""
        out = fingertip_markers(header, fingertips_mm, skeleton_mm, tip_radii_mm)
        for m in out.markers:
            m.lifetime.sec, m.lifetime.nanosec = self.lifetime
        return out

    def __call__(
        self, header: Header, fingertips_mm: NDArray[np.float64], skeleton_mm: NDArray[np.float64] | None,
        tip_radii_mm: NDArray[np.float64],
    ) -> bytes:
        """The CDR bytes of :meth:`message` (shapes (5, 3), (21, 3), (5,) mm; else through it)."""
        tips = np.asarray(fingertips_mm, dtype=np.float64)
        radii = np.asarray(tip_radii_mm, dtype=np.float64)
        shapes = (tips.shape, np.shape(skeleton_mm) if skeleton_mm is not None else None, radii.shape)
        if shapes == ((5, 3), (21, 3), (5,)):
            key = (header.frame_id, radii.tobytes())
            if key != self._key:
                self._key = key
                self._build(header.frame_id, radii)
            if self._template is not None:
                return self._fill(header.stamp, tips, np.asarray(skeleton_mm, dtype=np.float64))
        return bytes(serialize_message(self.message(header, fingertips_mm, skeleton_mm, tip_radii_mm)))

    def _fill(self, stamp: Time, tips_mm: NDArray[np.float64], skeleton_mm: NDArray[np.float64]) -> bytes:
        assert self._template is not None
        out = self._template.copy()
        out[self._stamp_at] = np.frombuffer(struct.pack("<iI", stamp.sec, stamp.nanosec), np.uint8)
        out[self._tips_at] = (tips_mm / 1000.0).astype("<f8").view(np.uint8).reshape(15, 8)
        points = (skeleton_mm / 1000.0)[self._BONE_ROWS].astype("<f8")
        out[self._points_at : self._points_at + points.nbytes] = points.view(np.uint8).ravel()
        return out.tobytes()

    def _build(self, frame_id: str, radii: NDArray[np.float64]) -> None:
        """The template of ``frame_id`` and ``radii`` and its fields' places, or None (see above)."""
        self._template = None
        header = Header(stamp=Time(sec=self._STAMP[0], nanosec=self._STAMP[1]), frame_id=frame_id)
        raw = bytes(serialize_message(self.message(header, self._TIPS_MM, self._SKELETON_MM, radii)))

        def at(pattern: bytes, align: int) -> list[int]:
            """Where ``pattern`` starts in ``raw`` at a multiple of ``align`` after the 4-byte CDR header."""
            found, k = [], raw.find(pattern)
            while k >= 0:
                found += [k] if (k - 4) % align == 0 else []
                k = raw.find(pattern, k + 1)
            return found

        stamps = at(struct.pack("<iI", *self._STAMP), 4)
        tips = [at(v.tobytes(), 8) for v in (self._TIPS_MM / 1000.0).astype("<f8").ravel()]
        points = at((self._SKELETON_MM / 1000.0)[self._BONE_ROWS].astype("<f8").tobytes(), 8)
        if raw[:2] != b"\x00\x01" or len(stamps) != 6 or any(len(t) != 1 for t in tips) or len(points) != 1:
            return  # (not little-endian CDR, or a sentinel not found once: the message path)
        self._stamp_at = np.array(stamps)[:, None] + np.arange(8)
        self._tips_at = np.array([t[0] for t in tips])[:, None] + np.arange(8)
        self._points_at = points[0]
        self._template = np.frombuffer(raw, dtype=np.uint8).copy()
        check = Header(stamp=Time(sec=-3, nanosec=999_999_999), frame_id=frame_id)
        written = self._fill(check.stamp, self._CHECK_TIPS_MM, self._CHECK_SKELETON_MM)
        wanted = serialize_message(self.message(check, self._CHECK_TIPS_MM, self._CHECK_SKELETON_MM, radii))
        if deserialize_message(written, MarkerArray) != deserialize_message(wanted, MarkerArray):
            self._template = None  # (compared as received: the colours are float32 on the wire)

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
