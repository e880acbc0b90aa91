"""The URDF description: shipped file, joint names and limits, forward kinematics from the XML alone."""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from hand_sog_tracker.core.hand_model import JOINT_NAMES, HandShape, default_hand_model, rest_pose
from hand_sog_tracker.core.kinematics import fingertips, global_rotation, skeleton_points
from hand_sog_tracker.core.urdf import TIP_LINKS, WRIST_JOINT_NAMES, WRIST_LINK, hand_urdf, rotation_to_rpy

REPO = Path(__file__).resolve().parents[1]


def _rot(axis: np.ndarray, q: float) -> np.ndarray:
    a = axis / np.linalg.norm(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(q) * k + (1 - math.cos(q)) * k @ k


def _rpy(r: float, p: float, y: float) -> np.ndarray:
    """URDF rpy: fixed axes x, y, z -> R = Rz(y) Ry(p) Rx(r)."""
    return _rot(np.array([0, 0, 1.0]), y) @ _rot(np.array([0, 1.0, 0]), p) @ _rot(np.array([1.0, 0, 0]), r)


def urdf_fk(text: str, values: dict[str, float]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """World pose (R, p) of every link, from the URDF text alone (root at the identity)."""
    root = ET.fromstring(text)
    joints = {}
    for j in root.findall("joint"):
        o = j.find("origin")
        xyz = np.array([float(v) for v in o.get("xyz").split()])
        rpy = [float(v) for v in o.get("rpy").split()]
        ax = j.find("axis")
        axis = np.array([float(v) for v in ax.get("xyz").split()]) if ax is not None else None
        parent = j.find("parent").get("link")
        joints[j.find("child").get("link")] = (j.get("name"), j.get("type"), parent, xyz, _rpy(*rpy), axis)
    links = [link.get("name") for link in root.findall("link")]
    roots = [n for n in links if n not in joints]
    assert len(roots) == 1, roots
    poses = {roots[0]: (np.eye(3), np.zeros(3))}

    def pose(link: str):
        if link not in poses:
            name, kind, parent, xyz, rot, axis = joints[link]
            pr, pp = pose(parent)
            r, p = pr @ rot, pp + pr @ xyz
            q = values.get(name, 0.0)
            if kind in ("revolute", "continuous"):
                r = r @ _rot(axis, q)
            elif kind == "prismatic":
                p = p + r @ axis * q
            else:
                assert kind == "fixed"
            poses[link] = (r, p)
        return poses[link]

    for n in links:
        pose(n)
    return poses


def random_pose(rng: np.random.Generator, model) -> np.ndarray:
    th = rest_pose((rng.uniform(-80, 80), rng.uniform(-60, 60), rng.uniform(300, 600)))
    th[3:6] += rng.uniform(-1.0, 1.0, 3)
    th[6:] = rng.uniform(model.limits_low, model.limits_high)
    return th


def test_shipped_urdfs_are_the_generated_default_hands() -> None:
    regen = "regenerate: python -m hand_sog_tracker.core.urdf [--left] > urdf/hand[_left].urdf"
    assert (REPO / "urdf" / "hand.urdf").read_text() == hand_urdf(), regen
    assert (REPO / "urdf" / "hand_left.urdf").read_text() == hand_urdf(default_hand_model(right=False)), regen


def test_command_line_prints_a_calibrated_description(tmp_path: Path, capsys) -> None:
    from hand_sog_tracker.core.model_io import save_hand_shape
    from hand_sog_tracker.core.urdf import main

    shape = HandShape(length=1.1, width=0.95)
    path = save_hand_shape(tmp_path / "m.yaml", shape, right=True)
    assert main(["--model", str(path), "--camera-frame", "cam"]) == 0
    assert capsys.readouterr().out == hand_urdf(default_hand_model().scaled(shape), camera_frame="cam")
    assert main(["--model", str(tmp_path / "missing.yaml")]) == 2
    assert "missing.yaml" in capsys.readouterr().err


def test_joints_names_types_and_limits_match_the_model() -> None:
    model = default_hand_model()
    root = ET.fromstring(hand_urdf(model, camera_frame="cam"))
    kinds = {j.get("name"): j.get("type") for j in root.findall("joint")}
    revolute = sorted(n for n, k in kinds.items() if k == "revolute")
    assert revolute == sorted(JOINT_NAMES)
    assert [n for n in kinds if n.startswith("hand_")] == list(WRIST_JOINT_NAMES)
    assert sum(k == "fixed" for k in kinds.values()) == 5
    for j in root.findall("joint"):
        if j.get("type") == "revolute":
            i = JOINT_NAMES.index(j.get("name"))
            lim = j.find("limit")
            assert float(lim.get("lower")) == pytest.approx(model.limits_low[i], abs=1e-8)
            assert float(lim.get("upper")) == pytest.approx(model.limits_high[i], abs=1e-8)
    links = {link.get("name") for link in root.findall("link")}
    assert set(TIP_LINKS) | {WRIST_LINK, "cam"} <= links


@pytest.mark.parametrize(
    "model",
    [
        default_hand_model(),
        default_hand_model().scaled(HandShape(length=1.15, width=0.9, depth=1.1, sigma=0.85)),
        default_hand_model(right=False),
        default_hand_model(right=False).scaled(HandShape(length=0.85, width=1.1)),
    ],
    ids=["default", "calibrated", "left", "left-calibrated"],
)
def test_urdf_forward_kinematics_matches_the_tracker(model) -> None:
    """Fingertip links and joint origins from the XML alone agree with core.kinematics (< 1 mm)."""
    text = hand_urdf(model, camera_frame="camera_depth_optical_frame")
    rng = np.random.default_rng(7)
    for _ in range(10):
        th = random_pose(rng, model)
        values = dict(zip(JOINT_NAMES, th[6:]))
        values.update(zip(("hand_tx", "hand_ty", "hand_tz"), th[:3] / 1000.0))
        values.update(hand_rx=th[3], hand_ry=th[4], hand_rz=th[5])
        poses = urdf_fk(text, values)
        tips = np.array([poses[t][1] for t in TIP_LINKS]) * 1000.0
        np.testing.assert_allclose(tips, fingertips(model, th), atol=1.0)
        r_wrist, p_wrist = poses[WRIST_LINK]
        np.testing.assert_allclose(r_wrist, global_rotation(th), atol=1e-9)
        np.testing.assert_allclose(p_wrist * 1000.0, th[:3], atol=1e-6)
        # The third joint of each chain sits at skeleton point 3 + 4c.
        sk = skeleton_points(model, th)
        third = ("thumb_distal", "index_distal", "middle_distal", "ring_distal", "little_distal")
        np.testing.assert_allclose(np.array([poses[n][1] for n in third]) * 1000.0, sk[3::4][:5], atol=1.0)


def test_description_without_camera_frame_is_rooted_at_the_wrist() -> None:
    root = ET.fromstring(hand_urdf())
    children = {j.find("child").get("link") for j in root.findall("joint")}
    assert [n.get("name") for n in root.findall("link") if n.get("name") not in children] == [WRIST_LINK]


def test_rotation_to_rpy_round_trip() -> None:
    rng = np.random.default_rng(3)
    for _ in range(50):
        r = _rpy(*rng.uniform(-3, 3, 3))
        np.testing.assert_allclose(_rpy(*rotation_to_rpy(r)), r, atol=1e-9)
    r = _rpy(0.3, math.pi / 2, -0.2)
    np.testing.assert_allclose(_rpy(*rotation_to_rpy(r)), r, atol=1e-7)
