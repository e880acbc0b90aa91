"""The node's initialisation over two frames (issue 14): deferred when a newer image waits."""

from __future__ import annotations

import time
from pathlib import Path

from hand_sog_tracker.core.hand_model import rest_pose
from hand_sog_tracker.core.types import TrackerStatus
from hand_sog_tracker.ros.conversions import stamp_to_ns
from test_ros_node import T0_NS, Rig, hand_depth, image_msg


def test_a_newer_image_finishes_the_initialisation_and_nothing_is_published_before(
    ros_context, tmp_path: Path
) -> None:
    rig = Rig(ros_context, tmp_path)
    try:
        rig.send_info()
        th = rest_pose((0.0, 20.0, 430.0))
        first, second = (image_msg(hand_depth(th, seed=i), T0_NS + i * 33_333_333) for i in range(2))
        tracker = rig.node._tracker
        process = tracker.process

        searched: list[bool] = []

        def process_then_camera_sends(depth, intr):
            """The camera's next image arrives while the first one is searched."""
            result = process(depth, intr)
            searched.append(tracker.initialising)
            if tracker.initialising:
                rig.image_pub.publish(second)
                time.sleep(0.3)  # loopback delivery into the node's subscription
            return result

        tracker.process = process_then_camera_sends
        rig.send(first)
        rig.spin_until(lambda: rig.node.stats.processed == 2)
        assert searched[0] and rig.node.stats.processed == 2  # the first image only searched
        js = rig.wait_joint(T0_NS + 33_333_333)
        assert len(js.position) == 20 and rig.node.stats.status is TrackerStatus.TRACKING
        assert all(stamp_to_ns(m.header.stamp) != T0_NS for m, _ in rig.joints)  # nothing for the first
        assert all(stamp_to_ns(p.header.stamp) != T0_NS for p in rig.poses)
    finally:
        rig.close()


def test_a_single_image_is_answered_on_its_own_frame(ros_context, tmp_path: Path) -> None:
    rig = Rig(ros_context, tmp_path)
    try:
        rig.send_info()
        rig.send(image_msg(hand_depth(rest_pose((0.0, 20.0, 430.0)), seed=1), T0_NS))
        assert not rig.node._tracker.initialising
        assert len(rig.wait_joint(T0_NS).position) == 20
        assert rig.node.stats.processed == 1 and rig.node.stats.status is TrackerStatus.TRACKING
    finally:
        rig.close()


def test_a_fast_camera_gets_the_restarts_at_a_limited_rate(ros_context, tmp_path: Path) -> None:
    from hand_sog_tracker.ros.node import FAST_CAMERA_RESTART_INTERVAL_S

    th = rest_pose((0.0, 20.0, 430.0))
    for period_ns, expected in ((10_000_000, FAST_CAMERA_RESTART_INTERVAL_S), (33_333_333, None)):
        rig = Rig(ros_context, tmp_path)
        try:
            rig.send_info()
            for i in range(3):
                rig.send(image_msg(hand_depth(th, seed=i), T0_NS + i * period_ns))
            assert rig.node.stats.processed == 3
            assert rig.node._tracker.restart_interval_s == expected
        finally:
            rig.close()
