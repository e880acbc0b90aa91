"""The silhouette term: every part of the hand projects onto the hand's pixels.

Depth overlap (``E_sim``) rewards model Gaussians on data but does not punish Gaussians over
empty background, and the dangling term (``E_dan``) only acts beyond 15 mm from the data.  A
finger lying next to its real finger, over the background (typically after the fingers have
shifted over by one), costs nothing in either.  Whatever the self-occlusion, every point of
the hand projects inside the hand's silhouette, so a model Gaussian whose centre projects
outside it is wrong by the distance to the silhouette.

``E_sil = 1 / m sum_p (max(D(u_p, v_p) - SILHOUETTE_MARGIN_PX, 0) z_p / f / SILHOUETTE_SCALE_MM)^2``

with ``D`` the distance (px) of a pixel to the nearest pixel of the hand's depth (bilinear
between pixel centres), ``(u_p, v_p)`` and ``z_p`` a model Gaussian's projected centre and
depth (mm), ``f = sqrt(fx fy)``: the squared distance in mm at the Gaussian's depth, in units of
``SILHOUETTE_SCALE_MM``, averaged over the ``m`` Gaussians.

Units: millimetres, pixels of the processing image.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final

import cv2
import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.depth_sog import Preprocessed
from hand_sog_tracker.core.types import Intrinsics

__all__ = [
    "SILHOUETTE_MARGIN_PX",
    "SILHOUETTE_SCALE_MM",
    "Silhouette",
    "silhouette",
    "silhouette_term",
]

# The term is not in the papers: both constants are chosen here.
#: Distances up to this (px) cost nothing: pixel quantisation and a ragged depth edge.
SILHOUETTE_MARGIN_PX: Final[float] = 1.0
#: The term measures distances in units of this (mm).
SILHOUETTE_SCALE_MM: Final[float] = 10.0


@dataclass(frozen=True, eq=False)
class Silhouette:
    """Distance (px) of every pixel of a window of the image to the hand's pixels; 0 on the hand.

    Attributes
    ----------
    distance : array, shape (h, w), float32
        Distances in the window (pixels of the processing image).
    origin : (u0, v0)
        Image pixel of the window's first element.
    intrinsics : Intrinsics
        Of the processing image the distances belong to.
    """

    distance: NDArray[np.float32]
    origin: tuple[int, int]
    intrinsics: Intrinsics


#: The distance map covers the region of interest plus this margin (px; chosen here, no
#: effect on the term inside the margin).
ROI_MARGIN_PX: Final[int] = 16


def silhouette(
    pre: Preprocessed, window_mm: tuple[float, float], roi: tuple[int, int, int, int] | None = None
) -> Silhouette:
    """The silhouette of the depth inside ``window_mm`` (near, far) and its distance map.

    With ``roi`` (u0, v0, u1, v1, end-exclusive) only that box plus :data:`ROI_MARGIN_PX` is
    mapped (a model Gaussian projecting beyond it is clamped to its edge).
    """
    d = pre.depth_mm
    h, w = d.shape
    u0, v0, u1, v1 = (0, 0, w, h) if roi is None else roi
    u0, v0 = max(u0 - ROI_MARGIN_PX, 0), max(v0 - ROI_MARGIN_PX, 0)
    u1, v1 = min(u1 + ROI_MARGIN_PX, w), min(v1 + ROI_MARGIN_PX, h)
    if u1 - u0 < 2 or v1 - v0 < 2:
        u0, v0, u1, v1 = 0, 0, w, h
    crop = d[v0:v1, u0:u1]
    near, far = window_mm
    background = ((crop <= near) | (crop >= far)).astype(np.uint8)
    dist = cv2.distanceTransform(background, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    return Silhouette(distance=dist, origin=(u0, v0), intrinsics=pre.intrinsics)


def silhouette_term(
    sil: Silhouette, P: NDArray[np.float64], g3: NDArray[np.float64] | None, weight: float
) -> float:
    """``E_sil`` at the model Gaussian centres ``P`` (m, 3) mm; adds ``-weight dE/dP`` into ``g3``."""
    intr = sil.intrinsics
    dist = sil.distance
    h, w = dist.shape
    x, y, z = P[:, 0], P[:, 1], np.maximum(P[:, 2], 1.0)
    u = intr.fx * x / z + (intr.cx - sil.origin[0])  # pixels of the mapped window
    v = intr.fy * y / z + (intr.cy - sil.origin[1])
    # Bilinear interpolation between pixel centres (clamped to the image).
    uc = np.clip(u, 0.0, w - 1.000001)
    vc = np.clip(v, 0.0, h - 1.000001)
    u0 = np.floor(uc).astype(np.int64)
    v0 = np.floor(vc).astype(np.int64)
    a, b = uc - u0, vc - v0
    d00 = dist[v0, u0].astype(np.float64)
    d01 = dist[v0, u0 + 1].astype(np.float64)
    d10 = dist[v0 + 1, u0].astype(np.float64)
    d11 = dist[v0 + 1, u0 + 1].astype(np.float64)
    D = (1 - b) * ((1 - a) * d00 + a * d01) + b * ((1 - a) * d10 + a * d11)
    over = np.maximum(D - SILHOUETTE_MARGIN_PX, 0.0)
    f = float(np.sqrt(intr.fx * intr.fy))
    k = 1.0 / (f * SILHOUETTE_SCALE_MM)
    s = over * z * k  # (m,)
    m = P.shape[0]
    val = float((s * s).sum() / m)
    if g3 is not None and weight > 0 and val > 0:
        inside_u = (u > 0.0) & (u < w - 1.000001)
        inside_v = (v > 0.0) & (v < h - 1.000001)
        dD_du = np.where(inside_u, (1 - b) * (d01 - d00) + b * (d11 - d10), 0.0)
        dD_dv = np.where(inside_v, (1 - a) * (d10 - d00) + a * (d11 - d01), 0.0)
        on = over > 0
        c = np.where(on, 2.0 / m * s * z * k, 0.0)  # dE/dD
        g_u, g_v = c * dD_du, c * dD_dv
        g_z = np.where(on, 2.0 / m * s * over * k, 0.0)  # explicit z in the mm conversion
        g3[:, 0] -= weight * g_u * intr.fx / z
        g3[:, 1] -= weight * g_v * intr.fy / z
        g3[:, 2] -= weight * (-g_u * intr.fx * x / (z * z) - g_v * intr.fy * y / (z * z) + g_z)
    return val
