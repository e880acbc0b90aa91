"""Scenes around the mesh hand: hands entering and leaving, objects, people, tables (issue 46).

One job: script and render the scene sets that test whether the tracker knows when it sees a
hand; kept together because the scene scripts share the object meshes and the ground truth.

A scene is a scripted sequence of camera-frame triangle meshes (the skinned mesh hand of
:mod:`.mesh` with its forearm, and simple objects: ellipsoids, cylinders, boxes) drawn by
:func:`~hand_sog_tracker.synth.raster.rasterise` and a sensor model of :mod:`.sensors`.
Scene types (:data:`SCENE_TYPES`):

* ``leave_bottom``, ``leave_left``, ``leave_right``, ``leave_top``: the forearm comes from that
  border (fingers pointing into the image; from the top with the back of the hand to the
  camera, as seen from the head); the hand slides out across that border, stays out, and comes
  back (forearm first out, fingers first back in).
* ``slide_out``: the forearm from below; the hand slides out sideways while the forearm stays
  in view at the border, and comes back.
* ``back``: the back of the hand to the camera (camera above and behind, tilted).
* ``nohand_head`` (head, neck and torso), ``nohand_arm`` (a forearm whose hand is beyond the
  border), ``nohand_objects`` (cup, bottle, box and a table edge): no hand at any frame.
* ``hold_cylinder``, ``hold_ball``, ``hold_box``: fingers wrapped round an object that hides
  part of them; seen from the thumb side.
* ``table``: the hand resting palm down on a table top, the camera looking down at it.

Ground truth per frame (:class:`SceneFrame`): the visibility (:data:`FULL`, :data:`PARTIAL`,
:data:`ABSENT`: all, some or none of the 21 joints project inside the image, 4 px margin), the
21 joints in MediaPipe order (wrist, then per chain thumb .. little its three joints and the
fingertip as :mod:`.mesh` defines it) and the five fingertips, camera optical frame, mm.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Final

import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.hand_model import JOINTS, rest_pose
from hand_sog_tracker.core.rotations import euler_from_matrix, rot_x, rot_y, rot_z
from hand_sog_tracker.core.types import Intrinsics
from hand_sog_tracker.errors import InputError
from hand_sog_tracker.synth.mesh import MeshShape, PosedMesh, pose_mesh
from hand_sog_tracker.synth.motions import motion_poses
from hand_sog_tracker.synth.raster import rasterise, view_cosine
from hand_sog_tracker.synth.sensors import SENSORS, apply_sensor

__all__ = [
    "SCENE_TYPES",
    "NO_HAND_TYPES",
    "FULL",
    "PARTIAL",
    "ABSENT",
    "SceneFrame",
    "scene_frames",
    "scene_group",
]

LEAVE_TYPES: Final = ("leave_bottom", "leave_left", "leave_right", "leave_top", "slide_out")
NO_HAND_TYPES: Final = ("nohand_head", "nohand_arm", "nohand_objects")
HOLD_TYPES: Final = ("hold_cylinder", "hold_ball", "hold_box")
#: Every scene type :func:`scene_frames` renders.
SCENE_TYPES: Final = LEAVE_TYPES + ("back",) + NO_HAND_TYPES + HOLD_TYPES + ("table",)

FULL: Final = "full"
PARTIAL: Final = "partial"
ABSENT: Final = "absent"
_MARGIN_PX = 4.0  #: a joint this close to the border counts as outside (the finger's width)

_DEG = np.pi / 180.0
Mesh = tuple[NDArray[np.float64], NDArray[np.int64]]


def scene_group(kind: str) -> str:
    """The reporting group of a scene type: ``leave``, ``no_hand``, ``hold`` or the type itself."""
    if kind in LEAVE_TYPES:
        return "leave"
    if kind in NO_HAND_TYPES:
        return "no_hand"
    if kind in HOLD_TYPES:
        return "hold"
    return kind


@dataclass(frozen=True, eq=False)
class SceneFrame:
    """One rendered scene frame and its ground truth.

    Attributes
    ----------
    index : int
    stamp_s : float
    depth_mm : array, shape (H, W), float32
        Depth, mm, 0 = invalid.
    visibility : str
        :data:`FULL`, :data:`PARTIAL` or :data:`ABSENT`.
    joints_mm : array, shape (21, 3) or None
        The hand's 21 joints (MediaPipe order), camera frame, mm; None without a hand.
    fingertips_mm : array, shape (5, 3) or None
        Its fingertips (thumb .. little), mm (rows 4, 8, 12, 16, 20 of ``joints_mm``).
    """

    index: int
    stamp_s: float
    depth_mm: NDArray[np.float32]
    visibility: str
    joints_mm: NDArray[np.float64] | None
    fingertips_mm: NDArray[np.float64] | None


# -- object meshes (camera frame, mm) ----------------------------------------------------------
def _ellipsoid(centre: NDArray[np.float64], radii: tuple[float, float, float], n: int = 14) -> Mesh:
    lat = np.linspace(0.0, np.pi, n + 1)[1:-1]
    lon = np.linspace(0.0, 2.0 * np.pi, 2 * n, endpoint=False)
    ring = np.stack(
        [
            np.sin(lat)[:, None] * np.cos(lon)[None, :],
            np.cos(lat)[:, None] + 0 * lon,
            np.sin(lat)[:, None] * np.sin(lon),
        ],
        axis=2,
    ).reshape(-1, 3)
    v = np.concatenate([[[0.0, 1.0, 0.0]], ring, [[0.0, -1.0, 0.0]]]) * np.asarray(radii) + centre
    m = 2 * n
    tris = [[0, 1 + (k + 1) % m, 1 + k] for k in range(m)]
    for i in range(n - 2):
        for k in range(m):
            a, b = 1 + i * m + k, 1 + i * m + (k + 1) % m
            tris += [[a, b, b + m], [a, b + m, a + m]]
    last = v.shape[0] - 1
    base = 1 + (n - 2) * m
    tris += [[last, base + k, base + (k + 1) % m] for k in range(m)]
    return v, np.asarray(tris, dtype=np.int64)


def _cylinder(
    centre: NDArray[np.float64], radius: float, height: float, R: NDArray[np.float64], sides: int = 20
) -> Mesh:
    """Closed cylinder along local y (height mm), rotated by ``R`` (3, 3), centred at ``centre``."""
    a = np.linspace(0.0, 2.0 * np.pi, sides, endpoint=False)
    ring = np.stack([radius * np.cos(a), np.zeros(sides), radius * np.sin(a)], 1)
    top, bot = ring + [0.0, -height / 2, 0.0], ring + [0.0, height / 2, 0.0]
    v = np.concatenate([top, bot, [[0.0, -height / 2, 0.0], [0.0, height / 2, 0.0]]])
    k = np.arange(sides)
    k1 = (k + 1) % sides
    tris = np.concatenate([
        np.stack([k, k1, k1 + sides], 1), np.stack([k, k1 + sides, k + sides], 1),
        np.stack([np.full(sides, 2 * sides), k1, k], 1),
        np.stack([np.full(sides, 2 * sides + 1), k + sides, k1 + sides], 1),
    ])
    return v @ R.T + centre, tris.astype(np.int64)


def _box(centre: NDArray[np.float64], half: tuple[float, float, float], R: NDArray[np.float64]) -> Mesh:
    s = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64)
    v = (s * np.asarray(half)) @ R.T + centre
    faces = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    tris = [[a, b, c] for a, b, c, d in faces] + [[a, c, d] for a, b, c, d in faces]
    return v, np.asarray(tris, dtype=np.int64)


# -- the scene scripts --------------------------------------------------------------------------
def _smooth(x: NDArray[np.float64]) -> NDArray[np.float64]:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def _out_in(n: int) -> NDArray[np.float64]:
    """Per frame 0 (in view) .. 1 (out): in 20%, out over 13%, out 13%, back over 17%, in 37%."""
    s = np.arange(n) / max(n - 1, 1)
    return _smooth((s - 0.2) / 0.13) * (1.0 - _smooth((s - 0.46) / 0.17))


def _pose_from(R: NDArray[np.float64], wrist: NDArray[np.float64], joints: NDArray[np.float64]) -> NDArray[np.float64]:
    theta = np.zeros(26)
    theta[:3] = wrist
    theta[3:6] = euler_from_matrix(R)
    theta[JOINTS] = joints
    return theta


def _grip(kind: str, rng: np.random.Generator) -> NDArray[np.float64]:
    """Joint angles (20,) of a grasp round an object of ``kind`` (rad)."""
    q = rest_pose()[JOINTS].copy()
    flex = {"hold_cylinder": (55.0, 70.0, 40.0), "hold_ball": (45.0, 50.0, 30.0), "hold_box": (60.0, 35.0, 20.0)}[kind]
    for c in range(1, 5):
        q[4 * c + 1 : 4 * c + 4] = np.array(flex) * _DEG * rng.uniform(0.9, 1.1, 3)
    q[0:4] = np.array([0.5, 0.4, 0.5, 0.4]) * rng.uniform(0.9, 1.1, 4)
    return q


def _script(kind: str, n: int, intr: Intrinsics, rng: np.random.Generator, motion_seed: int):
    """Per frame: (hand pose (26,) or None, forearm wrist turn (rad, rad), object meshes)."""
    t = np.arange(n) / 30.0
    motion = ("fingerwave", "abdadd", "flexex", "fingercount")[motion_seed % 4]
    art = motion_poses(motion, n, seed=motion_seed)[:, JOINTS]
    z = rng.uniform(380.0, 470.0)
    half_w = 0.5 * intr.width * z / intr.fx  # half the image width at depth z (mm)
    half_h = 0.5 * intr.height * z / intr.fy
    frames = []
    if kind in LEAVE_TYPES or kind == "back":
        roll = {"leave_bottom": 0.0, "leave_left": np.pi / 2, "leave_right": -np.pi / 2, "leave_top": np.pi,
                "slide_out": 0.0, "back": 0.0}[kind]
        back = kind in ("leave_top", "back")
        tilt = rng.uniform(-15.0, 15.0) * _DEG
        R = rot_z(roll + rng.uniform(-10.0, 10.0) * _DEG) @ rot_x(np.pi + tilt) @ (rot_y(np.pi) if back else np.eye(3))
        if kind == "back":
            R = rot_x(rng.uniform(20.0, 35.0) * _DEG) @ R  # the camera above and behind the hand
        fingers = R[:, 1]  # fingers' direction, camera frame; the arm points the other way
        centre_in = np.array([rng.uniform(-20.0, 20.0), rng.uniform(-15.0, 15.0), z])
        wrist_in = centre_in - 70.0 * fingers
        if kind == "slide_out":
            out_dir = np.array([1.0 if rng.random() < 0.5 else -1.0, 0.0, 0.0])
            dist = half_w + 110.0
        else:
            out_dir = -fingers * np.array([1.0, 1.0, 0.0])
            out_dir /= np.linalg.norm(out_dir)
            ext = half_h if abs(out_dir[1]) > abs(out_dir[0]) else half_w
            dist = ext + 230.0  # the fingertips ~ 190 mm beyond the wrist leave the image
        s = _out_in(n) if kind != "back" else np.zeros(n)
        for k in range(n):
            drift = 8.0 * np.array([np.sin(1.3 * t[k]), np.cos(0.9 * t[k]), 0.0])
            pose = _pose_from(R, wrist_in + drift + s[k] * dist * out_dir, art[k])
            frames.append((pose, (0.0, 0.0), []))
        return frames
    if kind in NO_HAND_TYPES:
        sway = rng.uniform(-1.0, 1.0, 2)
        for k in range(n):
            d = np.array([25.0 * np.sin(0.8 * t[k] + sway[0]), 8.0 * np.sin(1.1 * t[k] + sway[1]), 0.0])
            objs: list[Mesh] = []
            pose = None
            if kind == "nohand_head":
                zc = 600.0 + 60.0 * sway[1]
                head = np.array([0.0, -0.25 * half_h, zc]) + d
                objs += [
                    _ellipsoid(head, (72.0, 95.0, 85.0)),
                    _cylinder(head + [0.0, 120.0, 10.0], 45.0, 70.0, np.eye(3)),
                    _box(head + [0.0, 300.0, 40.0], (170.0, 150.0, 80.0), rot_y(0.2 * sway[0])),
                ]
            elif kind == "nohand_arm":
                # A hand beyond the left or right border, its forearm reaching into the image.
                side = 1.0 if sway[0] > 0 else -1.0
                R = rot_z(side * np.pi / 2 + 0.3 * sway[1]) @ rot_x(np.pi)
                wrist = np.array([side * (half_w + 25.0), 0.2 * half_h, z]) + d
                pose = _pose_from(R, wrist, art[k])
            else:
                zc = 560.0 + 40.0 * sway[1]
                objs += [
                    _cylinder(np.array([-0.45 * half_w, 0.2 * half_h, zc]) + d, 40.0, 95.0, np.eye(3)),
                    _cylinder(np.array([0.05 * half_w, 0.0, zc + 60.0]) + d, 35.0, 180.0, np.eye(3)),
                    _cylinder(np.array([0.05 * half_w, -115.0, zc + 60.0]) + d, 13.0, 50.0, np.eye(3)),
                    _box(np.array([0.5 * half_w, 0.25 * half_h, zc - 30.0]) + d, (45.0, 35.0, 30.0), rot_y(0.5)),
                    # A table edge across the bottom of the image, receding.
                    _box(np.array([0.0, 0.5 * half_h + 110.0, zc + 120.0]) + d, (420.0, 90.0, 200.0), rot_x(-0.35)),
                ]
            frames.append((pose, (0.0, 0.0), objs))
        return frames
    if kind in HOLD_TYPES:
        q = _grip(kind, rng)
        side = rng.uniform(45.0, 70.0) * _DEG
        R = rot_x(np.pi) @ rot_y(-side)  # palm turned away from the camera by ``side``, thumb toward it
        centre = np.array([rng.uniform(-20.0, 20.0), 10.0, z])
        for k in range(n):
            Rk = rot_z(0.15 * np.sin(1.1 * t[k])) @ R
            wrist = centre - Rk @ np.array([0.0, 60.0, 0.0]) + 6.0 * np.array([np.sin(t[k]), 0.0, 0.0])
            pose = _pose_from(Rk, wrist, q)
            palm = wrist + Rk @ np.array([0.0, 58.0, 0.0])
            normal = Rk[:, 2]  # palmar
            if kind == "hold_cylinder":
                obj = _cylinder(palm + normal * 42.0, 33.0, 160.0, Rk @ rot_z(np.pi / 2))
            elif kind == "hold_ball":
                obj = _ellipsoid(palm + normal * 45.0, (38.0, 38.0, 38.0))
            else:
                obj = _box(palm + normal * 38.0, (60.0, 28.0, 25.0), Rk)
            frames.append((pose, (0.0, 0.0), [obj]))
        return frames
    if kind == "table":
        down = rng.uniform(35.0, 55.0) * _DEG  # the camera looks down at the table by this angle
        up = np.array([0.0, -np.cos(down), -np.sin(down)])  # the table's normal, camera frame
        away = np.array([0.0, -np.sin(down), np.cos(down)])  # along the table, away from the camera
        yaw = rng.uniform(-25.0, 25.0) * _DEG
        c, s_ = np.cos(yaw), np.sin(yaw)
        fwd = c * away + s_ * np.array([1.0, 0.0, 0.0])
        zh = -up  # palm down
        R = np.stack([np.cross(fwd, zh), fwd, zh], axis=1)
        contact = np.array([rng.uniform(-20.0, 20.0), 40.0, z + 40.0]) - 60.0 * fwd
        table_R = np.stack([np.cross(up, away), -up, away], 1)
        table = _box(contact - up * 20.0 + 80.0 * fwd, (200.0, 15.0, 200.0), table_R)
        for k in range(n):
            q = art[k].copy()
            pose = _pose_from(R, contact + up * 16.0, q)
            frames.append((pose, (0.0, 0.0), [table]))
        return frames
    raise InputError(f"unknown scene type {kind!r}; choose one of {', '.join(SCENE_TYPES)}")


def _joints21(pm: PosedMesh, wrist: NDArray[np.float64]) -> NDArray[np.float64]:
    out = np.empty((21, 3))
    out[0] = wrist
    out[1:] = np.concatenate([pm.joints[:, :3], pm.fingertips[:, None, :]], axis=1).reshape(20, 3)
    return out


def _visibility(joints: NDArray[np.float64] | None, intr: Intrinsics) -> str:
    if joints is None:
        return ABSENT
    z = joints[:, 2]
    u = intr.fx * joints[:, 0] / np.maximum(z, 1.0) + intr.cx
    v = intr.fy * joints[:, 1] / np.maximum(z, 1.0) + intr.cy
    m = _MARGIN_PX
    inside = (z > 1.0) & (u >= m) & (u <= intr.width - 1 - m) & (v >= m) & (v <= intr.height - 1 - m)
    return FULL if inside.all() else (PARTIAL if inside.any() else ABSENT)


def scene_frames(
    kind: str,
    n_frames: int,
    intrinsics: Intrinsics,
    shape: MeshShape = MeshShape(),  # noqa: B008 - frozen, as in synth.mesh
    right: bool = True,
    seed: int = 0,
    sensor: str = "tof",
    fps: float = 30.0,
) -> Iterator[SceneFrame]:
    """Render a scene of type ``kind`` (:data:`SCENE_TYPES`) frame by frame.

    Equal arguments give identical frames.  The script (placement, depth, tilt) and the
    sensor noise have independent random streams from ``seed``.

    Raises
    ------
    InputError
        Unknown ``kind`` or ``sensor``, ``n_frames < 1``.
    """
    if kind not in SCENE_TYPES:
        raise InputError(f"unknown scene type {kind!r}; choose one of {', '.join(SCENE_TYPES)}")
    if sensor not in SENSORS:
        raise InputError(f"unknown sensor {sensor!r}; choose one of {', '.join(SENSORS)}")
    if int(n_frames) < 1:
        raise InputError(f"n_frames must be >= 1, got {n_frames}")
    ss = np.random.SeedSequence(seed).spawn(2)
    script = _script(kind, int(n_frames), intrinsics, np.random.default_rng(ss[0]), seed)
    rng = np.random.default_rng(ss[1])
    for k, (pose, wrist_rad, objs) in enumerate(script):
        verts: list[NDArray[np.float64]] = []
        tris: list[NDArray[np.int64]] = []
        joints = None
        if pose is not None:
            pm = pose_mesh(pose, shape, right, True, wrist_rad)
            joints = _joints21(pm, pose[:3])
            verts.append(pm.vertices)
            tris.append(pm.triangles)
        for v, f in objs:
            tris.append(f + sum(x.shape[0] for x in verts))
            verts.append(v)
        if verts:
            V, T = np.concatenate(verts), np.concatenate(tris)
            zbuf, tri_id = rasterise(V, T, intrinsics)
        else:
            zbuf = np.full((intrinsics.height, intrinsics.width), np.inf)
            tri_id = np.full(zbuf.shape, -1, dtype=np.int64)
        depth = np.where(np.isfinite(zbuf), zbuf, 0.0).astype(np.float32)
        if sensor != "clean" and verts:
            apply_sensor(depth, view_cosine(V, T, tri_id, intrinsics), sensor, intrinsics, rng)
        vis = _visibility(joints, intrinsics)
        yield SceneFrame(
            index=k,
            stamp_s=k / float(fps),
            depth_mm=depth,
            visibility=vis,
            joints_mm=None if joints is None else joints,
            fingertips_mm=None if joints is None else joints[4::4].copy(),
        )

