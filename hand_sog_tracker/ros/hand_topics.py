"""Per-hand outputs of the node with ``max_hands: 2``: one set of topics per hand label.

For each ``<side>`` (``left``, ``right``), relative names beside the one-hand topics:

==================================  ===========================================================
``hand/<side>/joint_states``        ``sensor_msgs/JointState``, the 20 angles (rad) named
                                    ``<side>_<joint>`` (+ the six wrist joints, also prefixed)
``hand/<side>/pose``                ``geometry_msgs/PoseStamped``, wrist pose (m)
``hand/<side>/keypoints``           ``geometry_msgs/PoseArray``, 21 points, MediaPipe order (m)
``hand/<side>/fingertips``          ``visualization_msgs/MarkerArray`` fingertips + skeleton
``hand/<side>/confidence``          ``sensor_msgs/JointState``, every processed frame (present 0
                                    while that hand is not tracked)
``hand/<side>/robot_description``   ``std_msgs/String``, URDF of that hand's model (latched):
                                    links ``<frame_prefix><side>_hand_wrist`` ..., joints
                                    ``<side>_<joint>``
==================================  ===========================================================

With ``publish_tf`` each hand's frames go on /tf with the prefix ``<frame_prefix><side>_``.
Everything is stamped with the input image's header.  Labels come from the data
(:mod:`hand_sog_tracker.core.hands`) and are held while a hand is tracked.
"""

from __future__ import annotations

from typing import Any, Final

from geometry_msgs.msg import PoseArray, PoseStamped
from numpy.typing import NDArray
from rclpy.node import Node
from rclpy.qos import QoSProfile
from sensor_msgs.msg import JointState
from std_msgs.msg import Header, String
from visualization_msgs.msg import MarkerArray

from hand_sog_tracker.core.hand_model import HandModel, default_hand_model
from hand_sog_tracker.core.handcheck import check_hand
from hand_sog_tracker.core.hands import HANDS, HandsResult
from hand_sog_tracker.core.types import Intrinsics
from hand_sog_tracker.core.urdf import UrdfJoint, hand_urdf, urdf_joints
from hand_sog_tracker.ros.conversions import (
    SerialisedMarkers,
    confidence_msg,
    delete_all_markers,
    joint_state_msg,
    keypoints_msg,
    pose_msg,
)
from hand_sog_tracker.ros.frames import description_transforms

__all__ = ["PER_HAND_TOPICS", "HandTopics", "hand_joint_prefix", "per_hand_topic"]

#: The per-hand topics' last parts (see the module docstring).
PER_HAND_TOPICS: Final[tuple[str, ...]] = (
    "joint_states", "pose", "keypoints", "fingertips", "confidence", "robot_description",
)


def per_hand_topic(side: str, name: str) -> str:
    """``hand/<side>/<name>``: the relative name of a per-hand topic."""
    return f"hand/{side}/{name}"


def hand_joint_prefix(side: str) -> str:
    """The prefix of the joint names of the hand labelled ``side`` (``left_`` / ``right_``)."""
    return f"{side}_"


class _Side:
    """The publishers of one hand label."""

    def __init__(self, node: Node, side: str, out_qos: QoSProfile, latched: QoSProfile, overrides: Any) -> None:
        def pub(kind: type, name: str, qos: QoSProfile = out_qos) -> Any:
            kw = {} if qos is latched else {"qos_overriding_options": overrides}
            return node.create_publisher(kind, per_hand_topic(side, name), qos, **kw)

        self.side = side
        self.joints = pub(JointState, "joint_states")
        self.pose = pub(PoseStamped, "pose")
        self.keypoints = pub(PoseArray, "keypoints")
        self.markers = pub(MarkerArray, "fingertips")
        self.confidence = pub(JointState, "confidence")
        self.description = pub(String, "robot_description", latched)
        self.described: tuple[HandModel, str | None] | None = None
        self.description_joints: tuple[UrdfJoint, ...] = ()
        self.markers_shown = False
        self.serialised_markers = SerialisedMarkers(0.0)  # (no lifetime: as fingertip_markers builds them)


class HandTopics:
    """Publishes a :class:`~hand_sog_tracker.core.hands.HandsResult` on the per-hand topics.

    Parameters
    ----------
    node : rclpy Node
    frame_prefix : str
        The node's ``frame_prefix`` (before ``<side>_``).
    publish_tf, wrist_joints : bool
        The node's ``publish_tf`` and ``publish_wrist_joints``.
    out_qos, latched : QoSProfile
        The node's output and latched (description) profiles.
    tf_publish : callable or None
        ``(transforms) -> None`` putting a list of TransformStamped on /tf (the node's).
    """

    def __init__(
        self, node: Node, frame_prefix: str, publish_tf: bool, wrist_joints: bool,
        out_qos: QoSProfile, latched: QoSProfile, overrides: Any = None, tf_publish: Any = None,
    ) -> None:
        self._sides = {s: _Side(node, s, out_qos, latched, overrides) for s in HANDS}
        self._frame_prefix = frame_prefix
        self._publish_tf = publish_tf
        self._wrist_joints = wrist_joints
        self._tf_publish = tf_publish
        for s in HANDS:
            self._describe(self._sides[s], default_hand_model(s == "right"), None)

    def _describe(self, out: _Side, model: HandModel, camera_frame: str | None) -> None:
        """Publish ``out``'s URDF of ``model`` when it changed."""
        if out.described is not None and out.described[0] is model and out.described[1] == camera_frame:
            return
        out.described = (model, camera_frame)
        text = hand_urdf(
            model, camera_frame=camera_frame, name=f"{out.side}_hand",
            prefix=f"{self._frame_prefix}{out.side}_", joint_prefix=hand_joint_prefix(out.side),
        )
        out.description_joints = urdf_joints(text)
        out.description.publish(String(data=text))

    def publish(self, header: Header, hands: HandsResult, depth_mm: NDArray, intr: Intrinsics) -> dict[str, Any]:
        """Publish one frame's hands; returns ``side -> HandDecision`` of the reported hands
        (their hand gate's, :mod:`hand_sog_tracker.core.hands`)."""
        decisions: dict[str, Any] = {}
        for side, out in self._sides.items():
            track = hands.hand(side)
            res = None if track is None else track.result
            if res is None or res.pose is None or res.fingertips_mm is None:
                if out.confidence.get_subscription_count():
                    held = hands.withheld.get(side)  # (a track its hand gate withheld: its check's values)
                    values = (False, 0.0, [0.0] * 5) if held is None else (held.present, held.confidence, held.fingers)
                    out.confidence.publish(confidence_msg(header, *values))
                if out.markers_shown:
                    out.markers.publish(delete_all_markers(header))
                    out.markers_shown = False
                continue
            assert track is not None
            # (the hand gate's decision, made on the data no other hand explains; else checked here)
            dec = res.hand if res.hand is not None else check_hand(depth_mm, intr, track.model, res)
            decisions[side] = dec
            if out.confidence.get_subscription_count():
                out.confidence.publish(confidence_msg(header, dec.present, dec.confidence, dec.fingers))
            self._describe(out, track.model, header.frame_id if self._wrist_joints else None)
            if out.markers.get_subscription_count():
                out.markers.publish(
                    out.serialised_markers(header, res.fingertips_mm, res.skeleton_mm, track.model.tip_radii)
                )
                out.markers_shown = True
            if out.joints.get_subscription_count():
                js = joint_state_msg(header, res.pose, self._wrist_joints)
                js.name = [hand_joint_prefix(side) + n for n in js.name]
                out.joints.publish(js)
            if out.pose.get_subscription_count():
                out.pose.publish(pose_msg(header, res.pose))
            if res.skeleton_mm is not None and out.keypoints.get_subscription_count():
                out.keypoints.publish(keypoints_msg(header, res.skeleton_mm, res.fingertips_mm))
            if self._publish_tf and self._tf_publish is not None:
                self._tf_publish(
                    description_transforms(
                        header, out.description_joints, res.pose, res.fingertips_mm, self._wrist_joints,
                        f"{self._frame_prefix}{side}_", hand_joint_prefix(side),
                    )
                )
        return decisions
