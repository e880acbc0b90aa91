"""The hand's region of a frame: its pixel box and depth window, and how well data explain it.

Units: mm (camera optical frame), pixels at the processing resolution.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.depth_sog import ImageSoG
from hand_sog_tracker.core.hand_model import HandModel
from hand_sog_tracker.core.kinematics import posed_centres
from hand_sog_tracker.core.objective import gaussian_support
from hand_sog_tracker.core.types import Intrinsics

__all__ = ["before_surface", "coverage", "hand_roi", "WINDOW_BEHIND_MM", "SURFACE_SEARCH_MM"]

#: A tracked frame's depth window ends this far behind the farthest Gaussian centre of its
#: start pose (mm; chosen here), or ``roi_radius_mm`` behind the hand's centre when nearer.
WINDOW_BEHIND_MM = 70.0
#: ... and before a surface behind the hand (:func:`before_surface`; chosen here): the first
#: ``SURFACE_SLICE_MM`` slice of depths, from ``SURFACE_SEARCH_MM`` behind the farthest centre
#: on, whose pixels in the hand's region cover more than ``SURFACE_SLICE_MM2`` (a wall or a
#: table fills a slice, a receding forearm a strip of it) ends it ``SURFACE_MARGIN_MM`` before.
SURFACE_SEARCH_MM = 15.0
SURFACE_SLICE_MM = 15.0
SURFACE_SLICE_MM2 = 5000.0
SURFACE_MARGIN_MM = 5.0
#: Bin width (mm) of :func:`before_surface`'s depth histogram.
_SURFACE_BIN_MM = 5.0


def coverage(
    model: HandModel,
    theta: NDArray[np.float64],
    data: ImageSoG,
    centres: NDArray[np.float64] | None = None,
    support: NDArray[np.float64] | None = None,
) -> float:
    """How well the data explain the model at ``theta``, in [0, 1].

    The mean :func:`gaussian_support` over the best-supported two thirds of
    the Gaussians (the rest may be legitimately occluded).  ``support``: that support (m,),
    when already known (:meth:`Objective.support`).
    """
    if support is None:
        support = gaussian_support(model, theta, data, centres)
    support = np.sort(support)[::-1]
    keep = max(1, (2 * support.size) // 3)
    return float(np.add.reduce(support[:keep]) / keep)  # (= .mean(), without its Python layer)


def hand_roi(
    model: HandModel,
    theta: NDArray[np.float64],
    intr: Intrinsics,
    radius_mm: float,
    centres: NDArray[np.float64] | None = None,
) -> tuple[tuple[int, int, int, int], tuple[float, float]]:
    """Pixel box and depth window around the hand at ``theta`` (``centres``: its
    :func:`posed_centres`, shape (m, 3) mm, when already computed).

    Returns
    -------
    roi : (u0, v0, u1, v1)
        End-exclusive pixel box at the resolution of ``intr``, clipped to the image (every
        consumer clips it so: a radius of many image widths, from implausible intrinsics or a
        large ``roi_radius_mm``, then costs no more than the whole image); empty
        ``(0, 0, 0, 0)`` when the centre does not project (not finite).
    window : (near_mm, far_mm)
    """
    P = posed_centres(model, theta) if centres is None else centres
    c = np.add.reduce(P, axis=0) / P.shape[0]  # (= P.mean(axis=0), without its Python layer)
    z = max(c[2], 50.0)
    window = (c[2] - radius_mm, c[2] + radius_mm)
    # The centre's pixel as Intrinsics.project computes it, by Python floats (the same IEEE
    # operations in the same order).
    x, y, zc = c.tolist()
    if not zc > 0.0:
        return (0, 0, 0, 0), window
    u, v = intr.fx * x / zc + intr.cx, intr.fy * y / zc + intr.cy
    r_px = radius_mm * max(intr.fx, intr.fy) / max(z - radius_mm * 0.5, 50.0)
    if not (math.isfinite(u) and math.isfinite(v) and math.isfinite(r_px)):
        return (0, 0, 0, 0), window
    w, h = intr.width, intr.height
    roi = (
        min(max(math.floor(u - r_px), 0), w),
        min(max(math.floor(v - r_px), 0), h),
        max(min(math.ceil(u + r_px) + 1, w), 0),
        max(min(math.ceil(v + r_px) + 1, h), 0),
    )
    return roi, window


def before_surface(
    depth_mm: NDArray[np.float32], intr: Intrinsics, roi: tuple[int, int, int, int], start_mm: float, end_mm: float
) -> float:
    """Where a depth window ending at ``end_mm`` should end instead, before a surface behind the
    hand (a wall, a table top): see :data:`SURFACE_SLICE_MM2`.

    Parameters
    ----------
    depth_mm : array, shape (H, W), float32
        Depth (mm, 0 invalid) at the resolution of ``intr``.
    intr : Intrinsics
    roi : (u0, v0, u1, v1)
        The hand's pixel box (:func:`hand_roi`; clipped to the image here).
    start_mm, end_mm : float
        The depths searched (mm): from ``start_mm`` (behind the hand) to ``end_mm``.

    Returns
    -------
    float
        ``SURFACE_MARGIN_MM`` before the nearest slice of ``SURFACE_SLICE_MM`` whose pixels (every
        second row and column, counted four times) cover more than ``SURFACE_SLICE_MM2`` at
        their depth, but not before ``start_mm``; ``end_mm`` when there is none.
    """
    h, w = depth_mm.shape
    sub = depth_mm[max(roi[1], 0) : min(roi[3], h) : 2, max(roi[0], 0) : min(roi[2], w) : 2]
    behind = sub[(sub > start_mm) & (sub <= end_mm)]
    if behind.size == 0:
        return end_mm
    per_bin = _SURFACE_BIN_MM
    n_bins = int(math.ceil((end_mm - start_mm) / per_bin))
    counts = np.bincount(
        np.minimum(((behind - start_mm) // per_bin).astype(np.int64), n_bins - 1), minlength=n_bins
    ).astype(np.float64)
    z = start_mm + per_bin * (np.arange(n_bins) + 0.5)
    area = counts * (4.0 * z * z / (intr.fx * intr.fy))  # mm^2 (each counted pixel stands for 4)
    k = int(round(SURFACE_SLICE_MM / per_bin))
    slices = np.convolve(area, np.ones(k))[k - 1 :]  # slices[i]: bins i .. i + k - 1
    hit = np.flatnonzero(slices > SURFACE_SLICE_MM2)
    if hit.size == 0:
        return end_mm
    return max(start_mm, start_mm + per_bin * float(hit[0]) - SURFACE_MARGIN_MM)


