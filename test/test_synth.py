"""Synthetic depth renderer, scripted motions and rendered sequences."""

from __future__ import annotations

import numpy as np
import pytest

from hand_sog_tracker.core.hand_model import HandShape, default_hand_model, rest_pose
from hand_sog_tracker.core.kinematics import fingertips, skeleton_points
from hand_sog_tracker.core.types import Intrinsics
from hand_sog_tracker.errors import InputError, IntrinsicsError
from hand_sog_tracker.synth import (
    MOTIONS,
    RenderOptions,
    default_intrinsics,
    default_start_pose,
    motion_poses,
    render_depth,
    synthetic_sequence,
)
from hand_sog_tracker.synth.motions import key_articulations

EXACT = RenderOptions(noise_mm=0.0, flying_pixels=False, holes=False)
EXACT_NO_ARM = RenderOptions(noise_mm=0.0, flying_pixels=False, holes=False, forearm=False)


def _px(intr: Intrinsics, p: np.ndarray) -> tuple[int, int]:
    uv = intr.project(p[None])[0]
    return int(round(uv[1])), int(round(uv[0]))


def test_default_intrinsics() -> None:
    i320 = default_intrinsics()
    assert (i320.width, i320.height) == (320, 240)
    assert i320.fx == pytest.approx(287.26) and i320.fy == pytest.approx(287.26)
    assert (i320.cx, i320.cy) == (159.5, 119.5)
    i640 = default_intrinsics(640, 480)
    assert i640.fx == pytest.approx(2 * 287.26) and (i640.cx, i640.cy) == (319.5, 239.5)
    with pytest.raises(IntrinsicsError):
        default_intrinsics(0, 240)


def test_fingertip_depth_is_exact() -> None:
    model = default_hand_model(True)
    intr = default_intrinsics()
    theta = default_start_pose()
    depth = render_depth(model, theta, intr, EXACT)
    assert depth.dtype == np.float32 and depth.shape == (240, 320)
    tips = fingertips(model, theta)
    for tip, r in zip(tips, model.tip_radii):
        v, u = _px(intr, tip)
        assert depth[v, u] == pytest.approx(tip[2] - r, abs=1.0)
    # A flexed finger: the tip sphere still sits exactly on the rendered surface.
    theta2 = theta.copy()
    theta2[14:18] = np.deg2rad([30.0, 0.0, 40.0, 20.0])  # middle finger
    depth2 = render_depth(model, theta2, intr, EXACT)
    tip = fingertips(model, theta2)[2]
    v, u = _px(intr, tip)
    ray = intr.backproject(np.array([[u, v]], dtype=float), np.array([depth2[v, u]]))[0]
    assert np.linalg.norm(ray - tip) == pytest.approx(model.tip_radii[2], abs=0.5)


def test_palm_depth_and_background() -> None:
    model = default_hand_model(True)
    intr = default_intrinsics()
    theta = default_start_pose()
    depth = render_depth(model, theta, intr, EXACT)
    # Palm centre (hand frame (0, 50, 0)) faces the camera: surface = centre z - palm thickness/2.
    centre = theta[:3] + np.array([0.0, -50.0, 0.0])
    v, u = _px(intr, centre)
    assert depth[v, u] == pytest.approx(theta[2] - 12.5, abs=0.5)
    assert depth[5, 5] == pytest.approx(900.0)
    d_none = render_depth(model, theta, intr, RenderOptions(0.0, False, False, True, None))
    assert d_none[5, 5] == 0.0
    hand = d_none > 0
    np.testing.assert_array_equal(depth[hand], d_none[hand])
    assert np.all(depth[~hand] == 900.0)


def test_finger_silhouette_width() -> None:
    model = default_hand_model(True)
    intr = default_intrinsics(640, 480)
    theta = default_start_pose()
    depth = render_depth(model, theta, intr, EXACT_NO_ARM)
    sk = skeleton_points(model, theta)
    # Middle of the middle finger's middle segment (skeleton joints 11 and 12).
    mid = 0.5 * (sk[11] + sk[12])
    v, u = _px(intr, mid)
    row = depth[v] < 600.0
    assert row[u]
    left = u
    while row[left - 1]:
        left -= 1
    right = u
    while row[right + 1]:
        right += 1
    width = right - left + 1
    r = 8.5  # middle finger, middle segment
    expected = 2 * r * intr.fx / mid[2]
    assert abs(width - expected) <= 1.5, (width, expected)


def test_left_hand_is_mirrored() -> None:
    intr = default_intrinsics()  # principal point in the exact image centre
    theta = default_start_pose()
    theta[0] = 0.0
    theta[6:] = key_articulations()["pinch"]
    right = render_depth(default_hand_model(True), theta, intr, EXACT)
    left = render_depth(default_hand_model(False), theta, intr, EXACT)
    assert not np.allclose(right, left)
    np.testing.assert_allclose(left, right[:, ::-1], atol=1e-3)


def test_640_matches_320() -> None:
    model = default_hand_model(True)
    theta = default_start_pose()
    small = render_depth(model, theta, default_intrinsics(), EXACT_NO_ARM)
    big = render_depth(model, theta, default_intrinsics(640, 480), EXACT_NO_ARM)
    assert big.shape == (480, 640) and big.dtype == np.float32
    ratio = np.count_nonzero(big < 600) / np.count_nonzero(small < 600)
    assert 3.8 < ratio < 4.2
    # 2x2 blocks of the big image straddle each small pixel's centre: close in depth.
    hand = small < 600
    block = big.reshape(240, 2, 320, 2).mean(axis=(1, 3))
    diff = np.abs(block - small)[hand & (block < 600)]
    assert np.median(diff) < 1.0


def test_scaled_hand_is_longer() -> None:
    intr = default_intrinsics()
    theta = default_start_pose()
    base = default_hand_model(True)
    big = base.scaled(HandShape(length=1.1, width=1.1, depth=1.2, sigma=1.1))
    d0 = render_depth(base, theta, intr, EXACT_NO_ARM)
    d1 = render_depth(big, theta, intr, EXACT_NO_ARM)
    assert np.count_nonzero(d1 < 600) > 1.15 * np.count_nonzero(d0 < 600)
    tip = fingertips(big, theta)[2]
    v, u = _px(intr, tip)
    assert d1[v, u] == pytest.approx(tip[2] - big.tip_radii[2], abs=1.0)
    # Thicker palm (shape.depth scales it): the palm surface is nearer.
    c = theta[:3] + np.array([0.0, -50.0 * 1.1, 0.0])
    v, u = _px(intr, c)
    assert d1[v, u] == pytest.approx(theta[2] - 12.5 * 1.2, abs=0.7)


def test_forearm_option() -> None:
    model = default_hand_model(True)
    intr = default_intrinsics()
    theta = default_start_pose()
    wrist_v, wrist_u = _px(intr, theta[:3])
    with_arm = render_depth(model, theta, intr, EXACT)
    no_arm = render_depth(model, theta, intr, EXACT_NO_ARM)
    below = (slice(wrist_v + 20, 240), slice(wrist_u - 10, wrist_u + 11))
    assert np.all(with_arm[below] < 500.0)
    assert np.all(no_arm[below] == 900.0)
    # Above the wrist (palm, fingers) both agree exactly apart from the forearm's wrist cap.
    top = slice(0, wrist_v - 40)
    np.testing.assert_array_equal(with_arm[top], no_arm[top])


def test_artefacts_change_image_but_keep_depth() -> None:
    model = default_hand_model(True)
    intr = default_intrinsics()
    theta = default_start_pose()
    theta[6:] = key_articulations()["claw"]
    clean = render_depth(model, theta, intr, EXACT)
    noisy = render_depth(model, theta, intr, RenderOptions(), np.random.default_rng(3))
    assert noisy.dtype == np.float32
    both = (clean > 0) & (noisy > 0)
    hand = both & (clean < 600)
    diff = np.abs(noisy - clean)
    assert np.count_nonzero(diff[both] > 0.1) > 0.5 * np.count_nonzero(both)
    assert np.median(diff[hand]) < 1.0
    # Holes on the hand, flying pixels between hand and wall.
    assert np.count_nonzero((clean < 600) & (noisy == 0)) >= 5
    flying = (noisy > 480) & (noisy < 850) & (clean > 850)
    flying |= (noisy > 480) & (noisy < 850) & (clean < 480)
    assert np.count_nonzero(flying) >= 20
    # Each option alone changes the image.
    for opts in (
        RenderOptions(noise_mm=1.0, flying_pixels=False, holes=False),
        RenderOptions(noise_mm=0.0, flying_pixels=True, holes=False),
        RenderOptions(noise_mm=0.0, flying_pixels=False, holes=True),
    ):
        img = render_depth(model, theta, intr, opts, np.random.default_rng(4))
        assert np.count_nonzero(img != clean) > 10, opts


def test_noise_grows_with_depth() -> None:
    model = default_hand_model(True)
    intr = default_intrinsics()
    theta = default_start_pose()
    opts = RenderOptions(noise_mm=2.0, flying_pixels=False, holes=False)
    noisy = render_depth(model, theta, intr, opts, np.random.default_rng(7))
    clean = render_depth(model, theta, intr, EXACT)
    wall = clean == 900.0
    assert np.std((noisy - clean)[wall]) == pytest.approx(2.0 * (900.0 / 400.0) ** 2, rel=0.05)


def test_render_is_deterministic() -> None:
    model = default_hand_model(True)
    intr = default_intrinsics()
    theta = default_start_pose()
    a = render_depth(model, theta, intr, RenderOptions(), np.random.default_rng(11))
    b = render_depth(model, theta, intr, RenderOptions(), np.random.default_rng(11))
    c = render_depth(model, theta, intr, RenderOptions(), np.random.default_rng(12))
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    np.testing.assert_array_equal(render_depth(model, theta, intr), render_depth(model, theta, intr))


def test_render_rejects_bad_input() -> None:
    model = default_hand_model(True)
    intr = default_intrinsics()
    with pytest.raises(InputError):
        render_depth(model, np.zeros(25), intr)
    bad = default_start_pose()
    bad[7] = np.nan
    with pytest.raises(InputError):
        render_depth(model, bad, intr)
    with pytest.raises(InputError):
        RenderOptions(noise_mm=-1.0)
    with pytest.raises(InputError):
        RenderOptions(background_mm=0.0)


def test_hand_out_of_view_renders_background() -> None:
    model = default_hand_model(True)
    intr = default_intrinsics()
    theta = rest_pose((2000.0, 0.0, 400.0))
    assert np.all(render_depth(model, theta, intr, EXACT) == 900.0)
    behind = rest_pose((0.0, 0.0, -400.0))
    assert np.all(render_depth(model, behind, intr, EXACT) == 900.0)


@pytest.mark.parametrize("name", MOTIONS)
def test_motion_in_view_and_within_limits(name: str) -> None:
    model = default_hand_model(True)
    intr = default_intrinsics()
    poses = motion_poses(name, 240, fps=30.0, seed=5)
    assert poses.shape == (240, 26)
    np.testing.assert_array_equal(poses[0], default_start_pose())
    q = poses[:, 6:]
    assert np.all(q >= model.limits_low) and np.all(q <= model.limits_high)
    # Smooth: at most ~15 degrees of any joint per frame at 30 fps.
    assert np.abs(np.diff(q, axis=0)).max() < np.deg2rad(15.0)
    # It really moves.
    assert np.ptp(q, axis=0).max() > np.deg2rad(25.0)
    for right in (True, False):
        m = default_hand_model(right)
        sk = np.stack([skeleton_points(m, p) for p in poses])
        uv = intr.project(sk.reshape(-1, 3))
        assert uv[:, 0].min() > 5 and uv[:, 0].max() < 315
        assert uv[:, 1].min() > 5 and uv[:, 1].max() < 235
        assert 250.0 < sk[..., 2].min() and sk[..., 2].max() < 500.0


def test_random_motion_is_fast_and_articulation_motions_drift_gently() -> None:
    def max_angular_speed(poses: np.ndarray) -> float:
        from hand_sog_tracker.core.kinematics import global_rotation

        Rs = np.stack([global_rotation(p) for p in poses])
        c = (np.einsum("tij,tij->t", Rs[:-1], Rs[1:]) - 1.0) / 2.0
        return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))).max() * 30.0)

    fast = motion_poses("random", 150, seed=2)
    assert 90.0 < max_angular_speed(fast) < 400.0
    assert np.ptp(fast[:, 2]) > 20.0
    slow = motion_poses("fingerwave", 150, seed=2)
    assert 0.5 < max_angular_speed(slow) < 20.0
    assert 0.5 < np.ptp(slow[:, :3], axis=0).max() < 12.0


def test_motion_options() -> None:
    long = motion_poses("random", 60, seed=1)
    np.testing.assert_array_equal(motion_poses("random", 20, seed=1), long[:20])
    assert not np.allclose(motion_poses("random", 60, seed=2), long)
    assert motion_poses("flexex", 1).shape == (1, 26)
    # 60 fps is the same motion sampled twice as densely.
    np.testing.assert_allclose(motion_poses("flexex", 61, fps=60.0)[::2], motion_poses("flexex", 31), atol=1e-9)
    rng = np.random.default_rng(0)
    start = rest_pose((10.0, 40.0, 380.0))
    start[3:6] += rng.uniform(-0.2, 0.2, 3)
    poses = motion_poses("pinch", 45, start=start)
    np.testing.assert_array_equal(poses[0], start)
    assert np.linalg.norm(poses[10, :3] - start[:3]) < 15.0
    with pytest.raises(InputError):
        motion_poses("moonwalk", 10)
    with pytest.raises(InputError):
        motion_poses("flexex", 0)
    with pytest.raises(InputError):
        motion_poses("flexex", 10, fps=0.0)
    with pytest.raises(InputError):
        motion_poses("flexex", 10, start=np.zeros(5))


def test_pinch_closes_thumb_on_index() -> None:
    model = default_hand_model(True)
    poses = motion_poses("pinch", 60)
    tips = np.stack([fingertips(model, p) for p in poses])
    gap = np.linalg.norm(tips[:, 0] - tips[:, 1], axis=1)
    touch = model.tip_radii[0] + model.tip_radii[1]
    assert gap[0] > 60.0
    assert abs(gap.min() - touch) < 2.0


def test_synthetic_sequence_ground_truth() -> None:
    shape = HandShape(length=1.05, width=0.95, depth=1.0, sigma=1.1)
    frames = list(synthetic_sequence("fingerwave", 4, shape=shape, right=False, seed=9, fps=25.0))
    assert [f.index for f in frames] == [0, 1, 2, 3]
    assert [f.stamp_s for f in frames] == pytest.approx([0.0, 0.04, 0.08, 0.12])
    poses = motion_poses("fingerwave", 4, fps=25.0, seed=9)
    model = default_hand_model(False).scaled(shape)
    for f, p in zip(frames, poses):
        np.testing.assert_array_equal(f.pose, p)
        np.testing.assert_allclose(f.fingertips_mm, fingertips(model, p))
        assert f.depth_mm.shape == (240, 320) and f.depth_mm.dtype == np.float32
    again = list(synthetic_sequence("fingerwave", 4, shape=shape, right=False, seed=9, fps=25.0))
    for a, b in zip(frames, again):
        np.testing.assert_array_equal(a.depth_mm, b.depth_mm)
    # Consecutive frames get different noise.
    wall = (frames[0].depth_mm > 850) & (frames[1].depth_mm > 850)
    assert np.count_nonzero(wall) > 10000
    assert np.count_nonzero(frames[0].depth_mm[wall] != frames[1].depth_mm[wall]) > 0.9 * np.count_nonzero(wall)
    # Exact rendering of the scaled model: the ground-truth tips sit on the surface.
    intr = default_intrinsics(640, 480)
    exact = next(iter(synthetic_sequence("flexex", 1, intrinsics=intr, shape=shape, options=EXACT)))
    m_right = default_hand_model(True).scaled(shape)
    for tip, r in zip(exact.fingertips_mm[1:], m_right.tip_radii[1:]):
        v, u = _px(intr, tip)
        assert exact.depth_mm[v, u] == pytest.approx(tip[2] - r, abs=1.0)
    with pytest.raises(InputError):
        next(iter(synthetic_sequence("nope", 3)))
