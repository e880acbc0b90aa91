"""Picture of the tracking state: depth colour map with the projected model on top."""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.hand_model import HandModel
from hand_sog_tracker.core.kinematics import fingertips, gaussian_centres, skeleton_points
from hand_sog_tracker.core.types import Intrinsics

__all__ = ["draw_overlay", "TIP_COLOURS_BGR"]

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


def draw_overlay(
    depth_mm: NDArray,
    intrinsics: Intrinsics,
    model: HandModel | None,
    pose: NDArray[np.float64] | None,
    near_mm: float = 150.0,
    far_mm: float = 600.0,
    label: str = "",
) -> NDArray[np.uint8]:
    """Render the depth image with the model's projected Gaussians, skeleton and fingertips.

    Parameters
    ----------
    depth_mm : array, shape (H, W)
        Depth in mm (0/NaN invalid).
    intrinsics : Intrinsics
        Intrinsics of ``depth_mm``.
    model, pose : HandModel and array (26,), or None
        Nothing is drawn over the depth when either is None.
    near_mm, far_mm : float
        Depth range mapped to the colour scale.
    label : str
        Text written in the top-left corner.

    Returns
    -------
    array, shape (H, W, 3), uint8, BGR
    """
    img = _colourise(depth_mm, near_mm, far_mm)
    scale = max(1, int(round(img.shape[1] / 320)))
    if model is not None and pose is not None:
        P = gaussian_centres(model, pose)
        z = np.maximum(P[:, 2], 1.0)
        uv = intrinsics.project(P)
        r = model.g_sigmas * intrinsics.fx / z
        for (u, v), rad, c in zip(uv, r, model.g_chain):
            colour = (200, 200, 200) if c < 0 else TIP_COLOURS_BGR[int(c)]
            if np.isfinite(u) and np.isfinite(v):
                cv2.circle(img, (int(round(u)), int(round(v))), max(1, int(round(rad))), colour, 1, cv2.LINE_AA)
        skel = intrinsics.project(skeleton_points(model, pose))
        for c in range(5):
            chain = [0] + [1 + 4 * c + k for k in range(4)]
            for a, b in zip(chain[:-1], chain[1:]):
                pa, pb = skel[a], skel[b]
                if np.all(np.isfinite([*pa, *pb])):
                    cv2.line(img, (int(pa[0]), int(pa[1])), (int(pb[0]), int(pb[1])), (255, 255, 255), 1, cv2.LINE_AA)
        for (u, v), colour in zip(intrinsics.project(fingertips(model, pose)), TIP_COLOURS_BGR):
            if np.isfinite(u) and np.isfinite(v):
                cv2.circle(img, (int(round(u)), int(round(v))), 2 * scale + 1, colour, -1, cv2.LINE_AA)
    if label:
        cv2.putText(
            img, label, (4, 12 * scale), cv2.FONT_HERSHEY_SIMPLEX, 0.35 * scale, (255, 255, 255), 1, cv2.LINE_AA
        )
    return img
