"""Forward kinematics of the 26-DOF hand and the analytic Jacobian of attached points.

One job: the skeleton's forward kinematics and its derivatives; kept together because the
objective's per-evaluation path (:func:`centres_with_pullback`, ``J^T g`` without building
``J``) and the general one (:func:`attached_points`) share the chain frames and must give the
same centres bit for bit.

All positions are millimetres in the camera optical frame (x right, y down,
z forward) unless a docstring says "hand frame".  See
:mod:`hand_sog_tracker.core.hand_model` for the frames and the pose vector.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.hand_model import (
    CHAIN_JOINTS,
    FIRST_JOINT,
    KEYPOINT_FACING_MM,
    KEYPOINT_OFFSETS_MM,
    N_PARAMS,
    HandModel,
)
from hand_sog_tracker.errors import InputError

__all__ = [
    "ChainFrames",
    "CentresPullback",
    "centres_batch",
    "centres_with_pullback",
    "check_pose",
    "check_poses",
    "global_rotation",
    "chain_frames",
    "attached_points",
    "gaussian_centres",
    "posed_centres",
    "chain_bases",
    "fingertips",
    "skeleton_points",
    "keypoint_skeleton",
    "PALM_KEYPOINT_ROWS",
    "PALM_ROWS",
    "keep_palm_centre",
    "SKELETON_CHAINS",
]


def check_pose(theta: NDArray[np.float64]) -> NDArray[np.float64]:
    """Validate a pose vector and return it as float64, shape (26,)."""
    arr = np.asarray(theta, dtype=np.float64)
    if arr.shape != (N_PARAMS,):
        raise InputError(f"pose must have shape ({N_PARAMS},), got {arr.shape}")
    # A finite sum proves every entry finite (one reduction instead of two).
    if not math.isfinite(np.add.reduce(arr)) and not np.all(np.isfinite(arr)):
        raise InputError("pose contains NaN or Inf")
    return arr


def check_poses(thetas: NDArray[np.float64]) -> NDArray[np.float64]:
    """Validate a batch of pose vectors and return it as float64, shape (B, 26)."""
    arr = np.asarray(thetas, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != N_PARAMS:
        raise InputError(f"poses must have shape (B, {N_PARAMS}), got {arr.shape}")
    if not math.isfinite(np.add.reduce(arr, axis=None)) and not np.all(np.isfinite(arr)):
        raise InputError("poses contain NaN or Inf")
    return arr


def _cross(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """Row-wise cross product of (k, 3) arrays (np.cross has a large fixed overhead)."""
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[..., 0] = a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1]
    out[..., 1] = a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2]
    out[..., 2] = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    return out


def global_rotation(theta: NDArray[np.float64], derivatives: bool = False):
    """Global rotation ``R = Rz(rz) @ Rx(rx) @ Ry(ry)`` of a pose (or of poses).

    The per-frame form of :func:`hand_sog_tracker.core.rotations.matrices_from_euler`
    (for one pose scalar ``math`` calls and one array build: it runs for every objective
    evaluation; for poses (..., 26) the same expressions on arrays, the same bits pose by pose).

    Parameters
    ----------
    theta : array, shape (26,) or (..., 26)
    derivatives : bool
        Also return ``dR/d(rx, ry, rz)``.

    Returns
    -------
    R : array, shape (3, 3) or (..., 3, 3)
    dR : array, shape (3, 3, 3) or (..., 3, 3, 3), only with ``derivatives``; ``dR[..., k, :, :]``
        is the derivative with respect to ``theta[..., 3 + k]``.
    """
    lead = theta.shape[:-1]
    if lead:
        return _global_rotations(theta, derivatives)
    cx, sx = math.cos(theta[3]), math.sin(theta[3])
    cy, sy = math.cos(theta[4]), math.sin(theta[4])
    cz, sz = math.cos(theta[5]), math.sin(theta[5])
    one, zero = 1.0, 0.0
    # (One pose: scalar math and one array build.  Building small arrays dominates the cost; a
    # flat tuple converts several times faster than a nested one.)
    Rxyz = _entries(
        (one, zero, zero, zero, cx, -sx, zero, sx, cx,
         cy, zero, sy, zero, one, zero, -sy, zero, cy,
         cz, -sz, zero, sz, cz, zero, zero, zero, one),
    )
    R = (Rxyz[2] @ Rxyz[0]) @ Rxyz[1]  # Rz Rx Ry
    if not derivatives:
        return R
    # dR in closed form, one array build.
    sxsy, sxcy = sx * sy, sx * cy
    dR = _entries(
        (
            # d/drx = Rz dRx Ry
            -sz * cx * sy, sz * sx, sz * cx * cy,
            cz * cx * sy, -cz * sx, -cz * cx * cy,
            sxsy, cx, -sxcy,
            # d/dry = Rz Rx dRy
            -cz * sy - sz * sxcy, zero, cz * cy - sz * sxsy,
            -sz * sy + cz * sxcy, zero, sz * cy + cz * sxsy,
            -cx * cy, zero, -cx * sy,
            # d/drz = dRz Rx Ry
            -sz * cy - cz * sxsy, -cz * cx, -sz * sy + cz * sxcy,
            cz * cy - sz * sxsy, -sz * cx, cz * sy + sz * sxcy,
            zero, zero, zero,
        ),
    )
    return R, dR


# The rotations of poses (..., 26) as gathers from one array of the values they are made of,
# per pose: 0 one, 1 zero, 2-4 cx cy cz, 5-7 sx sy sz, 8-13 their negatives, 14 sx sy,
# 15 sx cy, 16 -0.0 (see _global_rotations).
_ONE, _ZERO, _CX, _CY, _CZ, _SX, _SY, _SZ = range(8)
_NCX, _NCY, _NCZ, _NSX, _NSY, _NSZ = range(8, 14)
_SXSY, _SXCY, _NZERO = 14, 15, 16
#: The entries of Rx, Ry, Rz (as in global_rotation).
_R_ENTRIES = np.array([
    _ONE, _ZERO, _ZERO, _ZERO, _CX, _NSX, _ZERO, _SX, _CX,
    _CY, _ZERO, _SY, _ZERO, _ONE, _ZERO, _NSY, _ZERO, _CY,
    _CZ, _NSZ, _ZERO, _SZ, _CZ, _ZERO, _ZERO, _ZERO, _ONE,
])
#: Each entry of dR (as in global_rotation) as ``(f1 f2) f3 + g1 g2``: the same operations
#: (``a - b c`` is ``a + (-b) c``, ``-(a b)`` is ``(-a) b``, a missing factor is 1 and a missing
#: product -0.0, all exact), rows f1, f2, f3, g1, g2.
_DR_ENTRIES = np.array([
    # d/drx
    (_NSZ, _CX, _SY, _NZERO, _ONE), (_SZ, _SX, _ONE, _NZERO, _ONE), (_SZ, _CX, _CY, _NZERO, _ONE),
    (_CZ, _CX, _SY, _NZERO, _ONE), (_NCZ, _SX, _ONE, _NZERO, _ONE), (_NCZ, _CX, _CY, _NZERO, _ONE),
    (_SXSY, _ONE, _ONE, _NZERO, _ONE), (_CX, _ONE, _ONE, _NZERO, _ONE), (_NSX, _CY, _ONE, _NZERO, _ONE),
    # d/dry
    (_NCZ, _SY, _ONE, _NSZ, _SXCY), (_ZERO, _ONE, _ONE, _NZERO, _ONE), (_CZ, _CY, _ONE, _NSZ, _SXSY),
    (_NSZ, _SY, _ONE, _CZ, _SXCY), (_ZERO, _ONE, _ONE, _NZERO, _ONE), (_SZ, _CY, _ONE, _CZ, _SXSY),
    (_NCX, _CY, _ONE, _NZERO, _ONE), (_ZERO, _ONE, _ONE, _NZERO, _ONE), (_NCX, _SY, _ONE, _NZERO, _ONE),
    # d/drz
    (_NSZ, _CY, _ONE, _NCZ, _SXSY), (_NCZ, _CX, _ONE, _NZERO, _ONE), (_NSZ, _SY, _ONE, _CZ, _SXCY),
    (_CZ, _CY, _ONE, _NSZ, _SXSY), (_NSZ, _CX, _ONE, _NZERO, _ONE), (_CZ, _SY, _ONE, _SZ, _SXCY),
    (_ZERO, _ONE, _ONE, _NZERO, _ONE), (_ZERO, _ONE, _ONE, _NZERO, _ONE), (_ZERO, _ONE, _ONE, _NZERO, _ONE),
]).T.reshape(-1)
for _arr in (_R_ENTRIES, _DR_ENTRIES):
    _arr.setflags(write=False)


def _global_rotations(theta: NDArray[np.float64], derivatives: bool):
    """:func:`global_rotation` of poses (..., 26): the one-pose expressions on arrays (the same
    bits pose by pose), every entry of ``Rx, Ry, Rz`` and of ``dR`` gathered from one array of
    their factors per pose (a few calls instead of one per product)."""
    lead = theta.shape[:-1]
    V = np.empty(lead + (17,))
    V[..., :2] = (1.0, 0.0)
    V[..., _NZERO] = -0.0
    np.cos(theta[..., 3:6], out=V[..., _CX : _CZ + 1])
    np.sin(theta[..., 3:6], out=V[..., _SX : _SZ + 1])
    np.negative(V[..., _CX : _SZ + 1], out=V[..., _NCX : _NSZ + 1])
    np.multiply(V[..., _SX : _SX + 1], V[..., _SY : _SY + 1], out=V[..., _SXSY : _SXSY + 1])
    np.multiply(V[..., _SX : _SX + 1], V[..., _CY : _CY + 1], out=V[..., _SXCY : _SXCY + 1])
    # (C-contiguous whatever the batch's size: a matrix product's rounding may depend on the
    # memory layout of its operands, and a pose's result must not depend on its batch)
    Rxyz = V.take(_R_ENTRIES, axis=-1).reshape(lead + (3, 3, 3))
    R = (Rxyz[..., 2, :, :] @ Rxyz[..., 0, :, :]) @ Rxyz[..., 1, :, :]  # Rz Rx Ry
    if not derivatives:
        return R
    T = V.take(_DR_ENTRIES, axis=-1).reshape(lead + (5, 27))
    dR = T[..., 0, :] * T[..., 1, :]
    dR *= T[..., 2, :]
    dR += T[..., 3, :] * T[..., 4, :]
    return R, dR.reshape(lead + (3, 3, 3))


def _entries(values: tuple) -> NDArray[np.float64]:
    """27 entries (floats) as three matrices (3, 3, 3)."""
    return np.array(values).reshape(3, 3, 3)


@dataclass(frozen=True)
class ChainFrames:
    """Joint frames of the five chains in the hand frame (mm).

    Attributes
    ----------
    origins : array, shape (5, 4, 3)
        Joint positions: first joint, second joint, third joint, segment end.
    rotations : array, shape (5, 3, 3, 3)
        Orientation of each of the three segments.
    abd_axes : array, shape (5, 3)
        Abduction axis of each chain's first joint.
    """

    origins: NDArray[np.float64]
    rotations: NDArray[np.float64]
    abd_axes: NDArray[np.float64]


def chain_frames(model: HandModel, theta: NDArray[np.float64]) -> ChainFrames:
    """Compute the segment frames of all chains in the hand frame.

    Within a chain all flexion axes coincide (the first segment's x axis), so
    segment ``s`` is ``B @ Rx(f1 + ... + f_{s+1})`` with ``B = R0 @ Rz(abd)``.
    """
    mk = _model_kinematics(model)
    axes, o, _ = _frames(mk, theta)
    rots = np.ascontiguousarray(axes.transpose(0, 1, 3, 2))
    return ChainFrames(origins=o, rotations=rots, abd_axes=mk.r0z)


def _frames(
    mk: _ModelKinematics, theta: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """The segments' axes (..., 5, 3, 3, 3) (chain, segment, axis x / y / z, coordinate: the
    rotations of :class:`ChainFrames` transposed), the origins (..., 5, 4, 3) and the first
    segments' x axes (..., 5, 3) of all chains, for a pose (26,) or poses (..., 26).

    In a chain of base ``B = (bx, by, bz)``, segment ``s`` has the axes ``bx``,
    ``y_s = c_s by + s_s bz`` and ``z_s = c_s bz - s_s by`` (``c_s, s_s``: cosine and sine
    of its summed flexions ``phi_s``), with ``bx = ca r0x + sa r0y``, ``by = ca r0y - sa r0x``
    and ``bz = r0z`` (``ca, sa``: of the abduction; ``r0``: the rest rotation).  The
    differences are computed as sums with a negated factor (``a - b`` and ``a + (-b)`` are the
    same IEEE operation, and ``x (-y) = -(x y)`` exactly): every product and sum of a kind is
    then one NumPy call over all chains (a few dozen calls on tiny arrays cost more than their
    arithmetic), and over all poses of a batch (the leading axes: elementwise, the same bits
    pose by pose).
    """
    lead = theta.shape[:-1]
    # Each chain's abduction, then its flexions summed along the chain (phi): one cos and
    # one sin for all 20 angles, as trig[..., 0, :, :] and trig[..., 1, :, :].
    ang = theta.take(mk.angle_idx, axis=-1)  # (..., 5, 4)
    np.add.accumulate(ang[..., 1:], axis=-1, out=ang[..., 1:])  # (= np.cumsum, without its wrapper)
    trig = np.empty(lead + (2, 5, 4))
    np.cos(ang, out=trig[..., 0, :, :])
    np.sin(ang, out=trig[..., 1, :, :])
    # base[..., k, :, :] = ca r0_mix[0, k] + sa r0_mix[1, k]: bx, -by, (unused), by; then bz.
    prod = trig[..., None, :, :1] * mk.r0_mix  # (..., 2, 4, 5, 3)
    base = np.add(prod[..., 0, :, :, :], prod[..., 1, :, :, :], out=prod[..., 0, :, :, :])
    base[..., 2, :, :] = mk.r0z
    # pairs[.., a, c, 0, b] (a: cos / sin of phi, b: y / z): (by, bz) and (bz, -by) of chain c.
    pairs = np.swapaxes(base.take(_PAIR_ROWS, axis=-3), -3, -2)[..., None, :, :]  # (..., 2, 5, 1, 2, 3)
    prod2 = trig[..., 1:, None, None] * pairs  # (..., 2, 5, 3, 2, 3)
    axes = np.empty(lead + (5, 3, 3, 3))
    np.add(prod2[..., 0, :, :, :, :], prod2[..., 1, :, :, :, :], out=axes[..., 1:, :])  # y_s, z_s
    bx = base[..., 0, :, :]
    axes[..., 0, :] = bx[..., None, :]
    o = np.empty(lead + (5, 4, 3))
    o[..., 0, :] = mk.bases
    tail = np.add.accumulate(axes[..., 1, :] * mk.lengths3, axis=-2, out=o[..., 1:, :])  # (= cumsum, cheaper)
    tail += mk.bases3
    return axes, o, bx


#: Rows of ``base`` in :func:`_frames` that make the pairs (by, bz) and (bz, -by).
_PAIR_ROWS = np.array([[3, 2], [2, 1]])


@dataclass(frozen=True, eq=False)
class _ModelKinematics:
    """Per-model constants of the kinematics (cached per model object, see below)."""

    angle_idx: NDArray[np.int64]  # (5, 4) pose index of each chain's abduction and flexions
    # (2, 4, 5, 3) columns of the rest rotations: (r0x, -r0y, 0, r0y) and (r0y, r0x, 0, -r0x)
    r0_mix: NDArray[np.float64]
    r0z: NDArray[np.float64]  # (5, 3) column z
    bases: NDArray[np.float64]  # (5, 3)
    bases3: NDArray[np.float64]  # (5, 1, 3)
    lengths3: NDArray[np.float64]  # (5, 3, 1)
    # The model Gaussians (see attached_points): index into rotations (15, 9) / origins (20, 3).
    g_rot: NDArray[np.int64]  # (m,)
    g_org: NDArray[np.int64]  # (m,)
    g_finger: NDArray[np.bool_]  # (m, 1)
    g_offsets: NDArray[np.float64]  # (m, 3)
    # groups[4 c + j, i] = 1 when joint j of chain c moves Gaussian i (joint columns of J).
    groups: NDArray[np.float64]  # (20, m)
    pivot: NDArray[np.int64]  # (20,) index into origins (20, 3) of each joint's pivot
    axis_row: NDArray[np.int64]  # (20,) row of each joint's axis in the axis table of _centres_flat
    M: NDArray[np.float64]  # (3,) diagonal of the mirror (see _MIRROR)
    right: bool
    one: _FlatTables  # the index tables of _centres_flat


_KIN_CACHE: dict[int, tuple[HandModel, _ModelKinematics]] = {}


def _model_kinematics(model: HandModel) -> _ModelKinematics:
    """The :class:`_ModelKinematics` of a model (cached per model object, like
    :func:`hand_sog_tracker.core.objective.collision.model_constants`: models are frozen)."""
    hit = _KIN_CACHE.get(id(model))
    if hit is not None and hit[0] is model:
        return hit[1]
    layout = _layout_kinematics(model)
    mk = _ModelKinematics(
        **layout,
        bases=np.array(model.bases, dtype=np.float64),
        bases3=np.array(model.bases, dtype=np.float64)[:, None, :],
        lengths3=np.array(model.lengths, dtype=np.float64)[:, :, None],
        g_offsets=np.array(model.g_offsets, dtype=np.float64),
        M=_mirror(model),
        right=bool(model.right),
        one=_flat_tables(model, layout),
    )
    for arr in list(vars(mk).values()) + list(vars(mk.one).values()):
        if isinstance(arr, np.ndarray):
            arr.setflags(write=False)
    if len(_KIN_CACHE) > 32:
        _KIN_CACHE.clear()
    _KIN_CACHE[id(model)] = (model, mk)
    return mk


#: :func:`_layout_kinematics` by the identity of a model's rest rotations, chains and segments
#: (with the arrays themselves, which keep the ids valid): the models a calibration scales
#: from one default model share these arrays (:meth:`HandModel.scaled`).
_LAYOUT_CACHE: dict[tuple[int, int, int], tuple[tuple[NDArray, NDArray, NDArray], dict[str, NDArray]]] = {}


def _layout_kinematics(model: HandModel) -> dict[str, NDArray]:
    """The fields of :class:`_ModelKinematics` that the hand's shape does not change (read-only)."""
    arrays = (model.rest_rotations, model.g_chain, model.g_segment)
    key = (id(arrays[0]), id(arrays[1]), id(arrays[2]))
    hit = _LAYOUT_CACHE.get(key)
    if hit is not None and all(a is b for a, b in zip(hit[0], arrays)):
        return hit[1]
    first = FIRST_JOINT + CHAIN_JOINTS * np.arange(5)
    r0 = np.asarray(model.rest_rotations, dtype=np.float64)
    chain = np.asarray(model.g_chain)
    segment = np.asarray(model.g_segment)
    m = chain.shape[0]
    finger = chain >= 0
    c = np.where(finger, chain, 0).astype(np.int64)
    s = np.where(finger, segment, 0).astype(np.int64)
    first_seg = np.array([0, 0, 1, 2])
    groups = np.zeros((20, m))
    for cc in range(5):
        for j in range(CHAIN_JOINTS):
            groups[CHAIN_JOINTS * cc + j] = finger & (c == cc) & (s >= first_seg[j])
    layout = {
        "angle_idx": first[:, None] + np.array([1, 0, 2, 3])[None, :],
        "r0_mix": np.array(
            [
                [r0[:, :, 0], -r0[:, :, 1], np.zeros((5, 3)), r0[:, :, 1]],
                [r0[:, :, 1], r0[:, :, 0], np.zeros((5, 3)), -r0[:, :, 0]],
            ]
        ),
        "r0z": np.ascontiguousarray(r0[:, :, 2]),
        "g_rot": 3 * c + s,
        "g_org": 4 * c + s,
        "g_finger": finger[:, None],
        "groups": groups,
        "pivot": (4 * np.arange(5)[:, None] + first_seg[None, :]).ravel(),
        "axis_row": (np.arange(5)[:, None] + np.array([0, 15, 0, 0])[None, :]).ravel(),
    }
    for arr in layout.values():
        arr.setflags(write=False)
    if len(_LAYOUT_CACHE) >= 8:
        _LAYOUT_CACHE.clear()
    _LAYOUT_CACHE[key] = (arrays, layout)
    return layout


#: The mirror ``M`` of a right (identity) and a left hand (x negated) as its diagonal, shape
#: (3,): ``R @ M`` is ``R * diagonal`` and ``p @ M.T`` is ``p * diagonal`` (exact, one product).
_MIRROR = {True: np.array([1.0, 1.0, 1.0]), False: np.array([-1.0, 1.0, 1.0])}
for _m in _MIRROR.values():
    _m.setflags(write=False)


def _mirror(model: HandModel) -> NDArray[np.float64]:
    """The diagonal (3,) of the model's mirror ``M`` (see :data:`_MIRROR`)."""
    return _MIRROR[bool(model.right)]


@dataclass(frozen=True, eq=False)
class _PointIndex:
    """Index arrays of a set of attached points (depend on their chains and segments only)."""

    finger: NDArray[np.bool_]  # (k,) on a finger chain (else palm)
    finger_col: NDArray[np.bool_]  # (k, 1)
    c: NDArray[np.int64]  # (k,) chain, palm -> 0
    rot: NDArray[np.int64]  # (k,) index into rotations.reshape(15, 3, 3)
    org: NDArray[np.int64]  # (k,) index into origins.reshape(20, 3)
    pivot: NDArray[np.int64]  # (k, 4) joint origins of the four joint columns
    active: NDArray[np.bool_]  # (k, 4, 1) joint moves the point
    j_index: NDArray[np.int64]  # (k, 4, 3) flat index of the joint columns in J (k, 3, 26)
    j_template: NDArray[np.float64] | None  # (k, 3, 26) J with the translation columns set


#: Point sets up to this size keep a ready Jacobian template in the cache.
_TEMPLATE_MAX_POINTS = 256


def _j_template(k: int) -> NDArray[np.float64]:
    """J of k points with only the translation columns (identity) set, shape (k, 3, 26)."""
    tmpl = np.zeros((k, 3, N_PARAMS))
    tmpl[:, 0, 0] = tmpl[:, 1, 1] = tmpl[:, 2, 2] = 1.0
    return tmpl


_INDEX_CACHE: dict[tuple[int, int], tuple[NDArray, NDArray, NDArray, NDArray, _PointIndex]] = {}


def _point_index(chain: NDArray[np.int64], segment: NDArray[np.int64]) -> _PointIndex:
    """Cached :class:`_PointIndex` of points.

    Keyed by the identity of the ``chain`` and ``segment`` arrays (a model's arrays are
    reused every call; the cache holds them, so their ids cannot be recycled), confirmed by
    their contents (a cheap comparison against a private copy).
    """
    hit = _INDEX_CACHE.get((id(chain), id(segment)))
    if (
        hit is not None
        and hit[0] is chain
        and hit[1] is segment
        and hit[2].shape == chain.shape
        and hit[3].shape == segment.shape
        and bool((hit[2] == chain).all())
        and bool((hit[3] == segment).all())
    ):
        return hit[4]
    k = chain.shape[0]
    finger = chain >= 0
    c = np.where(finger, chain, 0).astype(np.int64)
    s = np.where(finger, segment, 0).astype(np.int64)
    active = np.stack([finger, finger, finger & (s >= 1), finger & (s >= 2)], axis=1)
    cols = FIRST_JOINT + CHAIN_JOINTS * c[:, None] + np.arange(CHAIN_JOINTS)[None, :]  # (k, 4)
    j_index = (
        np.arange(k)[:, None, None] * (3 * N_PARAMS)
        + np.arange(3)[None, None, :] * N_PARAMS
        + cols[:, :, None]
    )
    tmpl = _j_template(k) if k <= _TEMPLATE_MAX_POINTS else None
    idx = _PointIndex(
        finger=finger,
        finger_col=finger[:, None],
        c=c,
        rot=3 * c + s,
        org=4 * c + s,
        pivot=4 * c[:, None] + np.array([0, 0, 1, 2])[None, :],
        active=active[:, :, None],
        j_index=j_index,
        j_template=tmpl,
    )
    for arr in vars(idx).values():
        if arr is not None:
            arr.setflags(write=False)
    if len(_INDEX_CACHE) >= 8:
        _INDEX_CACHE.clear()
    _INDEX_CACHE[(id(chain), id(segment))] = (chain, segment, chain.copy(), segment.copy(), idx)
    return idx


def attached_points(
    model: HandModel,
    theta: NDArray[np.float64],
    chain: NDArray[np.int64],
    segment: NDArray[np.int64],
    offsets: NDArray[np.float64],
    jacobian: bool = False,
):
    """Positions (and Jacobian) of points rigidly attached to the skeleton.

    Parameters
    ----------
    model : HandModel
    theta : array, shape (26,)
        Pose (mm, rad).
    chain : int array, shape (k,)
        Chain of each point (0 thumb .. 4 little, -1 palm).
    segment : int array, shape (k,)
        Segment 0..2 along the chain (ignored for the palm).
    offsets : array, shape (k, 3), mm
        Point in its segment frame (palm: hand frame).
    jacobian : bool
        Also return the Jacobian.

    Returns
    -------
    points : array, shape (k, 3), mm, camera frame
    J : array, shape (k, 3, 26), only with ``jacobian``; ``J[i, :, j]`` is
        ``d points[i] / d theta[j]`` (mm per mm or mm per rad).
    """
    theta = check_pose(theta)
    fr = chain_frames(model, theta)
    ix = _point_index(np.asarray(chain), np.asarray(segment))
    offsets = np.asarray(offsets, dtype=np.float64)
    rot15 = fr.rotations.reshape(15, 3, 3)
    org20 = fr.origins.reshape(20, 3)
    local = np.einsum("kij,kj->ki", rot15[ix.rot], offsets) + org20[ix.org]
    p_hand = np.where(ix.finger_col, local, offsets)
    M = _mirror(model)
    if not jacobian:
        R = global_rotation(theta)
        return p_hand @ (R * M).T + theta[:3]
    R, dR = global_rotation(theta, derivatives=True)
    G = R * M
    pts = p_hand @ G.T + theta[:3]
    J = ix.j_template.copy() if ix.j_template is not None else _j_template(ix.c.shape[0])
    pm = p_hand * M
    for a in range(3):
        J[:, :, 3 + a] = pm @ dR[a].T
    # Joint columns, computed in the hand frame then rotated by G (which may
    # be a reflection, so cross products are taken before it).  All flexion
    # axes of a chain coincide (the first segment's x axis).
    chain_axes = np.empty((5, 4, 3))
    chain_axes[:, 0] = chain_axes[:, 2] = chain_axes[:, 3] = fr.rotations[:, 0, :, 0]
    chain_axes[:, 1] = fr.abd_axes
    axes = chain_axes[ix.c]  # (k, 4, 3)
    pivots = org20[ix.pivot]  # (k, 4, 3)
    dh = _cross(axes, p_hand[:, None, :] - pivots) * ix.active
    J.reshape(-1)[ix.j_index] = dh @ G.T
    return pts, J


def gaussian_centres(model: HandModel, theta: NDArray[np.float64], jacobian: bool = False):
    """Centres of the model Gaussians, shape (m, 3) mm, and optionally J (m, 3, 26)."""
    if not jacobian:  # the per-evaluation path: the model's index arrays cached
        return _posed(model, theta).pts.copy()
    return attached_points(
        model, theta, model.g_chain, model.g_segment, model.g_offsets, jacobian=jacobian
    )


class CentresPullback:
    """What :func:`centres_with_pullback` keeps of a pose to map ``dE/dP`` to ``dE/dtheta``.

    A plain class with slots (built once per objective evaluation: cheaper than a frozen
    dataclass).  Attributes: ``mk`` the model's constants, ``p_hand`` (m, 3) the centres in
    the hand frame (mm), ``pm`` the same mirrored (``p_hand @ M.T``), ``G`` (3, 3) the global
    rotation times the mirror, ``dR`` (3, 3, 3) the rotation's derivatives, ``org20`` (20, 3)
    the joint origins (hand frame, mm), ``axes`` (20, 3) the joint axes (hand frame).
    """

    __slots__ = ("mk", "p_hand", "pm", "G", "dR", "org20", "axes")

    def __init__(
        self,
        mk: _ModelKinematics,
        p_hand: NDArray[np.float64],
        pm: NDArray[np.float64],
        G: NDArray[np.float64],
        dR: NDArray[np.float64],
        org20: NDArray[np.float64],
        axes: NDArray[np.float64],
    ) -> None:
        self.mk, self.p_hand, self.pm, self.G, self.dR, self.org20, self.axes = mk, p_hand, pm, G, dR, org20, axes

    def __call__(self, g3: NDArray[np.float64]) -> NDArray[np.float64]:
        """``g3 (m, 3) -> J^T g3`` summed per parameter, shape (26,): the gradient of a
        function of the centres, from its gradient ``g3`` with respect to the centres (for a
        batch of poses, :func:`centres_batch`: ``g3 (B, m, 3) -> (B, 26)``).

        Equals ``np.einsum("mk,mkj->j", g3, J)`` with ``J`` of :func:`gaussian_centres` (up to
        float rounding) without building ``J``: for a joint with axis ``a`` and pivot ``o``,
        ``sum_i g3_i . G (a x (p_i - o)) = a . sum_i (p_i - o) x h_i`` with ``h_i = G^T g3_i``,
        and the sums over the points a joint moves are one product with a constant matrix.
        """
        mk = self.mk
        p = self.p_hand
        lead = g3.shape[:-2]
        grad = np.empty(lead + (N_PARAMS,))
        grad[..., :3] = np.add.reduce(g3, axis=-2)  # (= g3.sum(axis=-2) without the method's Python layer)
        # Rotation columns: sum_i g3_i . dR_a M p_i = <dR_a, g3^T (p M^T)>.
        gp = np.matmul(np.swapaxes(g3, -1, -2), self.pm)
        if lead:
            grad[..., 3:6] = np.matmul(self.dR.reshape(lead + (3, 9)), gp.reshape(lead + (9, 1)))[..., 0]
        else:
            grad[3:6] = self.dR.reshape(3, 9) @ gp.reshape(9)
        m = p.shape[-2]
        Q = np.empty(lead + (m, 12))
        h = np.matmul(g3, self.G, out=Q[..., 9:])  # (..., m, 3), h_i = G^T g3_i (hand frame)
        np.multiply(p[..., None], h[..., None, :], out=Q[..., :9].reshape(lead + (m, 3, 3)))
        T = mk.groups @ Q  # (..., 20, 12): sum p h^T (9) and sum h (3) per joint
        pivots = self.org20.take(mk.pivot, axis=-2)[..., None]
        outer = T[..., :9].reshape(lead + (20, 3, 3)) - pivots * T[..., None, 9:]
        outer = outer.reshape(lead + (20, 9))  # sum (p - o) h^T per joint
        X = outer.take(_CROSS_A, axis=-1) - outer.take(_CROSS_B, axis=-1)  # sum (p - o) x h per joint
        grad[..., FIRST_JOINT:] = np.einsum("...ij,...ij->...i", self.axes, X)
        return grad


#: ``(p x h)_k = O[a_k] - O[b_k]`` for ``O = p h^T`` flattened (9,).
_CROSS_A = np.array([5, 6, 1])
_CROSS_B = np.array([7, 2, 3])


def centres_batch(
    model: HandModel, thetas: NDArray[np.float64], pullback: bool = True
) -> tuple[NDArray[np.float64], CentresPullback | None]:
    """Centres of the model Gaussians at every pose of ``thetas`` (B, 26), shape (B, m, 3) mm,
    and (with ``pullback``) the :class:`CentresPullback` that maps ``dE/dP`` (B, m, 3) to
    ``dE/dtheta`` (B, 26).

    :func:`centres_with_pullback` with a leading batch axis through every step (the same
    values up to rounding; nothing cached: a batch's poses are new poses).
    """
    mk = _model_kinematics(model)
    p_hand, org20, table = _centres_flat(mk, thetas)
    R, dR = global_rotation(thetas, derivatives=True)
    G = R if mk.right else R * mk.M
    P = np.matmul(p_hand, np.swapaxes(G, -1, -2))
    P += thetas[:, None, :3]
    if not pullback:
        return P, None
    pm = p_hand if mk.right else p_hand * mk.M
    axes = table.take(mk.axis_row, axis=-2)
    return P, CentresPullback(mk, p_hand, pm, G, dR, org20, axes)


def centres_with_pullback(
    model: HandModel, theta: NDArray[np.float64]
) -> tuple[NDArray[np.float64], CentresPullback]:
    """Centres of the model Gaussians (m, 3) mm and a :class:`CentresPullback`.

    The per-evaluation form of ``gaussian_centres(model, theta, jacobian=True)`` followed by
    ``einsum("mk,mkj->j", g3, J)``: the same centres (bit-identical), the same gradient up to
    float rounding, several times cheaper (no Jacobian is built).
    """
    posed = _posed(model, theta, pullback=True)
    return posed.pts, posed.pullback


class _Posed:
    """The model at one pose: centres (m, 3) mm (read-only), centres in the hand frame (m, 3),
    joint origins (20, 3) mm, the axis table (20, 3) of :func:`_centres_flat`, ``G`` (3, 3) and,
    once asked for, the :class:`CentresPullback` (a plain class with slots: built on every
    evaluation)."""

    __slots__ = ("mk", "key", "pts", "p_hand", "org20", "table", "G", "pullback")

    def __init__(self, mk: _ModelKinematics, key: bytes, theta: NDArray[np.float64], pullback: bool) -> None:
        self.mk, self.key = mk, key
        self.p_hand, self.org20, self.table = _hand_frame(mk, key, theta)
        if pullback:
            R, dR = global_rotation(theta, derivatives=True)
        else:
            R, dR = global_rotation(theta), None
        self.G = R if mk.right else R * mk.M  # (a right hand's mirror is the identity: R * 1 = R)
        self.pts = self.p_hand @ self.G.T + theta[:3]
        self.pts.setflags(write=False)
        self.pullback: CentresPullback | None = None
        if dR is not None:
            self._add_pullback(dR)

    def _add_pullback(self, dR: NDArray[np.float64]) -> None:
        mk = self.mk
        pm = self.p_hand if mk.right else self.p_hand * mk.M
        # Joint axes (20, 3): flexions about the chain's bx, abductions about its (fixed) bz.
        axes = self.table.take(mk.axis_row, axis=0)
        self.pullback = CentresPullback(mk, self.p_hand, pm, self.G, dR, self.org20, axes)


#: The last few posed models (:class:`_Posed`) by ``(model constants id, pose bytes)``, oldest
#: first.  A tracked frame asks for the centres, fingertips and skeleton of the same poses
#: several times (the fit's best pose, which may be any of its iterates, the restarts' start
#: poses, the result, the next frame's data window): each is computed once.  (A dict: a
#: lookup costs the same for any size; the entries keep their model constants alive, so the
#: ids in the keys cannot be recycled while cached.)
_POSED: dict[tuple[int, bytes], _Posed] = {}
_POSED_SIZE = 24


def _posed(model: HandModel, theta: NDArray[np.float64], pullback: bool = False) -> _Posed:
    """``model`` at ``theta`` (cached for the last :data:`_POSED_SIZE` poses); with
    ``pullback`` its :class:`CentresPullback` is set."""
    theta = check_pose(theta)
    mk = _model_kinematics(model)
    key = theta.tobytes()
    posed = _POSED.get((id(mk), key))
    if posed is not None:
        if pullback and posed.pullback is None:
            posed._add_pullback(global_rotation(theta, derivatives=True)[1])
        return posed
    posed = _Posed(mk, key, theta, pullback)
    if len(_POSED) >= _POSED_SIZE:
        del _POSED[next(iter(_POSED))]
    _POSED[(id(mk), key)] = posed
    return posed


#: The last few articulations' :func:`_centres_hand` by ``(model constants id, joint angles'
#: bytes)``, oldest first, with their model constants (which keep the ids valid): a rigid fit
#: (the initialisation's first stage) moves only the wrist, the hand frame's centres stay.
_HAND: dict[tuple[int, bytes], tuple[_ModelKinematics, tuple]] = {}
_HAND_SIZE = 4
#: Bytes of the global parameters (translation, rotation) at the start of a pose's bytes.
_GLOBAL_BYTES = FIRST_JOINT * 8


def _hand_frame(
    mk: _ModelKinematics, key: bytes, theta: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """:func:`_centres_hand` of ``theta`` (its bytes ``key``), cached by its joint angles
    (read-only arrays: shared by the poses with these angles)."""
    hkey = (id(mk), key[_GLOBAL_BYTES:])
    hit = _HAND.get(hkey)
    if hit is not None:
        return hit[1]
    hand = _centres_flat(mk, theta)
    for arr in hand:
        arr.setflags(write=False)
    if len(_HAND) >= _HAND_SIZE:
        del _HAND[next(iter(_HAND))]
    _HAND[hkey] = (mk, hand)
    return hand


@dataclass(frozen=True, eq=False)
class _FlatTables:
    """Flat tables of :func:`_centres_flat` for one model (see there).

    ``trig`` is ``(cos, sin)`` of the 20 angles of :func:`_frames` (chain-major, abduction
    first), flat (40,); ``W`` (150,) holds, flat: ``bx``, ``-by``, ``by`` (45: 3 x 5 chains x
    3), ``bz`` (15) and the segments' ``y_s, z_s`` (90: chain, segment, y / z, coordinate).
    """

    ang: NDArray[np.int64]  # (20,) pose index of each angle
    base_trig: NDArray[np.int64]  # (90,) index into trig: ca (45) then sa (45) per bx, -by, by entry
    base_mix: NDArray[np.float64]  # (90,) the rest rotations' columns they multiply (r0_mix)
    bz: NDArray[np.float64]  # (15,) r0z, flat
    axis_trig: NDArray[np.int64]  # (180,) index into trig: cos (90) then sin (90) of phi_s per y / z entry
    axis_base: NDArray[np.int64]  # (180,) index into W: (by, bz) then (bz, -by)
    y_idx: NDArray[np.int64]  # (45,) index into W of y_s (chain, segment, coordinate)
    lengths: NDArray[np.float64]  # (45,) the segment lengths per y_s entry
    bases: NDArray[np.float64]  # (5, 3, 3) each chain's base, per segment end
    local_idx: NDArray[np.int64]  # (3 m 3,) index into W of bx, y_s, z_s of each Gaussian's segment
    local_off: NDArray[np.float64]  # (3 m 3,) the offsets they multiply (axis, Gaussian, coordinate)
    org_idx: NDArray[np.int64]  # (m 3,) flat index into the origins (20 3,) of each Gaussian's origin


#: The shape-independent index tables of :func:`_flat_tables` by the identity of their layout
#: (:func:`_layout_kinematics`'s dict, kept alive here): a calibration scores a hundred scaled
#: models of one layout, each built once.
_FLAT_INDEX: dict[int, tuple[dict[str, NDArray], dict[str, NDArray]]] = {}


def _flat_index(layout: dict[str, NDArray]) -> dict[str, NDArray]:
    """The fields of :class:`_FlatTables` that only ``layout`` decides (read-only, cached)."""
    hit = _FLAT_INDEX.get(id(layout))
    if hit is not None and hit[0] is layout:
        return hit[1]
    r0_mix = layout["r0_mix"]  # (2, 4, 5, 3): a (ca / sa), k (bx, -by, 0, by), chain, coordinate
    rows = np.array([0, 1, 3])  # (k = 2 is bz, set as r0z)
    # base entries (a, k, c, i): trig[a, c, 0] (the abduction's cos / sin) times r0_mix[a, k, c, i]
    base_trig = np.broadcast_to(20 * np.arange(2)[:, None, None, None] + 4 * np.arange(5)[:, None], (2, 3, 5, 3))
    base_mix = r0_mix[:, rows]
    # axis entries (a, c, s, b, i): trig[a, c, 1 + s] times W's pairs[a, c, b]: (by, bz), (bz, -by)
    a, c, sg, b, i = np.meshgrid(np.arange(2), np.arange(5), np.arange(3), np.arange(2), np.arange(3), indexing="ij")
    axis_trig = 20 * a + 4 * c + 1 + sg
    row_of = np.array([[30, 45], [45, 15]])  # W's offsets of by, bz / bz, -by
    axis_base = row_of[a, b] + 3 * c + i
    c2, s2, i2 = np.meshgrid(np.arange(5), np.arange(3), np.arange(3), indexing="ij")
    y_idx = 60 + ((3 * c2 + s2) * 2 + 0) * 3 + i2
    g_rot = layout["g_rot"]
    gc, gs = g_rot // 3, g_rot % 3
    m = g_rot.size
    gi = np.arange(3)[None, :]
    local_idx = np.stack([
        3 * gc[:, None] + gi,
        60 + ((3 * gc[:, None] + gs[:, None]) * 2 + 0) * 3 + gi,
        60 + ((3 * gc[:, None] + gs[:, None]) * 2 + 1) * 3 + gi,
    ])  # (3, m, 3)
    index = {
        "ang": layout["angle_idx"].reshape(-1),
        "base_trig": base_trig.reshape(-1),
        "base_mix": np.ascontiguousarray(base_mix).reshape(-1),
        "bz": np.ascontiguousarray(layout["r0z"]).reshape(-1),
        "axis_trig": axis_trig.reshape(-1),
        "axis_base": axis_base.reshape(-1),
        "y_idx": y_idx.reshape(-1),
        "local_idx": local_idx.reshape(-1),
        "org_idx": (3 * layout["g_org"][:, None] + gi).reshape(-1) if m else np.zeros(0, np.int64),
    }
    for arr in index.values():
        arr.setflags(write=False)
    if len(_FLAT_INDEX) >= 8:
        _FLAT_INDEX.clear()
    _FLAT_INDEX[id(layout)] = (layout, index)
    return index


def _flat_tables(model: HandModel, layout: dict[str, NDArray]) -> _FlatTables:
    """The :class:`_FlatTables` of ``model`` (``layout``: its :func:`_layout_kinematics`)."""
    lengths = np.repeat(np.asarray(model.lengths, dtype=np.float64)[:, :, None], 3, axis=2)
    off = np.asarray(model.g_offsets, dtype=np.float64)
    local_off = np.repeat(off.T[:, :, None], 3, axis=2)  # (3, m, 3): off[k, j] per coordinate
    bases = np.repeat(np.asarray(model.bases, dtype=np.float64)[:, None, :], 3, axis=1)
    return _FlatTables(
        **_flat_index(layout), lengths=lengths.reshape(-1), bases=bases, local_off=local_off.reshape(-1)
    )


def _centres_flat(
    mk: _ModelKinematics, theta: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """:func:`_centres_hand` of a pose (26,) or poses (B, 26), the same bits: the same products
    and sums as :func:`_frames` and the centres there, on flat arrays gathered by the model's
    tables (:class:`_FlatTables`) instead of broadcasts over four or five axes (a NumPy call on a
    1-D array of 20-180 entries costs a fraction of one that broadcasts such shapes).  The
    per-evaluation path of the objective.

    Returns the centres (..., m, 3) and joint origins (..., 20, 3) of :func:`_centres_hand`, and
    in place of its flexion axes the axis table (..., 20, 3): per chain ``bx`` (rows 0-4),
    ``-by``, ``by`` and ``bz`` (rows 15-19), from which the joint axes are one gather
    (``axis_row``)."""
    t = mk.one
    lead = theta.shape[:-1]
    ang = theta.take(t.ang, axis=-1)  # (..., 20): per chain abduction, f1, f2, f3
    ang4 = ang.reshape(lead + (5, 4))
    ang4[..., 2] += ang4[..., 1]  # phi: the flexions summed along the chain (as np.add.accumulate)
    ang4[..., 3] += ang4[..., 2]
    trig = np.empty(lead + (40,))
    np.cos(ang, out=trig[..., :20])
    np.sin(ang, out=trig[..., 20:])
    W = np.empty(lead + (150,))
    F = trig.take(t.base_trig, axis=-1)
    F *= t.base_mix
    np.add(F[..., :45], F[..., 45:], out=W[..., :45])  # bx, -by, by = ca r0_mix[0] + sa r0_mix[1]
    W[..., 45:60] = t.bz
    G = trig.take(t.axis_trig, axis=-1)
    G *= W.take(t.axis_base, axis=-1)
    np.add(G[..., :90], G[..., 90:], out=W[..., 60:])  # y_s = c by + s bz, z_s = c bz + s (-by)
    Y = W.take(t.y_idx, axis=-1)
    Y *= t.lengths
    Y3 = Y.reshape(lead + (5, 3, 3))
    Y3[..., 1, :] += Y3[..., 0, :]  # the segment ends along the chain (as np.add.accumulate)
    Y3[..., 2, :] += Y3[..., 1, :]
    o = np.empty(lead + (5, 4, 3))
    o[..., 0, :] = mk.bases
    np.add(Y3, t.bases, out=o[..., 1:, :])
    org20 = o.reshape(lead + (20, 3))
    L = W.take(t.local_idx, axis=-1)
    L *= t.local_off
    # The sum over the axes in the einsum's order (_centres_hand): (L0 + L1) + L2.
    local = np.add.reduce(L.reshape(lead + (3, -1)), axis=-2)
    local += o.reshape(lead + (60,)).take(t.org_idx, axis=-1)
    local = local.reshape(lead + (-1, 3))
    return np.where(mk.g_finger, local, mk.g_offsets), org20, W[..., :60].reshape(lead + (20, 3))


def _centres_hand(
    mk: _ModelKinematics, theta: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Model Gaussian centres in the hand frame (..., m, 3), joint origins (..., 20, 3),
    flexion axes (..., 5, 3) of a pose (26,) or poses (..., 26).

    The same arithmetic as :func:`attached_points` (bit-identical), with the model's index
    arrays cached.
    """
    axes, o, bx = _frames(mk, theta)
    lead = theta.shape[:-1]
    org20 = o.reshape(lead + (20, 3))
    # (The rotation of each Gaussian's segment, transposed: its axes as rows.)
    rot = axes.reshape(lead + (15, 3, 3)).take(mk.g_rot, axis=-3)
    local = np.einsum("...kji,kj->...ki", rot, mk.g_offsets)
    local += org20.take(mk.g_org, axis=-2)
    return np.where(mk.g_finger, local, mk.g_offsets), org20, bx


def posed_centres(model: HandModel, theta: NDArray[np.float64]) -> NDArray[np.float64]:
    """:func:`gaussian_centres` without the copy: the cached centres (m, 3) mm, read-only."""
    return _posed(model, theta).pts


#: Rows of the joint origins (20, 3) that are each chain's first joint (thumb CMC, the MCPs).
_CHAIN_FIRST = np.arange(0, 20, CHAIN_JOINTS)


def chain_bases(model: HandModel, theta: NDArray[np.float64]) -> NDArray[np.float64]:
    """Each chain's first joint, shape (5, 3), mm, camera frame (thumb .. little), from the
    cached posed model; the same values as :func:`attached_points` of the five chains at
    segment 0 with zero offsets."""
    theta = check_pose(theta)
    posed = _posed(model, theta)
    return posed.org20.take(_CHAIN_FIRST, axis=0) @ posed.G.T + theta[:3]


def fingertips(model: HandModel, theta: NDArray[np.float64]) -> NDArray[np.float64]:
    """Fingertip positions, shape (5, 3), mm, camera frame (thumb .. little)."""
    return _posed(model, theta).pts[model.tip_index]  # (a new array)


#: Indices into :func:`skeleton_points` of the wrist and each chain's four points
#: (first joint .. segment end), thumb .. little: ``SKELETON_CHAINS[c]`` is a (5,) tuple.
SKELETON_CHAINS: tuple[tuple[int, ...], ...] = tuple(
    (0,) + tuple(1 + CHAIN_JOINTS * c + k for k in range(4)) for c in range(5)
)


def skeleton_points(model: HandModel, theta: NDArray[np.float64]) -> NDArray[np.float64]:
    """The 21 skeleton joints, shape (21, 3), mm, camera frame.

    Order: wrist, then for each chain (thumb .. little) its first joint,
    second joint, third joint and segment end (the very tip of the bone).
    """
    theta = check_pose(theta)
    posed = _posed(model, theta)
    p_hand = np.concatenate([np.zeros((1, 3)), posed.org20])
    return p_hand @ posed.G.T + theta[:3]


#: Rows of :func:`skeleton_points` (and of the 21 keypoints) that are rigid in the palm: the
#: wrist, the thumb CMC and the four finger MCPs (:data:`~hand_sog_tracker.core.hand_model.KEYPOINT_OFFSETS_MM`).
PALM_KEYPOINT_ROWS: tuple[int, ...] = (0,) + tuple(1 + CHAIN_JOINTS * c for c in range(5))
#: The wrist and the four finger MCPs of :data:`PALM_KEYPOINT_ROWS` (the palm keypoints issue 46 scores).
PALM_ROWS: tuple[int, ...] = PALM_KEYPOINT_ROWS[:1] + PALM_KEYPOINT_ROWS[2:]


def keypoint_skeleton(model: HandModel, theta: NDArray[np.float64]) -> NDArray[np.float64]:
    """The published keypoints' skeleton (``hand/keypoints`` but for the fingertip rows), shape
    (21, 3), mm, camera frame: :func:`skeleton_points` with its wrist, thumb CMC and finger MCP
    rows (:data:`PALM_KEYPOINT_ROWS`) moved to the anatomical joint centres
    (:data:`~hand_sog_tracker.core.hand_model.KEYPOINT_OFFSETS_MM` and ``KEYPOINT_FACING_MM``,
    scaled by the model's shape).  The other rows are the skeleton's (the fingers' joints
    and segment ends).  The tracker's own geometry (the hand check, the objective) uses
    :func:`skeleton_points`: this changes what is reported, not what is fitted.
    """
    theta = check_pose(theta)
    posed = _posed(model, theta)
    p_hand = np.concatenate([np.zeros((1, 3)), posed.org20])
    shape = model.shape
    offsets = KEYPOINT_OFFSETS_MM * np.array([shape.width, shape.length, shape.depth])
    t = theta[:3]
    ray = t / max(float(np.linalg.norm(t)), 1e-9)
    facing = float(posed.G[:, 2] @ ray)  # (hand z, the palm's normal: the mirror negates x only)
    offsets[:, 2] += KEYPOINT_FACING_MM * shape.depth * facing
    p_hand[list(PALM_KEYPOINT_ROWS)] += offsets
    return p_hand @ posed.G.T + t


def _palm_mean(model: HandModel) -> NDArray[np.float64]:
    """Mean palm-Gaussian offset in the hand frame (mm), mirrored for a left hand."""
    mean = model.g_offsets[model.g_chain < 0].mean(axis=0)
    return mean if model.right else mean * np.array([-1.0, 1.0, 1.0])


def keep_palm_centre(theta: NDArray[np.float64], old: HandModel, new: HandModel) -> NDArray[np.float64]:
    """``theta`` (26,) with the wrist moved (mm) so that ``new``'s palm centre lies where
    ``old``'s lies at ``theta`` (a rescaled model, e.g. a calibration's).

    The palm Gaussians are rigid in the hand frame, so their centre is
    ``t + R @ mean offset``.
    """
    out = theta.copy()
    out[:3] += global_rotation(theta) @ (_palm_mean(old) - _palm_mean(new))
    return out
