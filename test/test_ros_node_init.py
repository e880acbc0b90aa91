"""The node runs what the core runs (issue 45): the same answers, whole frames or none."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from hand_sog_tracker.core.tracker import Tracker
from hand_sog_tracker.core.types import TrackerConfig, TrackerStatus
from hand_sog_tracker.ros.conversions import stamp_to_ns
from test_ros_node import INTR, T0_NS, Rig, hand_depth, hand_poses, image_msg


def test_an_image_arriving_during_a_frame_waits_and_every_answer_is_the_cores(
    ros_context, tmp_path: Path
) -> None:
    """The camera's next image arrives while the first (the initialisation) is tracked: it is
    tracked after it, and both answers equal a core tracker's on the same two images."""
    rig = Rig(ros_context, tmp_path)
    try:
        rig.send_info()
        frames = [hand_depth(th, seed=i) for i, th in enumerate(hand_poses(2))]
        first, second = (image_msg(d, T0_NS + i * 33_333_333) for i, d in enumerate(frames))
        tracker = rig.node._tracker
        process = tracker.process
        sent: list[bool] = []

        def process_then_camera_sends(depth, intr):
            result = process(depth, intr)
            if not sent:
                rig.image_pub.publish(second)
                time.sleep(0.3)  # loopback delivery into the node's subscription
                sent.append(True)
            return result

        tracker.process = process_then_camera_sends
        rig.send(first)
        rig.spin_until(lambda: rig.node.stats.processed == 2)
        reference = Tracker(TrackerConfig())
        for i, depth in enumerate(frames):
            expected = reference.process(depth, INTR)
            assert expected.status is TrackerStatus.TRACKING
            js = rig.wait_joint(T0_NS + i * 33_333_333)
            np.testing.assert_allclose(js.position, expected.pose[6:], atol=1e-9)
        s = rig.node.stats
        assert (s.processed, s.dropped, s.missed) == (2, 0, 0)
    finally:
        rig.close()


def test_an_image_resent_with_its_stamp_gets_the_same_answer(ros_context, tmp_path: Path) -> None:
    """A re-sent image (the same stamp and pixels, e.g. a best-effort retry) is answered
    again with the same pose, not tracked a second time; the next image is tracked as the
    core tracks it after the first."""
    rig = Rig(ros_context, tmp_path)
    try:
        rig.send_info()
        frames = [hand_depth(th, seed=i) for i, th in enumerate(hand_poses(2))]
        rig.send(image_msg(frames[0], T0_NS))
        rig.send(image_msg(frames[0], T0_NS))
        rig.send(image_msg(frames[1], T0_NS + 33_333_333))
        assert rig.spin_until(lambda: len(rig.joints) == 3, 5.0)
        got = [(stamp_to_ns(m.header.stamp), np.array(m.position)) for m, _ in rig.joints]
        reference = Tracker(TrackerConfig())
        expected = [reference.process(d, INTR).pose[6:] for d in frames]
        assert [g[0] for g in got] == [T0_NS, T0_NS, T0_NS + 33_333_333]
        np.testing.assert_array_equal(got[0][1], got[1][1])
        np.testing.assert_allclose(got[0][1], expected[0], atol=1e-9)
        np.testing.assert_allclose(got[2][1], expected[1], atol=1e-9)
        assert rig.node.stats.processed == 3
    finally:
        rig.close()
