"""A hand's output topics: the one-hand topics, and with ``max_hands: 2`` one set per hand label.

:class:`HandOutputs` publishes one hand below a base name: ``hand`` for the one-hand topics
(see :mod:`hand_sog_tracker.ros.node`), ``hand/<side>`` for each label of :class:`HandTopics`.
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

from typing import Any, Callable, Final, Mapping

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
from hand_sog_tracker.core.types import HandDecision, Intrinsics, TrackResult
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

__all__ = ["PER_HAND_TOPICS", "HandOutputs", "HandTopics", "TfPublish", "hand_joint_prefix", "per_hand_topic"]

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


#: ``(transforms) -> None``: puts a list of TransformStamped on /tf (the node's publisher).
TfPublish = Callable[[list], None]


class HandOutputs:
    """The topics of one hand below ``base`` and what they last showed.

    Each message is built and published only while something subscribes to its topic (issue 14:
    a publication costs 0.2-0.5 ms between frames; a pose and keypoints nobody reads cost 0.45 ms
    per frame); the fingertips first, what most listeners wait for.

    Parameters
    ----------
    node : rclpy Node
    base : str
        ``hand`` (the one-hand topics) or ``hand/<side>``.
    out_qos, latched : QoSProfile
        The node's output and latched (description) profiles.
    overrides : QoSOverridingOptions or None
        For every topic but the latched description.
    robot_name, frame_prefix, joint_prefix : str
        The URDF's robot name, the prefix of its links (and TF frames) and of its joint names
        (also put on ``joint_states``).
    marker_lifetime_s : float
        Lifetime of the fingertip markers (0: for ever).
    """

    def __init__(
        self, node: Node, base: str, out_qos: QoSProfile, latched: QoSProfile, overrides: Any = None, *,
        robot_name: str = "hand", frame_prefix: str = "", joint_prefix: str = "", marker_lifetime_s: float = 0.0,
    ) -> None:
        def pub(kind: type, name: str, qos: QoSProfile = out_qos) -> Any:
            kw = {} if qos is latched else {"qos_overriding_options": overrides}
            return node.create_publisher(kind, f"{base}/{name}", qos, **kw)

        self.joints = pub(JointState, "joint_states")
        self.pose = pub(PoseStamped, "pose")
        self.keypoints = pub(PoseArray, "keypoints")
        self.markers = pub(MarkerArray, "fingertips")
        self.confidence = pub(JointState, "confidence")
        self.description = pub(String, "robot_description", latched)
        self._robot_name, self._frame_prefix, self._joint_prefix = robot_name, frame_prefix, joint_prefix
        self._described: tuple[HandModel, str | None] | None = None
        self._description_joints: tuple[UrdfJoint, ...] = ()
        self._markers_shown = False
        self._serialised_markers = SerialisedMarkers(marker_lifetime_s)

    def describe(self, model: HandModel, camera_frame: str | None) -> None:
        """Publish the URDF of ``model`` (rooted at ``camera_frame`` if given) when it changed."""
        if self._described is not None and self._described[0] is model and self._described[1] == camera_frame:
            return
        self._described = (model, camera_frame)
        text = hand_urdf(
            model, camera_frame=camera_frame, name=self._robot_name, prefix=self._frame_prefix,
            joint_prefix=self._joint_prefix,
        )
        self._description_joints = urdf_joints(text)
        self.description.publish(String(data=text))

    def publish(
        self, header: Header, decision: HandDecision | None, result: TrackResult | None = None,
        model: HandModel | None = None, wrist_joints: bool = False, tf_publish: TfPublish | None = None,
    ) -> None:
        """One frame: ``decision`` on ``confidence`` (if given); the pose of ``result`` (tracked
        with ``model``) on the other topics and on /tf through ``tf_publish`` (if given), or,
        without a pose, the fingertip markers taken away."""
        if decision is not None and self.confidence.get_subscription_count():
            self.confidence.publish(confidence_msg(header, decision.present, decision.confidence, decision.fingers))
        if result is None or result.pose is None or result.fingertips_mm is None or model is None:
            self.clear(header)
            return
        self.describe(model, header.frame_id if wrist_joints else None)
        tips = result.fingertips_mm
        if self.markers.get_subscription_count():  # (as CDR bytes: built once, SerialisedMarkers)
            self.markers.publish(self._serialised_markers(header, tips, result.skeleton_mm, model.tip_radii))
            self._markers_shown = True
        if self.joints.get_subscription_count():
            js = joint_state_msg(header, result.pose, wrist_joints)
            if self._joint_prefix:
                js.name = [self._joint_prefix + n for n in js.name]
            self.joints.publish(js)
        if self.pose.get_subscription_count():
            self.pose.publish(pose_msg(header, result.pose))
        if result.skeleton_mm is not None and self.keypoints.get_subscription_count():
            self.keypoints.publish(keypoints_msg(header, result.skeleton_mm, tips))
        if tf_publish is not None:
            tf_publish(
                description_transforms(
                    header, self._description_joints, result.pose, tips, wrist_joints, self._frame_prefix,
                    self._joint_prefix,
                )
            )

    def clear(self, header: Header) -> None:
        """Take the fingertip markers away (a delete-all) if they are shown."""
        if self._markers_shown:
            self.markers.publish(delete_all_markers(header))
            self._markers_shown = False


class HandTopics:
    """Publishes a :class:`~hand_sog_tracker.core.hands.HandsResult` on the per-hand topics.

    Parameters
    ----------
    node : rclpy Node
    frame_prefix : str
        The node's ``frame_prefix`` (before ``<side>_``).
    out_qos, latched : QoSProfile
        The node's output and latched (description) profiles.
    overrides : QoSOverridingOptions or None
    marker_lifetime_s : float
        Lifetime of each hand's fingertip markers (0: for ever), as on the one-hand topics.
    models : mapping of side to HandModel, optional
        The model each hand starts with, described at once (default: each side's default model).
    """

    def __init__(
        self, node: Node, frame_prefix: str, out_qos: QoSProfile, latched: QoSProfile, overrides: Any = None,
        marker_lifetime_s: float = 0.0, models: Mapping[str, HandModel] | None = None,
    ) -> None:
        self._sides = {
            s: HandOutputs(
                node, f"hand/{s}", out_qos, latched, overrides, robot_name=f"{s}_hand",
                frame_prefix=f"{frame_prefix}{s}_", joint_prefix=hand_joint_prefix(s),
                marker_lifetime_s=marker_lifetime_s,
            )
            for s in HANDS
        }
        for s in HANDS:
            self._sides[s].describe((models or {}).get(s) or default_hand_model(s == "right"), None)

    def publish(
        self, header: Header, hands: HandsResult, depth_mm: NDArray, intr: Intrinsics, wrist_joints: bool,
        tf_publish: TfPublish | None = None,
    ) -> dict[str, HandDecision]:
        """Publish one frame's hands (``wrist_joints``, ``tf_publish``: as :meth:`HandOutputs.publish`);
        returns ``side -> HandDecision`` of the reported hands (their hand gate's,
        :mod:`hand_sog_tracker.core.hands`)."""
        decisions: dict[str, HandDecision] = {}
        for side, out in self._sides.items():
            track = hands.hand(side)
            res = None if track is None else track.result
            if track is None or res is None or res.pose is None or res.fingertips_mm is None:
                # (a track its hand gate withheld publishes its check's values)
                out.publish(header, hands.withheld.get(side, HandDecision(False, 0.0)))
                continue
            # (the hand gate's decision, made on the data no other hand explains; else checked here)
            dec = res.hand if res.hand is not None else check_hand(depth_mm, intr, track.model, res)
            decisions[side] = dec
            out.publish(header, dec, res, track.model, wrist_joints, tf_publish)
        return decisions
