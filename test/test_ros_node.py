"""The tracker node in-process: outputs, robustness, parameters, calibration, latency.

Each test has its own rclpy context, a unique namespace (so concurrent test runs on the same
machine and domain never see each other's topics) and loopback-only DDS (conftest.py).
"""

from __future__ import annotations

import time
import uuid
from pathlib import Path
from typing import Callable

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseArray, PoseStamped
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, JointState
from std_srvs.srv import Trigger
from visualization_msgs.msg import Marker, MarkerArray

from hand_sog_tracker.core.hand_model import JOINT_NAMES, HandShape, default_hand_model, rest_pose
from hand_sog_tracker.core.kinematics import fingertips
from hand_sog_tracker.core.model_io import load_hand_shape, save_hand_shape
from hand_sog_tracker.core.tracker import Tracker
from hand_sog_tracker.core.types import Intrinsics, TrackerConfig, TrackerStatus
from hand_sog_tracker.ros.conversions import stamp_to_ns
from hand_sog_tracker.ros.node import TrackerNode, make_executor
from hand_sog_tracker.synth.render import RenderOptions, render_depth

#: Principal point at the exact image centre (159.5, 119.5), unlike helpers.INTR (160, 120).
INTR = Intrinsics(fx=287.26, fy=287.26, cx=159.5, cy=119.5, width=320, height=240)
FRAME = "depth_optical"
T0_NS = 1_700_000_000 * 10**9


def hand_poses(n: int) -> list[np.ndarray]:
    """An open hand at 420 mm slowly closing its index and middle fingers."""
    out = []
    for i in range(n):
        th = rest_pose((5.0, 10.0, 420.0))
        th[6 + 4 * 1] = th[6 + 4 * 2] = 0.03 * i
        out.append(th)
    return out


def hand_depth(theta: np.ndarray, seed: int, intr: Intrinsics = INTR, model=None) -> np.ndarray:
    """A rendered depth frame rounded to whole mm (what a 16UC1 camera sends)."""
    model = model or default_hand_model()
    d = render_depth(model, theta, intr, RenderOptions(noise_mm=1.0), rng=np.random.default_rng(seed))
    return np.round(d).astype(np.float32)


def image_msg(depth_mm: np.ndarray, stamp_ns: int, encoding: str = "16UC1", frame: str = FRAME) -> Image:
    msg = Image(height=depth_mm.shape[0], width=depth_mm.shape[1], encoding=encoding, is_bigendian=0)
    if encoding == "32FC1":
        data = (depth_mm / 1000.0).astype("<f4")
    else:
        data = np.round(np.nan_to_num(depth_mm)).astype("<u2")
    msg.step = depth_mm.shape[1] * data.itemsize
    msg.data = data.tobytes()
    msg.header.frame_id = frame
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, 10**9)
    return msg


def info_msg(intr: Intrinsics = INTR, k: list[float] | None = None) -> CameraInfo:
    msg = CameraInfo(width=intr.width, height=intr.height, distortion_model="plumb_bob")
    msg.k = k if k is not None else [intr.fx, 0.0, intr.cx, 0.0, intr.fy, intr.cy, 0.0, 0.0, 1.0]
    msg.header.frame_id = FRAME
    return msg


class Rig:
    """The node under test plus a helper node that plays camera and listener."""

    def __init__(self, context, tmp_path: Path, compressed: bool = False, namespace: str = "", **params) -> None:
        self.ns = namespace or f"/t{uuid.uuid4().hex[:10]}"
        if compressed:
            params["input_transport"] = "compressedDepth"
        # The automatic fit (a child process at half a second of tracking) is off unless a test
        # asks for it: it would compete for the CPU with what the other tests time.
        params.setdefault("auto_calibrate", False)
        # The frame budget cuts a single image's refinement on a busy machine: tests that compare
        # the node's answer with the core's give it all the time it needs.
        params.setdefault("frame_budget_ms", 10000.0)
        overrides = [Parameter("user_model_path", value=str(tmp_path / "hand_model.yaml"))]
        overrides += [Parameter(k, value=v) for k, v in params.items()]
        self.node = TrackerNode(context=context, namespace=self.ns, parameter_overrides=overrides)
        self.io = Node("rig", context=context, namespace=self.ns)
        reliable = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        if compressed:  # what image_transport's compressedDepth plugin publishes
            self.image_pub = self.io.create_publisher(
                CompressedImage, "camera/depth/image_rect_raw/compressedDepth", reliable
            )
        else:
            self.image_pub = self.io.create_publisher(Image, "camera/depth/image_rect_raw", reliable)
        self.info_pub = self.io.create_publisher(CameraInfo, "camera/depth/camera_info", reliable)
        self.joints: list[tuple[JointState, float]] = []
        self.poses: list[PoseStamped] = []
        self.markers: list[MarkerArray] = []
        self.diagnostics: list[DiagnosticArray] = []
        self.io.create_subscription(
            JointState, "hand/joint_states", lambda m: self.joints.append((m, time.perf_counter())), reliable
        )
        self.io.create_subscription(PoseStamped, "hand/pose", self.poses.append, reliable)
        self.io.create_subscription(MarkerArray, "hand/fingertips", self.markers.append, reliable)
        self.io.create_subscription(DiagnosticArray, "/diagnostics", self.diagnostics.append, reliable)
        self.calib = self.io.create_client(Trigger, f"{self.ns}/hand_sog_tracker/calibrate")
        self.executor = make_executor(context)
        self.executor.add_node(self.node)
        self.executor.add_node(self.io)
        pubs = {p.topic_name: p for p in self.node.publishers}
        assert self.spin_until(
            lambda: self.image_pub.get_subscription_count() > 0
            and self.info_pub.get_subscription_count() > 0
            and all(
                pubs[f"{self.ns}/hand/{t}"].get_subscription_count() > 0 for t in ("joint_states", "pose", "fingertips")
            )
        ), "DDS discovery on loopback did not complete"

    def spin_until(self, cond: Callable[[], bool], timeout: float = 15.0) -> bool:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if cond():
                return True
            self.executor.spin_once(timeout_sec=0.01)
        return cond()

    def send_info(self, msg: CameraInfo | None = None) -> None:
        msg = msg or info_msg()
        self.info_pub.publish(msg)
        want = None if not any(msg.k) else (msg.width, msg.height)
        def size() -> tuple[int, int] | None:
            intr = self.node.intrinsics
            return intr and (intr.width, intr.height)

        self.spin_until(lambda: size() == want or want is None, 5.0)

    def send(self, msg: Image | CompressedImage) -> None:
        """Publish one image and wait until the node has processed or rejected it."""
        s = self.node.stats
        before = s.processed + s.rejected
        self.image_pub.publish(msg)
        assert self.spin_until(lambda: self.node.stats.processed + self.node.stats.rejected > before), "frame lost"

    def wait_joint(self, stamp_ns: int, timeout: float = 10.0) -> JointState:
        assert self.spin_until(lambda: any(stamp_to_ns(m.header.stamp) == stamp_ns for m, _ in self.joints), timeout)
        return next(m for m, _ in self.joints if stamp_to_ns(m.header.stamp) == stamp_ns)

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self.io.destroy_node()


@pytest.fixture
def rig(ros_context, tmp_path: Path):
    r = Rig(ros_context, tmp_path)
    yield r
    r.close()


def test_outputs_carry_the_input_stamp_and_frame_and_match_the_core(rig: Rig) -> None:
    rig.send_info()
    reference = Tracker(TrackerConfig())
    model = default_hand_model()
    for i, theta in enumerate(hand_poses(3)):
        depth = hand_depth(theta, seed=i)
        stamp = T0_NS + i * 33_333_333
        rig.send(image_msg(depth, stamp))
        js = rig.wait_joint(stamp)
        expected = reference.process(depth, INTR)  # (issue 45: the node answers what the core does)
        assert expected.status is TrackerStatus.TRACKING
        assert js.header.frame_id == FRAME and tuple(js.name) == JOINT_NAMES
        np.testing.assert_allclose(js.position, expected.pose[6:], atol=1e-9)
    assert rig.spin_until(lambda: len(rig.poses) == 3 and len(rig.markers) == 3, 5.0)
    pose, markers = rig.poses[-1], rig.markers[-1]
    assert stamp_to_ns(pose.header.stamp) == stamp and pose.header.frame_id == FRAME
    p = pose.pose.position
    np.testing.assert_allclose([p.x, p.y, p.z], expected.pose[:3] / 1000.0, atol=1e-12)
    assert abs(p.z - 0.420) < 0.03  # metres, near the rendered hand
    tips = [m for m in markers.markers if m.ns == "fingertips"]
    assert [m.id for m in tips] == [0, 1, 2, 3, 4] and all(m.type == Marker.SPHERE for m in tips)
    assert all(stamp_to_ns(m.header.stamp) == stamp and m.header.frame_id == FRAME for m in markers.markers)
    got = np.array([[m.pose.position.x, m.pose.position.y, m.pose.position.z] for m in tips]) * 1000.0
    np.testing.assert_allclose(got, expected.fingertips_mm, atol=1e-6)
    # Units and frame: the published fingertips sit on the rendered hand (metres -> mm).
    assert np.linalg.norm(got.mean(axis=0) - fingertips(model, theta).mean(axis=0)) < 40.0
    assert [m.type for m in markers.markers if m.ns == "skeleton"] == [Marker.LINE_LIST]
    s = rig.node.stats
    assert (s.received, s.processed, s.dropped, s.missed, s.rejected) == (3, 3, 0, 0, 0)
    assert s.status is TrackerStatus.TRACKING and s.confidence > 0.35


def test_an_output_nobody_subscribes_to_is_not_built(rig: Rig, monkeypatch) -> None:
    """hand/keypoints has no subscriber in the rig: no message is built for it (issue 14: each
    publication costs the node 0.2-0.5 ms) until one subscribes."""
    import hand_sog_tracker.ros.hand_topics as topics_module

    built: list[int] = []
    real = topics_module.keypoints_msg
    monkeypatch.setattr(topics_module, "keypoints_msg", lambda *a, **k: built.append(1) or real(*a, **k))
    rig.send_info()
    depths = [hand_depth(theta, seed=i) for i, theta in enumerate(hand_poses(2))]
    rig.send(image_msg(depths[0], T0_NS))
    assert rig.wait_joint(T0_NS) and built == []
    received: list[PoseArray] = []
    reliable = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    rig.io.create_subscription(PoseArray, "hand/keypoints", received.append, reliable)
    pub = next(p for p in rig.node.publishers if p.topic_name == f"{rig.ns}/hand/keypoints")
    assert rig.spin_until(lambda: pub.get_subscription_count() > 0), "DDS discovery on loopback did not complete"
    rig.send(image_msg(depths[1], T0_NS + 33_333_333))
    assert rig.spin_until(lambda: len(received) == 1, 5.0) and built == [1]
    assert stamp_to_ns(received[0].header.stamp) == T0_NS + 33_333_333


def test_bad_inputs_are_skipped_with_a_reason_and_the_next_good_frame_is_tracked(rig: Rig, capfd) -> None:
    good = hand_depth(hand_poses(1)[0], seed=7)
    stamp = T0_NS

    def expect_rejected(msg: Image, words: str) -> None:
        rejected = rig.node.stats.rejected
        rig.send(msg)
        s = rig.node.stats
        assert s.rejected == rejected + 1, (words, s)
        assert words in s.last_problem, (words, s.last_problem)

    def next_stamp() -> int:
        nonlocal stamp
        stamp += 33_333_333
        return stamp

    expect_rejected(image_msg(good, next_stamp()), "no CameraInfo received yet")
    rig.send_info()
    wrong = image_msg(good, next_stamp())
    wrong.encoding = "rgb8"
    expect_rejected(wrong, "unsupported depth encoding 'rgb8'")
    short = image_msg(good, next_stamp())
    short.data = bytes(short.data)[: len(short.data) // 2]
    expect_rejected(short, "truncated")
    narrow = image_msg(good, next_stamp())
    narrow.step = 100
    expect_rejected(narrow, "step 100 is smaller")
    empty = image_msg(good, next_stamp())
    empty.height, empty.width, empty.step, empty.data = 0, 0, 0, b""
    expect_rejected(empty, "zero size")
    expect_rejected(image_msg(good[::2, ::2].copy(), next_stamp()), "image is 160x120 but CameraInfo is 320x240")
    expect_rejected(image_msg(good, stamp - 10**9), "stamp went backwards")
    rig.send_info(info_msg(k=[0.0] * 9))
    expect_rejected(image_msg(good, next_stamp()), "K is all zeros")
    rig.send_info()

    # Frames that are valid but useless: processed, no hand, no crash.
    processed = rig.node.stats.processed
    rig.send(image_msg(np.zeros_like(good), next_stamp()))
    all_nan = np.full_like(good, np.nan)
    rig.send(image_msg(all_nan, next_stamp(), encoding="32FC1"))
    holes = good.copy()
    holes[::3] = np.inf
    rig.send(image_msg(holes, next_stamp(), encoding="32FC1"))
    assert rig.node.stats.processed == processed + 3

    last = next_stamp()
    rig.send(image_msg(good, last))
    js = rig.wait_joint(last)
    assert js.header.frame_id == FRAME and len(js.position) == 20
    s = rig.node.stats
    assert s.rejected == 8 and s.status is TrackerStatus.TRACKING
    err = capfd.readouterr().err
    for words in ("no CameraInfo received yet", "unsupported depth encoding", "truncated", "zero size",
                  "CameraInfo is 320x240", "resolution changed", "went backwards", "K is all zeros",
                  "no valid pixels"):
        assert words in err, words


def test_lost_hand_clears_the_markers(rig: Rig) -> None:
    rig.send_info()
    depth = hand_depth(hand_poses(1)[0], seed=3)
    rig.send(image_msg(depth, T0_NS))
    rig.wait_joint(T0_NS)
    for k in range(1, 5):  # the hand leaves: the tracker reports LOST / NO_HAND within a few frames
        rig.send(image_msg(np.zeros_like(depth), T0_NS + k * 10**8))
    assert rig.spin_until(lambda: any(m.action == Marker.DELETEALL for a in rig.markers for m in a.markers), 5.0)
    assert rig.node.stats.status is not TrackerStatus.TRACKING


def test_resolution_change_needs_a_matching_camera_info(rig: Rig) -> None:
    rig.send_info()
    theta = hand_poses(1)[0]
    rig.send(image_msg(hand_depth(theta, seed=1), T0_NS))
    rig.wait_joint(T0_NS)
    big = INTR.scaled(2.0)
    frame = image_msg(hand_depth(theta, seed=2, intr=big), T0_NS + 10**8)
    rig.send(frame)
    assert "image is 640x480 but CameraInfo is 320x240" in rig.node.stats.last_problem
    rig.send_info(info_msg(big))
    stamp = T0_NS + 2 * 10**8
    rig.send(image_msg(hand_depth(theta, seed=3, intr=big), stamp))
    js = rig.wait_joint(stamp)
    assert len(js.position) == 20 and rig.node.stats.rejected == 1


def test_an_image_beyond_max_image_pixels_makes_the_image_subscription_anew(rig: Rig) -> None:
    """The middleware kept a buffer of the rejected image's size for the subscription's life
    (test_ros_node_memory); made anew, the subscription receives again."""
    rig.send_info()
    theta = hand_poses(1)[0]
    rig.send(image_msg(hand_depth(theta, seed=1), T0_NS))
    rig.wait_joint(T0_NS)
    big = image_msg(np.zeros((1, 1)), T0_NS + 10**8)
    big.width, big.height, big.step = 2000, 2000, 4000
    big.data = bytes(2000 * 4000)
    rig.send(big)
    assert "more than max_image_pixels" in rig.node.stats.last_problem
    assert rig.spin_until(lambda: rig.node.renewals == 1, 5.0)
    # (Images published before the new subscription matched are lost: publish until one is tracked.)
    stamps = [T0_NS + (2 + k) * 10**8 for k in range(50)]
    for stamp in stamps:
        rig.image_pub.publish(image_msg(hand_depth(theta, seed=2), stamp))
        if rig.spin_until(lambda: any(stamp_to_ns(m.header.stamp) in stamps for m, _ in rig.joints), 0.2):
            break
    assert any(stamp_to_ns(m.header.stamp) in stamps for m, _ in rig.joints), "nothing tracked after the renewal"
    assert rig.node.renewals == 1  # (a resolution change or a clean image renews nothing)


def test_runtime_parameter_changes_reach_the_tracker(rig: Rig) -> None:
    bad = rig.node.set_parameters([Parameter("far_mm", value=100.0)])[0]
    assert not bad.successful and "near_mm < far_mm" in bad.reason
    assert rig.node.set_parameters([Parameter("iterations", value=4)])[0].successful
    rig.send_info()
    rig.send(image_msg(hand_depth(hand_poses(1)[0], seed=1), T0_NS))
    assert rig.node._tracker.config.iterations == 4


def _burst(rig: Rig, n: int, period_ns: int = 10**7) -> tuple[list[np.ndarray], list[int]]:
    """Publish ``n`` frames of a hand (stamps ``period_ns`` apart) while nobody spins, and wait
    until DDS holds them all: the node then finds them waiting at once, as after a long frame."""
    frames = [hand_depth(th, seed=i) for i, th in enumerate(hand_poses(n))]
    stamps = [T0_NS + i * period_ns for i in range(n)]
    for depth, stamp in zip(frames, stamps):
        rig.image_pub.publish(image_msg(depth, stamp))
    time.sleep(0.5)
    return frames, stamps


def _settle(rig: Rig, n: int) -> None:
    """Spin until the node has handled (processed, rejected or dropped) ``n`` frames, and a bit more."""
    assert rig.spin_until(lambda: (lambda s: s.processed + s.rejected + s.dropped)(rig.node.stats) >= n, 30.0)
    rig.spin_until(lambda: False, 0.3)  # (anything else would arrive now)


def test_a_burst_within_max_lag_is_tracked_in_order_as_the_core_tracks_it(rig: Rig) -> None:
    """A 100 Hz burst that arrives while the node is busy (the first frame starts a track, ~100
    ms): every frame is tracked, in order, with the answers of the core tracker."""
    rig.send_info()
    frames, stamps = _burst(rig, 8)
    _settle(rig, 8)
    s = rig.node.stats
    assert (s.received, s.processed, s.dropped, s.rejected) == (8, 8, 0, 0), s
    assert [stamp_to_ns(m.header.stamp) for m, _ in rig.joints] == stamps
    reference = Tracker(TrackerConfig())
    for (js, _), depth in zip(rig.joints, frames):
        expected = reference.process(depth, INTR)
        np.testing.assert_allclose(js.position, expected.pose[6:], atol=1e-9)


def test_a_backlog_older_than_max_lag_is_dropped_whole_from_its_oldest_frame(ros_context, tmp_path: Path) -> None:
    """max_lag_ms 25 with a 90 ms burst waiting: the frames more than 25 ms behind the newest are
    dropped (counted), the last three tracked in order; max_lag_ms 0 tracks only the newest."""
    rig = Rig(ros_context, tmp_path, max_lag_ms=25.0)
    try:
        rig.send_info()
        _, stamps = _burst(rig, 10)
        _settle(rig, 10)
        s = rig.node.stats
        assert (s.received, s.processed, s.dropped, s.rejected) == (10, 3, 7, 0), s
        assert [stamp_to_ns(m.header.stamp) for m, _ in rig.joints] == stamps[-3:]
        rig.node.set_parameters([Parameter("max_lag_ms", value=0.0)])
        rig.joints.clear()
        frames = [hand_depth(th, seed=i) for i, th in enumerate(hand_poses(16))][10:]
        later = [stamps[-1] + (i + 1) * 10**7 for i in range(6)]
        for depth, stamp in zip(frames, later):
            rig.image_pub.publish(image_msg(depth, stamp))
        time.sleep(0.5)
        _settle(rig, 16)
        s = rig.node.stats
        assert (s.processed, s.dropped) == (4, 12), s
        assert [stamp_to_ns(m.header.stamp) for m, _ in rig.joints] == later[-1:]
        values = _diagnostics_values(rig)
        assert values["frames_dropped"] == "12" and float(values["backlog_ms"]) >= 0.0
    finally:
        rig.close()


def test_a_qos_override_of_the_depth_bounds_the_backlog(ros_context, tmp_path: Path) -> None:
    """``qos_overrides.<topic>.subscription.depth: 1`` keeps only the newest image, in DDS and in
    the node's backlog."""
    ns = f"/t{uuid.uuid4().hex[:10]}"
    key = f"qos_overrides.{ns}/camera/depth/image_rect_raw.subscription.depth"
    rig = Rig(ros_context, tmp_path, namespace=ns, **{key: 1})
    try:
        assert rig.node._image_sub.qos_profile.depth == 1
        rig.send_info()
        _, stamps = _burst(rig, 5)
        assert rig.spin_until(lambda: rig.node.stats.processed >= 1, 30.0)
        rig.spin_until(lambda: False, 0.3)
        assert [stamp_to_ns(m.header.stamp) for m, _ in rig.joints] == stamps[-1:]
        assert rig.node.stats.received == 1
    finally:
        rig.close()


def test_each_frame_of_a_backlog_gets_the_camera_info_of_its_stamp(rig: Rig) -> None:
    """CameraInfo that arrives after its image (same stamp) but before it is processed pairs with
    it, not with the images before it."""
    rig.send_info()
    frames = [hand_depth(th, seed=i) for i, th in enumerate(hand_poses(6))]
    stamps = [T0_NS + i * 10**7 for i in range(6)]
    other = Intrinsics(fx=574.5, fy=574.5, cx=319.5, cy=239.5, width=640, height=480)
    for depth, stamp in zip(frames, stamps):
        rig.image_pub.publish(image_msg(depth, stamp))
    for i, stamp in enumerate(stamps):
        info = info_msg(INTR if i < 3 else other)
        info.header.stamp.sec, info.header.stamp.nanosec = divmod(stamp, 10**9)
        rig.info_pub.publish(info)
    time.sleep(0.5)
    _settle(rig, 6)
    s = rig.node.stats
    assert (s.processed, s.rejected, s.dropped) == (3, 3, 0), s
    assert "CameraInfo is 640x480" in s.last_problem
    assert [stamp_to_ns(m.header.stamp) for m, _ in rig.joints] == stamps[:3]


def _diagnostics_values(rig: Rig) -> dict[str, str]:
    """The values of the node's next /diagnostics report."""
    name = f"hand_sog_tracker: {rig.ns}/hand_sog_tracker"
    n = len(rig.diagnostics)
    assert rig.spin_until(lambda: any(s.name == name for d in rig.diagnostics[n:] for s in d.status), 3.0)
    status = next(s for d in rig.diagnostics[n:] for s in d.status if s.name == name)
    return {kv.key: kv.value for kv in status.values}


def test_calibrate_fails_cleanly_without_frames(rig: Rig) -> None:
    assert rig.calib.wait_for_service(timeout_sec=5.0)
    future = rig.calib.call_async(Trigger.Request())
    assert rig.spin_until(future.done, 10.0)
    answer = future.result()
    assert answer.success is False and "no depth frames received yet" in answer.message


def test_calibrate_fits_saves_and_a_new_node_loads_the_model(
    ros_context, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The service plumbing: fit on the last frame, switch the tracker, save, reload on start.

    (How well the fit recovers the true shape is the core's business: test_core_calibration.
    The real fit runs, without its guard: on four frames of a hand held still the guard
    answers "the current model already fits"; here a guard's verdict that accepts stands in.)
    """
    from dataclasses import replace

    from test_core_calibration import _rows

    from hand_sog_tracker.core import calibration
    from hand_sog_tracker.ros import calibration_service

    def fit_without_guard(frames, intrinsics, config, model, start_pose=None, **kwargs):  # type: ignore[no-untyped-def]
        kwargs.pop("holdout"), kwargs.pop("holdout_poses")
        res = calibration.calibrate(frames, intrinsics, config, model, start_pose, **kwargs)
        good = calibration.Validation(**_rows([0.02] * 3, [0.0] * 3, [0.02] * 3, [0.0] * 3))
        return replace(res, validation=good)

    monkeypatch.setattr(calibration_service, "calibrate", fit_without_guard)
    monkeypatch.setattr(calibration_service, "FIT_IN_PROCESS", False)
    model = default_hand_model().scaled(HandShape(length=1.1, width=1.05, depth=1.0, sigma=1.0))
    # (The renderer's wall at 900 mm left outside the depth window: with it inside, this fit on a
    # single frame comes out 4% long and the guard refuses it; see the README's limitations.)
    rig = Rig(ros_context, tmp_path, calibration_frames=1, far_mm=600.0)
    try:
        rig.send_info()
        th = rest_pose((0.0, 20.0, 430.0))
        for i in range(4):
            rig.send(image_msg(hand_depth(th, seed=i, model=model), T0_NS + i * 10**8))
        future = rig.calib.call_async(Trigger.Request())
        assert rig.spin_until(future.done, 90.0)
        answer = future.result()
        assert answer.success, answer.message
        assert "(1 frames" in answer.message and "saved to" in answer.message
        shape, right = load_hand_shape(tmp_path / "hand_model.yaml")
        assert right and f"length={shape.length:.3f} width={shape.width:.3f}" in answer.message
        before, after = (float(x) for x in answer.message.split("fit score ")[1].split(" (")[0].split(" -> "))
        # (The fit frames' score is reported, not a rule: with measured widths and per-finger
        # lengths, scored at the refitted finger poses, it may end below the start; the guard decides.)
        assert 0.0 < before <= 1.0 and 0.0 < after <= 1.0
        assert rig.node.hand_model.shape == shape
        stamp = T0_NS + 5 * 10**8  # tracking goes on with the calibrated model
        rig.send(image_msg(hand_depth(th, seed=5, model=model), stamp))
        rig.wait_joint(stamp)
    finally:
        rig.close()
    again = Rig(ros_context, tmp_path)
    try:
        assert again.node.hand_model.shape == shape
    finally:
        again.close()


def test_malformed_user_model_is_ignored_with_a_warning(ros_context, tmp_path: Path, capfd) -> None:
    (tmp_path / "hand_model.yaml").write_text("format: something else\n")
    node = TrackerNode(
        context=ros_context, parameter_overrides=[Parameter("user_model_path", value=str(tmp_path / "hand_model.yaml"))]
    )
    try:
        assert node.hand_model.shape == HandShape()
    finally:
        node.destroy_node()
    assert "ignoring the user hand model" in capfd.readouterr().err
    save_hand_shape(tmp_path / "left.yaml", HandShape(sigma=1.2), right=False)
    node = TrackerNode(
        context=ros_context, parameter_overrides=[Parameter("user_model_path", value=str(tmp_path / "left.yaml"))]
    )
    try:
        assert node.hand_model.shape == HandShape(sigma=1.2) and node.hand_model.right
    finally:
        node.destroy_node()
    assert "calibrated on a left hand" in capfd.readouterr().err


def test_diagnostics_report_rates_and_counters(rig: Rig) -> None:
    rig.send_info()
    for i in range(3):
        rig.send(image_msg(hand_depth(hand_poses(1)[0], seed=i), T0_NS + i * 10**8))
    name = f"hand_sog_tracker: {rig.ns}/hand_sog_tracker"

    def reports() -> list[dict[str, str]]:
        return [{kv.key: kv.value for kv in s.values} for d in rig.diagnostics for s in d.status if s.name == name]

    # A report published while the frames were still being sent counts fewer: wait for a later one.
    assert rig.spin_until(lambda: any(v.get("frames_processed") == "3" for v in reports()), 3.0), reports()
    status = next(s for d in rig.diagnostics for s in d.status
                  if s.name == name and {kv.key: kv.value for kv in s.values}.get("frames_processed") == "3")
    values = {kv.key: kv.value for kv in status.values}
    assert {"input_rate_hz", "output_rate_hz", "processing_ms", "answer_ms", "latency_ms", "status", "confidence",
            "frames_dropped", "frames_missed", "frames_rejected"} <= set(values)
    assert values["frames_processed"] == "3" and values["frames_rejected"] == "0"
    assert float(values["processing_ms"]) > 0 and status.hardware_id == FRAME
    # The answer (result published) comes within the processing (the restarts run after it).
    assert 0 < float(values["answer_ms"]) <= float(values["processing_ms"])


def test_end_to_end_latency(rig: Rig) -> None:
    """Publish -> JointState receipt while tracking, one frame at a time (numbers in the report).

    What the node adds to its own processing of the frame (DDS both ways, the conversion, the
    executor's wake-up) is judged, not the processing itself: that scales with the machine's
    load, which the speed targets of the benchmark command measure."""
    rig.send_info()
    frames = [hand_depth(th, seed=i) for i, th in enumerate(hand_poses(15))]
    node, process = rig.node, rig.node._process_pending
    proc: list[float] = []

    def timed() -> None:
        t = time.perf_counter()
        process()
        proc.append((time.perf_counter() - t) * 1e3)

    node._process_pending = timed
    lat = []
    for i, d in enumerate(frames):
        stamp = T0_NS + i * 33_333_333
        msg = image_msg(d, stamp)
        proc.clear()
        t0 = time.perf_counter()
        rig.image_pub.publish(msg)
        rig.wait_joint(stamp)
        t1 = next(t for m, t in rig.joints if stamp_to_ns(m.header.stamp) == stamp)
        lat.append(((t1 - t0) * 1e3, sum(proc)))
    tracking = np.array(lat[1:])  # the first frame initialises the track
    overhead = tracking[:, 0] - tracking[:, 1]
    print(f"latency ms: first {lat[0][0]:.1f}, tracking median {np.median(tracking[:, 0]):.1f}, "
          f"p95 {np.percentile(tracking[:, 0], 95):.1f}; processing median {np.median(tracking[:, 1]):.1f}, "
          f"the rest median {np.median(overhead):.1f}")
    assert np.all(tracking[:, 1] > 0)  # (every frame was processed on its way)
    assert np.median(overhead) < 50.0  # loose: the machine may be busy (measured: 5-10 ms at load 18)


def test_hand_confidence_is_published_for_every_processed_frame(rig: Rig) -> None:
    """hand/confidence (issue 46): one message per processed frame with the image's stamp, a hand
    with present = 1 and a high confidence, and "no hand" (present = 0) for a frame without one
    or with a wall where the hand was; no markers or pose for those."""
    from hand_sog_tracker.interface import CONFIDENCE_NAMES

    got: list[JointState] = []
    reliable = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    rig.io.create_subscription(JointState, "hand/confidence", got.append, reliable)
    pub = next(p for p in rig.node.publishers if p.topic_name == f"{rig.ns}/hand/confidence")
    assert rig.spin_until(lambda: pub.get_subscription_count() > 0), "DDS discovery on loopback did not complete"
    rig.send_info()
    depth = hand_depth(hand_poses(1)[0], seed=5)
    frames = [depth, np.full_like(depth, 432.0), np.zeros_like(depth)]
    stamps = [T0_NS + k * 33_333_333 for k in range(3)]
    for d, s in zip(frames, stamps):
        rig.send(image_msg(d, s))
    assert rig.spin_until(lambda: len(got) == 3, 5.0)
    by = {stamp_to_ns(m.header.stamp): m for m in got}
    assert sorted(by) == stamps and all(m.header.frame_id == FRAME for m in got)
    assert all(tuple(m.name) == CONFIDENCE_NAMES for m in got)
    hand, wall, empty = (by[s].position for s in stamps)
    assert hand[0] == 1.0 and hand[1] > 0.5 and min(hand[2:]) > 0.3
    assert wall[0] == 0.0 and wall[1] < 0.2
    assert empty[0] == 0.0 and empty[1] == 0.0
    assert [stamp_to_ns(p.header.stamp) for p in rig.poses] == stamps[:1]
