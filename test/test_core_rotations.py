"""Rotations, named articulations, joint slots and the drawable geometry of a TrackResult."""

from __future__ import annotations

import numpy as np
import pytest

from hand_sog_tracker.core import articulations as art
from hand_sog_tracker.core.hand_model import (
    ABD,
    FINGER_ABD,
    JOINT_NAMES,
    JOINTS,
    N_JOINTS,
    PARAM_NAMES,
    chain_joint_slice,
    chain_slice,
    default_hand_model,
    rest_pose,
)
from hand_sog_tracker.core.kinematics import SKELETON_CHAINS, gaussian_centres, global_rotation, skeleton_points
from hand_sog_tracker.core.overlay import draw_overlay
from hand_sog_tracker.core.rotations import (
    euler_from_matrix,
    matrices_from_euler,
    quaternion_from_matrix,
    rot_x,
    rot_y,
    rot_z,
    rpy_from_matrix,
)
from hand_sog_tracker.core.tracker import Tracker
from hand_sog_tracker.synth.render import render_depth
from hand_sog_tracker.synth.sequence import default_intrinsics


def test_euler_matrices_match_global_rotation_and_invert() -> None:
    rng = np.random.default_rng(4)
    angles = rng.uniform(-3.0, 3.0, (20, 3))
    Rs = matrices_from_euler(angles)
    for a, R in zip(angles, Rs):
        theta = np.zeros(26)
        theta[3:6] = a
        np.testing.assert_allclose(R, global_rotation(theta), atol=1e-12)
        np.testing.assert_allclose(R, rot_z(a[2]) @ rot_x(a[0]) @ rot_y(a[1]), atol=1e-12)
        back = np.array(euler_from_matrix(R, rx_ref=float(a[0])))
        np.testing.assert_allclose(matrices_from_euler(back[None])[0], R, atol=1e-9)
        roll, pitch, yaw = rpy_from_matrix(R)
        np.testing.assert_allclose(rot_z(yaw) @ rot_y(pitch) @ rot_x(roll), R, atol=1e-9)
        x, y, z, w = quaternion_from_matrix(R)
        assert w >= 0.0
        # Rotating by the quaternion equals rotating by R.
        v = rng.normal(size=3)
        u = np.array([x, y, z])
        rotated = v + 2.0 * np.cross(u, np.cross(u, v) + w * v)
        np.testing.assert_allclose(rotated, R @ v, atol=1e-9)


def test_old_names_still_import() -> None:
    from hand_sog_tracker.core.hand_model import rot_x as hm_rot_x
    from hand_sog_tracker.core.initialise import euler_from_matrix as init_euler
    from hand_sog_tracker.core.urdf import rotation_to_rpy

    assert hm_rot_x is rot_x and init_euler is euler_from_matrix and rotation_to_rpy is rpy_from_matrix


def test_articulations_are_read_only_and_within_limits() -> None:
    model = default_hand_model()
    for name in ("OPEN", "HALF_CLOSED", "CLOSED"):
        q = getattr(art, name)
        assert q.shape == (N_JOINTS,) and not q.flags.writeable
        assert np.all(q >= model.limits_low) and np.all(q <= model.limits_high), name
    for c in range(1, 5):
        np.testing.assert_array_equal(art.CLOSED[chain_joint_slice(c)], art.FINGER_CURLED)
    with pytest.raises(ValueError):
        art.OPEN[0] = 1.0


def test_joint_slots_name_the_pose_vector() -> None:
    names = np.array(PARAM_NAMES)
    assert tuple(names[JOINTS]) == JOINT_NAMES
    for c, finger in enumerate(("thumb", "index", "middle", "ring", "little")):
        assert all(n.startswith(finger + "_") for n in names[chain_slice(c)])
        assert tuple(np.array(JOINT_NAMES)[chain_joint_slice(c)]) == tuple(names[chain_slice(c)])
        assert "abd" in names[chain_slice(c)][ABD]
    assert list(names[FINGER_ABD]) == [f"{f}_mcp_abd" for f in ("index", "middle", "ring", "little")]
    # Each skeleton chain starts at the wrist and runs through that chain's four points.
    model = default_hand_model()
    sk = skeleton_points(model, rest_pose())
    for c, chain in enumerate(SKELETON_CHAINS):
        assert chain[0] == 0
        np.testing.assert_allclose(sk[chain[1]], skeleton_points(model, rest_pose())[1 + 4 * c])


def test_track_result_carries_the_geometry_the_overlay_draws() -> None:
    intr = default_intrinsics(160, 120)
    model = default_hand_model()
    pose = rest_pose((0.0, 40.0, 420.0))
    depth = render_depth(model, pose, intr)
    tracker = Tracker(model=model)
    res = tracker.process(depth, intr)
    assert res.pose is not None
    P = gaussian_centres(tracker.model, res.pose)
    np.testing.assert_array_equal(res.gaussians_mm, P)
    np.testing.assert_array_equal(res.gaussian_radii_mm, tracker.model.g_sigmas)
    np.testing.assert_array_equal(res.fingertips_mm, P[tracker.model.tip_index])
    from_pose = draw_overlay(depth, intr, tracker.model, res.pose)
    from_result = draw_overlay(depth, intr, tracker.model, None, result=res)
    np.testing.assert_array_equal(from_result, from_pose)
    assert (from_pose != draw_overlay(depth, intr, None, None)).any()
