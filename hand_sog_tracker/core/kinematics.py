"""Forward kinematics of the 26-DOF hand and the analytic Jacobian of attached points.

All positions are millimetres in the camera optical frame (x right, y down,
z forward) unless a docstring says "hand frame".  See
:mod:`hand_sog_tracker.core.hand_model` for the frames and the pose vector.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.hand_model import CHAIN_JOINTS, FIRST_JOINT, JOINTS, N_PARAMS, HandModel
from hand_sog_tracker.errors import InputError

__all__ = [
    "ChainFrames",
    "check_pose",
    "global_rotation",
    "chain_frames",
    "attached_points",
    "gaussian_centres",
    "fingertips",
    "skeleton_points",
    "SKELETON_CHAINS",
]


def check_pose(theta: NDArray[np.float64]) -> NDArray[np.float64]:
    """Validate a pose vector and return it as float64, shape (26,)."""
    arr = np.asarray(theta, dtype=np.float64)
    if arr.shape != (N_PARAMS,):
        raise InputError(f"pose must have shape ({N_PARAMS},), got {arr.shape}")
    # A finite sum proves every entry finite (one reduction instead of two).
    if not math.isfinite(arr.sum()) and not np.all(np.isfinite(arr)):
        raise InputError("pose contains NaN or Inf")
    return arr


def _cross(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """Row-wise cross product of (k, 3) arrays (np.cross has a large fixed overhead)."""
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[..., 0] = a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1]
    out[..., 1] = a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2]
    out[..., 2] = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    return out


def global_rotation(theta: NDArray[np.float64], derivatives: bool = False):
    """Global rotation ``R = Rz(rz) @ Rx(rx) @ Ry(ry)`` of a pose.

    The per-frame form of :func:`hand_sog_tracker.core.rotations.matrices_from_euler`
    (scalar ``math`` calls, one array build: it runs for every objective evaluation).

    Parameters
    ----------
    theta : array, shape (26,)
    derivatives : bool
        Also return ``dR/d(rx, ry, rz)``.

    Returns
    -------
    R : array, shape (3, 3)
    dR : array, shape (3, 3, 3), only with ``derivatives``; ``dR[k]`` is the
        derivative with respect to ``theta[3 + k]``.
    """
    cx, sx = math.cos(theta[3]), math.sin(theta[3])
    cy, sy = math.cos(theta[4]), math.sin(theta[4])
    cz, sz = math.cos(theta[5]), math.sin(theta[5])
    if not derivatives:
        Rx, Ry, Rz = np.array(
            (
                ((1.0, 0.0, 0.0), (0.0, cx, -sx), (0.0, sx, cx)),
                ((cy, 0.0, sy), (0.0, 1.0, 0.0), (-sy, 0.0, cy)),
                ((cz, -sz, 0.0), (sz, cz, 0.0), (0.0, 0.0, 1.0)),
            )
        )
        return (Rz @ Rx) @ Ry
    # One array for all six factors: building small arrays dominates the cost.
    Rx, Ry, Rz, dRx, dRy, dRz = np.array(
        (
            ((1.0, 0.0, 0.0), (0.0, cx, -sx), (0.0, sx, cx)),
            ((cy, 0.0, sy), (0.0, 1.0, 0.0), (-sy, 0.0, cy)),
            ((cz, -sz, 0.0), (sz, cz, 0.0), (0.0, 0.0, 1.0)),
            ((0.0, 0.0, 0.0), (0.0, -sx, -cx), (0.0, cx, -sx)),
            ((-sy, 0.0, cy), (0.0, 0.0, 0.0), (-cy, 0.0, -sy)),
            ((-sz, -cz, 0.0), (cz, -sz, 0.0), (0.0, 0.0, 0.0)),
        )
    )
    RzRx = Rz @ Rx
    R = RzRx @ Ry
    dR = np.empty((3, 3, 3))
    dR[0] = Rz @ dRx @ Ry
    dR[1] = RzRx @ dRy
    dR[2] = dRz @ Rx @ Ry
    return R, dR


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
    q = theta[JOINTS].reshape(5, CHAIN_JOINTS)
    r0 = model.rest_rotations
    ca, sa = np.cos(q[:, 1])[:, None], np.sin(q[:, 1])[:, None]
    bx = ca * r0[:, :, 0] + sa * r0[:, :, 1]  # (5, 3)
    by = -sa * r0[:, :, 0] + ca * r0[:, :, 1]
    bz = r0[:, :, 2]
    phi = np.cumsum(q[:, [0, 2, 3]], axis=1)  # (5, 3)
    cp, sp = np.cos(phi)[:, :, None], np.sin(phi)[:, :, None]
    rots = np.empty((5, 3, 3, 3))
    rots[:, :, :, 0] = bx[:, None, :]
    rots[:, :, :, 1] = cp * by[:, None, :] + sp * bz[:, None, :]
    rots[:, :, :, 2] = -sp * by[:, None, :] + cp * bz[:, None, :]
    o = np.empty((5, 4, 3))
    o[:, 0] = model.bases
    o[:, 1:] = model.bases[:, None, :] + np.cumsum(rots[:, :, :, 1] * model.lengths[:, :, None], axis=1)
    return ChainFrames(origins=o, rotations=rots, abd_axes=bz)


_MIRROR = {True: np.diag([1.0, 1.0, 1.0]), False: np.diag([-1.0, 1.0, 1.0])}
for _m in _MIRROR.values():
    _m.setflags(write=False)


def _mirror(model: HandModel) -> NDArray[np.float64]:
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
        return p_hand @ (R @ M).T + theta[:3]
    R, dR = global_rotation(theta, derivatives=True)
    G = R @ M
    pts = p_hand @ G.T + theta[:3]
    J = ix.j_template.copy() if ix.j_template is not None else _j_template(ix.c.shape[0])
    pm = p_hand @ M.T
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
    return attached_points(
        model, theta, model.g_chain, model.g_segment, model.g_offsets, jacobian=jacobian
    )


def fingertips(model: HandModel, theta: NDArray[np.float64]) -> NDArray[np.float64]:
    """Fingertip positions, shape (5, 3), mm, camera frame (thumb .. little)."""
    return gaussian_centres(model, theta)[model.tip_index]


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
    fr = chain_frames(model, theta)
    p_hand = np.concatenate([np.zeros((1, 3)), fr.origins.reshape(20, 3)])
    G = global_rotation(theta) @ _mirror(model)
    return p_hand @ G.T + theta[:3]
