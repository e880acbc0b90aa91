"""A supporting surface under or behind the hand: find the frame's dominant plane and drop it.

A hand resting on a table (or pressed to a wall) touches a surface the hand model cannot
explain: its depth pixels lie within a finger's thickness of the hand, pass every depth window,
join the hand in the hand finder's nearest blob and pull the model into the surface.  A plane
much larger than any hand is no part of one: :func:`find_support` fits the frame's dominant
plane (RANSAC over a grid of back-projected pixels, local triples, least-squares refit on the
inliers) and accepts it when its inliers cover more than :data:`SUPPORT_MIN_AREA_MM2`;
:func:`drop_support` then sets every pixel on the plane or behind it (within
:data:`SUPPORT_CLEARANCE_MM` of its camera side or beyond) to no data.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final

import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.depth_sog import Preprocessed
from hand_sog_tracker.core.types import Intrinsics

__all__ = [
    "SupportPlane", "find_support", "drop_support", "without_support", "SUPPORT_MIN_AREA_MM2", "SUPPORT_CLEARANCE_MM",
]

#: A plane is a support when its inliers cover this much (mm^2, summed pixel footprints at
#: their depth): twice an open hand's outline (about 180 x 100 mm), so that no hand (nor a
#: flat hand with its forearm) can be one.
SUPPORT_MIN_AREA_MM2: Final = 40000.0
#: Pixels less than this far in front of the support (mm) are dropped with it: above the
#: sensor noise on the surface, below half a finger's thickness.
SUPPORT_CLEARANCE_MM: Final = 8.0
#: A pixel within this distance of a hypothesis (mm) is its inlier.
_INLIER_MM: Final = 6.0
#: Grid points the plane is fitted on (about; the grid's stride follows the image size).
_GRID_POINTS: Final = 3000
#: Plane hypotheses per frame, each through a grid point and two others within
#: ``_LOCAL_CELLS`` grid cells of it (a local triple lies on one surface far more often than
#: three points drawn from the whole image).
_HYPOTHESES: Final = 48
_LOCAL_CELLS: Final = 6


@dataclass(frozen=True)
class SupportPlane:
    """A plane ``normal . p = offset`` (camera frame, mm), ``normal`` (3,) unit, towards the
    camera (``normal . p - offset`` > 0 in front of the plane); ``area_mm2``: its inliers'
    summed pixel footprints (mm^2)."""

    normal: NDArray[np.float64]
    offset: float
    area_mm2: float


def _grid_depths(depth: NDArray[np.float32]) -> tuple[NDArray[np.float64], NDArray[np.bool_], int]:
    """The depths (gh, gw) mm of the grid the plane is fitted on, their validity (gh, gw) and its stride (px)."""
    h, w = depth.shape
    s = max(1, int(round(np.sqrt(h * w / _GRID_POINTS))))
    z = depth[s // 2 :: s, s // 2 :: s].astype(np.float64)
    return z, np.isfinite(z) & (z > 0), s


def _grid_points(z: NDArray[np.float64], s: int, intr: Intrinsics) -> NDArray[np.float64]:
    """The grid depths ``z`` (gh, gw) mm of stride ``s`` (px) back-projected (gh, gw, 3) mm."""
    vs = np.arange(s // 2, s // 2 + s * z.shape[0], s, dtype=np.float64)
    us = np.arange(s // 2, s // 2 + s * z.shape[1], s, dtype=np.float64)
    P = np.empty(z.shape + (3,))
    P[..., 0] = z * ((us[None, :] - intr.cx) / intr.fx)
    P[..., 1] = z * ((vs[:, None] - intr.cy) / intr.fy)
    P[..., 2] = z
    return P


def find_support(
    depth_mm: NDArray, intr: Intrinsics, min_area_mm2: float = SUPPORT_MIN_AREA_MM2
) -> SupportPlane | None:
    """The dominant plane of ``depth_mm`` (H, W) mm (0, NaN invalid) if its inliers cover more
    than ``min_area_mm2``, else None.  Deterministic (a fixed seed per call)."""
    z, valid, s = _grid_depths(np.asarray(depth_mm, dtype=np.float32))
    gh, gw = valid.shape
    idx = np.flatnonzero(valid)
    if idx.size < 3:
        return None
    foot = z.ravel()[idx] ** 2 * (s * s / (intr.fx * intr.fy))  # each grid point's footprint (mm^2)
    if foot.sum() <= min_area_mm2:
        return None  # (before the back-projection: a hand alone never covers it)
    flat = _grid_points(z, s, intr).reshape(-1, 3)
    pts = flat[idx]
    rng = np.random.default_rng(0)
    a = idx[rng.integers(0, idx.size, _HYPOTHESES)]
    ar, ac = np.divmod(a, gw)
    off = rng.integers(-_LOCAL_CELLS, _LOCAL_CELLS + 1, (2, 2, _HYPOTHESES))
    br = np.clip(ar + off[0, 0], 0, gh - 1)
    bc = np.clip(ac + off[0, 1], 0, gw - 1)
    cr = np.clip(ar + off[1, 0], 0, gh - 1)
    cc = np.clip(ac + off[1, 1], 0, gw - 1)
    b, c = br * gw + bc, cr * gw + cc
    ok = valid.ravel()[b] & valid.ravel()[c]
    p0, p1, p2 = flat[a[ok]], flat[b[ok]], flat[c[ok]]
    n = np.cross(p1 - p0, p2 - p0)
    norm = np.linalg.norm(n, axis=1)
    good = norm > 1e-6 * np.maximum(np.linalg.norm(p1 - p0, axis=1), 1.0) ** 2
    if not good.any():
        return None
    n = n[good] / norm[good, None]
    d = np.einsum("hk,hk->h", n, p0[good])
    inl = np.abs(pts @ n.T - d[None, :]) < _INLIER_MM  # (N, hypotheses)
    scores = foot @ inl
    best = int(np.argmax(scores))
    if scores[best] <= min_area_mm2:
        return None
    # Least-squares refit on the best hypothesis' inliers, then its own inliers.
    q = pts[inl[:, best]]
    centre = q.mean(axis=0)
    normal = np.linalg.svd(q - centre, full_matrices=False)[2][2]
    if normal[2] > 0:
        normal = -normal  # towards the camera
    offset = float(normal @ centre)
    inliers = np.abs(pts @ normal - offset) < _INLIER_MM
    area = float(foot[inliers].sum())
    if area <= min_area_mm2:
        return None
    return SupportPlane(normal=normal, offset=offset, area_mm2=area)


def drop_support(
    depth_mm: NDArray, intr: Intrinsics, plane: SupportPlane | None, clearance_mm: float = SUPPORT_CLEARANCE_MM
) -> NDArray:
    """``depth_mm`` (H, W) mm with every pixel less than ``clearance_mm`` in front of ``plane``
    (or behind it) set to 0, as a new float32 array; ``depth_mm`` itself without a plane."""
    if plane is None:
        return depth_mm
    depth = np.array(depth_mm, dtype=np.float32)
    h, w = depth.shape
    n = plane.normal
    # normal . p = z (n_x (u - cx) / fx + n_y (v - cy) / fy + n_z): one ray factor per pixel.
    ray = (n[0] / intr.fx) * (np.arange(w, dtype=np.float32) - np.float32(intr.cx))[None, :] + (
        (n[1] / intr.fy) * (np.arange(h, dtype=np.float32) - np.float32(intr.cy)) + np.float32(n[2])
    )[:, None]
    height = depth * ray.astype(np.float32) - np.float32(plane.offset)
    depth[(height < clearance_mm) & (depth > 0)] = 0.0
    return depth


def without_support(pre: Preprocessed) -> Preprocessed:
    """The preprocessed frame ``pre`` without the plane :func:`find_support` finds in it
    (``pre`` itself when there is none)."""
    plane = find_support(pre.depth_mm, pre.intrinsics)
    if plane is None:
        return pre
    return Preprocessed(drop_support(pre.depth_mm, pre.intrinsics, plane), pre.intrinsics, pre.decimation)
