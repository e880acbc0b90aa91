"""Forward kinematics, Jacobians and the hand model."""

from __future__ import annotations

import numpy as np
import pytest

from hand_sog_tracker.core.hand_model import (
    JOINT_NAMES,
    N_PARAMS,
    PARAM_NAMES,
    HandShape,
    default_hand_model,
    rest_pose,
)
from hand_sog_tracker.core.initialise import euler_from_matrix
from hand_sog_tracker.core.kinematics import (
    attached_points,
    centres_batch,
    centres_with_pullback,
    chain_frames,
    fingertips,
    gaussian_centres,
    global_rotation,
    skeleton_points,
)
from hand_sog_tracker.errors import InputError


def random_pose(rng: np.random.Generator) -> np.ndarray:
    theta = rest_pose((rng.uniform(-50, 50), rng.uniform(-50, 50), rng.uniform(300, 500)))
    theta[3:6] += rng.uniform(-1.5, 1.5, 3)
    theta[6:] = rng.uniform(-0.4, 1.2, 20)
    return theta


def test_parameter_names() -> None:
    assert len(PARAM_NAMES) == N_PARAMS == 26
    assert len(JOINT_NAMES) == 20 and len(set(JOINT_NAMES)) == 20
    assert JOINT_NAMES[:4] == ("thumb_cmc_flex", "thumb_cmc_abd", "thumb_mcp_flex", "thumb_ip_flex")
    assert JOINT_NAMES[4:8] == ("index_mcp_flex", "index_mcp_abd", "index_pip_flex", "index_dip_flex")
    assert JOINT_NAMES[-1] == "little_dip_flex"


@pytest.mark.parametrize("right", [True, False])
def test_jacobian_matches_central_differences(right: bool) -> None:
    rng = np.random.default_rng(11 if right else 12)
    model = default_hand_model(right)
    for _ in range(5):
        theta = random_pose(rng)
        _, J = gaussian_centres(model, theta, jacobian=True)
        Jn = np.zeros_like(J)
        for j in range(N_PARAMS):
            e = np.zeros(N_PARAMS)
            e[j] = 1e-6
            Jn[:, :, j] = (gaussian_centres(model, theta + e) - gaussian_centres(model, theta - e)) / 2e-6
        np.testing.assert_allclose(J, Jn, atol=1e-5 * max(1.0, np.abs(Jn).max()))


def test_batched_points_equal_one_at_a_time() -> None:
    rng = np.random.default_rng(3)
    model = default_hand_model()
    theta = random_pose(rng)
    all_pts = gaussian_centres(model, theta)
    for k in rng.choice(model.n_gaussians, 6, replace=False):
        one = attached_points(
            model, theta, model.g_chain[k : k + 1], model.g_segment[k : k + 1], model.g_offsets[k : k + 1]
        )
        np.testing.assert_allclose(one[0], all_pts[k])


def test_rest_pose_geometry() -> None:
    model = default_hand_model()
    theta = rest_pose((0.0, 0.0, 400.0))
    skel = skeleton_points(model, theta)
    assert skel.shape == (21, 3)
    # Palm toward the camera, fingers up (-y in the image), all at the wrist depth.
    tips = fingertips(model, theta)
    assert np.all(tips[1:, 1] < -120.0)
    np.testing.assert_allclose(tips[1:, 2], 400.0, atol=1e-9)
    # Index on the thumb side (+x for a right hand seen palm-on), little on the other.
    assert tips[1, 0] > tips[4, 0]
    # Fingertip = one tip radius back from the bone end along the distal bone.
    bone_end = skel[[4, 8, 12, 16, 20]]
    np.testing.assert_allclose(np.linalg.norm(bone_end - tips, axis=1), model.tip_radii, rtol=1e-9)


def test_left_hand_is_mirror_image() -> None:
    theta = rest_pose((0.0, 0.0, 400.0))
    right = fingertips(default_hand_model(True), theta)
    left = fingertips(default_hand_model(False), theta)
    np.testing.assert_allclose(left[:, 0], -right[:, 0])
    np.testing.assert_allclose(left[:, 1:], right[:, 1:])


def test_flexion_bends_toward_palm() -> None:
    model = default_hand_model()
    theta = rest_pose((0.0, 0.0, 400.0))
    bent = theta.copy()
    bent[6 + 4 * 2 + 0] = 1.2  # middle MCP flexion
    # The palm faces the camera (-z), so flexion brings the tip closer to it.
    assert fingertips(model, bent)[2, 2] < fingertips(model, theta)[2, 2] - 50.0


def test_shape_scaling() -> None:
    base = default_hand_model()
    big = base.scaled(HandShape(length=1.1, width=1.2, depth=1.3, sigma=0.9))
    np.testing.assert_allclose(big.lengths, base.lengths * 1.1)
    np.testing.assert_allclose(big.bases[:, 0], base.bases[:, 0] * 1.2)
    palm = base.g_chain < 0
    np.testing.assert_allclose(big.g_sigmas[~palm], base.g_sigmas[~palm] * 0.9)
    np.testing.assert_allclose(big.g_sigmas[palm], base.g_sigmas[palm] * 1.3)
    # Re-scaling starts from the default, not from the scaled model.
    again = big.scaled(HandShape())
    np.testing.assert_allclose(again.g_offsets, base.g_offsets)
    with pytest.raises(InputError):
        HandShape(length=5.0)


@pytest.mark.parametrize("right", [True, False])
def test_joint_gaussians_sit_on_the_second_and_third_joints(right: bool) -> None:
    """``with_joint_gaussians``: 10 Gaussians more, on the second and third joint of every
    chain with the radius of the segment beyond; the others, the fingertips and the skeleton
    are the model's own, for a scaled model too."""
    shape = HandShape(length=0.9, width=1.1, sigma=1.2).with_fingers((1.0, 1.05, 0.95, 1.0, 1.1))
    model = default_hand_model(right).scaled(shape)
    joint = model.with_joint_gaussians()
    m = model.n_gaussians
    assert joint.n_gaussians == m + 10
    np.testing.assert_array_equal(joint.tip_index, model.tip_index)
    theta = rest_pose((10.0, -20.0, 420.0))
    theta[6:] = np.random.default_rng(4).uniform(0.0, 1.2, 20)
    P, J = gaussian_centres(model, theta), gaussian_centres(joint, theta)
    np.testing.assert_allclose(J[:m], P, atol=1e-9)
    np.testing.assert_allclose(fingertips(joint, theta), fingertips(model, theta), atol=1e-9)
    skeleton = skeleton_points(model, theta)
    for k, (c, s) in enumerate((c, s) for c in range(5) for s in (1, 2)):
        np.testing.assert_allclose(J[m + k], skeleton[1 + 4 * c + s], atol=1e-9)
        on_segment = (model.g_chain == c) & (model.g_segment == s)
        assert joint.g_sigmas[m + k] == model.g_sigmas[on_segment][0]


def test_euler_round_trip() -> None:
    rng = np.random.default_rng(5)
    for _ in range(20):
        theta = np.zeros(N_PARAMS)
        theta[3:6] = rng.uniform(-3.0, 3.0, 3)
        R = global_rotation(theta)
        rx, ry, rz = euler_from_matrix(R, rx_ref=float(theta[3]))
        back = theta.copy()
        back[3:6] = rx, ry, rz
        np.testing.assert_allclose(global_rotation(back), R, atol=1e-9)


def test_bad_pose_rejected() -> None:
    model = default_hand_model()
    with pytest.raises(InputError):
        gaussian_centres(model, np.zeros(25))
    bad = rest_pose()
    bad[7] = np.nan
    with pytest.raises(InputError):
        gaussian_centres(model, bad)


def test_point_index_cache_follows_the_arrays_contents() -> None:
    # Index arrays are cached per (chain, segment) array pair; changing the arrays in place or
    # passing new ones must give the same points and Jacobian as a fresh computation.
    model = default_hand_model()
    rng = np.random.default_rng(3)
    theta = rest_pose((0.0, 50.0, 400.0))
    theta[6:] = rng.normal(0.0, 0.3, theta.size - 6)
    chain = np.array([0, 1, 2, -1, 4])
    segment = np.array([2, 0, 1, 0, 2])
    offsets = rng.normal(0.0, 5.0, (5, 3))
    p1, j1 = attached_points(model, theta, chain, segment, offsets, jacobian=True)
    chain[:] = [3, 3, -1, 2, 0]  # in place: same array objects
    segment[:] = [0, 1, 2, 2, 1]
    p2, j2 = attached_points(model, theta, chain, segment, offsets, jacobian=True)
    p3, j3 = attached_points(model, theta, chain.copy(), segment.copy(), offsets, jacobian=True)
    np.testing.assert_array_equal(p2, p3)
    np.testing.assert_array_equal(j2, j3)
    assert not np.allclose(p1, p2)
    for k in range(5):  # and one point at a time
        pk, jk = attached_points(model, theta, chain[k : k + 1], segment[k : k + 1], offsets[k : k + 1], jacobian=True)
        np.testing.assert_allclose(pk[0], p2[k], atol=1e-12)
        np.testing.assert_allclose(jk[0], j2[k], atol=1e-12)


@pytest.mark.parametrize("right", [True, False])
def test_pullback_equals_the_jacobian_transpose_product(right: bool) -> None:
    # centres_with_pullback: the same centres as gaussian_centres (bit for bit) and, for any
    # gradient g3 with respect to the centres, J^T g3 without building J (up to rounding);
    # rows of g3 that are zero (points nothing pulls) leave their joints' entries exactly 0.
    model = default_hand_model(right)
    rng = np.random.default_rng(21 if right else 22)
    for _ in range(10):
        theta = random_pose(rng)
        P, J = gaussian_centres(model, theta, jacobian=True)
        P2, pullback = centres_with_pullback(model, theta)
        np.testing.assert_array_equal(P2, P)
        np.testing.assert_array_equal(gaussian_centres(model, theta), P)
        g3 = rng.normal(0.0, 1.0, P.shape)
        g3[model.g_chain == 2] = 0.0  # the middle finger: no pull
        expected = np.einsum("mk,mkj->j", g3, J)
        got = pullback(g3)
        np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-12 * np.abs(expected).max())
        middle = slice(6 + 4 * 2, 6 + 4 * 3)
        assert np.all(got[middle] == 0.0) and np.all(expected[middle] == 0.0)


def test_global_rotation_derivatives_match_central_differences() -> None:
    rng = np.random.default_rng(8)
    for _ in range(5):
        theta = random_pose(rng)
        R, dR = global_rotation(theta, derivatives=True)
        np.testing.assert_array_equal(R, global_rotation(theta))
        for a in range(3):
            e = np.zeros(N_PARAMS)
            e[3 + a] = 1e-6
            num = (global_rotation(theta + e) - global_rotation(theta - e)) / 2e-6
            np.testing.assert_allclose(dR[a], num, atol=1e-8)


def test_repeated_poses_give_fresh_equal_results() -> None:
    # The centres of the last few poses are kept (a frame asks for the same poses several
    # times): every call must still equal a fresh computation (attached_points, not cached),
    # for each model and hand at the same pose, after the pose array changed in place, after
    # the kept poses were replaced by others, and callers get arrays of their own.
    rng = np.random.default_rng(31)
    right, left = default_hand_model(True), default_hand_model(False)
    models = [right, left, right.scaled(HandShape(length=1.1))]

    def check(model, th) -> None:
        fresh = attached_points(model, th, model.g_chain, model.g_segment, model.g_offsets)
        got = gaussian_centres(model, th)
        np.testing.assert_array_equal(got, fresh)
        np.testing.assert_array_equal(fingertips(model, th), fresh[model.tip_index])
        np.testing.assert_array_equal(centres_with_pullback(model, th)[0], fresh)
        got += 1.0  # the caller's own array
        np.testing.assert_array_equal(gaussian_centres(model, th), fresh)

    theta = random_pose(rng)
    poses = [theta] + [random_pose(rng) for _ in range(12)]
    for _ in range(2):
        for th in poses:
            for model in models:
                check(model, th)
        for model in models:
            theta[6:] += 0.05  # the same array object, new contents
            check(model, theta)
    # The skeleton from the kept joint origins equals the one from the chain frames.
    model = models[1]
    fr = chain_frames(model, theta)
    p_hand = np.concatenate([np.zeros((1, 3)), fr.origins.reshape(20, 3)])
    expected = p_hand @ (global_rotation(theta) * np.array([-1.0, 1.0, 1.0])).T + theta[:3]
    np.testing.assert_array_equal(skeleton_points(model, theta), expected)


def test_batch_centres_and_rotations_equal_one_pose_at_a_time() -> None:
    # centres_batch and global_rotation of poses (B, 26) give each pose the bits of the one-pose
    # calls (and of attached_points, the general path), whatever B, for both hands, a scaled
    # model and a joint model; zero and negative-zero angles included (signs of zeros in dR).
    rng = np.random.default_rng(41)
    right = default_hand_model(True)
    models = [right, default_hand_model(False), right.scaled(HandShape(length=1.1)), right.with_joint_gaussians()]
    for model in models:
        for B in (1, 2, 7):
            thetas = np.array([random_pose(rng) for _ in range(B)])
            thetas[0, 3:6] = (0.0, -0.0, 0.0)
            thetas[-1, 6:] = 0.0
            P, _ = centres_batch(model, thetas)
            R, dR = global_rotation(thetas, derivatives=True)
            np.testing.assert_array_equal(global_rotation(thetas), R)
            for b in range(B):
                fresh = attached_points(model, thetas[b], model.g_chain, model.g_segment, model.g_offsets)
                assert P[b].tobytes() == fresh.tobytes() == centres_with_pullback(model, thetas[b])[0].tobytes()
                R1, dR1 = global_rotation(thetas[b], derivatives=True)
                assert R[b].tobytes() == R1.tobytes() and dR[b].tobytes() == dR1.tobytes()


def test_keypoint_skeleton_moves_only_the_palm_rows_by_the_fitted_offsets() -> None:
    from hand_sog_tracker.core.hand_model import KEYPOINT_FACING_MM, KEYPOINT_OFFSETS_MM
    from hand_sog_tracker.core.kinematics import PALM_KEYPOINT_ROWS, keypoint_skeleton

    rng = np.random.default_rng(12)
    shape = HandShape(length=1.1, width=0.9, depth=1.2)
    for right in (True, False):
        model = default_hand_model(right).scaled(shape)
        for _ in range(4):
            th = random_pose(rng)
            kp, sk = keypoint_skeleton(model, th), skeleton_points(model, th)
            other = [r for r in range(21) if r not in PALM_KEYPOINT_ROWS]
            np.testing.assert_array_equal(kp[other], sk[other])  # the fingers' joints are the skeleton's
            G = global_rotation(th) * np.array([1.0 if right else -1.0, 1.0, 1.0])
            facing = G[:, 2] @ th[:3] / np.linalg.norm(th[:3])
            off = KEYPOINT_OFFSETS_MM * [0.9, 1.1, 1.2]
            off[:, 2] += KEYPOINT_FACING_MM * 1.2 * facing
            rows = list(PALM_KEYPOINT_ROWS)
            np.testing.assert_allclose(kp[rows], sk[rows] + off @ G.T, atol=1e-9)
    # The wrist's joint centre lies deeper than the model's origin: by 16 mm palm to the camera
    # (the model fits the palmar skin), by 3 mm back to it (the dorsal skin).
    model = default_hand_model(True)
    th = rest_pose((0.0, 0.0, 400.0))  # palm to the camera
    assert keypoint_skeleton(model, th)[0, 2] - th[2] > 10.0
    th[3] = 0.0  # back to the camera
    assert 0.0 < keypoint_skeleton(model, th)[0, 2] - th[2] < 6.0
