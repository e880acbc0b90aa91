"""Two mesh hands (and an object) in one depth image, with per-hand ground truth.

One job: the two-hand scenes; kept together because the scene scripts, the compositing and the
per-hand ground truth describe one data set (:mod:`hand_sog_tracker.tools.make_sample_bags`
writes it as bags).

Scenes (:data:`SCENES`), the person faces the camera, right hand on the image's left:

``apart``     both hands palm to the camera, far apart, each with its own finger motion;
``approach``  the same, moving together until the thumbs almost meet;
``occlude``   the ``front`` hand passes in front of the other (about 130 mm nearer) and hides part of it;
``cross``     the hands swap image sides, the ``front`` hand nearer;
``touch``     fingers pointing at each other, the middle fingertips meet and stay in contact;
``clap``      palms facing, clapping twice per 1.5 s (seen 25 degrees off the clapping plane);
``pass``      palms facing, a 60 mm ball held by the ``front`` hand is handed over to the other.

Each hand is the skinned WebXR mesh of :mod:`hand_sog_tracker.synth.mesh` with its own
:class:`~hand_sog_tracker.synth.mesh.MeshShape` and forearm.  All triangles (both hands, forearms,
the ball) are rasterised together, so the nearest surface wins at every pixel, then one sensor
model of :mod:`hand_sog_tracker.synth.sensors` is applied to the composite (flying pixels and
shadows appear at the edges between the hands as at any depth edge).

Ground truth per hand (:class:`HandTruth`): handedness, the 5 fingertips of
:func:`~hand_sog_tracker.synth.mesh.pose_mesh` (mm), 21 keypoints (wrist, then per chain
thumb .. little its three joints and the ground-truth fingertip, MediaPipe's order), the visible
fraction (of the pixels the hand, without its forearm, covers rendered alone, the share not
hidden by the other hand or the ball) and per fingertip whether the pixel it projects to shows
that same hand (not hidden by the other hand or the ball, inside the image).  Every scene is a
smooth function of time, so the first frames of a short and a long sequence agree; the motions
are periodic, so longer sequences keep moving.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from functools import lru_cache
from typing import Final, Literal

import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.hand_model import JOINTS, N_PARAMS, default_hand_model
from hand_sog_tracker.core.rotations import euler_from_matrix, rot_y
from hand_sog_tracker.core.types import Intrinsics
from hand_sog_tracker.errors import InputError
from hand_sog_tracker.synth.mesh import MeshShape, PosedMesh, load_mesh_hand, pose_mesh
from hand_sog_tracker.synth.motions import key_articulations, motion_poses
from hand_sog_tracker.synth.raster import rasterise, view_cosine
from hand_sog_tracker.synth.sensors import SENSORS, apply_sensor

__all__ = [
    "SCENES",
    "HANDS",
    "HandTruth",
    "TwoHandFrame",
    "TwoHandScene",
    "scene_poses",
    "render_two_hands",
    "two_hand_sequence",
]

#: The scripted two-hand scenes.
SCENES: Final[tuple[str, ...]] = ("apart", "approach", "occlude", "cross", "touch", "clap", "pass")
#: Order of the hands in every per-hand tuple here.
HANDS: Final[tuple[str, str]] = ("left", "right")
Side = Literal["left", "right"]

_PALM_CENTRE: Final = np.array([0.0, 50.0, 0.0])  #: hand-frame point the scenes place (mm)
_BALL_RADIUS_MM: Final = 30.0
_PALM_HALF_THICKNESS_MM: Final = 18.0  #: palm centre to the palmar skin, about (mm)
_UP: Final = np.array([0.0, -1.0, 0.0])  #: camera -y: up in the image
_TOWARD_CAMERA: Final = np.array([0.0, 0.0, -1.0])


@dataclass(frozen=True)
class TwoHandScene:
    """What to render: a scene script, its hands' shapes and which hand is in front.

    Attributes
    ----------
    scene : str
        One of :data:`SCENES`.
    shapes : tuple of 2 MeshShape
        Shapes of the left and the right hand.
    front : {"left", "right"}
        ``occlude``, ``cross``: the nearer hand; ``pass``: the hand holding the ball first.
    depth_mm : float
        Distance of the scene's centre from the camera (mm).
    """

    scene: str
    shapes: tuple[MeshShape, MeshShape] = (MeshShape(), MeshShape())
    front: Side = "right"
    depth_mm: float = 460.0

    def __post_init__(self) -> None:
        if self.scene not in SCENES:
            raise InputError(f"unknown two-hand scene {self.scene!r}; choose one of {', '.join(SCENES)}")
        if self.front not in HANDS:
            raise InputError(f"front must be 'left' or 'right', got {self.front!r}")
        if len(self.shapes) != 2 or not all(isinstance(s, MeshShape) for s in self.shapes):
            raise InputError("shapes must be two MeshShape (left, right)")
        if not (np.isfinite(self.depth_mm) and 250.0 <= self.depth_mm <= 1500.0):
            raise InputError(f"depth_mm must be in [250, 1500], got {self.depth_mm!r}")


@dataclass(frozen=True, eq=False)
class HandTruth:
    """Ground truth of one hand in one frame (camera optical frame, mm).

    Attributes
    ----------
    handedness : {"left", "right"}
    pose : array, shape (26,)
        The hand's pose (mm, rad; a left hand in the mirrored convention of ``HandModel``).
    fingertips_mm : array, shape (5, 3)
        Fingertips thumb .. little (:func:`synth.mesh.pose_mesh`).
    keypoints_mm : array, shape (21, 3)
        Wrist, then per chain its three joints and its fingertip.
    visible_fraction : float
        In [0, 1]: of the pixels the hand (no forearm) covers rendered alone, the share that shows
        this hand (or its forearm) in the composite, i.e. not hidden by the other hand or the object.
    tips_visible : bool array, shape (5,)
        The fingertip's pixel shows this hand (not hidden by the other hand or the object).
    """

    handedness: Side
    pose: NDArray[np.float64]
    fingertips_mm: NDArray[np.float64]
    keypoints_mm: NDArray[np.float64]
    visible_fraction: float
    tips_visible: NDArray[np.bool_]


@dataclass(frozen=True, eq=False)
class TwoHandFrame:
    """One rendered two-hand frame.

    Attributes
    ----------
    index : int
    stamp_s : float
        ``index / fps`` seconds.
    depth_mm : array, shape (H, W), float32
        Depth (mm), 0 = no measurement.
    hands : tuple of 2 HandTruth
        Left, then right.
    owner : int array, shape (H, W)
        Clean composite: 0 = left hand, 1 = right hand (both with forearms), 2 = object, -1 = none.
    """

    index: int
    stamp_s: float
    depth_mm: NDArray[np.float32]
    hands: tuple[HandTruth, HandTruth]
    owner: NDArray[np.int64]


# -- scene scripts --------------------------------------------------------------------------------
def _cycle(t: NDArray[np.float64], period: float) -> NDArray[np.float64]:
    """0 -> 1 -> 0 once per ``period`` seconds, 0 at t = 0."""
    return 0.5 - 0.5 * np.cos(2.0 * np.pi * t / period)


def _global(
    centre: NDArray[np.float64], fingers: NDArray[np.float64], palmar: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Global pose rows (T, 6) placing the palm centre at ``centre`` (T, 3) mm with the fingers along
    ``fingers`` and the palmar normal along ``palmar`` (T, 3), camera frame (for either hand: the
    left hand's mirror flips only hand x, the thumb side)."""
    out = np.empty((centre.shape[0], 6))
    rx_ref = np.pi
    for k in range(centre.shape[0]):
        y = fingers[k] / np.linalg.norm(fingers[k])
        z = palmar[k] - y * (palmar[k] @ y)
        z /= np.linalg.norm(z)
        G = np.stack([np.cross(y, z), y, z], axis=1)
        rx, ry, rz = euler_from_matrix(G, rx_ref)
        rx_ref = rx
        out[k, :3] = centre[k] - G @ _PALM_CENTRE
        out[k, 3:] = (rx, ry, rz)
    return out


def _articulation(motion: str, t: NDArray[np.float64], seed: int) -> NDArray[np.float64]:
    """Joint angles (T, 20) of a one-hand motion of :mod:`synth.motions` (its global part unused)."""
    fps = 1.0 / float(t[1] - t[0]) if t.size > 1 else 30.0
    return motion_poses(motion, t.size, fps=fps, seed=seed)[:, JOINTS]


def _blend(name_a: str, name_b: str, s: NDArray[np.float64]) -> NDArray[np.float64]:
    """Articulations (T, 20) between two key articulations, ``s`` (T,) in [0, 1]."""
    k = key_articulations()
    return k[name_a][None, :] + (k[name_b] - k[name_a])[None, :] * s[:, None]


def _rows(v: NDArray[np.float64] | tuple[float, float, float], n: int) -> NDArray[np.float64]:
    return np.broadcast_to(np.asarray(v, dtype=np.float64), (n, 3)).copy()


def scene_poses(
    scene: TwoHandScene, n_frames: int, fps: float = 30.0, seed: int = 0
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Poses of both hands and the object's centre, frame by frame.

    Returns
    -------
    left, right : array, shape (T, 26)
        Poses (mm, rad).
    ball : array, shape (T, 4)
        Ball centre (mm) and owner (0 left, 1 right); NaN rows without a ball.
    """
    if int(n_frames) != n_frames or n_frames < 1:
        raise InputError(f"n_frames must be a positive integer, got {n_frames!r}")
    if not (np.isfinite(fps) and fps > 0):
        raise InputError(f"fps must be positive, got {fps!r}")
    n = int(n_frames)
    t = np.arange(n) / float(fps)
    ss = np.random.SeedSequence(seed).spawn(3)
    seeds = [int(s.generate_state(1)[0]) for s in ss[:2]]
    rng = np.random.default_rng(ss[2])
    z0 = scene.depth_mm
    # Small per-scene offsets so that no two seeds give the same picture.
    jitter = rng.uniform(-1.0, 1.0, (2, 3)) * np.array([8.0, 8.0, 15.0])
    name = scene.scene
    fi = 1 if scene.front == "right" else 0  # index of the front hand in (left, right)
    cl, cr = np.zeros((n, 3)), np.zeros((n, 3))
    fl, fr = _rows(_UP, n), _rows(_UP, n)
    pl, pr = _rows(_TOWARD_CAMERA, n), _rows(_TOWARD_CAMERA, n)
    ball = np.full((n, 4), np.nan)
    yaw = 0.0
    if name == "apart":
        cr[:] = (-115.0, 5.0, z0)
        cl[:] = (115.0, -5.0, z0 + 15.0)
        art_l, art_r = _articulation("fingerwave", t, seeds[0]), _articulation("fingercount", t, seeds[1])
    elif name == "approach":
        p = _cycle(t, 3.0)
        cr[:, 0], cl[:, 0] = -125.0 + 62.0 * p, 125.0 - 62.0 * p
        cr[:, 1:], cl[:, 1:] = (0.0, z0), (-8.0, z0 + 10.0)
        art_l, art_r = _articulation("flexex", t, seeds[0]), _articulation("abdadd", t, seeds[1])
    elif name in ("occlude", "cross"):
        p = _cycle(t, 3.0)
        front, back = np.zeros((n, 3)), np.zeros((n, 3))
        if name == "occlude":  # the front hand slides over the still back hand, covering part of it
            side = -1.0 if fi == 1 else 1.0  # the front hand starts on its own side of the image
            back[:] = (-side * 45.0, 0.0, z0 + 60.0)
            front[:, 0] = side * (150.0 - 150.0 * p)
            front[:, 1:] = (-15.0, z0 - 70.0)
            art_f, art_b = _articulation("pinch", t, seeds[fi]), _articulation("fingerwave", t, seeds[1 - fi])
        else:  # both move across, the front hand nearer
            side = -1.0 if fi == 1 else 1.0
            front[:, 0] = side * (110.0 - 220.0 * p)
            back[:, 0] = -front[:, 0]
            front[:, 1:], back[:, 1:] = (15.0, z0 - 65.0), (-15.0, z0 + 55.0)
            art_f, art_b = _articulation("flexex", t, seeds[fi]), _articulation("abdadd", t, seeds[1 - fi])
        (cl, cr) = (back, front) if fi == 1 else (front, back)
        (art_l, art_r) = (art_b, art_f) if fi == 1 else (art_f, art_b)
    elif name == "touch":  # fingers pointing at each other, palms to the camera; middle tips meet
        gap = np.maximum(0.0, 75.0 * (1.0 - _cycle(t, 2.4)) - 15.0)
        fr[:], fl[:] = (1.0, 0.0, 0.0), (-1.0, 0.0, 0.0)
        cr[:] = (-150.0, 10.0, z0)
        cl[:] = (150.0, 10.0, z0)
        art_l = _articulation("abdadd", t, seeds[0])
        art_r = _articulation("abdadd", t, seeds[1])
    elif name in ("clap", "pass"):  # palms facing each other, thumbs away from the camera
        pr[:], pl[:] = (1.0, 0.0, 0.0), (-1.0, 0.0, 0.0)
        if name == "clap":
            yaw = np.deg2rad(25.0)
            half = 0.5 * (2.0 * _PALM_HALF_THICKNESS_MM + 4.0 + 90.0 * (1.0 - _cycle(t, 0.75)))
            art_l, art_r = _articulation("abdadd", t, seeds[0]), _articulation("abdadd", t, seeds[1])
        else:
            yaw = np.deg2rad(30.0)
            p = _cycle(t, 1.5)
            touch = _BALL_RADIUS_MM + _PALM_HALF_THICKNESS_MM
            half = touch + 60.0 * (1.0 - p)
            # The holder changes at each meeting (t = 0.75 s + k 1.5 s).
            first = np.floor((t + 0.75) / 1.5).astype(np.int64) % 2 == 0
            holder = np.where(first, fi, 1 - fi)
            curl_hold, curl_other = np.full(n, 0.55), 0.55 * p
            art_l = _blend("open", "claw", np.where(holder == 0, curl_hold, curl_other))
            art_r = _blend("open", "claw", np.where(holder == 1, curl_hold, curl_other))
        cr[:, 0], cl[:, 0] = -half, half
        cr[:, 1:], cl[:, 1:] = (0.0, z0), (0.0, z0)
        if name == "pass":
            palmar = np.where(holder[:, None] == 1, pr, pl)
            centre = np.where(holder[:, None] == 1, cr, cl)
            ball[:, :3] = centre + palmar * touch
            ball[:, 3] = holder
    else:  # pragma: no cover - TwoHandScene checks the name
        raise InputError(f"unknown scene {name!r}")
    # Gentle drift of the whole scene, and the per-seed offsets.
    drift = 4.0 * np.sin(2.0 * np.pi * (t[:, None] / 2.7 + rng.uniform(0, 1, 3)[None, :]))
    centre = np.array([0.0, 0.0, z0])
    R = rot_y(yaw)
    rot = lambda v: v @ R.T  # noqa: E731 - a one-line local map
    cl = rot(cl - centre) + centre + drift + jitter[0]
    cr = rot(cr - centre) + centre + drift + jitter[1]
    if name == "pass":
        ball[:, :3] = rot(ball[:, :3] - centre) + centre + drift + jitter[np.where(ball[:, 3] == 0, 0, 1)]
    out = []
    lo, hi = default_hand_model(True).limits_low, default_hand_model(True).limits_high
    for c, f, pa, art in ((cl, fl, pl, art_l), (cr, fr, pr, art_r)):
        pose = np.empty((n, N_PARAMS))
        pose[:, :6] = _global(c, rot(f), rot(pa))
        pose[:, JOINTS] = np.clip(art, lo, hi)
        out.append(pose)
    left, right = out
    if name == "touch":  # shift each hand along the fingers so that the middle tips' skins touch
        for k in range(n):
            _touch_middle_tips(left[k], right[k], scene.shapes, gap[k])
    return left, right, ball


def _touch_middle_tips(
    left: NDArray[np.float64], right: NDArray[np.float64], shapes: tuple[MeshShape, MeshShape], gap: float
) -> None:
    """Move both poses (in place) so that the middle fingertips' skins are ``gap`` mm apart along
    camera x (and level in y and z), about their mean."""
    tl = pose_mesh(left, shapes[0], False, forearm=False).fingertips[2]
    tr = pose_mesh(right, shapes[1], True, forearm=False).fingertips[2]
    rl = load_mesh_hand(False).tip_radius[2] * shapes[0].thickness
    rr = load_mesh_hand(True).tip_radius[2] * shapes[1].thickness
    mid = 0.5 * (tl + tr)
    ex = np.array([1.0, 0.0, 0.0])
    right[:3] += (mid - (0.5 * gap + rr) * ex) - tr
    left[:3] += (mid + (0.5 * gap + rl) * ex) - tl


# -- rendering ------------------------------------------------------------------------------------
@lru_cache(maxsize=1)
def _ball_mesh() -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Unit UV sphere: vertices (k, 3), triangles (t, 3)."""
    n_lat, n_lon = 10, 18
    lat = np.linspace(0.0, np.pi, n_lat + 1)[1:-1]
    lon = np.linspace(0.0, 2.0 * np.pi, n_lon, endpoint=False)
    ring = np.stack(
        [np.sin(lat)[:, None] * np.cos(lon)[None, :], np.broadcast_to(np.cos(lat)[:, None], (lat.size, n_lon)),
         np.sin(lat)[:, None] * np.sin(lon)[None, :]], axis=2,
    ).reshape(-1, 3)
    verts = np.concatenate([[[0.0, 1.0, 0.0]], ring, [[0.0, -1.0, 0.0]]])
    m = n_lon
    k = np.arange(m)
    k1 = (k + 1) % m
    tris = [np.stack([np.zeros(m, np.int64), 1 + k, 1 + k1], 1)]
    for i in range(lat.size - 1):
        a, b = 1 + i * m, 1 + (i + 1) * m
        tris += [np.stack([a + k, b + k, b + k1], 1), np.stack([a + k, b + k1, a + k1], 1)]
    last, bottom = 1 + (lat.size - 1) * m, verts.shape[0] - 1
    tris.append(np.stack([np.full(m, bottom), last + k1, last + k], 1))
    return verts, np.concatenate(tris).astype(np.int64)


def _hand_triangles(pm: PosedMesh) -> NDArray[np.bool_]:
    """Which triangles (t,) of a posed mesh are the hand's (not the forearm's)."""
    return np.all(pm.triangles < pm.n_hand_vertices, axis=1)


def render_two_hands(
    left: NDArray[np.float64],
    right: NDArray[np.float64],
    intrinsics: Intrinsics,
    shapes: tuple[MeshShape, MeshShape] = (MeshShape(), MeshShape()),
    sensor: str = "tof",
    rng: np.random.Generator | None = None,
    ball_mm: NDArray[np.float64] | None = None,
    forearm: bool = True,
    shown: tuple[str, ...] = HANDS,
) -> tuple[NDArray[np.float32], tuple[HandTruth, HandTruth], NDArray[np.int64]]:
    """Render both hands (and a ball) into one depth image, nearest surface first.

    Parameters
    ----------
    left, right : array, shape (26,)
        Poses (mm, rad), camera optical frame.
    intrinsics : Intrinsics
    shapes : tuple of 2 MeshShape
        Left, right.
    sensor : str
        One of :data:`synth.sensors.SENSORS`, applied once to the composite.
    rng : numpy.random.Generator, optional
        Sensor randomness (default ``default_rng(0)``).
    ball_mm : array, shape (3,), optional
        Centre (mm) of a ball of radius 30 mm; None or NaN = no ball.
    forearm : bool
    shown : tuple of str
        The hands drawn (default both): ``("right",)`` renders the right hand of the same scene
        alone (the reference "the same motion tracked alone"); a hand not drawn still gets its
        ground truth, with visible fraction 0.

    Returns
    -------
    depth : array, shape (H, W), float32
        Depth (mm), 0 = no measurement.
    truths : tuple of 2 HandTruth
        Left, right.
    owner : int array, shape (H, W)
        0 left, 1 right, 2 ball, -1 none (clean composite).
    """
    if sensor not in SENSORS:
        raise InputError(f"unknown sensor {sensor!r}; choose one of {', '.join(SENSORS)}")
    if not shown or any(h not in HANDS for h in shown):
        raise InputError(f"shown must name 'left' and/or 'right', got {shown!r}")
    if rng is None:
        rng = np.random.default_rng(0)
    posed = [pose_mesh(left, shapes[0], False, forearm), pose_mesh(right, shapes[1], True, forearm)]
    verts, tris, label = [], [], []
    base = 0
    for i, pm in enumerate(posed):
        if HANDS[i] not in shown:
            continue
        verts.append(pm.vertices)
        tris.append(pm.triangles + base)
        label.append(np.full(pm.triangles.shape[0], i))
        base += pm.vertices.shape[0]
    if ball_mm is not None and np.all(np.isfinite(ball_mm)):
        bv, bt = _ball_mesh()
        verts.append(bv * _BALL_RADIUS_MM + np.asarray(ball_mm, dtype=np.float64)[:3])
        tris.append(bt + base)
        label.append(np.full(bt.shape[0], 2))
    V, Tr, lab = np.concatenate(verts), np.concatenate(tris), np.concatenate(label)
    zbuf, tri_id = rasterise(V, Tr, intrinsics)
    hit = tri_id >= 0
    owner = np.where(hit, lab[np.maximum(tri_id, 0)], -1)
    depth = np.where(hit, zbuf, 0.0).astype(np.float32)
    if sensor != "clean":
        apply_sensor(depth, view_cosine(V, Tr, tri_id, intrinsics), sensor, intrinsics, rng)
    truths = []
    H, W = owner.shape
    for i, (pm, pose) in enumerate(zip(posed, (left, right))):
        alone_mask = rasterise(pm.vertices, pm.triangles[_hand_triangles(pm)], intrinsics)[1] >= 0
        alone = int(np.count_nonzero(alone_mask))
        own_hand = alone_mask & (owner == i)  # (its own forearm may cover its wrist: still this hand)
        tips = pm.fingertips
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.rint(intrinsics.fx * tips[:, 0] / tips[:, 2] + intrinsics.cx)
            v = np.rint(intrinsics.fy * tips[:, 1] / tips[:, 2] + intrinsics.cy)
        inside = (tips[:, 2] > 0) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
        ui, vi = np.where(inside, u, 0).astype(np.int64), np.where(inside, v, 0).astype(np.int64)
        tips_visible = inside & (owner[vi, ui] == i)
        chains = np.concatenate([pm.joints[:, :3], tips[:, None, :]], axis=1)  # (5, 4, 3)
        truths.append(
            HandTruth(
                handedness=HANDS[i],
                pose=np.array(pose, dtype=np.float64),
                fingertips_mm=tips.copy(),
                keypoints_mm=np.concatenate([np.asarray(pose, dtype=np.float64)[None, :3], chains.reshape(20, 3)]),
                visible_fraction=float(np.count_nonzero(own_hand) / alone) if alone else 0.0,
                tips_visible=tips_visible,
            )
        )
    return depth, (truths[0], truths[1]), owner


def two_hand_sequence(
    scene: TwoHandScene,
    n_frames: int,
    intrinsics: Intrinsics | None = None,
    seed: int = 0,
    sensor: str = "tof",
    fps: float = 30.0,
    shown: tuple[str, ...] = HANDS,
) -> Iterator[TwoHandFrame]:
    """Render a two-hand scene frame by frame (motion from ``seed``; an independent noise stream);
    ``shown`` as in :func:`render_two_hands`.

    Yields
    ------
    TwoHandFrame
    """
    from hand_sog_tracker.synth.sequence import default_intrinsics

    intr = default_intrinsics() if intrinsics is None else intrinsics
    left, right, ball = scene_poses(scene, n_frames, fps=fps, seed=seed)
    rng = np.random.default_rng(np.random.SeedSequence(seed).spawn(4)[3])
    for k in range(left.shape[0]):
        depth, truths, owner = render_two_hands(
            left[k], right[k], intr, scene.shapes, sensor, rng, ball[k, :3], shown=shown
        )
        yield TwoHandFrame(index=k, stamp_s=k / float(fps), depth_mm=depth, hands=truths, owner=owner)
