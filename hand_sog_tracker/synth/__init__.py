"""Synthetic depth data with ground truth: a ray-cast surface hand (not the tracker's Gaussians).

NumPy only.  See :mod:`~hand_sog_tracker.synth.render` (the renderer),
:mod:`~hand_sog_tracker.synth.motions` (scripted Dexter-1-like motions) and
:mod:`~hand_sog_tracker.synth.sequence` (rendered sequences with ground truth);
the skinned mesh hand: :mod:`~hand_sog_tracker.synth.mesh` (with :mod:`~hand_sog_tracker.synth.gltf`
its file reader, :mod:`~hand_sog_tracker.synth.raster` its rasteriser and
:mod:`~hand_sog_tracker.synth.sensors` its sensor models).
"""

from __future__ import annotations

from hand_sog_tracker.synth.motions import MOTIONS, default_start_pose, motion_poses
from hand_sog_tracker.synth.render import RenderOptions, render_depth
from hand_sog_tracker.synth.sequence import SyntheticFrame, default_intrinsics, synthetic_sequence

__all__ = [
    "MOTIONS",
    "RenderOptions",
    "SyntheticFrame",
    "default_intrinsics",
    "default_start_pose",
    "motion_poses",
    "render_depth",
    "synthetic_sequence",
]
