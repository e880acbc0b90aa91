"""Depth renderer of a skinned triangle-mesh hand: synthetic data independent of the tracker's model.

One job: load, shape, pose and skin the mesh hand and render it (the rasteriser and sensors are
:mod:`.raster` and :mod:`.sensors`); kept together because the pose mapping below describes
:func:`load_mesh_hand` and :func:`pose_mesh` as one design.

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
perpendicular to the finger and thumb bones; ``fingers`` scales one chain's
bone lengths and the coordinates along its bones further (thumb .. little:
hands whose fingers' proportions differ from the mesh's, as the tracker's
model's ``HandShape.fingers`` do).

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
``(lateral_x * T, end * L F_c - r * T, lateral_z * T)`` in the distal bone's
frame (``L`` = length, ``F_c`` = the chain's ``fingers`` factor, ``T`` = thickness factor).  A perfect fit therefore
scores about 0 mm.

Rasteriser and sensors
----------------------
The posed mesh is drawn by the Z-buffer rasteriser :func:`rasterise` of
:mod:`hand_sog_tracker.synth.raster`, and a sensor model (:data:`SENSORS`:
``clean``, ``tof``, ``structured``) of :mod:`hand_sog_tracker.synth.sensors`
is applied to the clean depth; both are re-exported here.
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
from hand_sog_tracker.core.rotations import rot_x, rot_z
from hand_sog_tracker.core.types import Intrinsics
from hand_sog_tracker.errors import InputError
from hand_sog_tracker.synth.gltf import read_glb
from hand_sog_tracker.synth.raster import rasterise, view_cosine
from hand_sog_tracker.synth.sensors import SENSORS, apply_sensor

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
    fingers : tuple of 5 floats
        Per chain (thumb .. little), times ``length``: its bone lengths and the vertex
        coordinates along its bones (a hand with a long ring finger and a short little finger:
        other proportions than the mesh's, for measuring how the tracker copes with them).
    """

    length: float = 1.0
    palm_width: float = 1.0
    thickness: float = 1.0
    fingers: tuple[float, float, float, float, float] = (1.0, 1.0, 1.0, 1.0, 1.0)

    def __post_init__(self) -> None:
        for name in ("length", "palm_width", "thickness"):
            v = float(getattr(self, name))
            if not (np.isfinite(v) and 0.5 <= v <= 2.0):
                raise InputError(f"MeshShape.{name} must be in [0.5, 2.0], got {v!r}")
        fingers = tuple(float(v) for v in self.fingers)
        if len(fingers) != 5 or not all(np.isfinite(v) and 0.5 <= v <= 2.0 for v in fingers):
            raise InputError(f"MeshShape.fingers must be 5 factors in [0.5, 2.0], got {self.fingers!r}")
        object.__setattr__(self, "fingers", fingers)  # (a tuple of floats: hashable, compared by value)

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
    wrist_deviation_deg, wrist_flexion_deg : float
        The forearm's turn at the wrist (degrees, at most 60 each): in the palm plane (about
        hand z, positive toward hand +x) and out of it (about hand x).  0: the forearm
        continues the hand's long axis.  Real wrists bend both ways (by 20-30 degrees in
        the labelled real frames), so that the blob of hand and forearm is not aligned with
        the hand.
    """

    sensor: str = "tof"
    forearm: bool = True
    background_mm: float | None = None
    wrist_deviation_deg: float = 0.0
    wrist_flexion_deg: float = 0.0

    def __post_init__(self) -> None:
        if self.sensor not in SENSORS:
            raise InputError(f"unknown sensor {self.sensor!r}; choose one of {', '.join(SENSORS)}")
        for name in ("wrist_deviation_deg", "wrist_flexion_deg"):
            value = getattr(self, name)
            if not (np.isfinite(value) and abs(value) <= 60.0):
                raise InputError(f"{name} must be within [-60, 60] degrees, got {value!r}")

    @property
    def wrist_rad(self) -> tuple[float, float]:
        """``(wrist_deviation, wrist_flexion)`` in radians, as :func:`pose_mesh` takes them."""
        return float(np.deg2rad(self.wrist_deviation_deg)), float(np.deg2rad(self.wrist_flexion_deg))
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
    along = L * np.asarray(shape.fingers)  # (5,) each chain's factor along its bones
    palm = hand.infl_bone == 0
    # The length factor of each influence's chain (bones 1-15: chain (bone - 1) // 3; palm: unused).
    along_infl = along[np.maximum(hand.infl_bone - 1, 0) // 3]  # (n, 4)
    finger_local = hand.infl_local * np.array([T, 1.0, T])
    finger_local[:, :, 1] *= along_infl
    local = np.where(palm[:, :, None], hand.infl_local * np.array([W, 1.0, 1.0]), finger_local)
    bases = hand.bases * np.array([W, 1.0, 1.0])
    lengths = hand.lengths * along[:, None]
    tip_y = hand.tip_end * along - hand.tip_radius * T
    tip = np.stack([hand.tip_lateral[:, 0] * T, tip_y, hand.tip_lateral[:, 1] * T], 1)
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
    wrist_rad: tuple[float, float] = (0.0, 0.0),
) -> PosedMesh:
    """Skin the mesh hand to pose ``theta`` (26,) (mm, rad); camera optical frame, mm.

    ``wrist_rad``: the forearm's deviation and flexion at the wrist (rad, see
    :class:`MeshRenderOptions`)."""
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
        if wrist_rad != (0.0, 0.0):
            # (About the wrist, the hand frame's origin.)
            fore_v = fore_v @ (rot_z(wrist_rad[0]) @ rot_x(wrist_rad[1])).T
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
    pm = pose_mesh(theta, shape, right, options.forearm, options.wrist_rad) if posed is None else posed
    zbuf, tri_id = rasterise(pm.vertices, pm.triangles, intrinsics)
    hit = np.isfinite(zbuf)
    if options.background_mm is not None:
        zbuf = np.where(zbuf < options.background_mm, zbuf, options.background_mm)
    depth = np.where(np.isfinite(zbuf), zbuf, 0.0).astype(np.float32)
    if options.sensor != "clean":
        cos = view_cosine(pm.vertices, pm.triangles, np.where(hit, tri_id, -1), intrinsics)
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
        pm = pose_mesh(pose, shape, right, options.forearm, options.wrist_rad)
        depth = render_mesh_depth(pose, intr, shape, right, options, rng, posed=pm)
        yield SyntheticFrame(
            index=k, stamp_s=k / float(fps), depth_mm=depth, pose=pose.copy(), fingertips_mm=pm.fingertips.copy()
        )
