"""The node with max_hands 2: per-hand topics, joint and frame names, one URDF per hand."""

from __future__ import annotations

import time
import uuid
from pathlib import Path

import numpy as np
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, Image, JointState
from std_msgs.msg import Header, String
from visualization_msgs.msg import MarkerArray

from hand_sog_tracker.core.hand_model import JOINT_NAMES
from hand_sog_tracker.core.hands import HANDS, HandsResult
from hand_sog_tracker.core.types import HandDecision, Intrinsics
from hand_sog_tracker.core.urdf import urdf_joints
from hand_sog_tracker.ros.conversions import stamp_to_ns
from hand_sog_tracker.ros.hand_topics import per_hand_topic
from hand_sog_tracker.ros.node import TrackerNode, make_executor
from hand_sog_tracker.tools.bagio import BagTopics, DepthBagReader
from hand_sog_tracker.tools.twohand_bags import read_hand_truth

APART = Path(__file__).resolve().parents[1] / "bags" / "twohands_dev" / "apart"
FRAME = "depth_optical"


def _image(depth_mm: np.ndarray, stamp_ns: int) -> Image:
    msg = Image(height=depth_mm.shape[0], width=depth_mm.shape[1], encoding="16UC1", is_bigendian=0)
    msg.step = depth_mm.shape[1] * 2
    msg.data = np.round(np.nan_to_num(depth_mm)).astype("<u2").tobytes()
    msg.header.frame_id = FRAME
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, 10**9)
    return msg


def test_two_hands_are_published_per_hand_with_prefixed_names(ros_context, tmp_path: Path) -> None:
    ns = f"/t{uuid.uuid4().hex[:10]}"
    params = {"max_hands": 2, "auto_calibrate": False, "frame_budget_ms": 10000.0}
    overrides = [Parameter("user_model_path", value=str(tmp_path / "hand_model.yaml"))]
    overrides += [Parameter(k, value=v) for k, v in params.items()]
    node = TrackerNode(context=ros_context, namespace=ns, parameter_overrides=overrides)
    io = Node("rig", context=ros_context, namespace=ns)
    reliable = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    image_pub = io.create_publisher(Image, "camera/depth/image_rect_raw", reliable)
    info_pub = io.create_publisher(CameraInfo, "camera/depth/camera_info", reliable)
    joints: dict[str, list[JointState]] = {"left": [], "right": []}
    tips: dict[str, list[MarkerArray]] = {"left": [], "right": []}
    urdf: dict[str, list[String]] = {"left": [], "right": []}
    one_hand: list[JointState] = []
    for side in ("left", "right"):
        io.create_subscription(JointState, per_hand_topic(side, "joint_states"), joints[side].append, reliable)
        io.create_subscription(MarkerArray, per_hand_topic(side, "fingertips"), tips[side].append, reliable)
        io.create_subscription(String, per_hand_topic(side, "robot_description"), urdf[side].append, latched)
    io.create_subscription(JointState, "hand/joint_states", one_hand.append, reliable)
    executor = make_executor(ros_context)
    executor.add_node(node)
    executor.add_node(io)

    def spin_until(cond, timeout: float = 20.0) -> bool:
        end = time.monotonic() + timeout
        while time.monotonic() < end and not cond():
            executor.spin_once(timeout_sec=0.01)
        return bool(cond())

    try:
        pubs = {p.topic_name: p for p in node.publishers}
        assert spin_until(
            lambda: image_pub.get_subscription_count() > 0
            and all(pubs[f"{ns}/{per_hand_topic(s, 'joint_states')}"].get_subscription_count() for s in HANDS)
            and pubs[f"{ns}/hand/joint_states"].get_subscription_count() > 0
        )
        truth = read_hand_truth(APART)
        truth_at: dict[int, dict[str, np.ndarray]] = {}
        with DepthBagReader(APART, BagTopics(), require_truth=False) as reader:
            for f in reader.frames():
                if f.index >= 10:
                    break
                intr = f.intrinsics
                info = CameraInfo(width=intr.width, height=intr.height, distortion_model="plumb_bob")
                info.k = [intr.fx, 0.0, intr.cx, 0.0, intr.fy, intr.cy, 0.0, 0.0, 1.0]
                info.header.frame_id = FRAME
                info_pub.publish(info)
                before = node.stats.processed + node.stats.rejected
                stamp = 1_700_000_000 * 10**9 + f.index * 33_333_333
                last = _image(f.depth_mm, stamp)
                image_pub.publish(last)
                assert spin_until(lambda b=before: node.stats.processed + node.stats.rejected > b)
                truth_at[stamp] = {s: truth[s][f.stamp_ns].fingertips_mm for s in HANDS}
        assert spin_until(lambda: all(joints[s] and tips[s] for s in ("left", "right")) and bool(one_hand), 10.0)
        for side in ("left", "right"):
            js = joints[side][-1]
            assert tuple(js.name) == tuple(f"{side}_{n}" for n in JOINT_NAMES) and js.header.frame_id == FRAME
            for msg in tips[side]:  # each label on its own hand (the other is about 230 mm away)
                m = [k for k in msg.markers if k.ns == "fingertips"]
                got = np.array([[k.pose.position.x, k.pose.position.y, k.pose.position.z] for k in m]) * 1000.0
                gt = truth_at[stamp_to_ns(m[0].header.stamp)][side]
                assert np.linalg.norm(got - gt, axis=1).mean() < 25.0
            assert spin_until(lambda s=side: bool(urdf[s]), 5.0)
            text = urdf[side][-1].data
            names = {j.name for j in urdf_joints(text)}
            assert names >= {f"{side}_{n}" for n in JOINT_NAMES}
            assert f'link name="{side}_hand_wrist"' in text
        # The one-hand topic carries the hand labelled with handedness (right), unprefixed.
        assert tuple(one_hand[-1].name) == JOINT_NAMES
        assert stamp_to_ns(one_hand[-1].header.stamp) == stamp_to_ns(joints["right"][-1].header.stamp)
        np.testing.assert_allclose(one_hand[-1].position, joints["right"][-1].position)
        # The last image again, with its stamp: the same answer on every hand's topics too.
        assert spin_until(lambda: all(stamp_to_ns(joints[s][-1].header.stamp) == stamp for s in HANDS), 5.0)
        sent = {s: len(joints[s]) for s in HANDS}
        image_pub.publish(last)
        assert spin_until(lambda: all(len(joints[s]) > sent[s] for s in HANDS), 10.0)
        for side in HANDS:
            assert stamp_to_ns(joints[side][-1].header.stamp) == stamp
            np.testing.assert_array_equal(joints[side][-1].position, joints[side][sent[side] - 1].position)
    finally:
        executor.shutdown()
        node.destroy_node()
        io.destroy_node()


def test_the_one_hand_confidence_of_a_withheld_hand_is_its_checks(ros_context, tmp_path: Path) -> None:
    """max_hands 2: when the gate withholds the hand labelled ``handedness``, the one-hand result
    (what ``hand/confidence`` publishes) carries that check's decision, not a zero."""
    overrides = [Parameter("user_model_path", value=str(tmp_path / "hand_model.yaml"))]
    overrides += [Parameter("max_hands", value=2), Parameter("auto_calibrate", value=False)]
    node = TrackerNode(context=ros_context, namespace=f"/t{uuid.uuid4().hex[:10]}", parameter_overrides=overrides)
    try:
        held = HandDecision(False, 0.13, np.array([0.1, 0.2, 0.3, 0.4, 0.5]), None)
        assert node._hands is not None
        node._hands.process = lambda depth, intr: HandsResult((), {"total": 1.0}, {"right": held})  # type: ignore[method-assign]
        intr = Intrinsics(300.0, 300.0, 160.0, 120.0, 320, 240)
        result = node._process_hands(Header(frame_id=FRAME), np.zeros((240, 320), np.float32), intr)
        assert result.pose is None and result.hand is held
        node._hands.process = lambda depth, intr: HandsResult((), {"total": 1.0}, {"left": held})  # type: ignore[method-assign]
        result = node._process_hands(Header(frame_id=FRAME), np.zeros((240, 320), np.float32), intr)
        assert result.hand is not None and result.hand.confidence == 0.0 and not result.hand.present
    finally:
        node.destroy_node()
