"""Rendered synthetic depth sequences with ground-truth poses and fingertips.

A sequence is a scripted motion (:mod:`hand_sog_tracker.synth.motions`)
rendered by :func:`hand_sog_tracker.synth.render.render_depth` on the hand
``default_hand_model(right).scaled(shape)``; the ground-truth fingertips are
:func:`hand_sog_tracker.core.kinematics.fingertips` of that same scaled model.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.hand_model import HandShape, default_hand_model
from hand_sog_tracker.core.kinematics import fingertips
from hand_sog_tracker.core.types import Intrinsics
from hand_sog_tracker.errors import InputError
from hand_sog_tracker.synth.motions import motion_poses
from hand_sog_tracker.synth.render import RenderOptions, render_depth

__all__ = ["REALSENSE_FX_320", "default_intrinsics", "SyntheticFrame", "synthetic_sequence"]

#: Focal length (pixels) of a RealSense-like depth camera at 320 x 240.
REALSENSE_FX_320 = 287.26


def default_intrinsics(width: int = 320, height: int = 240) -> Intrinsics:
    """RealSense-like pinhole intrinsics for a ``width`` x ``height`` depth image.

    ``fx = fy = 287.26 * width / 320`` (about 58 deg horizontal field of view)
    and the principal point in the image centre, ``((W - 1) / 2, (H - 1) / 2)``.

    Raises
    ------
    IntrinsicsError
        If the size is not positive.
    """
    f = REALSENSE_FX_320 * width / 320.0
    return Intrinsics(fx=f, fy=f, cx=(width - 1) / 2.0, cy=(height - 1) / 2.0, width=int(width), height=int(height))


@dataclass(frozen=True, eq=False)
class SyntheticFrame:
    """One rendered frame and its ground truth.

    Attributes
    ----------
    index : int
        Frame number, from 0.
    stamp_s : float
        Time stamp, ``index / fps`` seconds.
    depth_mm : array, shape (H, W), float32
        Depth image, millimetres, 0 = invalid.
    pose : array, shape (26,)
        Ground-truth pose (mm, rad).
    fingertips_mm : array, shape (5, 3)
        Ground-truth fingertip centres (thumb .. little), camera optical frame, mm.
    """

    index: int
    stamp_s: float
    depth_mm: NDArray[np.float32]
    pose: NDArray[np.float64]
    fingertips_mm: NDArray[np.float64]


def synthetic_sequence(
    motion: str,
    n_frames: int,
    intrinsics: Intrinsics | None = None,
    shape: HandShape = HandShape(),
    right: bool = True,
    seed: int = 0,
    options: RenderOptions = RenderOptions(),
    fps: float = 30.0,
) -> Iterator[SyntheticFrame]:
    """Render a scripted motion frame by frame.

    Parameters
    ----------
    motion : str
        One of :data:`hand_sog_tracker.synth.motions.MOTIONS`.
    n_frames : int
        Number of frames.
    intrinsics : Intrinsics, optional
        Camera; default :func:`default_intrinsics` (320 x 240).
    shape : HandShape
        Scale factors of the rendered (and ground-truth) hand.
    right : bool
        Right (``True``) or left hand.
    seed : int
        Seeds the motion and the sensor artefacts: equal seeds give identical frames.
    options : RenderOptions
        Sensor artefacts, forearm and background.
    fps : float
        Frame rate (Hz).

    Yields
    ------
    SyntheticFrame

    Raises
    ------
    InputError
        Unknown motion, bad ``n_frames`` or ``fps`` (raised on the first ``next``).
    """
    if not isinstance(shape, HandShape):
        raise InputError(f"shape must be a HandShape, got {type(shape).__name__}")
    intr = default_intrinsics() if intrinsics is None else intrinsics
    poses = motion_poses(motion, n_frames, fps=fps, seed=seed)
    model = default_hand_model(right).scaled(shape)
    # The render noise has its own stream, independent of the motion's.
    rng = np.random.default_rng(np.random.SeedSequence(seed).spawn(3)[2])
    for k, pose in enumerate(poses):
        depth = render_depth(model, pose, intr, options, rng)
        yield SyntheticFrame(
            index=k,
            stamp_s=k / float(fps),
            depth_mm=depth,
            pose=pose.copy(),
            fingertips_mm=fingertips(model, pose),
        )
