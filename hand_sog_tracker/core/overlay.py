"""Picture of the tracking state: depth colour map with the projected model on top."""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.hand_model import HandModel
from hand_sog_tracker.core.kinematics import SKELETON_CHAINS, gaussian_centres, keypoint_skeleton
from hand_sog_tracker.core.types import Intrinsics, TrackResult

__all__ = ["draw_overlay", "draw_hand", "TIP_COLOURS_BGR"]

#: Fingertip colours, thumb .. little (BGR).
TIP_COLOURS_BGR = ((0, 0, 255), (0, 165, 255), (0, 255, 255), (0, 255, 0), (255, 0, 255))


def _colourise(depth_mm: NDArray, near_mm: float, far_mm: float) -> NDArray[np.uint8]:
    d = np.nan_to_num(np.asarray(depth_mm, dtype=np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    valid = d > 0
    scaled = np.clip((d - near_mm) / max(far_mm - near_mm, 1.0), 0.0, 1.0)
    grey = (255 * (1.0 - scaled)).astype(np.uint8)
    img = cv2.applyColorMap(grey, cv2.COLORMAP_BONE)
    img[~valid] = 0
    return img


def draw_hand(
    img: NDArray[np.uint8],
    intrinsics: Intrinsics,
    centres_mm: NDArray[np.float64],
    radii_mm: NDArray[np.float64],
    chains: NDArray[np.int64],
    skeleton_mm: NDArray[np.float64],
    fingertips_mm: NDArray[np.float64],
) -> None:
    """Draw a posed hand into ``img`` (in place) from its computed geometry (no kinematics).

    Parameters
    ----------
    img : array, shape (H, W, 3), uint8, BGR
    intrinsics : Intrinsics
        Intrinsics of ``img``.
    centres_mm, radii_mm : arrays, shapes (m, 3) and (m,), mm
        Model Gaussian centres (camera frame) and standard deviations (circles).
    chains : int array, shape (m,)
        Chain of each Gaussian (0 thumb .. 4 little, -1 palm: grey), as ``HandModel.g_chain``.
    skeleton_mm : array, shape (21, 3), mm
        :func:`~hand_sog_tracker.core.kinematics.keypoint_skeleton` (white lines).
    fingertips_mm : array, shape (5, 3), mm
        Fingertips thumb .. little (filled dots in :data:`TIP_COLOURS_BGR`).
    """
    scale = max(1, int(round(img.shape[1] / 320)))
    z = np.maximum(centres_mm[:, 2], 1.0)
    uv = intrinsics.project(centres_mm)
    r = radii_mm * intrinsics.fx / z
    for (u, v), rad, c in zip(uv, r, chains):
        colour = (200, 200, 200) if c < 0 else TIP_COLOURS_BGR[int(c)]
        if np.isfinite(u) and np.isfinite(v):
            cv2.circle(img, (int(round(u)), int(round(v))), max(1, int(round(rad))), colour, 1, cv2.LINE_AA)
    skel = intrinsics.project(skeleton_mm)
    for chain in SKELETON_CHAINS:
        for a, b in zip(chain[:-1], chain[1:]):
            pa, pb = skel[a], skel[b]
            if np.all(np.isfinite([*pa, *pb])):
                cv2.line(img, (int(pa[0]), int(pa[1])), (int(pb[0]), int(pb[1])), (255, 255, 255), 1, cv2.LINE_AA)
    for (u, v), colour in zip(intrinsics.project(fingertips_mm), TIP_COLOURS_BGR):
        if np.isfinite(u) and np.isfinite(v):
            cv2.circle(img, (int(round(u)), int(round(v))), 2 * scale + 1, colour, -1, cv2.LINE_AA)


def draw_overlay(
    depth_mm: NDArray,
    intrinsics: Intrinsics,
    model: HandModel | None,
    pose: NDArray[np.float64] | None,
    near_mm: float = 150.0,
    far_mm: float = 600.0,
    label: str = "",
    result: TrackResult | None = None,
) -> NDArray[np.uint8]:
    """Render the depth image with the model's projected Gaussians, skeleton and fingertips.

    Parameters
    ----------
    depth_mm : array, shape (H, W)
        Depth in mm (0/NaN invalid).
    intrinsics : Intrinsics
        Intrinsics of ``depth_mm``.
    model, pose : HandModel and array (26,), or None
        Nothing is drawn over the depth when either is None.  Without ``result`` the
        geometry is computed from them by forward kinematics.
    near_mm, far_mm : float
        Depth range mapped to the colour scale.
    label : str
        Text written in the top-left corner.
    result : TrackResult, optional
        A frame's tracking result: its Gaussians, skeleton and fingertips are drawn as
        computed by the tracker (``pose`` is then not used; ``model`` gives the Gaussians'
        chain colours).

    Returns
    -------
    array, shape (H, W, 3), uint8, BGR
    """
    img = _colourise(depth_mm, near_mm, far_mm)
    scale = max(1, int(round(img.shape[1] / 320)))
    drawn = result is not None and all(
        a is not None for a in (result.gaussians_mm, result.skeleton_mm, result.fingertips_mm)
    )
    if model is not None and result is not None and drawn:
        radii = result.gaussian_radii_mm if result.gaussian_radii_mm is not None else model.g_sigmas
        draw_hand(
            img, intrinsics, result.gaussians_mm, radii, model.g_chain, result.skeleton_mm, result.fingertips_mm
        )
    elif model is not None and pose is not None:
        centres = gaussian_centres(model, pose)
        draw_hand(
            img, intrinsics, centres, model.g_sigmas, model.g_chain,
            keypoint_skeleton(model, pose), centres[model.tip_index],
        )
    if label:
        cv2.putText(
            img, label, (4, 12 * scale), cv2.FONT_HERSHEY_SIMPLEX, 0.35 * scale, (255, 255, 255), 1, cv2.LINE_AA
        )
    return img
