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

from hand_sog_tracker.core.hand_model import N_PARAMS, HandModel
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
]


def check_pose(theta: NDArray[np.float64]) -> NDArray[np.float64]:
    """Validate a pose vector and return it as float64, shape (26,)."""
    arr = np.asarray(theta, dtype=np.float64)
    if arr.shape != (N_PARAMS,):
        raise InputError(f"pose must have shape ({N_PARAMS},), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
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
    Rx = np.array([[1.0, 0.0, 0.0], [0.0, cx, -sx], [0.0, sx, cx]])
    Ry = np.array([[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]])
    Rz = np.array([[cz, -sz, 0.0], [sz, cz, 0.0], [0.0, 0.0, 1.0]])
    RzRx = Rz @ Rx
    R = RzRx @ Ry
    if not derivatives:
        return R
    dRx = np.array([[0.0, 0.0, 0.0], [0.0, -sx, -cx], [0.0, cx, -sx]])
    dRy = np.array([[-sy, 0.0, cy], [0.0, 0.0, 0.0], [-cy, 0.0, -sy]])
    dRz = np.array([[-sz, -cz, 0.0], [cz, -sz, 0.0], [0.0, 0.0, 0.0]])
    dR = np.stack([Rz @ dRx @ Ry, RzRx @ dRy, dRz @ Rx @ Ry])
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
    q = theta[6:].reshape(5, 4)
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


def _mirror(model: HandModel) -> NDArray[np.float64]:
    return np.diag([1.0 if model.right else -1.0, 1.0, 1.0])


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
    chain = np.asarray(chain)
    segment = np.asarray(segment)
    offsets = np.asarray(offsets, dtype=np.float64)
    k = chain.shape[0]
    finger = chain >= 0
    c = np.where(finger, chain, 0)
    s = np.where(finger, segment, 0)
    local = np.einsum("kij,kj->ki", fr.rotations[c, s], offsets) + fr.origins[c, s]
    p_hand = np.where(finger[:, None], local, offsets)
    M = _mirror(model)
    if not jacobian:
        R = global_rotation(theta)
        return p_hand @ (R @ M).T + theta[:3]
    R, dR = global_rotation(theta, derivatives=True)
    G = R @ M
    pts = p_hand @ G.T + theta[:3]
    J = np.zeros((k, 3, N_PARAMS))
    J[:, 0, 0] = J[:, 1, 1] = J[:, 2, 2] = 1.0
    pm = p_hand @ M.T
    for a in range(3):
        J[:, :, 3 + a] = pm @ dR[a].T
    # Joint columns, computed in the hand frame then rotated by G (which may
    # be a reflection, so cross products are taken before it).
    x_axis = fr.rotations[c, 0, :, 0]  # all flexion axes of a chain coincide
    axes = np.stack([x_axis, fr.abd_axes[c], x_axis, x_axis], axis=1)  # (k, 4, 3)
    pivots = fr.origins[c][:, [0, 0, 1, 2], :]  # (k, 4, 3)
    active = np.stack([finger, finger, finger & (s >= 1), finger & (s >= 2)], axis=1)
    dh = _cross(axes, p_hand[:, None, :] - pivots) * active[:, :, None]
    cols = 6 + 4 * c[:, None] + np.arange(4)[None, :]  # (k, 4)
    J.transpose(0, 2, 1)[np.arange(k)[:, None], cols] = dh @ G.T
    return pts, J


def gaussian_centres(model: HandModel, theta: NDArray[np.float64], jacobian: bool = False):
    """Centres of the model Gaussians, shape (m, 3) mm, and optionally J (m, 3, 26)."""
    return attached_points(
        model, theta, model.g_chain, model.g_segment, model.g_offsets, jacobian=jacobian
    )


def fingertips(model: HandModel, theta: NDArray[np.float64]) -> NDArray[np.float64]:
    """Fingertip positions, shape (5, 3), mm, camera frame (thumb .. little)."""
    return gaussian_centres(model, theta)[model.tip_index]


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
