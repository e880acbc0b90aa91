"""What a user plugging the node into a robot meets: the shipped params file in a namespace, the
live description and its TF, the frame prefix (two trackers side by side), marker lifetimes and
the diagnostics' hardware id."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
from rclpy.parameter import Parameter
from std_msgs.msg import Header, String
from test_ros_node_ecosystem import LATCHED

from hand_sog_tracker.core.hand_model import HandShape, default_hand_model
from hand_sog_tracker.core.kinematics import fingertips, global_rotation
from hand_sog_tracker.core.urdf import hand_urdf, urdf_joints
from hand_sog_tracker.errors import InputError
from hand_sog_tracker.ros.frames import description_transforms
from hand_sog_tracker.ros.node import MARKER_LIFETIME_S, TrackerNode
from hand_sog_tracker.ros.params import settings_from_values
from test_ros_node import FRAME, T0_NS, Rig, hand_depth, hand_poses, image_msg

REPO = Path(__file__).resolve().parents[1]
CONFIG = REPO / "config" / "hand_sog_tracker.yaml"


def test_the_shipped_params_file_reaches_a_namespaced_node(ros_context, tmp_path: Path) -> None:
    text = CONFIG.read_text()
    assert "    iterations: 7\n" in text
    params = tmp_path / "params.yaml"
    params.write_text(text.replace("    iterations: 7\n", "    iterations: 11\n"))  # the shipped key, one value changed
    node = TrackerNode(
        context=ros_context, namespace="/robot",
        cli_args=["--ros-args", "--params-file", str(params)],
        parameter_overrides=[Parameter("user_model_path", value=str(tmp_path / "m.yaml"))],
    )
    try:
        assert node.get_fully_qualified_name() == "/robot/hand_sog_tracker"
        assert node.settings.tracker.iterations == 11
    finally:
        node.destroy_node()


def _world(transforms, root: str) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Pose (R, p in m) of every child frame in ``root`` by chaining the transforms."""
    local = {}
    for t in transforms:
        x, y, z, w = (t.transform.rotation.x, t.transform.rotation.y, t.transform.rotation.z, t.transform.rotation.w)
        r = np.array([
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ])
        tr = t.transform.translation
        assert t.child_frame_id not in local, f"{t.child_frame_id} has two parents"
        local[t.child_frame_id] = (t.header.frame_id, r, np.array([tr.x, tr.y, tr.z]))
    out = {root: (np.eye(3), np.zeros(3))}

    def pose(frame: str):
        if frame not in out:
            parent, r, p = local[frame]
            pr, pp = pose(parent)
            out[frame] = (pr @ r, pp + pr @ p)
        return out[frame]

    for f in local:
        pose(f)
    return out


@pytest.mark.parametrize("wrist_joints", [False, True])
@pytest.mark.parametrize("right", [True, False])
def test_tf_of_the_description_puts_the_tips_where_the_tracker_does(wrist_joints: bool, right: bool) -> None:
    model = default_hand_model(right).scaled(HandShape(length=0.9, width=1.05))
    pose = np.zeros(26)
    pose[:3] = (30.0, -20.0, 450.0)
    pose[3:6] = (2.9, 0.3, -0.4)
    pose[6:] = np.random.default_rng(3).uniform(0.0, 0.5, 20) * (model.limits_high > 0)
    tips = fingertips(model, pose)
    header = Header(frame_id=FRAME)
    text = hand_urdf(model, camera_frame=FRAME if wrist_joints else None, prefix="left_")
    tfs = description_transforms(header, urdf_joints(text), pose, tips, wrist_joints, prefix="left_")
    frames = {t.child_frame_id for t in tfs} | {t.header.frame_id for t in tfs}
    links = {link.get("name") for link in ET.fromstring(text).findall("link")}
    assert links <= frames  # every link of the description is on TF
    assert all(f.startswith("left_") for f in frames - {FRAME}), sorted(frames)
    world = _world(tfs, FRAME)
    for i, finger in enumerate(("thumb", "index", "middle", "ring", "little")):
        np.testing.assert_allclose(world[f"left_{finger}_tip"][1] * 1000.0, tips[i], atol=1e-6)
        np.testing.assert_allclose(world[f"left_{finger}_fingertip"][1] * 1000.0, tips[i], atol=1e-6)
    r_wrist, p_wrist = world["left_hand_wrist"]
    np.testing.assert_allclose(p_wrist * 1000.0, pose[:3], atol=1e-9)
    np.testing.assert_allclose(r_wrist, global_rotation(pose), atol=1e-9)


def test_frame_prefix_is_validated() -> None:
    assert settings_from_values({"frame_prefix": "robot1/left_"}).frame_prefix == "robot1/left_"
    with pytest.raises(InputError, match="frame_prefix"):
        settings_from_values({"frame_prefix": "left hand"})


def test_two_trackers_side_by_side_describe_their_own_frames(ros_context, tmp_path: Path) -> None:
    rigs = [Rig(ros_context, tmp_path / name, frame_prefix=f"{name}_") for name in ("left", "right")]
    try:
        for rig in rigs:
            got: list[String] = []
            rig.io.create_subscription(String, "hand/robot_description", got.append, LATCHED)
            assert rig.spin_until(lambda got=got: len(got) >= 1, 10.0)
            prefix = rig.node.settings.frame_prefix
            root = ET.fromstring(got[-1].data)
            links = [link.get("name") for link in root.findall("link")]
            assert got[-1].data == hand_urdf(rig.node.hand_model, prefix=prefix)  # the model in use
            assert links and all(n.startswith(prefix) for n in links), links
        names = [{link.get("name") for link in ET.fromstring(hand_urdf(prefix=p)).findall("link")}
                 for p in ("left_", "right_")]
        assert not names[0] & names[1]
    finally:
        for rig in rigs:
            rig.close()


def test_markers_expire_and_diagnostics_name_the_camera(ros_context, tmp_path: Path) -> None:
    rig = Rig(ros_context, tmp_path)
    try:
        assert rig.spin_until(lambda: bool(rig.diagnostics), 3.0)
        first = rig.diagnostics[0].status[0]
        assert first.hardware_id == f"{rig.ns}/camera/depth/image_rect_raw"  # before any image: its topic
        rig.send_info()
        rig.send(image_msg(hand_depth(hand_poses(1)[0], seed=2), T0_NS))
        assert rig.spin_until(lambda: bool(rig.markers), 5.0)
        lifetimes = {m.lifetime.sec + m.lifetime.nanosec * 1e-9 for m in rig.markers[-1].markers}
        assert lifetimes == {MARKER_LIFETIME_S}
        assert rig.spin_until(lambda: rig.diagnostics[-1].status[0].hardware_id == FRAME, 3.0)
    finally:
        rig.close()
