"""Rotation matrices, the pose vector's Euler angles, quaternions and URDF rpy.

The pose vector's global rotation (see :mod:`hand_sog_tracker.core.hand_model`) is
``R = Rz(rz) @ Rx(rx) @ Ry(ry)`` from ``theta[3:6] = rx, ry, rz`` (rad).  Per-frame code
uses :func:`hand_sog_tracker.core.kinematics.global_rotation`, which builds the same matrix
(and its derivatives) with scalar ``math`` calls for speed; the functions here serve
model construction, initialisation, the synthetic motions and the ROS/URDF outputs.

Names follow ``<to>_from_<from>``; matrices are (3, 3) (or (T, 3, 3)), angles radians,
quaternions ``(x, y, z, w)``.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.errors import InputError

__all__ = [
    "rot_x",
    "rot_y",
    "rot_z",
    "matrices_from_euler",
    "euler_from_matrix",
    "quaternion_from_matrix",
    "rpy_from_matrix",
]


def rot_x(a: float) -> NDArray[np.float64]:
    """Rotation matrix (3, 3) about x by ``a`` radians."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(a: float) -> NDArray[np.float64]:
    """Rotation matrix (3, 3) about y by ``a`` radians."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(a: float) -> NDArray[np.float64]:
    """Rotation matrix (3, 3) about z by ``a`` radians."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def matrices_from_euler(angles: NDArray[np.float64]) -> NDArray[np.float64]:
    """``R = Rz(rz) @ Rx(rx) @ Ry(ry)`` for angles (T, 3) ``rx, ry, rz`` (rad) -> (T, 3, 3)."""
    rx, ry, rz = angles[:, 0], angles[:, 1], angles[:, 2]
    cx, sx, cy, sy, cz, sz = np.cos(rx), np.sin(rx), np.cos(ry), np.sin(ry), np.cos(rz), np.sin(rz)
    T = angles.shape[0]
    Rx = np.zeros((T, 3, 3))
    Rx[:, 0, 0] = 1.0
    Rx[:, 1, 1], Rx[:, 1, 2], Rx[:, 2, 1], Rx[:, 2, 2] = cx, -sx, sx, cx
    Ry = np.zeros((T, 3, 3))
    Ry[:, 1, 1] = 1.0
    Ry[:, 0, 0], Ry[:, 0, 2], Ry[:, 2, 0], Ry[:, 2, 2] = cy, sy, -sy, cy
    Rz = np.zeros((T, 3, 3))
    Rz[:, 2, 2] = 1.0
    Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1] = cz, -sz, sz, cz
    return Rz @ Rx @ Ry


def euler_from_matrix(R: NDArray[np.float64], rx_ref: float = np.pi) -> tuple[float, float, float]:
    """Angles ``(rx, ry, rz)`` (rad) with ``R = Rz(rz) @ Rx(rx) @ Ry(ry)``, R (3, 3).

    Of the two solutions the one whose ``rx`` is nearer ``rx_ref`` is returned.
    """
    sx = float(np.clip(R[2, 1], -1.0, 1.0))
    cx_abs = float(np.hypot(R[2, 0], R[2, 2]))
    cands = []
    for cx in (cx_abs, -cx_abs):
        rx = float(np.arctan2(sx, cx))
        if abs(cx) < 1e-9:
            ry, rz = 0.0, float(np.arctan2(R[1, 0], R[0, 0]))
        else:
            ry = float(np.arctan2(-R[2, 0] / cx, R[2, 2] / cx))
            rz = float(np.arctan2(-R[0, 1] / cx, R[1, 1] / cx))
        d = np.angle(np.exp(1j * (rx - rx_ref)))
        cands.append((abs(d), rx_ref + d, ry, rz))
    _, rx, ry, rz = min(cands)
    return rx, ry, rz


def quaternion_from_matrix(rot: NDArray[np.float64]) -> NDArray[np.float64]:
    """Unit quaternion ``(x, y, z, w)`` of a rotation matrix, shape (3, 3), with ``w >= 0``.

    Uses the numerically stable branch on the largest diagonal term (Shepperd).

    Raises
    ------
    InputError
        When ``rot`` is not (3, 3).
    """
    m = np.asarray(rot, dtype=np.float64)
    if m.shape != (3, 3):
        raise InputError(f"rotation must have shape (3, 3), got {m.shape}")
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0.0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = np.array([(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s])
    elif m[0, 0] >= m[1, 1] and m[0, 0] >= m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = np.array([0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s])
    elif m[1, 1] >= m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = np.array([(m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s])
    else:
        s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = np.array([(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s])
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def rpy_from_matrix(rot: NDArray[np.float64]) -> tuple[float, float, float]:
    """URDF ``rpy`` (fixed-axis roll about x, pitch about y, yaw about z: ``R = Rz Ry Rx``), rad."""
    r = np.asarray(rot, dtype=np.float64)
    pitch = math.atan2(-r[2, 0], math.hypot(r[2, 1], r[2, 2]))
    if math.hypot(r[2, 1], r[2, 2]) < 1e-9:  # gimbal lock: put everything in yaw
        return 0.0, pitch, math.atan2(-r[0, 1], r[1, 1])
    return math.atan2(r[2, 1], r[2, 2]), pitch, math.atan2(r[1, 0], r[0, 0])
