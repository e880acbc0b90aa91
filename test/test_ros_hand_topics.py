"""The hand topics (ros/hand_topics.py): the one-hand names and the per-hand topics of ``max_hands: 2``,
published through a recording node."""

from __future__ import annotations

from typing import Any

import numpy as np
from rclpy.qos import QoSProfile
from std_msgs.msg import Header

from hand_sog_tracker.core.hands import HandsResult
from hand_sog_tracker.core.types import HandDecision, Intrinsics
from hand_sog_tracker.interface import (
    CONFIDENCE_TOPIC,
    DESCRIPTION_TOPIC,
    FINGERTIPS_TOPIC,
    JOINTS_TOPIC,
    KEYPOINTS_TOPIC,
    POSE_TOPIC,
)
from hand_sog_tracker.ros.hand_topics import HandOutputs, HandTopics
from hand_sog_tracker.ros.node import HAND_BASE


class _Publisher:
    def __init__(self, name: str) -> None:
        self.name, self.sent = name, []

    def get_subscription_count(self) -> int:
        return 1

    def publish(self, msg: Any) -> None:
        self.sent.append(msg)


class _Node:
    """The one call of rclpy's Node that HandTopics makes, recording what is published."""

    def __init__(self) -> None:
        self.publishers: dict[str, _Publisher] = {}

    def create_publisher(self, kind: type, name: str, qos: QoSProfile, **kw: Any) -> _Publisher:
        return self.publishers.setdefault(name, _Publisher(name))


def test_a_withheld_hand_publishes_its_checks_confidence() -> None:
    """A hand its gate withheld publishes the check's confidence and finger values (not zeros),
    as the one-hand node does; a label with no track at all publishes zeros."""
    node = _Node()
    qos = QoSProfile(depth=1)
    topics = HandTopics(node, "", qos, qos)
    held = HandDecision(False, 0.13, np.array([0.1, 0.2, 0.3, 0.4, 0.5]), None)
    intr = Intrinsics(300.0, 300.0, 160.0, 120.0, 320, 240)
    decisions = topics.publish(Header(), HandsResult((), {}, {"right": held}), np.zeros((240, 320)), intr, False)
    assert decisions == {}
    sent = {name: p.sent for name, p in node.publishers.items() if name.endswith("confidence")}
    (right,) = [msgs for name, msgs in sent.items() if "right" in name]
    (left,) = [msgs for name, msgs in sent.items() if "left" in name]
    np.testing.assert_allclose(right[-1].position, [0.0, 0.13, 0.1, 0.2, 0.3, 0.4, 0.5])
    np.testing.assert_allclose(left[-1].position, [0.0] * 7)


def test_the_one_hand_outputs_are_the_interface_topics() -> None:
    """The node's one-hand outputs use the names the interface documents, and nothing else."""
    node = _Node()
    qos = QoSProfile(depth=1)
    HandOutputs(node, HAND_BASE, qos, qos)
    assert set(node.publishers) == {
        JOINTS_TOPIC, POSE_TOPIC, KEYPOINTS_TOPIC, FINGERTIPS_TOPIC, CONFIDENCE_TOPIC, DESCRIPTION_TOPIC,
    }


def test_each_hands_fingertip_markers_expire_as_the_one_hand_markers_do() -> None:
    """A tracked hand's markers on hand/<side>/fingertips carry the lifetime the node gives (so a
    stopped node's hands leave RViz), and the hand's other topics get its pose."""
    from rclpy.serialization import deserialize_message
    from visualization_msgs.msg import MarkerArray

    from hand_sog_tracker.core.hand_model import default_hand_model
    from hand_sog_tracker.core.hands import HandTrack
    from hand_sog_tracker.core.kinematics import fingertips, keypoint_skeleton
    from hand_sog_tracker.core.types import TrackerStatus, TrackResult

    node = _Node()
    qos = QoSProfile(depth=1)
    topics = HandTopics(node, "", qos, qos, marker_lifetime_s=1.5)
    model = default_hand_model(True)
    pose = np.zeros(26)
    pose[2] = 400.0
    res = TrackResult(
        TrackerStatus.TRACKING, pose, fingertips(model, pose), keypoint_skeleton(model, pose), 0.9, 0.0, 10,
        hand=HandDecision(True, 0.9, np.ones(5), None),
    )
    intr = Intrinsics(300.0, 300.0, 160.0, 120.0, 320, 240)
    hands = HandsResult((HandTrack("right", 1, res, model),))
    decisions = topics.publish(Header(), hands, np.zeros((240, 320)), intr, False)
    assert set(decisions) == {"right"}
    (sent,) = node.publishers["hand/right/fingertips"].sent
    markers = deserialize_message(bytes(sent), MarkerArray)  # (the node publishes them as CDR bytes)
    assert markers.markers and all((m.lifetime.sec, m.lifetime.nanosec) == (1, 500_000_000) for m in markers.markers)
    assert node.publishers["hand/right/joint_states"].sent[-1].name[0].startswith("right_")
    assert node.publishers["hand/left/fingertips"].sent == []
