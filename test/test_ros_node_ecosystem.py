"""The node's ROS-ecosystem outputs and inputs: keypoints, URDF description, wrist joints,
compressedDepth input, TF (tf2_msgs is optional)."""

from __future__ import annotations

import importlib.util
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
from geometry_msgs.msg import PoseArray
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CompressedImage
from std_msgs.msg import String

from hand_sog_tracker.compressed_depth import encode_compressed_depth
from hand_sog_tracker.core.hand_model import JOINT_NAMES
from hand_sog_tracker.core.kinematics import fingertips, keypoint_skeleton
from hand_sog_tracker.core.tracker import Tracker
from hand_sog_tracker.core.types import TrackerConfig, TrackerStatus
from hand_sog_tracker.core.urdf import WRIST_JOINT_NAMES, hand_urdf
from hand_sog_tracker.errors import InputError
from hand_sog_tracker.ros.conversions import keypoints_mm, stamp_to_ns
from hand_sog_tracker.ros.node import TrackerNode
from test_ros_node import FRAME, INTR, T0_NS, Rig, hand_depth, hand_poses, image_msg

HAVE_TF2 = importlib.util.find_spec("tf2_msgs") is not None
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)


def compressed_msg(depth_mm: np.ndarray, stamp_ns: int, encoding: str, codec: str) -> CompressedImage:
    fmt, data = encode_compressed_depth(depth_mm, encoding, codec)
    msg = CompressedImage(format=fmt, data=data)
    msg.header.frame_id = FRAME
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, 10**9)
    return msg


def test_keypoints_description_and_wrist_joints(ros_context, tmp_path: Path) -> None:
    rig = Rig(ros_context, tmp_path, publish_wrist_joints=True)
    try:
        keypoints: list[PoseArray] = []
        descriptions: list[String] = []
        reliable = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        rig.io.create_subscription(PoseArray, "hand/keypoints", keypoints.append, reliable)
        # Latched: a late subscriber still gets the description published at start-up.
        rig.io.create_subscription(String, "hand/robot_description", descriptions.append, LATCHED)
        assert rig.spin_until(lambda: len(descriptions) == 1, 10.0)
        assert descriptions[0].data == hand_urdf(rig.node.hand_model)  # no frame yet: rooted at the wrist
        rig.send_info()
        depth = hand_depth(hand_poses(1)[0], seed=2)
        rig.send(image_msg(depth, T0_NS))
        js = rig.wait_joint(T0_NS)
        assert list(js.name) == list(JOINT_NAMES) + list(WRIST_JOINT_NAMES)
        assert rig.spin_until(lambda: len(keypoints) == 1 and len(rig.poses) == 1 and len(descriptions) == 2, 5.0)
        kp = keypoints[0]
        assert stamp_to_ns(kp.header.stamp) == T0_NS and kp.header.frame_id == FRAME and len(kp.poses) == 21
        pts = np.array([[p.position.x, p.position.y, p.position.z] for p in kp.poses])
        pos = rig.poses[0].pose.position
        np.testing.assert_allclose(js.position[20:23], [pos.x, pos.y, pos.z], atol=1e-12)  # hand_tx/ty/tz in m
        # The keypoints are the published pose's (rebuilt from the joint states): the wrist, the
        # thumb CMC and the MCPs at the joint centres, the others the kinematic chain's.
        jp = np.asarray(js.position)
        theta = np.concatenate([jp[20:23] * 1000.0, [jp[24], jp[25], jp[23]], jp[:20]])
        np.testing.assert_allclose(pts * 1000.0, keypoints_mm(keypoint_skeleton(rig.node.hand_model, theta),
                                                              fingertips(rig.node.hand_model, theta)), atol=1e-6)
        assert 0.003 < np.linalg.norm(pts[0] - [pos.x, pos.y, pos.z]) < 0.025  # not the pose's origin
        tips = [m for m in rig.markers[0].markers if m.ns == "fingertips"]
        marker_tips = np.array([[m.pose.position.x, m.pose.position.y, m.pose.position.z] for m in tips])
        np.testing.assert_allclose(pts[[4, 8, 12, 16, 20]], marker_tips, atol=1e-12)  # TIPs = fingertips
        # With the wrist joints the description starts at the image frame.
        assert descriptions[1].data == hand_urdf(rig.node.hand_model, camera_frame=FRAME)
        root = ET.fromstring(descriptions[1].data)
        assert {j.get("name") for j in root.findall("joint")} >= set(js.name)
        # The same frame again: no republication.
        rig.send(image_msg(depth, T0_NS + 10**8))
        rig.wait_joint(T0_NS + 10**8)
        rig.spin_until(lambda: False, 0.2)
        assert len(descriptions) == 2
    finally:
        rig.close()


def test_compressed_depth_input_is_tracked_and_bad_payloads_are_rejected(ros_context, tmp_path: Path) -> None:
    rig = Rig(ros_context, tmp_path, compressed=True)
    try:
        assert any(
            s.topic_name.endswith("/camera/depth/image_rect_raw/compressedDepth") for s in rig.node.subscriptions
        )
        rig.send_info()
        reference = Tracker(TrackerConfig())
        poses = hand_poses(2)
        d0 = hand_depth(poses[0], seed=0)
        rig.send(compressed_msg(d0, T0_NS, "16UC1", "png"))
        js = rig.wait_joint(T0_NS)
        expected = reference.process(d0, INTR)  # 16UC1 png is lossless: the same result as raw
        assert expected.status is TrackerStatus.TRACKING
        np.testing.assert_allclose(js.position, expected.pose[6:], atol=1e-9)
        assert js.header.frame_id == FRAME

        bad = compressed_msg(d0, T0_NS + 10**8, "16UC1", "png")
        bad.data = bytes(bad.data)[:40]
        rig.send(bad)
        problem = rig.node.stats.last_problem
        assert "bad depth image" in problem and "corrupt or truncated" in problem
        wrong = compressed_msg(d0, T0_NS + 2 * 10**8, "16UC1", "png")
        wrong.format = "16UC1; compressed jpeg"
        rig.send(wrong)
        assert "unsupported compressed depth format" in rig.node.stats.last_problem
        assert rig.node.stats.rejected == 2

        stamp = T0_NS + 3 * 10**8
        d1 = hand_depth(poses[1], seed=1)
        rig.send(compressed_msg(d1, stamp, "32FC1", "rvl"))
        js = rig.wait_joint(stamp)
        assert rig.node.stats.status is TrackerStatus.TRACKING and rig.node.stats.processed == 2
        # 32FC1 is quantised (< 0.02 mm at 0.42 m): the angles agree with the raw result closely.
        raw = reference.process(d1, INTR)
        assert np.max(np.abs(np.asarray(js.position) - raw.pose[6:])) < 0.05
    finally:
        rig.close()


def test_input_transport_is_validated() -> None:
    from hand_sog_tracker.ros.params import settings_from_values

    assert settings_from_values({"input_transport": "compressedDepth"}).input_transport == "compressedDepth"
    with pytest.raises(InputError, match="input_transport must be one of raw, compressedDepth"):
        settings_from_values({"input_transport": "compressed"})


@pytest.mark.skipif(HAVE_TF2, reason="tf2_msgs is installed: publish_tf is allowed")
def test_publish_tf_without_tf2_msgs_is_rejected_with_the_reason(ros_context, tmp_path: Path) -> None:
    rig = Rig(ros_context, tmp_path)
    try:
        res = rig.node.set_parameters([Parameter("publish_tf", value=True)])[0]
        assert not res.successful and "tf2_msgs" in res.reason
        assert rig.node.settings.publish_tf is False
    finally:
        rig.close()
    with pytest.raises(InputError, match="publish_tf=true needs the tf2_msgs"):
        TrackerNode(context=ros_context, parameter_overrides=[Parameter("publish_tf", value=True)])


@pytest.mark.skipif(not HAVE_TF2, reason="tf2_msgs is not installed here (no PyPI wheel)")
def test_publish_tf_broadcasts_the_wrist_and_fingertips(ros_context, tmp_path: Path) -> None:  # pragma: no cover
    from tf2_msgs.msg import TFMessage

    rig = Rig(ros_context, tmp_path, publish_tf=True)
    try:
        got: list[TFMessage] = []
        rig.io.create_subscription(
            TFMessage, "/tf", got.append, QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        )
        rig.spin_until(lambda: False, 0.5)
        rig.send_info()
        rig.send(image_msg(hand_depth(hand_poses(1)[0], seed=2), T0_NS))
        assert rig.spin_until(lambda: any(stamp_to_ns(m.transforms[0].header.stamp) == T0_NS for m in got), 10.0)
        frames = [t.child_frame_id for t in got[-1].transforms]
        assert frames[0] == "hand_wrist" and len(frames) == 6
    finally:
        rig.close()
