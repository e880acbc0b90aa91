"""max_hands 2 through the node: each hand's saved model, ``~/calibrate`` per hand.

Uses the in-process rig of test_ros_node.py (own rclpy context, unique namespace, loopback DDS,
the ROS_HOME and domain of conftest.py) and the frames of the shipped two-hand dev bag 'apart'.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo
from std_msgs.msg import String
from std_srvs.srv import Trigger
from test_core_calibration import _rows

from hand_sog_tracker.core.calibration import CalibrationRejected, CalibrationResult, Validation
from hand_sog_tracker.core.hand_model import HandShape, default_hand_model
from hand_sog_tracker.core.hands import HANDS
from hand_sog_tracker.core.model_io import load_hand_shape, read_calibration_info, save_hand_shape, side_model_path
from hand_sog_tracker.core.urdf import hand_urdf
from hand_sog_tracker.ros import calibration_service
from hand_sog_tracker.ros.hand_topics import per_hand_topic
from hand_sog_tracker.tools.bagio import BagTopics, DepthBagReader
from hand_sog_tracker.tools.twohand_bags import read_hand_truth
from test_ros_node import FRAME, T0_NS, Rig, image_msg

APART = Path(__file__).resolve().parents[1] / "bags" / "twohands_dev" / "apart"
PERIOD_NS = 33_333_333


def _apart(n: int):
    """The first ``n`` frames of the dev bag 'apart': (depth mm, intrinsics, truth keypoints per side)."""
    truth = read_hand_truth(APART)
    out = []
    with DepthBagReader(APART, BagTopics(), require_truth=False) as reader:
        for f in reader.frames():
            if f.index >= n:
                break
            out.append((f.depth_mm, f.intrinsics, {s: truth[s][f.stamp_ns].keypoints_mm for s in HANDS}))
    return out


def _info(intr) -> CameraInfo:
    msg = CameraInfo(width=intr.width, height=intr.height, distortion_model="plumb_bob")
    msg.k = [intr.fx, 0.0, intr.cx, 0.0, intr.fy, intr.cy, 0.0, 0.0, 1.0]
    msg.header.frame_id = FRAME
    return msg


def _track(rig: Rig, frames) -> None:
    """Send the frames at 30 Hz stamps, each processed before the next (none dropped)."""
    rig.send_info(_info(frames[0][1]))
    for k, (depth, _, _) in enumerate(frames):
        rig.send(image_msg(depth, T0_NS + k * PERIOD_NS))


def _description(rig: Rig, side: str) -> str:
    got: list[String] = []
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    rig.io.create_subscription(String, per_hand_topic(side, "robot_description"), got.append, latched)
    assert rig.spin_until(lambda: bool(got), 10.0), f"no robot_description of the {side} hand"
    return got[-1].data


def _urdf(shape: HandShape, side: str) -> str:
    """The per-hand URDF the node publishes for the ``side`` hand of ``shape`` (frame_prefix empty)."""
    model = default_hand_model(side == "right").scaled(shape)
    return hand_urdf(model, name=f"{side}_hand", prefix=f"{side}_", joint_prefix=f"{side}_")


def test_a_saved_model_is_used_for_both_hands_and_a_hands_own_file_for_that_hand(ros_context, tmp_path: Path) -> None:
    """max_hands 2: the user model (saved on the right hand) is each hand's shape, mirrored for
    the left; it is in the trackers and in each hand's robot_description.  A hand's own file
    (side_model_path, what ~/calibrate saves with two hands) wins for that hand."""
    shared = HandShape(length=1.08, width=0.95, depth=1.02, sigma=1.04)
    save_hand_shape(tmp_path / "hand_model.yaml", shared, right=True)
    rig = Rig(ros_context, tmp_path, max_hands=2)
    try:
        models = rig.node.hand_models
        assert {s: m.shape for s, m in models.items()} == {"left": shared, "right": shared}
        assert models["right"].right and not models["left"].right
        for side in HANDS:
            assert rig.node._hands._new_tracker(side).model.shape == shared  # (a new track starts with it)
            assert _description(rig, side) == _urdf(shared, side)
        assert rig.node.hand_model.shape == shared  # (the one-hand topics' hand: handedness right)
    finally:
        rig.close()
    own = HandShape(length=0.92, width=1.06, depth=0.97, sigma=0.96)
    save_hand_shape(side_model_path(tmp_path / "hand_model.yaml", "left"), own, right=False)
    rig = Rig(ros_context, tmp_path, max_hands=2)
    try:
        assert {s: m.shape for s, m in rig.node.hand_models.items()} == {"left": own, "right": shared}
        assert _description(rig, "left") == _urdf(own, "left")
        assert _description(rig, "right") == _urdf(shared, "right")
    finally:
        rig.close()


def test_each_hand_is_fitted_on_its_own_frames_and_the_answer_says_which_fit_was_refused(
    ros_context, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """~/calibrate with two hands tracked: one fit per hand, with that hand's handedness, on its
    own frames (the other hand's pixels left out) and poses.  A stand-in guard accepts the
    right hand's fit and refuses the left's: the answer says so per hand, the right hand
    switches to its fit, which is saved to its own file, and the left hand keeps its model."""
    frames = _apart(16)
    shape = HandShape(1.06, 0.97, 1.0, 1.02)
    good = Validation(**_rows([0.02, 0.03, 0.025, 0.02], [-1.0] * 4, [0.03, 0.02, 0.04, 0.03], [0.0] * 4))
    bad = Validation(**_rows([-0.02, -0.01, -0.012, -0.015], [0.0] * 4, [-0.02, -0.01, -0.012], [0.0] * 4))
    calls: dict[str, tuple] = {}

    def fit(depths, intrinsics, config, model, start_pose=None, **kwargs):  # type: ignore[no-untyped-def]
        side = "right" if config.right_hand else "left"
        assert model.right == config.right_hand
        calls[side] = (list(depths) + list(kwargs["holdout"]), kwargs["poses"])
        if side == "left":
            raise CalibrationRejected(HandShape(0.9, 0.9, 0.9, 0.9), bad)
        poses = np.array(kwargs["poses"])
        used = tuple(range(len(depths)))
        return CalibrationResult(shape, model.scaled(shape), poses[0], 0.80, 0.83, 0.3, poses, used, good)

    monkeypatch.setattr(calibration_service, "calibrate", fit)
    monkeypatch.setattr(calibration_service, "FIT_IN_PROCESS", False)
    rig = Rig(ros_context, tmp_path, max_hands=2)
    try:
        _track(rig, frames)
        before = rig.node.hand_models
        future = rig.calib.call_async(Trigger.Request())
        assert rig.spin_until(future.done, 30.0)
        answer = future.result()
        left, right = answer.message.split(" | ")
        assert answer.success, answer.message
        assert left.startswith("left hand: calibration rejected, nothing changed or saved") and "held-out score" in left
        right_file = side_model_path(tmp_path / "hand_model.yaml", "right")
        assert right.startswith("right hand: length=1.060") and f"saved to {right_file}" in right
        assert load_hand_shape(right_file) == (shape, True)
        assert read_calibration_info(right_file)["holdout_frames"] >= 1
        assert not side_model_path(tmp_path / "hand_model.yaml", "left").exists()
        assert not (tmp_path / "hand_model.yaml").exists()  # (the one-hand file is not written)
        models = rig.node.hand_models
        assert models["right"].shape == shape and models["right"].right
        assert models["left"] is before["left"]
        # Each hand's fit saw its own hand and not the other: at the other hand's true keypoints
        # its frames hold no depth, at its own they do (a frame of the fit is one of the history's).
        for side, (depths, poses) in calls.items():
            other = "left" if side == "right" else "right"
            assert len(depths) >= 2 and all(p is not None for p in poses)
            own_px, other_px = [], []
            for depth in depths:
                k = next(i for i, f in enumerate(frames) if _masked_of(f[0], depth))
                intr, kp = frames[k][1], frames[k][2]
                own_px.append(_valid_at(depth, intr, kp[side]))
                other_px.append(_valid_at(depth, intr, kp[other]))
            assert np.mean(other_px) < 0.1 and np.mean(own_px) > 0.6, (side, np.mean(own_px), np.mean(other_px))
    finally:
        rig.close()


def _masked_of(raw: np.ndarray, depth: np.ndarray) -> bool:
    """Whether ``depth`` is ``raw`` with some pixels set to 0."""
    kept = depth > 0
    return bool(kept.any() and not np.any(kept & (raw <= 0)) and np.array_equal(depth[kept], raw[kept]))


def _valid_at(depth: np.ndarray, intr, points_mm: np.ndarray) -> float:
    """The share of ``points_mm`` (n, 3) whose pixel in ``depth`` has a depth."""
    u = np.rint(intr.fx * points_mm[:, 0] / points_mm[:, 2] + intr.cx).astype(int)
    v = np.rint(intr.fy * points_mm[:, 1] / points_mm[:, 2] + intr.cy).astype(int)
    ok = (u >= 0) & (u < depth.shape[1]) & (v >= 0) & (v < depth.shape[0])
    return float(np.mean(depth[v[ok], u[ok]] > 0)) if ok.any() else 0.0


def test_calibrate_fits_both_rendered_hands_in_the_child_process(ros_context, tmp_path: Path) -> None:
    """A real fit of each hand of the dev bag 'apart' (left 0.9 / 1.05 / 0.95, right the mesh at 1):
    the answer has the guard's numbers per hand; each accepted fit is that hand's model and
    file, a refused one changes and saves nothing."""
    frames = _apart(16)
    rig = Rig(ros_context, tmp_path, max_hands=2)
    try:
        _track(rig, frames)
        before = rig.node.hand_models
        future = rig.calib.call_async(Trigger.Request())
        assert rig.spin_until(future.done, 120.0), "no answer within 120 s"
        answer = future.result()
        print(answer.message)
        parts = dict(p.split(" hand: ", 1) for p in answer.message.split(" | "))
        assert set(parts) == {"left", "right"}
        models = rig.node.hand_models
        for side, text in parts.items():
            assert "held-out score" in text and "re-tracked score" in text, text
            path = side_model_path(tmp_path / "hand_model.yaml", side)
            if "saved to" in text:
                shape, right = load_hand_shape(path)
                assert right == (side == "right") and models[side].shape == shape
            else:
                assert "nothing changed or saved" in text and not path.exists()
                assert models[side] is before[side] or models[side].shape == before[side].shape
        assert answer.success == any("saved to" in t for t in parts.values())
    finally:
        rig.close()
