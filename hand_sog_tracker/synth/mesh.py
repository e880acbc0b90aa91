"""Depth renderer of a skinned triangle-mesh hand: synthetic data independent of the tracker's model.

The capsule renderer (:mod:`hand_sog_tracker.synth.render`) is built from the
tracker's own segments and radii, so it flatters the tracker.  This one poses
the skinned WebXR generic hand mesh (``data/webxr_hand/right.glb`` and
``left.glb``, MIT licence, Amazon 2019; about 1360 vertices, 2314 triangles,
25 joints) with our 26-DOF pose vector, adds a forearm and rasterises the
triangles with a Z-buffer in NumPy.  The glTF files are read by the small
parser :mod:`hand_sog_tracker.synth.gltf` (no new dependency).

Mapping of the pose onto the mesh
---------------------------------
*Hand frame of the mesh* (mm, after scaling): origin at the ``wrist`` joint,
``y`` toward the ``middle-finger-phalanx-proximal`` joint, ``x`` across the
palm toward the thumb (``index - pinky`` proximal joints, made orthogonal to
``y``) and ``z = x cross y`` out of the palm (palmar), like
:mod:`hand_sog_tracker.core.hand_model`.  The file's metres are multiplied by
1000 and by a uniform factor that makes the wrist-to-middle-fingertip length
(the wrist to the end of the skin of the straight middle finger, at zero
joint angles) equal to that of ``default_hand_model()`` at shape 1.0,
185.2 mm (:data:`DEFAULT_HAND_LENGTH_MM`); the factor is 0.970 for
``right.glb`` (:attr:`MeshHand.unit_scale`).

*Bones.*  The wrist and the four finger metacarpals are rigid in the hand
frame (the palm).  For each chain ``c`` (thumb .. little) and segment ``k``
the mesh bone is thumb metacarpal / proximal / distal or finger proximal /
intermediate / distal; its pivot is the mesh's own joint and its length the
mesh's own joint distance.  In the bind pose each bone gets a frame
``F`` (``y`` along the bone, ``x`` = our model's zero-pose flexion axis of
that chain made orthogonal to the bone, ``z = x cross y``), and every vertex
influence stores its coordinates ``l = F^T (v - pivot)``.  At pose
``theta`` the bone's hand-frame rotation is ``S_ck(theta)``, the rotation
of segment ``(c, k)`` of :func:`hand_sog_tracker.core.kinematics.chain_frames`
(our own kinematic chain, same flexion and abduction axes), and its pivot is
chained along those rotations with the mesh bone lengths.  So, in the terms
of the design note, the bone's world rotation is
``R_global(theta) @ S_ck(theta) @ A`` with the constant ``A = F^T``: at zero
angles each mesh bone points along our model's zero-pose direction (the
slightly curled bind pose is straightened) and the pose vector means what it
means for the tracker, while finger proportions, palm and skin come from the
mesh.  Vertices are linear-blend skinned from their four influences.  A left
hand uses ``left.glb`` with its x mirrored into a right hand, is posed like a
right hand, and is mirrored back (hand ``x -> -x``), exactly as
``HandModel(right=False)`` does.

*Shape* (:class:`MeshShape`, each factor independent): ``length`` scales the
bone lengths of fingers and thumb and the vertex coordinates along their
bones; ``palm_width`` scales hand x of the palm vertices and of the chain
pivots (MCP bases, thumb CMC); ``thickness`` scales vertex coordinates
perpendicular to the finger and thumb bones.

Ground-truth fingertips
-----------------------
The tracker reports the centre of its fingertip sphere, one finger radius
inside the skin.  The mesh's ``*-tip`` joints already sit 9-12 mm behind
the end of the skin (about one radius plus 2-5 mm), so moving them back by
another radius would put the truth two radii deep.  Instead the truth is
the point on the distal bone, one local finger radius back from the end of
the skin: at bind pose, for each chain, ``end`` = the largest coordinate
along the distal bone of the vertices of that finger, ``r`` = the median
distance from the bone axis of those vertices 2-12 mm behind the tip joint
(after the uniform scale: thumb 8.7, index 7.1, middle 7.3, ring 6.8,
little 6.2 mm)
and the lateral offset = the centre of their extent; the truth is
``(lateral_x * T, end * L - r * T, lateral_z * T)`` in the distal bone's
frame (``L`` = length, ``T`` = thickness factor).  A perfect fit therefore
scores about 0 mm.

Rasteriser and sensors
----------------------
:func:`rasterise`: vertices are projected with any pinhole
:class:`~hand_sog_tracker.core.types.Intrinsics`; triangles are grouped by the
power-of-two size of their pixel bounding box, each group is tested on the
pixel centres of its boxes at once (edge functions), depth is interpolated
as ``1/z`` (exact for planar triangles) and the nearest hit per pixel is kept
with ``np.minimum.at``.  Sensor models (:data:`SENSORS`): ``clean``; ``tof``
(Gaussian depth noise growing with depth, flying pixels interpolated between
foreground and background at depth edges, dropout at grazing angles from the
true surface normal, sparse random dropout, whole millimetres like the uint16
output of ToF cameras); ``structured`` (a projector
50 mm to the right of the camera: shadow holes left of depth edges, holes
at grazing angles and on the left border of the silhouette, sub-pixel
disparity noise, a 3x3 median over the disparity, and disparity quantised in
1/8 px, so the depth step grows with ``z**2``).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING, Final

import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.hand_model import default_hand_model
from hand_sog_tracker.core.kinematics import chain_frames, check_pose, global_rotation
from hand_sog_tracker.core.types import Intrinsics
from hand_sog_tracker.errors import InputError
from hand_sog_tracker.synth.gltf import read_glb

if TYPE_CHECKING:
    from hand_sog_tracker.synth.sequence import SyntheticFrame

__all__ = [
    "DEFAULT_HAND_LENGTH_MM",
    "MESH_DIR",
    "SENSORS",
    "MeshShape",
    "MeshRenderOptions",
    "MeshHand",
    "PosedMesh",
    "load_mesh_hand",
    "pose_mesh",
    "mesh_fingertips",
    "rasterise",
    "render_mesh_depth",
    "apply_sensor",
    "mirror_pose",
    "mesh_sequence",
]

#: Directory of the bundled WebXR hand meshes (``right.glb``, ``left.glb``, ``LICENSE.md``).
MESH_DIR: Final[Path] = Path(__file__).resolve().parent.parent / "data" / "webxr_hand"
#: Sensor models of :func:`apply_sensor`.
SENSORS: Final[tuple[str, ...]] = ("clean", "tof", "structured")

_FINGER_PREFIX: Final = ("thumb", "index-finger", "middle-finger", "ring-finger", "pinky-finger")
_CHAIN_JOINTS: Final[tuple[tuple[str, ...], ...]] = (
    ("thumb-metacarpal", "thumb-phalanx-proximal", "thumb-phalanx-distal", "thumb-tip"),
) + tuple(
    (f"{f}-phalanx-proximal", f"{f}-phalanx-intermediate", f"{f}-phalanx-distal", f"{f}-tip")
    for f in _FINGER_PREFIX[1:]
)
_PALM_JOINTS: Final = ("wrist",) + tuple(f"{f}-metacarpal" for f in _FINGER_PREFIX[1:])

_FOREARM_START_Y = -5.0  #: hand-frame y (mm) where the forearm starts (inside the mesh's wrist)
_FOREARM_LENGTH = 250.0  #: mm along -hand-y from the wrist
_FOREARM_R_WRIST = 26.5  #: mm, radial-ulnar semi-axis at the wrist (the mesh's wrist is ~52 mm wide)
_FOREARM_R_ELBOW = 33.0  #: mm, at the far end
_FOREARM_FLATTEN = 0.72  #: palmar-dorsal / radial-ulnar semi-axis (the mesh's wrist section)
_FOREARM_RINGS = 11
_FOREARM_SIDES = 20

_NEAR_MM = 1.0  #: triangles with a vertex closer than this (or behind the camera) are skipped


def _ref_model():  # the tracker's default right hand: zero-pose directions and chain rotations
    return default_hand_model(True)


def _ref_hand_length() -> float:
    m = _ref_model()
    end = m.bases[2] + m.rest_rotations[2][:, 1] * m.lengths[2].sum()
    return float(np.linalg.norm(end))


#: Wrist to the end of the straight middle finger of ``default_hand_model()`` (mm).
DEFAULT_HAND_LENGTH_MM: Final[float] = _ref_hand_length()


@dataclass(frozen=True)
class MeshShape:
    """Shape factors of the mesh hand (unitless, each independent; 1 = the mesh as scaled).

    Attributes
    ----------
    length : float
        Bone lengths of the fingers and thumb (and vertex coordinates along them).
    palm_width : float
        Hand-x positions of the palm vertices and of the chain bases.
    thickness : float
        Vertex offsets perpendicular to the finger and thumb bones.
    """

    length: float = 1.0
    palm_width: float = 1.0
    thickness: float = 1.0

    def __post_init__(self) -> None:
        for name in ("length", "palm_width", "thickness"):
            v = float(getattr(self, name))
            if not (np.isfinite(v) and 0.5 <= v <= 2.0):
                raise InputError(f"MeshShape.{name} must be in [0.5, 2.0], got {v!r}")

    def as_tuple(self) -> tuple[float, float, float]:
        """``(length, palm_width, thickness)``."""
        return (float(self.length), float(self.palm_width), float(self.thickness))


@dataclass(frozen=True)
class MeshRenderOptions:
    """Options of :func:`render_mesh_depth`.

    Attributes
    ----------
    sensor : str
        One of :data:`SENSORS`.
    forearm : bool
        Render the tapered elliptic forearm (250 mm along -hand-y).
    background_mm : float or None
        Depth (mm) of a fronto-parallel wall; ``None`` = no return (0) off the hand.
    """

    sensor: str = "tof"
    forearm: bool = True
    background_mm: float | None = None

    def __post_init__(self) -> None:
        if self.sensor not in SENSORS:
            raise InputError(f"unknown sensor {self.sensor!r}; choose one of {', '.join(SENSORS)}")
        if self.background_mm is not None and not (np.isfinite(self.background_mm) and self.background_mm > 0):
            raise InputError(f"background_mm must be None or > 0, got {self.background_mm!r}")


@dataclass(frozen=True, eq=False)
class MeshHand:
    """Bind geometry of one mesh hand in right-hand semantics (hand frame, mm).

    Attributes
    ----------
    right : bool
        Handedness (a left hand is stored mirrored and mirrored back when posed).
    triangles : int array, shape (t, 3)
    vertices : array, shape (n, 3), mm
        Bind-pose vertices in the hand frame (right-hand semantics).
    infl_bone : int array, shape (n, 4)
        Bone of each influence: 0 = palm (rigid), ``1 + 3 c + k`` = chain ``c`` segment ``k``.
    infl_weight : array, shape (n, 4)
    infl_local : array, shape (n, 4, 3), mm
        Palm influences: the hand-frame vertex; others: ``F^T (v - pivot)`` in the bone frame.
    bases : array, shape (5, 3), mm
        First pivot of each chain (thumb metacarpal joint, finger proximal joints).
    lengths : array, shape (5, 3), mm
        Mesh bone lengths (joint to joint; distal: distal joint to tip joint).
    tip_end : array, shape (5,), mm
        End of the skin along the distal bone, from the distal joint.
    tip_radius : array, shape (5,), mm
        Finger radius at the tip.
    tip_lateral : array, shape (5, 2), mm
        Centre of the tip cross-section in the distal bone frame (x, z).
    unit_scale : float
        mm per file metre divided by 1000 (the uniform scale applied).
    bind_joints : array, shape (25, 3), mm
        Hand-frame bind positions of the 25 joints (file order).
    joint_names : tuple of str
    """

    right: bool
    triangles: NDArray[np.int64]
    vertices: NDArray[np.float64]
    infl_bone: NDArray[np.int64]
    infl_weight: NDArray[np.float64]
    infl_local: NDArray[np.float64]
    bases: NDArray[np.float64]
    lengths: NDArray[np.float64]
    tip_end: NDArray[np.float64]
    tip_radius: NDArray[np.float64]
    tip_lateral: NDArray[np.float64]
    unit_scale: float
    bind_joints: NDArray[np.float64]
    joint_names: tuple[str, ...]


def _orthonormal_frame(y: NDArray[np.float64], x_hint: NDArray[np.float64]) -> NDArray[np.float64]:
    """Rotation (3, 3) with columns x, y, z: y given, x = x_hint made orthogonal to y."""
    y = y / np.linalg.norm(y)
    x = x_hint - y * (x_hint @ y)
    x /= np.linalg.norm(x)
    return np.stack([x, y, np.cross(x, y)], axis=1)


@lru_cache(maxsize=2)
def load_mesh_hand(right: bool = True) -> MeshHand:
    """Load and prepare the bundled right (or left) WebXR hand mesh.

    Raises
    ------
    InputError
        If the file is missing or does not have the WebXR joints.
    """
    mesh = read_glb(MESH_DIR / ("right.glb" if right else "left.glb"))
    names = mesh.joint_names
    P = mesh.bind_positions() * 1000.0
    V = mesh.positions * 1000.0
    if not right:  # mirror the left mesh into a right hand
        P = P * np.array([-1.0, 1.0, 1.0])
        V = V * np.array([-1.0, 1.0, 1.0])
    j = {n: mesh.joint_index(n) for n in names}
    for n in _PALM_JOINTS + sum(_CHAIN_JOINTS, ()):
        if n not in j:
            raise InputError(f"the hand mesh has no joint {n!r}")
    origin = P[j["wrist"]]
    F_hand = _orthonormal_frame(
        P[j["middle-finger-phalanx-proximal"]] - origin,
        P[j["index-finger-phalanx-proximal"]] - P[j["pinky-finger-phalanx-proximal"]],
    )
    Ph = (P - origin) @ F_hand
    Vh = (V - origin) @ F_hand
    if Ph[j["thumb-phalanx-distal"], 2] <= 0:
        raise InputError("unexpected hand mesh: the thumb is not on the palmar side")

    ref = _ref_model()
    chains = np.array([[Ph[j[n]] for n in ch] for ch in _CHAIN_JOINTS])  # (5, 4, 3)
    lengths = np.linalg.norm(np.diff(chains, axis=1), axis=2)  # (5, 3)
    frames = np.empty((5, 3, 3, 3))
    for c in range(5):
        for k in range(3):
            frames[c, k] = _orthonormal_frame(chains[c, k + 1] - chains[c, k], ref.rest_rotations[c][:, 0])

    # Bone of each joint: palm joints -> 0, chain joints -> 1 + 3c + k (tip joint -> distal bone).
    bone_of_joint = np.zeros(len(names), dtype=np.int64)
    for c, ch in enumerate(_CHAIN_JOINTS):
        for k, n in enumerate(ch):
            bone_of_joint[j[n]] = 1 + 3 * c + min(k, 2)
    infl_bone = bone_of_joint[mesh.joints]
    dominant = infl_bone[np.arange(Vh.shape[0]), np.argmax(mesh.weights, axis=1)]

    # Fingertip geometry from the bind vertices of each chain's phalanges.
    tip_end = np.empty(5)
    tip_radius = np.empty(5)
    tip_lateral = np.empty((5, 2))
    for c in range(5):
        F = frames[c, 2]
        loc = (Vh - chains[c, 2]) @ F  # distal-bone frame, from the distal joint
        mine = np.isin(dominant, [1 + 3 * c + k for k in range(3)])
        radial = np.hypot(loc[:, 0], loc[:, 2])
        finger = mine & (radial < 16.0) & (loc[:, 1] > -5.0)
        tip_end[c] = float(loc[finger, 1].max())
        band = finger & (loc[:, 1] > lengths[c, 2] - 12.0) & (loc[:, 1] < lengths[c, 2] - 2.0)
        lat = 0.5 * (loc[band][:, [0, 2]].min(axis=0) + loc[band][:, [0, 2]].max(axis=0))
        tip_lateral[c] = lat
        tip_radius[c] = float(np.median(np.hypot(loc[band, 0] - lat[0], loc[band, 2] - lat[1])))

    # Uniform scale: wrist to the end of the straight middle finger = the default model's.
    mid_dir = ref.rest_rotations[2][:, 1]
    mid_end = chains[2, 0] + mid_dir * (lengths[2, 0] + lengths[2, 1] + tip_end[2])
    s = DEFAULT_HAND_LENGTH_MM / float(np.linalg.norm(mid_end))
    Ph, Vh, chains = Ph * s, Vh * s, chains * s
    lengths, tip_end, tip_radius, tip_lateral = lengths * s, tip_end * s, tip_radius * s, tip_lateral * s

    # Local coordinates of every influence.
    local = np.repeat(Vh[:, None, :], 4, axis=1)
    for b in range(1, 16):
        c, k = divmod(b - 1, 3)
        sel = infl_bone == b
        local[sel] = (Vh[np.nonzero(sel)[0]] - chains[c, k]) @ frames[c, k]
    return MeshHand(
        right=right,
        triangles=mesh.triangles.copy(),
        vertices=Vh,
        infl_bone=infl_bone,
        infl_weight=mesh.weights.copy(),
        infl_local=local,
        bases=chains[:, 0].copy(),
        lengths=lengths,
        tip_end=tip_end,
        tip_radius=tip_radius,
        tip_lateral=tip_lateral,
        unit_scale=s,
        bind_joints=Ph,
        joint_names=names,
    )


@lru_cache(maxsize=32)
def _shaped(right: bool, shape: MeshShape) -> tuple[NDArray[np.float64], ...]:
    """Shape-scaled bind data: local (n, 4, 3), bases (5, 3), lengths (5, 3), tip offsets (5, 3)."""
    hand = load_mesh_hand(right)
    L, W, T = shape.as_tuple()
    palm = hand.infl_bone == 0
    local = np.where(
        palm[:, :, None],
        hand.infl_local * np.array([W, 1.0, 1.0]),
        hand.infl_local * np.array([T, L, T]),
    )
    bases = hand.bases * np.array([W, 1.0, 1.0])
    lengths = hand.lengths * L
    tip = np.stack([hand.tip_lateral[:, 0] * T, hand.tip_end * L - hand.tip_radius * T, hand.tip_lateral[:, 1] * T], 1)
    fore = _forearm_mesh(W)
    for a in (local, bases, lengths, tip, fore[0]):
        a.setflags(write=False)
    return local, bases, lengths, tip, fore[0], fore[1]


def _forearm_mesh(width: float) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Hand-frame vertices (k, 3) mm and triangles of the tapered elliptic forearm (with an end cap)."""
    s = np.linspace(0.0, 1.0, _FOREARM_RINGS)
    y = _FOREARM_START_Y + s * (-_FOREARM_LENGTH - _FOREARM_START_Y)
    r = _FOREARM_R_WRIST + s * (_FOREARM_R_ELBOW - _FOREARM_R_WRIST)
    a = np.linspace(0.0, 2.0 * np.pi, _FOREARM_SIDES, endpoint=False)
    ring = np.stack(
        [
            (r[:, None] * width) * np.cos(a)[None, :],
            np.broadcast_to(y[:, None], (s.size, a.size)),
            (r[:, None] * _FOREARM_FLATTEN) * np.sin(a)[None, :],
        ],
        axis=2,
    ).reshape(-1, 3)
    verts = np.concatenate([ring, [[0.0, y[-1], 0.0]]])
    n, m = _FOREARM_RINGS, _FOREARM_SIDES
    i = np.arange(n - 1)[:, None] * m
    k = np.arange(m)[None, :]
    k1 = (k + 1) % m
    q0, q1, q2, q3 = (i + k).ravel(), (i + k1).ravel(), (i + m + k1).ravel(), (i + m + k).ravel()
    tris = np.concatenate([np.stack([q0, q1, q2], 1), np.stack([q0, q2, q3], 1)])
    last = (n - 1) * m
    cap = np.stack([np.full(m, n * m), last + k.ravel(), last + k1.ravel()], 1)
    return verts, np.concatenate([tris, cap]).astype(np.int64)


@dataclass(frozen=True, eq=False)
class PosedMesh:
    """A posed mesh hand in the camera frame (mm).

    Attributes
    ----------
    vertices : array, shape (n, 3)
    triangles : int array, shape (t, 3)
    fingertips : array, shape (5, 3)
        Ground-truth fingertips (thumb .. little), see the module docstring.
    joints : array, shape (5, 4, 3)
        Chain pivots and tip joints of each chain.
    n_hand_vertices : int
        The first vertices belong to the hand; the rest to the forearm.
    """

    vertices: NDArray[np.float64]
    triangles: NDArray[np.int64]
    fingertips: NDArray[np.float64]
    joints: NDArray[np.float64]
    n_hand_vertices: int


def mirror_pose(theta: NDArray[np.float64]) -> NDArray[np.float64]:
    """The pose whose render is the mirror image (camera ``x -> -x``) of ``theta`` on the other hand.

    ``tx, ry, rz`` change sign (``S R S`` with ``S = diag(-1, 1, 1)`` and
    ``R = Rz Rx Ry``); joint angles are unchanged.
    """
    out = check_pose(theta).copy()
    out[0] = -out[0]
    out[4] = -out[4]
    out[5] = -out[5]
    return out


def pose_mesh(
    theta: NDArray[np.float64],
    shape: MeshShape = MeshShape(),
    right: bool = True,
    forearm: bool = True,
) -> PosedMesh:
    """Skin the mesh hand to pose ``theta`` (26,) (mm, rad); camera optical frame, mm."""
    theta = check_pose(theta)
    hand = load_mesh_hand(bool(right))
    local, bases, lengths, tip, fore_v, fore_t = _shaped(bool(right), shape)
    rots = chain_frames(_ref_model(), theta).rotations  # (5, 3, 3, 3), hand frame
    piv = np.empty((5, 4, 3))
    piv[:, 0] = bases
    piv[:, 1:] = bases[:, None, :] + np.cumsum(rots[:, :, :, 1] * lengths[:, :, None], axis=1)
    R_b = np.empty((16, 3, 3))
    R_b[0] = np.eye(3)
    R_b[1:] = rots.reshape(15, 3, 3)
    t_b = np.zeros((16, 3))
    t_b[1:] = piv[:, :3].reshape(15, 3)
    b = hand.infl_bone
    p = np.einsum("nkij,nkj->nki", R_b[b], local) + t_b[b]
    v_hand = np.einsum("nk,nki->ni", hand.infl_weight, p)
    tips_hand = np.einsum("cij,cj->ci", rots[:, 2], tip) + piv[:, 2]
    verts = [v_hand]
    tris = [hand.triangles]
    if forearm:
        verts.append(fore_v)
        tris.append(fore_t + v_hand.shape[0])
    allv = np.concatenate(verts + [tips_hand, piv.reshape(20, 3)])
    G = global_rotation(theta)
    if not right:
        G = G * np.array([-1.0, 1.0, 1.0])[None, :]
    cam = allv @ G.T + theta[:3]
    nv = sum(v.shape[0] for v in verts)
    return PosedMesh(
        vertices=cam[:nv],
        triangles=np.concatenate(tris),
        fingertips=cam[nv : nv + 5],
        joints=cam[nv + 5 :].reshape(5, 4, 3),
        n_hand_vertices=int(v_hand.shape[0]),
    )


def mesh_fingertips(
    theta: NDArray[np.float64], shape: MeshShape = MeshShape(), right: bool = True
) -> NDArray[np.float64]:
    """Ground-truth fingertips (5, 3) mm, camera frame (thumb .. little)."""
    return pose_mesh(theta, shape, right, forearm=False).fingertips


_SIZE_CLASSES = (1, 2, 4, 8, 16, 32, 64, 128, 256, 512, 1024, 2048, 4096, 8192)


def rasterise(
    vertices: NDArray[np.float64], triangles: NDArray[np.int64], intrinsics: Intrinsics
) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Z-buffer a triangle mesh.

    Parameters
    ----------
    vertices : array, shape (n, 3), mm, camera optical frame
    triangles : int array, shape (t, 3)
    intrinsics : Intrinsics

    Returns
    -------
    zbuf : array, shape (H, W), float64
        Depth ``z`` (mm) of the nearest triangle at each pixel centre; ``inf`` = none.
    tri_id : int array, shape (H, W)
        Index of that triangle, -1 where none.
    """
    W, H = intrinsics.width, intrinsics.height
    v = np.asarray(vertices, dtype=np.float64)
    tris = np.asarray(triangles, dtype=np.int64)
    zbuf = np.full(H * W, np.inf)
    tri_id = np.full(H * W, -1, dtype=np.int64)
    z = v[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = intrinsics.fx * v[:, 0] / z + intrinsics.cx
        w = intrinsics.fy * v[:, 1] / z + intrinsics.cy
    tu, tv, tz = u[tris], w[tris], z[tris]  # (t, 3)
    ok = np.all(tz > _NEAR_MM, axis=1)
    u0 = np.ceil(tu.min(axis=1))
    u1 = np.floor(tu.max(axis=1))
    v0 = np.ceil(tv.min(axis=1))
    v1 = np.floor(tv.max(axis=1))
    u0, v0 = np.maximum(u0, 0), np.maximum(v0, 0)
    u1, v1 = np.minimum(u1, W - 1), np.minimum(v1, H - 1)
    area = (tu[:, 1] - tu[:, 0]) * (tv[:, 2] - tv[:, 0]) - (tu[:, 2] - tu[:, 0]) * (tv[:, 1] - tv[:, 0])
    ok &= (u1 >= u0) & (v1 >= v0) & (np.abs(area) > 1e-12)
    idx = np.nonzero(ok)[0]
    if idx.size == 0:
        return zbuf.reshape(H, W), tri_id.reshape(H, W)
    bw = (u1[idx] - u0[idx] + 1).astype(np.int64)
    bh = (v1[idx] - v0[idx] + 1).astype(np.int64)
    cw = np.searchsorted(_SIZE_CLASSES, bw)
    ch = np.searchsorted(_SIZE_CLASSES, bh)
    key = cw * 64 + ch
    pix_all, z_all, id_all = [], [], []
    for k in np.unique(key):
        sel = idx[key == k]
        SW, SH = _SIZE_CLASSES[int(k) // 64], _SIZE_CLASSES[int(k) % 64]
        pu = u0[sel][:, None, None] + np.arange(SW)[None, None, :]  # (m, 1, SW)
        pv = v0[sel][:, None, None] + np.arange(SH)[None, :, None]  # (m, SH, 1)
        a, b_, c = tu[sel], tv[sel], tz[sel]
        inv_area = 1.0 / area[sel][:, None, None]
        U = [a[:, i][:, None, None] for i in range(3)]
        Vv = [b_[:, i][:, None, None] for i in range(3)]
        # barycentric weights from edge functions
        l0 = ((U[1] - pu) * (Vv[2] - pv) - (U[2] - pu) * (Vv[1] - pv)) * inv_area
        l1 = ((U[2] - pu) * (Vv[0] - pv) - (U[0] - pu) * (Vv[2] - pv)) * inv_area
        l2 = 1.0 - l0 - l1
        eps = -1e-9
        inside = (l0 >= eps) & (l1 >= eps) & (l2 >= eps)
        inside &= (pu <= u1[sel][:, None, None]) & (pv <= v1[sel][:, None, None])
        if not inside.any():
            continue
        invz = l0 / c[:, 0][:, None, None] + l1 / c[:, 1][:, None, None] + l2 / c[:, 2][:, None, None]
        m_i, y_i, x_i = np.nonzero(inside)
        pix_all.append((v0[sel][m_i] + y_i).astype(np.int64) * W + (u0[sel][m_i] + x_i).astype(np.int64))
        z_all.append(1.0 / invz[m_i, y_i, x_i])
        id_all.append(sel[m_i])
    if not pix_all:
        return zbuf.reshape(H, W), tri_id.reshape(H, W)
    pix = np.concatenate(pix_all)
    zz = np.concatenate(z_all)
    ids = np.concatenate(id_all)
    np.minimum.at(zbuf, pix, zz)
    win = zz <= zbuf[pix]
    tri_id[pix[win]] = ids[win]
    return zbuf.reshape(H, W), tri_id.reshape(H, W)


def _view_cosine(
    vertices: NDArray[np.float64], triangles: NDArray[np.int64], tri_id: NDArray[np.int64], intr: Intrinsics
) -> NDArray[np.float32]:
    """|cos| of the angle between each pixel's ray and its triangle's normal, (H, W); 1 off the mesh."""
    p = vertices[triangles]
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    H, W = tri_id.shape
    uu = (np.arange(W) - intr.cx) / intr.fx
    vv = (np.arange(H) - intr.cy) / intr.fy
    ray = np.empty((H, W, 3))
    ray[:, :, 0] = uu[None, :]
    ray[:, :, 1] = vv[:, None]
    ray[:, :, 2] = 1.0
    ray /= np.linalg.norm(ray, axis=2, keepdims=True)
    hit = tri_id >= 0
    cos = np.ones((H, W), dtype=np.float32)
    cos[hit] = np.abs(np.einsum("ki,ki->k", n[tri_id[hit]], ray[hit]))
    return cos


# --- sensor models ----------------------------------------------------------------------------

_EDGE_JUMP_MM = 20.0
_TOF_NOISE_MM = 1.2  #: ToF noise sigma at 400 mm, grows with (z / 400)^2
_TOF_FLYING_SHARE = 0.4
_TOF_GRAZING_COS = 0.3
_TOF_RANDOM_DROPOUT = 0.002
_SL_BASELINE_MM = 50.0
_SL_SUBPIXEL = 8.0  #: disparity steps per pixel
_SL_DISP_NOISE_PX = 0.06
_SL_GRAZING_COS = (0.2, 0.4)  #: holes certain below the first, none above the second


def _neighbours(z: NDArray[np.float32], fill: float) -> NDArray[np.float32]:
    p = np.pad(z, 1, mode="constant", constant_values=fill)
    return np.stack([p[:-2, 1:-1], p[2:, 1:-1], p[1:-1, :-2], p[1:-1, 2:]])


def _roi(mask: NDArray[np.bool_], pad: int) -> tuple[slice, slice] | None:
    rows = np.nonzero(mask.any(axis=1))[0]
    cols = np.nonzero(mask.any(axis=0))[0]
    if rows.size == 0:
        return None
    H, W = mask.shape
    return (
        slice(max(rows[0] - pad, 0), min(rows[-1] + pad + 1, H)),
        slice(max(cols[0] - pad, 0), min(cols[-1] + pad + 1, W)),
    )


def _tof(depth: NDArray[np.float32], cos: NDArray[np.float32], rng: np.random.Generator) -> None:
    roi = _roi(depth > 0, 2)
    if roi is None:
        return
    d = depth[roi]
    c = cos[roi]
    clean = d.copy()
    ok = clean > 0
    # Dropout at grazing angles (weak return).
    p_drop = 0.75 * np.clip((_TOF_GRAZING_COS - c) / _TOF_GRAZING_COS, 0.0, 1.0)
    cand = np.nonzero(ok & (p_drop > 0))
    drop = rng.random(cand[0].size) < p_drop[cand]
    d[cand[0][drop], cand[1][drop]] = 0.0
    # Flying pixels: mixed returns between foreground and background at depth edges.
    nb = _neighbours(clean, -1.0)
    valid_nb = nb > 0
    lo = np.minimum(np.where(valid_nb, nb, np.inf).min(axis=0), clean)
    hi = np.maximum(np.where(valid_nb, nb, -np.inf).max(axis=0), clean)
    jump = ok & (hi - lo > _EDGE_JUMP_MM)
    cand = np.nonzero(jump)
    pick = rng.random(cand[0].size) < _TOF_FLYING_SHARE
    iy, ix = cand[0][pick], cand[1][pick]
    frac = rng.uniform(0.1, 0.9, iy.size)
    d[iy, ix] = (lo[iy, ix] + frac * (hi[iy, ix] - lo[iy, ix])).astype(np.float32)
    cand = np.nonzero(ok & ~jump & np.any(nb == 0, axis=0))  # next to no return: weak, often lost
    drop = rng.random(cand[0].size) < 0.3
    d[cand[0][drop], cand[1][drop]] = 0.0
    # Depth noise and sparse dropout.
    sigma = np.float32(_TOF_NOISE_MM / 400.0**2) * d * d
    d += sigma * rng.standard_normal(d.shape, dtype=np.float32)
    np.maximum(d, 0.0, out=d)
    n_drop = rng.binomial(d.size, _TOF_RANDOM_DROPOUT)
    d.reshape(-1)[rng.integers(0, d.size, n_drop)] = 0.0
    np.round(d, out=d)  # ToF cameras report whole millimetres


def _structured(
    depth: NDArray[np.float32], cos: NDArray[np.float32], rng: np.random.Generator, intr: Intrinsics
) -> None:
    roi = _roi(depth > 0, 2)
    if roi is None:
        return
    d = depth[roi]
    c = cos[roi]
    ok = d > 0
    fb = intr.fx * _SL_BASELINE_MM
    disp = np.where(ok, fb / np.maximum(d, 1e-3), 0.0).astype(np.float64)  # px, 0 = none
    # Projector shadow: the projector sits to the right (+x); a pixel is hidden
    # from it if something to its right has a disparity larger by the pixel distance.
    Hh, Ww = disp.shape
    span = int(np.ceil(disp[ok].max() - disp[ok].min())) if ok.any() else 0
    shadow = np.zeros_like(ok)
    for k in range(1, min(span, Ww - 1) + 1):
        occl = np.zeros_like(disp)
        occl[:, :-k] = disp[:, k:] - k
        shadow |= occl > disp + 0.5
    # Left border of the silhouette: the matching window straddles the edge.
    left = np.zeros_like(ok)
    left[:, 1:] = ok[:, 1:] & (~ok[:, :-1] | (disp[:, :-1] < disp[:, 1:] - fb / 400.0**2 * _EDGE_JUMP_MM))
    left &= rng.random(left.shape) < 0.5
    # Grazing angles.
    p_hole = np.clip((_SL_GRAZING_COS[1] - c) / (_SL_GRAZING_COS[1] - _SL_GRAZING_COS[0]), 0.0, 1.0)
    graze = ok & (rng.random(ok.shape) < p_hole)
    # Disparity noise, 3x3 median over valid neighbours of similar disparity, quantisation.
    noisy = disp + _SL_DISP_NOISE_PX * rng.standard_normal(disp.shape)
    pad = np.pad(noisy, 1, mode="edge")
    padok = np.pad(ok, 1, mode="constant", constant_values=False)
    stack = np.stack([pad[i : i + Hh, j : j + Ww] for i in range(3) for j in range(3)])
    sok = np.stack([padok[i : i + Hh, j : j + Ww] for i in range(3) for j in range(3)])
    sok &= np.abs(stack - noisy[None]) < 1.0
    srt = np.sort(np.where(sok, stack, np.inf), axis=0)  # valid values first
    cnt = np.maximum(sok.sum(axis=0), 1)
    lo_i = ((cnt - 1) // 2)[None]
    hi_i = (cnt // 2)[None]
    med = 0.5 * (np.take_along_axis(srt, lo_i, axis=0)[0] + np.take_along_axis(srt, hi_i, axis=0)[0])
    med = np.where(ok & np.isfinite(med), med, 0.0)
    q = np.round(med * _SL_SUBPIXEL) / _SL_SUBPIXEL
    out = np.where(ok & (q > 0), fb / np.maximum(q, 1e-6), 0.0)
    out[shadow | left | graze] = 0.0
    n_drop = rng.binomial(out.size, 0.001)
    out.reshape(-1)[rng.integers(0, out.size, n_drop)] = 0.0
    d[...] = out.astype(np.float32)


def apply_sensor(
    depth: NDArray[np.float32],
    cos: NDArray[np.float32],
    sensor: str,
    intrinsics: Intrinsics,
    rng: np.random.Generator,
) -> None:
    """Apply a sensor model (:data:`SENSORS`) in place to a clean depth image (H, W) mm (0 = none).

    ``cos`` (H, W) is |cos| of the angle between the viewing ray and the surface normal.
    """
    if sensor == "clean":
        return
    if sensor == "tof":
        _tof(depth, cos, rng)
    elif sensor == "structured":
        _structured(depth, cos, rng, intrinsics)
    else:
        raise InputError(f"unknown sensor {sensor!r}; choose one of {', '.join(SENSORS)}")


def render_mesh_depth(
    theta: NDArray[np.float64],
    intrinsics: Intrinsics,
    shape: MeshShape = MeshShape(),
    right: bool = True,
    options: MeshRenderOptions = MeshRenderOptions(),
    rng: np.random.Generator | None = None,
    posed: PosedMesh | None = None,
) -> NDArray[np.float32]:
    """Render the depth image of the posed mesh hand.

    Parameters
    ----------
    theta : array, shape (26,)
        Pose (mm, rad), camera optical frame.
    intrinsics : Intrinsics
        Pinhole camera; output shape ``(height, width)``.
    shape : MeshShape
    right : bool
    options : MeshRenderOptions
        Sensor model, forearm, background.
    rng : numpy.random.Generator, optional
        Sensor randomness; ``None`` = ``default_rng(0)``.
    posed : PosedMesh, optional
        Reuse an already posed mesh (must match the other arguments).

    Returns
    -------
    array, shape (H, W), float32
        Depth ``z`` in mm; 0 = no measurement.
    """
    if rng is None:
        rng = np.random.default_rng(0)
    pm = pose_mesh(theta, shape, right, options.forearm) if posed is None else posed
    zbuf, tri_id = rasterise(pm.vertices, pm.triangles, intrinsics)
    hit = np.isfinite(zbuf)
    if options.background_mm is not None:
        zbuf = np.where(zbuf < options.background_mm, zbuf, options.background_mm)
    depth = np.where(np.isfinite(zbuf), zbuf, 0.0).astype(np.float32)
    if options.sensor != "clean":
        cos = _view_cosine(pm.vertices, pm.triangles, np.where(hit, tri_id, -1), intrinsics)
        if options.background_mm is not None:
            cos[~hit] = 1.0
        apply_sensor(depth, cos, options.sensor, intrinsics, rng)
    return depth


def mesh_sequence(
    motion: str,
    n_frames: int,
    intrinsics: Intrinsics | None = None,
    shape: MeshShape = MeshShape(),
    right: bool = True,
    seed: int = 0,
    options: MeshRenderOptions = MeshRenderOptions(),
    fps: float = 30.0,
) -> Iterator["SyntheticFrame"]:
    """Render a scripted motion with the mesh hand, frame by frame.

    Same contract as :func:`hand_sog_tracker.synth.sequence.synthetic_sequence`
    (poses from :func:`hand_sog_tracker.synth.motions.motion_poses` with
    ``seed``; an independent noise stream), but the depth comes from the mesh
    and the ground-truth fingertips are :func:`mesh_fingertips`.

    Yields
    ------
    SyntheticFrame
    """
    from hand_sog_tracker.synth.motions import motion_poses
    from hand_sog_tracker.synth.sequence import SyntheticFrame, default_intrinsics

    if not isinstance(shape, MeshShape):
        raise InputError(f"shape must be a MeshShape, got {type(shape).__name__}")
    intr = default_intrinsics() if intrinsics is None else intrinsics
    poses = motion_poses(motion, n_frames, fps=fps, seed=seed)
    rng = np.random.default_rng(np.random.SeedSequence(seed).spawn(3)[2])
    for k, pose in enumerate(poses):
        pm = pose_mesh(pose, shape, right, options.forearm)
        depth = render_mesh_depth(pose, intr, shape, right, options, rng, posed=pm)
        yield SyntheticFrame(
            index=k, stamp_s=k / float(fps), depth_mm=depth, pose=pose.copy(), fingertips_mm=pm.fingertips.copy()
        )
