"""The per-hand topics of ``max_hands: 2`` (ros/hand_topics.py), published through a recording node."""

from __future__ import annotations

from typing import Any

import numpy as np
from rclpy.qos import QoSProfile
from std_msgs.msg import Header

from hand_sog_tracker.core.hands import HandsResult
from hand_sog_tracker.core.types import HandDecision, Intrinsics
from hand_sog_tracker.ros.hand_topics import HandTopics


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
    topics = HandTopics(node, "", False, False, qos, qos)
    held = HandDecision(False, 0.13, np.array([0.1, 0.2, 0.3, 0.4, 0.5]), None)
    intr = Intrinsics(300.0, 300.0, 160.0, 120.0, 320, 240)
    decisions = topics.publish(Header(), HandsResult((), {}, {"right": held}), np.zeros((240, 320)), intr)
    assert decisions == {}
    sent = {name: p.sent for name, p in node.publishers.items() if name.endswith("confidence")}
    (right,) = [msgs for name, msgs in sent.items() if "right" in name]
    (left,) = [msgs for name, msgs in sent.items() if "left" in name]
    np.testing.assert_allclose(right[-1].position, [0.0, 0.13, 0.1, 0.2, 0.3, 0.4, 0.5])
    np.testing.assert_allclose(left[-1].position, [0.0] * 7)
