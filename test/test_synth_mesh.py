"""Mesh-hand renderer: glTF parser, skinning / pose mapping, rasteriser, sensors, shapes, new motions."""

from __future__ import annotations

import json
import struct
import time

import cv2
import numpy as np
import pytest

from hand_sog_tracker.core.hand_model import default_hand_model, rest_pose
from hand_sog_tracker.core.kinematics import global_rotation, skeleton_points
from hand_sog_tracker.core.types import Intrinsics
from hand_sog_tracker.errors import InputError
from hand_sog_tracker.synth.gltf import parse_glb, read_glb
from hand_sog_tracker.synth.mesh import (
    DEFAULT_HAND_LENGTH_MM,
    MESH_DIR,
    MeshRenderOptions,
    MeshShape,
    load_mesh_hand,
    mesh_fingertips,
    mesh_sequence,
    mirror_pose,
    pose_mesh,
    rasterise,
    render_mesh_depth,
)
from hand_sog_tracker.synth.motions import ALL_MOTIONS, EXTRA_MOTIONS, MOTIONS, key_articulations, motion_poses
from hand_sog_tracker.synth.sequence import default_intrinsics

CLEAN = MeshRenderOptions(sensor="clean")
CLEAN_NO_ARM = MeshRenderOptions(sensor="clean", forearm=False)


def _ray_mesh(verts: np.ndarray, tris: np.ndarray, o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Sorted ray parameters of all hits of ``o + t d`` with a triangle mesh (Moller-Trumbore)."""
    p0, p1, p2 = verts[tris[:, 0]], verts[tris[:, 1]], verts[tris[:, 2]]
    e1, e2 = p1 - p0, p2 - p0
    pv = np.cross(d, e2)
    det = np.einsum("ki,ki->k", e1, pv)
    ok = np.abs(det) > 1e-12
    inv = 1.0 / np.where(ok, det, 1.0)
    tv = o - p0
    u = np.einsum("ki,ki->k", tv, pv) * inv
    qv = np.cross(tv, e1)
    v = (qv @ d) * inv
    t = np.einsum("ki,ki->k", qv, e2) * inv
    hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
    return np.sort(t[hit])


def _pixel(intr: Intrinsics, p: np.ndarray) -> tuple[int, int]:
    uv = intr.project(np.asarray(p, dtype=float)[None])[0]
    return int(round(uv[1])), int(round(uv[0]))


# --- parser ------------------------------------------------------------------------------------


def test_parser_reads_the_webxr_hand() -> None:
    m = read_glb(MESH_DIR / "right.glb")
    assert m.positions.shape == (1360, 3) and m.triangles.shape == (2314, 3)
    assert len(m.joint_names) == 25
    assert m.joint_names[0] == "wrist" and "index-finger-phalanx-intermediate" in m.joint_names
    assert "thumb-tip" in m.joint_names and "pinky-finger-tip" in m.joint_names
    np.testing.assert_allclose(m.weights.sum(axis=1), 1.0, atol=1e-6)
    assert m.triangles.max() < 1360 and m.joints.max() < 25
    # The node hierarchy reproduces the skin's bind pose.
    np.testing.assert_allclose(m.bind_matrices @ m.inverse_bind_matrices, np.tile(np.eye(4), (25, 1, 1)), atol=1e-5)
    # Metres: a hand is about 0.2 m long.
    assert 0.15 < np.ptp(m.positions, axis=0).max() < 0.25
    left = read_glb(MESH_DIR / "left.glb")
    assert left.triangles.shape == (2314, 3) and sorted(left.joint_names) == sorted(m.joint_names)
    assert "MIT" in (MESH_DIR / "LICENSE.md").read_text()


def _tiny_glb() -> bytes:
    """Two triangles, interleaved POSITION + normalised ubyte WEIGHTS (stride 16), a matrix node."""
    pos = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], dtype="<f4")
    wts = np.array([[255, 0, 0, 0], [128, 127, 0, 0], [255, 0, 0, 0], [0, 255, 0, 0]], dtype=np.uint8)
    inter = b"".join(pos[i].tobytes() + wts[i].tobytes() for i in range(4))  # 16-byte records
    joints = np.array([[0, 1, 0, 0]] * 4, dtype=np.uint8).tobytes()
    idx = np.array([0, 1, 2, 2, 1, 3], dtype="<u2").tobytes() + b"\0\0"
    ibm = np.stack([np.eye(4), np.eye(4)]).astype("<f4").transpose(0, 2, 1).tobytes()
    binary = inter + joints + idx + ibm
    o1, o2, o3 = len(inter), len(inter) + len(joints), len(inter) + len(joints) + len(idx)
    mat = np.eye(4)
    mat[:3, 3] = [0.0, 0.0, 2.0]
    gltf = {
        "asset": {"version": "2.0"},
        "buffers": [{"byteLength": len(binary)}],
        "bufferViews": [
            {"buffer": 0, "byteOffset": 0, "byteLength": len(inter), "byteStride": 16},
            {"buffer": 0, "byteOffset": o1, "byteLength": len(joints)},
            {"buffer": 0, "byteOffset": o2, "byteLength": 12},
            {"buffer": 0, "byteOffset": o3, "byteLength": len(ibm)},
        ],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3"},
            {"bufferView": 0, "byteOffset": 12, "componentType": 5121, "normalized": True, "count": 4, "type": "VEC4"},
            {"bufferView": 1, "componentType": 5121, "count": 4, "type": "VEC4"},
            {"bufferView": 2, "componentType": 5123, "count": 6, "type": "SCALAR"},
            {"bufferView": 3, "componentType": 5126, "count": 2, "type": "MAT4"},
        ],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "WEIGHTS_0": 1, "JOINTS_0": 2}, "indices": 3}]}],
        "skins": [{"joints": [1, 2], "inverseBindMatrices": 4}],
        "nodes": [
            {"mesh": 0, "skin": 0},
            {"name": "root", "matrix": mat.T.reshape(-1).tolist(), "children": [2]},
            {"name": "child", "translation": [1.0, 0.0, 0.0],
             "rotation": [0.0, 0.0, np.sin(np.pi / 4), np.cos(np.pi / 4)]},
        ],
    }
    js = json.dumps(gltf).encode()
    js += b" " * (-len(js) % 4)
    body = struct.pack("<II", len(js), 0x4E4F534A) + js + struct.pack("<II", len(binary), 0x004E4942) + binary
    return struct.pack("<III", 0x46546C67, 2, 12 + len(body)) + body


def test_parser_handles_stride_normalized_and_node_matrices() -> None:
    m = parse_glb(_tiny_glb())
    np.testing.assert_allclose(m.positions, [[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]])
    np.testing.assert_allclose(m.weights[1, :2], [128 / 255, 127 / 255], atol=1e-6)  # normalized ubytes
    np.testing.assert_array_equal(m.triangles, [[0, 1, 2], [2, 1, 3]])
    assert m.joint_names == ("root", "child")
    np.testing.assert_allclose(m.bind_matrices[0][:3, 3], [0, 0, 2])
    child = m.bind_matrices[1]
    np.testing.assert_allclose(child[:3, 3], [1, 0, 2], atol=1e-12)
    np.testing.assert_allclose(child[:3, :3] @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=1e-12)  # 90 deg about z
    with pytest.raises(InputError):
        parse_glb(b"not a glb file at all")


# --- rasteriser --------------------------------------------------------------------------------


def test_rasteriser_matches_an_analytic_plane() -> None:
    intr = Intrinsics(fx=300.0, fy=310.0, cx=80.3, cy=59.7, width=160, height=120)
    # A tilted square plane z = 500 + 0.3 x - 0.2 y, x, y in [-60, 60] mm.
    xs = np.array([-60.0, 60.0, 60.0, -60.0])
    ys = np.array([-60.0, -60.0, 60.0, 60.0])
    verts = np.stack([xs, ys, 500 + 0.3 * xs - 0.2 * ys], axis=1)
    zbuf, tri = rasterise(verts, np.array([[0, 1, 2], [0, 2, 3]]), intr)
    hit = np.isfinite(zbuf)
    assert np.array_equal(hit, tri >= 0)
    v, u = np.nonzero(hit)
    rx, ry = (u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy
    z_true = 500.0 / (1.0 - 0.3 * rx + 0.2 * ry)  # ray t (rx, ry, 1) meets the plane
    np.testing.assert_allclose(zbuf[hit], z_true, rtol=1e-9)
    x_hit, y_hit = rx * z_true, ry * z_true
    assert np.all(np.abs(x_hit) <= 60 + 1e-6) and np.all(np.abs(y_hit) <= 60 + 1e-6)
    # Every pixel whose ray meets the square (away from the border) is covered: no cracks.
    vv, uu = np.mgrid[0:120, 0:160]
    rx, ry = (uu - intr.cx) / intr.fx, (vv - intr.cy) / intr.fy
    z = 500.0 / (1.0 - 0.3 * rx + 0.2 * ry)
    inside = (np.abs(rx * z) < 59.0) & (np.abs(ry * z) < 59.0)
    assert np.all(hit[inside])
    # A nearer triangle wins the z-test.
    near = np.array([[-10.0, -10.0, 300.0], [10.0, -10.0, 300.0], [0.0, 10.0, 300.0]])
    zb2, t2 = rasterise(np.concatenate([verts, near]), np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6]]), intr)
    v0, u0 = _pixel(intr, np.array([0.0, 0.0, 300.0]))
    assert zb2[v0, u0] == pytest.approx(300.0) and t2[v0, u0] == 2


# --- pose mapping and ground truth -------------------------------------------------------------


def test_flat_hand_palm_depth_and_hand_size() -> None:
    """Open flat hand, palm to the camera, wrist at 400 mm.

    The wrist joint (hand-frame origin) lies inside the hand near its back, so
    what is compared is the rendered palm skin at the projected palm centre
    (hand point (0, 50, 0)) against 400 mm minus the palm's palmar skin offset
    measured on the bind mesh along hand z (about 26 mm: the mesh's palm is
    ~39 mm thick there, 13 mm behind the wrist plane and 26 mm in front).  The
    pixel ray is 7 deg off hand z and meets the palm ~4 mm nearer the wrist,
    where it is thicker, and the skinning moves the thenar a little: about
    4 mm in all, hence the 5 mm tolerance; the exact check is against a ray
    cast of the posed mesh.
    """
    intr = default_intrinsics()
    theta = rest_pose((0.0, 0.0, 400.0))
    theta[6] = 0.0
    depth = render_mesh_depth(theta, intr, options=CLEAN_NO_ARM)
    hand = load_mesh_hand(True)
    hits = _ray_mesh(hand.vertices, hand.triangles, np.array([0.0, 50.0, -200.0]), np.array([0.0, 0.0, 1.0])) - 200.0
    assert hits[0] == pytest.approx(-12.6, abs=1.5)  # dorsal skin
    palmar = hits[-1]
    assert 20.0 < palmar < 32.0
    centre = global_rotation(theta) @ np.array([0.0, 50.0, 0.0]) + theta[:3]
    v, u = _pixel(intr, centre)
    assert depth[v, u] == pytest.approx(400.0 - palmar, abs=5.0)
    # Exactly the posed mesh's surface on that pixel's ray.
    pm = pose_mesh(theta, forearm=False)
    ray = np.array([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, 1.0])
    t = _ray_mesh(pm.vertices, pm.triangles, np.zeros(3), ray)
    assert depth[v, u] == pytest.approx(t[0], abs=1e-3)
    # Scaled to the default model: wrist to the end of the middle finger = 185 mm.
    tips = pose_mesh(theta).fingertips
    wrist_to_mid_tip = np.linalg.norm(tips[2] - theta[:3]) + hand.tip_radius[2]
    assert wrist_to_mid_tip == pytest.approx(DEFAULT_HAND_LENGTH_MM, abs=2.0)
    assert 184.0 < DEFAULT_HAND_LENGTH_MM < 187.0
    # Hand y points up the image (fingers above the wrist), thumb to the right for a right hand.
    uv = intr.project(tips)
    assert np.all(uv[1:, 1] < intr.project(theta[None, :3])[0, 1] - 60)
    assert uv[0, 0] > uv[4, 0] + 40


def _poses_with_visible_tips() -> list[np.ndarray]:
    k = key_articulations()
    out = []
    for name, tz in (("open", 400.0), ("spread", 350.0), ("pinch", 420.0), ("claw", 380.0)):
        th = rest_pose((10.0, 40.0, tz))
        th[6:] = k[name]
        out.append(th)
    tilted = rest_pose((0.0, 50.0, 420.0))
    tilted[3:6] += (0.3, 0.5, -0.2)
    out.append(tilted)
    return out


@pytest.mark.parametrize("right", [True, False])
def test_fingertip_truth_lies_just_behind_the_rendered_skin(right: bool) -> None:
    intr = default_intrinsics(640, 480)
    for theta in _poses_with_visible_tips():
        th = theta if right else mirror_pose(theta)
        pm = pose_mesh(th, right=right)
        depth = render_mesh_depth(th, intr, right=right, options=CLEAN, posed=pm)
        for tip in pm.fingertips:
            v, u = _pixel(intr, tip)
            assert depth[v, u] > 0, "fingertip projects off the hand"
            behind = tip[2] - depth[v, u]
            assert 0.5 < behind < 15.0, behind


def test_zero_pose_points_along_the_model_and_joints_follow_our_chain() -> None:
    """Bones follow our kinematic chain: at any pose, consecutive mesh pivots lie along our segment directions."""
    model = default_hand_model(True)
    hand = load_mesh_hand(True)
    theta = motion_poses("random", 40, seed=3)[-1]
    pm = pose_mesh(theta, forearm=False)
    ours = skeleton_points(model, theta)[1:].reshape(5, 4, 3)
    for c in range(5):
        for k in range(3):
            d_mesh = pm.joints[c, k + 1] - pm.joints[c, k]
            d_ours = ours[c, k + 1] - ours[c, k]
            assert np.linalg.norm(d_mesh) == pytest.approx(hand.lengths[c, k], rel=1e-9)
            cosang = d_mesh @ d_ours / np.linalg.norm(d_mesh) / np.linalg.norm(d_ours)
            assert cosang > 1 - 1e-9
    # Mesh proportions, not the model's: the truth differs from the model's fingertips by mm, not cm.
    from hand_sog_tracker.core.kinematics import fingertips

    diff = np.linalg.norm(pm.fingertips - fingertips(model, theta), axis=1)
    assert 2.0 < diff.mean() < 25.0


def test_left_render_mirrors_the_right() -> None:
    intr = default_intrinsics()
    for name, k in (("pinch", 30), ("random", 40), ("fistopen", 20)):
        th = motion_poses(name, 45, seed=4)[k]
        right = render_mesh_depth(th, intr, options=CLEAN)
        left = render_mesh_depth(mirror_pose(th), intr, right=False, options=CLEAN)[:, ::-1]
        mr, ml = right > 0, left > 0
        assert (mr & ml).sum() / (mr | ml).sum() > 0.97
        both = mr & ml
        assert np.median(np.abs(right[both] - left[both])) < 1.0
        uv_r = intr.project(mesh_fingertips(th))
        uv_l = intr.project(mesh_fingertips(mirror_pose(th), right=False))
        uv_l[:, 0] = intr.width - 1 - uv_l[:, 0]
        assert np.linalg.norm(uv_r - uv_l, axis=1).max() < 4.0


def test_shape_factors_change_what_they_should() -> None:
    theta = rest_pose((0.0, 40.0, 400.0))
    base = pose_mesh(theta, forearm=False)
    longer = pose_mesh(theta, MeshShape(length=1.12), forearm=False)
    # Finger length: pivot-to-tip distance scales by the factor (within 3%); the palm does not move.
    d0 = np.linalg.norm(base.fingertips - base.joints[:, 0], axis=1)
    d1 = np.linalg.norm(longer.fingertips - longer.joints[:, 0], axis=1)
    np.testing.assert_allclose(d1 / d0, 1.12, rtol=0.03)
    np.testing.assert_allclose(longer.joints[:, 0], base.joints[:, 0], atol=1e-9)
    # Palm width: hand-x of the finger bases scales, their y stays.
    wide = pose_mesh(theta, MeshShape(palm_width=1.1), forearm=False)
    G = global_rotation(theta)
    hb = (base.joints[:, 0] - theta[:3]) @ G
    hw = (wide.joints[:, 0] - theta[:3]) @ G
    np.testing.assert_allclose(hw[:, 0], 1.1 * hb[:, 0], rtol=1e-9)
    np.testing.assert_allclose(hw[:, 1], hb[:, 1], atol=1e-9)
    # Thickness: the rendered middle finger gets wider across; finger lengths stay.
    intr = default_intrinsics(640, 480)

    def finger_width(shape: MeshShape) -> int:
        pm = pose_mesh(theta, shape, forearm=False)
        depth = render_mesh_depth(theta, intr, shape, options=CLEAN_NO_ARM, posed=pm)
        mid = 0.5 * (pm.joints[2, 1] + pm.joints[2, 2])  # middle of the intermediate phalanx
        v, u = _pixel(intr, mid)
        row = depth[v] > 0
        lo = u
        while row[lo - 1]:
            lo -= 1
        hi = u
        while row[hi + 1]:
            hi += 1
        return hi - lo + 1

    w0, w1 = finger_width(MeshShape()), finger_width(MeshShape(thickness=1.15))
    assert 1.05 < w1 / w0 < 1.25, (w0, w1)
    thick = pose_mesh(theta, MeshShape(thickness=1.15), forearm=False)
    np.testing.assert_allclose(thick.joints, base.joints, atol=1e-9)
    with pytest.raises(InputError):
        MeshShape(length=0.2)


@pytest.mark.parametrize("right", [True, False])
def test_per_finger_length_factors_lengthen_that_finger_alone(right: bool) -> None:
    """``MeshShape.fingers``: a long ring finger and a short little finger, the rest as before."""
    theta = rest_pose((0.0, 40.0, 400.0))
    base = pose_mesh(theta, MeshShape(length=0.95), right=right, forearm=False)
    shape = MeshShape(length=0.95, fingers=(1.0, 1.0, 1.0, 1.08, 0.9))
    odd = pose_mesh(theta, shape, right=right, forearm=False)
    d0 = np.linalg.norm(base.fingertips - base.joints[:, 0], axis=1)
    d1 = np.linalg.norm(odd.fingertips - odd.joints[:, 0], axis=1)
    np.testing.assert_allclose(d1[3:] / d0[3:], (1.08, 0.9), rtol=0.03)
    np.testing.assert_allclose(odd.fingertips[:3], base.fingertips[:3], atol=1e-9)
    np.testing.assert_allclose(odd.joints[:, 0], base.joints[:, 0], atol=1e-9)
    # The skin follows its bones: the ring finger's rendered end moves out with its truth.
    intr = default_intrinsics(640, 480)
    far = render_mesh_depth(theta, intr, shape, right=right, options=CLEAN_NO_ARM, posed=odd)
    near = render_mesh_depth(theta, intr, MeshShape(length=0.95), right=right, options=CLEAN_NO_ARM, posed=base)
    u = int(round(intr.project(odd.fingertips[3:4])[0, 0]))
    assert (far[:, u] > 0).nonzero()[0].min() < (near[:, u] > 0).nonzero()[0].min() - 3  # (v grows down the hand)
    assert MeshShape(fingers=[1, 1, 1, 1, 1]) == MeshShape()  # (stored as a tuple of floats)
    for bad in ((1.0, 1.0), (1.0, 1.0, 1.0, 1.0, 0.2), (1.0, 1.0, float("nan"), 1.0, 1.0)):
        with pytest.raises(InputError):
            MeshShape(fingers=bad)


# --- sensors, determinism ----------------------------------------------------------------------


def test_sensor_models_and_determinism() -> None:
    intr = default_intrinsics()
    theta = motion_poses("pinch", 30, seed=1)[-1]
    clean = render_mesh_depth(theta, intr, options=CLEAN)
    on = clean > 0
    tof = render_mesh_depth(theta, intr, options=MeshRenderOptions(sensor="tof"), rng=np.random.default_rng(5))
    both = on & (tof > 0)
    err = tof[both] - clean[both]
    inner = np.abs(err) < 20.0  # away from flying pixels
    assert 0.7 < np.std(err[inner]) < 2.5 and abs(np.mean(err[inner])) < 0.3
    assert np.all(tof == np.round(tof))  # whole millimetres
    assert 0.8 * on.sum() < (tof > 0).sum() < on.sum()  # some dropout, not much
    # Flying pixels between foreground and background at the silhouette (with a wall behind).
    wall_opts = dict(background_mm=700.0)
    clean_w = render_mesh_depth(theta, intr, options=MeshRenderOptions(sensor="clean", **wall_opts))
    tof_w = render_mesh_depth(
        theta, intr, options=MeshRenderOptions(sensor="tof", **wall_opts), rng=np.random.default_rng(5)
    )
    flying = (tof_w > 0) & (np.abs(tof_w - clean_w) > 20.0)
    assert flying.sum() > 30
    assert np.all((tof_w[flying] > clean[on].min() - 5) & (tof_w[flying] < 705.0))
    sl = render_mesh_depth(theta, intr, options=MeshRenderOptions(sensor="structured"), rng=np.random.default_rng(5))
    valid = sl > 0
    assert valid.sum() > 0.7 * on.sum() and not np.any(valid & ~on)
    disp8 = intr.fx * 50.0 / sl[valid].astype(np.float64) * 8.0
    np.testing.assert_allclose(disp8, np.round(disp8), atol=2e-3)  # quantised disparity, 1/8 px
    assert np.median(np.abs(sl[valid] - clean[valid])) < 2.0
    again = render_mesh_depth(theta, intr, options=MeshRenderOptions(sensor="tof"), rng=np.random.default_rng(5))
    np.testing.assert_array_equal(tof, again)
    other = render_mesh_depth(theta, intr, options=MeshRenderOptions(sensor="tof"), rng=np.random.default_rng(6))
    assert not np.array_equal(tof, other)
    wall = render_mesh_depth(theta, intr, options=MeshRenderOptions(sensor="clean", background_mm=800.0))
    assert np.all(wall[~on] == 800.0) and np.array_equal(wall[on], clean[on])
    with pytest.raises(InputError):
        MeshRenderOptions(sensor="lidar")


def test_tof_sparse_dropout_reaches_the_hand_without_a_wall() -> None:
    """Sparse random dropout (0.2% of the pixels) falls inside the hand too, with or without a
    wall: before the fix it was written to a copy whenever the valid depth did not span the
    image's width, so that a hand alone had none."""
    intr = default_intrinsics()
    theta = motion_poses("pinch", 30, seed=1)[0]
    clean = render_mesh_depth(theta, intr, options=CLEAN)
    # The interior of the hand: 5 x 5 neighbourhoods all on the hand and within 10 mm (no edge,
    # no grazing surface, where the other dropouts fall).
    k = np.ones((5, 5), np.uint8)
    on = cv2.erode((clean > 0).astype(np.uint8), k) > 0
    interior = on & (cv2.dilate(clean, k) - cv2.erode(clean, k) < 10.0)
    assert interior.sum() > 3000
    for wall in (None, 700.0):
        opts = MeshRenderOptions(sensor="tof", background_mm=wall)
        renders = [render_mesh_depth(theta, intr, options=opts, rng=np.random.default_rng(s)) for s in range(4)]
        counts = [int(np.count_nonzero(interior & (depth == 0))) for depth in renders]
        share = sum(counts) / (4 * interior.sum())
        assert 0.001 < share < 0.004, (wall, counts)


def test_mesh_sequence_is_deterministic_and_times_frames() -> None:
    intr = default_intrinsics()
    a = list(mesh_sequence("fistopen", 3, intr, MeshShape(0.9, 1.05, 0.95), seed=7))
    b = list(mesh_sequence("fistopen", 3, intr, MeshShape(0.9, 1.05, 0.95), seed=7))
    c = list(mesh_sequence("fistopen", 3, intr, MeshShape(0.9, 1.05, 0.95), seed=8))
    for fa, fb in zip(a, b):
        np.testing.assert_array_equal(fa.depth_mm, fb.depth_mm)
        np.testing.assert_array_equal(fa.fingertips_mm, fb.fingertips_mm)
    assert not np.array_equal(a[2].depth_mm, c[2].depth_mm)
    assert a[0].depth_mm.dtype == np.float32 and a[0].depth_mm.shape == (240, 320)
    # Benchmark-like print, not asserted: render time per frame.
    theta = a[1].pose
    for w, h in ((320, 240), (640, 480)):
        it = default_intrinsics(w, h)
        t0 = time.perf_counter()
        for _ in range(3):
            render_mesh_depth(theta, it, options=MeshRenderOptions(sensor="tof"))
        print(f"mesh render {w}x{h} tof: {(time.perf_counter() - t0) / 3 * 1000:.1f} ms/frame")


# --- new motions -------------------------------------------------------------------------------


def test_capsule_motion_set_is_unchanged_and_extras_are_separate() -> None:
    assert MOTIONS == ("abdadd", "fingercount", "fingerwave", "flexex", "pinch", "tigergrasp", "random")
    assert EXTRA_MOTIONS == ("fistopen", "rotate") and ALL_MOTIONS == MOTIONS + EXTRA_MOTIONS


@pytest.mark.parametrize("name", EXTRA_MOTIONS)
def test_extra_motions_in_view_and_within_limits(name: str) -> None:
    model = default_hand_model(True)
    intr = default_intrinsics()
    poses = motion_poses(name, 120, seed=5)
    q = poses[:, 6:]
    assert np.all(q >= model.limits_low) and np.all(q <= model.limits_high)
    assert np.abs(np.diff(q, axis=0)).max() < np.deg2rad(20.0)
    for right in (True, False):
        tips = np.stack([mesh_fingertips(p if right else mirror_pose(p), right=right) for p in poses[::4]])
        uv = intr.project(tips.reshape(-1, 3))
        assert uv[:, 0].min() > 5 and uv[:, 0].max() < 315 and uv[:, 1].min() > 5 and uv[:, 1].max() < 235
        assert 250.0 < tips[..., 2].min() and tips[..., 2].max() < 520.0
    R = np.stack([global_rotation(p) for p in poses])
    cosang = (np.einsum("tij,tij->t", R[:-1], R[1:]) - 1.0) / 2.0
    speed = np.degrees(np.arccos(np.clip(cosang, -1.0, 1.0))).max() * 30.0
    if name == "fistopen":
        deg = np.degrees(q.max(axis=0)).reshape(5, 4)
        assert np.all(deg[1:, 0] > 84) and np.all(deg[1:, 2] > 100) and np.all(deg[1:, 3] > 70)
        assert np.degrees(q.min(axis=0)).reshape(5, 4)[1:, 0].max() < 5  # opens again
        assert speed < 20.0
    else:
        assert speed > 150.0
        # The palm turns away / sideways: the palm normal leaves the camera axis by 50-80 deg.
        normal = R[:, :, 2]  # hand z in the camera frame
        away = np.degrees(np.arccos(np.clip(-normal[:, 2], -1.0, 1.0)))
        assert 50.0 < away.max() < 85.0


@pytest.mark.parametrize("right", [True, False])
def test_the_forearm_turns_at_the_wrist_and_the_hand_stays(right: bool) -> None:
    """MeshRenderOptions' wrist angles turn only the forearm, about the wrist, by their angle."""
    theta = motion_poses("abdadd", 1, seed=2)[0]
    straight = pose_mesh(theta, right=right)
    options = MeshRenderOptions(wrist_deviation_deg=30.0, wrist_flexion_deg=-20.0)
    bent = pose_mesh(theta, right=right, wrist_rad=options.wrist_rad)
    n = straight.n_hand_vertices
    np.testing.assert_array_equal(bent.vertices[:n], straight.vertices[:n])
    np.testing.assert_array_equal(bent.fingertips, straight.fingertips)
    # The forearm's end (its cap centre, the last vertex) seen from the wrist (the hand origin).
    a = straight.vertices[-1] - theta[:3]
    b = bent.vertices[-1] - theta[:3]
    assert np.linalg.norm(a) == pytest.approx(np.linalg.norm(b))
    cos = float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))
    expected = np.cos(np.deg2rad(30.0)) * np.cos(np.deg2rad(20.0))  # (a along -y: z then x turn)
    assert cos == pytest.approx(expected, abs=1e-9)
    with pytest.raises(InputError, match="wrist_deviation_deg"):
        MeshRenderOptions(wrist_deviation_deg=75.0)


def test_reported_palm_keypoints_lie_on_the_mesh_hands_joints() -> None:
    """The tracker's published wrist and MCPs (``TrackResult.skeleton_mm``) are the anatomical
    joint centres of the mesh hand it is fitted to, where the kinematic skeleton is 9-18 mm off."""
    from hand_sog_tracker.core.tracker import Tracker
    from hand_sog_tracker.core.types import TrackerConfig

    intr = default_intrinsics()
    palm = [0, 5, 9, 13, 17]
    for right in (True, False):
        tracker = Tracker(TrackerConfig(right_hand=right))
        theta = rest_pose((10.0, 0.0, 420.0))
        theta[6:] += 0.15
        pm = pose_mesh(theta, right=right, forearm=True)
        depth = render_mesh_depth(theta, intr, right=right, options=CLEAN, posed=pm)
        truth = np.concatenate([theta[None, :3], pm.joints[1:, 0]])
        for _ in range(3):
            res = tracker.process(depth, intr)
        assert res.pose is not None and res.skeleton_mm is not None
        reported = np.linalg.norm(res.skeleton_mm[palm] - truth, axis=1).mean()
        kinematic = np.linalg.norm(skeleton_points(tracker.model, res.pose)[palm] - truth, axis=1).mean()
        assert reported < 8.0 and kinematic > reported + 3.0, (reported, kinematic)
