"""Two-hand scenes: compositing (the nearer hand wins), per-hand ground truth consistent with the depth."""

from __future__ import annotations

import numpy as np
import pytest

from hand_sog_tracker.errors import InputError
from hand_sog_tracker.synth.mesh import (
    MeshRenderOptions,
    MeshShape,
    load_mesh_hand,
    mesh_fingertips,
    render_mesh_depth,
)
from hand_sog_tracker.synth.sequence import default_intrinsics
from hand_sog_tracker.synth.twohands import SCENES, TwoHandScene, render_two_hands, scene_poses, two_hand_sequence

SHAPES = (MeshShape(0.9, 1.05, 0.95), MeshShape(1.1, 0.92, 1.08))


def _frame(scene: str, k: int, n: int = 45):
    sc = TwoHandScene(scene, SHAPES)
    left, right, ball = scene_poses(sc, n, seed=3)
    return sc, left[k], right[k], ball[k, :3]


def test_composite_is_the_nearer_of_the_two_hands_rendered_alone() -> None:
    intr = default_intrinsics(160, 120)
    sc, left, right, _ = _frame("occlude", 40)
    depth, truths, owner = render_two_hands(left, right, intr, SHAPES, "clean")
    alone = [
        render_mesh_depth(pose, intr, shape, side, MeshRenderOptions(sensor="clean"))
        for pose, shape, side in ((left, SHAPES[0], False), (right, SHAPES[1], True))
    ]
    za, zb = (np.where(a > 0, a, np.inf) for a in alone)
    both = (za < np.inf) & (zb < np.inf)
    assert both.sum() > 200  # the hands overlap in the image
    expect = np.minimum(za, zb)
    np.testing.assert_allclose(depth[expect < np.inf], expect[expect < np.inf], atol=1e-3)
    assert np.all(depth[expect == np.inf] == 0)
    # the owner is the nearer hand: the right hand is in front in the dev scene
    assert np.all(owner[both & (zb < za - 1.0)] == 1) and np.all(owner[both & (za < zb - 1.0)] == 0)
    assert truths[1].visible_fraction == pytest.approx(1.0)
    assert 0.1 < truths[0].visible_fraction < 0.95


def test_fingertip_visibility_agrees_with_the_depth() -> None:
    intr = default_intrinsics()
    seen_hidden = seen_visible = 0
    for scene, k in (("occlude", 44), ("cross", 22), ("apart", 10)):
        _, left, right, ball = _frame(scene, k)
        depth, truths, _ = render_two_hands(left, right, intr, SHAPES, "clean", ball_mm=ball)
        for t, right_hand, shape in zip(truths, (False, True), SHAPES):
            r = load_mesh_hand(right_hand).tip_radius * shape.thickness
            u = np.rint(intr.fx * t.fingertips_mm[:, 0] / t.fingertips_mm[:, 2] + intr.cx).astype(int)
            v = np.rint(intr.fy * t.fingertips_mm[:, 1] / t.fingertips_mm[:, 2] + intr.cy).astype(int)
            for c in range(5):
                z = depth[v[c], u[c]]
                if t.tips_visible[c]:  # the skin in front of the tip's centre, about one radius
                    assert t.fingertips_mm[c, 2] - 2.5 * r[c] - 2.0 < z < t.fingertips_mm[c, 2] + 1.0
                    seen_visible += 1
                else:  # something well in front of it
                    assert 0 < z < t.fingertips_mm[c, 2] - 20.0
                    seen_hidden += 1
            np.testing.assert_allclose(t.keypoints_mm[4::4], t.fingertips_mm)
            np.testing.assert_allclose(t.keypoints_mm[0], t.pose[:3])
    assert seen_hidden >= 2 and seen_visible >= 20


def test_every_scene_renders_both_hands_in_view_and_is_deterministic() -> None:
    intr = default_intrinsics(160, 120)
    for scene in SCENES:
        sc = TwoHandScene(scene, SHAPES)
        a = list(two_hand_sequence(sc, 2, intr, seed=5, sensor="tof"))
        b = list(two_hand_sequence(sc, 2, intr, seed=5, sensor="tof"))
        np.testing.assert_array_equal(a[1].depth_mm, b[1].depth_mm)
        for f in a:
            assert {int(x) for x in np.unique(f.owner)} >= {0, 1}, scene
            assert [h.handedness for h in f.hands] == ["left", "right"]
    c = next(iter(two_hand_sequence(TwoHandScene("cross", SHAPES), 1, intr, seed=6, sensor="tof")))
    assert not np.array_equal(c.depth_mm, a[0].depth_mm)


def test_sensor_noise_is_applied_to_the_composite() -> None:
    intr = default_intrinsics(160, 120)
    _, left, right, _ = _frame("cross", 20)
    clean = render_two_hands(left, right, intr, SHAPES, "clean")[0]
    for sensor in ("tof", "structured"):
        noisy = render_two_hands(left, right, intr, SHAPES, sensor, np.random.default_rng(1))[0]
        both = (clean > 0) & (noisy > 0)
        assert 0 < np.mean(np.abs(noisy[both] - clean[both])) < 5.0
        assert np.count_nonzero(noisy == 0) > np.count_nonzero(clean == 0)  # holes, dropout


def test_touching_middle_fingertips_end_in_contact() -> None:
    sc = TwoHandScene("touch", SHAPES)
    left, right, _ = scene_poses(sc, 40, seed=2)

    d = [np.linalg.norm(mesh_fingertips(left[k], SHAPES[0], False)[2] - mesh_fingertips(right[k], SHAPES[1], True)[2])
         for k in (0, 39)]
    r = (load_mesh_hand(True).tip_radius[2] * SHAPES[1].thickness
         + load_mesh_hand(False).tip_radius[2] * SHAPES[0].thickness)
    assert d[0] > r + 40.0 and d[1] == pytest.approx(r, abs=1e-6)


def test_scene_arguments_are_checked() -> None:
    with pytest.raises(InputError):
        TwoHandScene("juggle")
    with pytest.raises(InputError):
        TwoHandScene("cross", front="middle")  # type: ignore[arg-type]
    with pytest.raises(InputError):
        scene_poses(TwoHandScene("cross"), 0)
    with pytest.raises(InputError):
        render_two_hands(*scene_poses(TwoHandScene("cross"), 1)[:2], default_intrinsics(), sensor="lidar")


def test_a_hand_can_be_rendered_alone_in_its_scene() -> None:
    intr = default_intrinsics(160, 120)
    _, left, right, _ = _frame("occlude", 40)
    depth, truths, owner = render_two_hands(left, right, intr, SHAPES, "clean", shown=("left",))
    alone = render_mesh_depth(left, intr, SHAPES[0], False, MeshRenderOptions(sensor="clean"))
    np.testing.assert_allclose(depth, alone, atol=1e-3)
    assert 1 not in owner and truths[0].visible_fraction == pytest.approx(1.0)
    assert truths[1].visible_fraction == 0.0 and not truths[1].tips_visible.any()
    with pytest.raises(InputError):
        render_two_hands(left, right, intr, SHAPES, "clean", shown=())
