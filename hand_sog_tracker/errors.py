"""All exceptions raised by hand_sog_tracker.

One hierarchy for the whole package so that callers can catch
:class:`HandSogError` and know they caught only our own failures.
"""

from __future__ import annotations

__all__ = [
    "HandSogError",
    "InputError",
    "DepthImageError",
    "IntrinsicsError",
    "ModelFileError",
    "CalibrationError",
    "BagError",
]


class HandSogError(Exception):
    """Base class of every error raised by this package."""


class InputError(HandSogError, ValueError):
    """An argument has the wrong shape, dtype or value."""


class DepthImageError(InputError):
    """A depth image cannot be used (encoding, size, step, data length...)."""


class IntrinsicsError(InputError):
    """Camera intrinsics are missing, degenerate or unsupported (binning, ROI)."""


class ModelFileError(HandSogError):
    """A user hand-model file is missing, unreadable or malformed."""


class CalibrationError(HandSogError):
    """The hand-model calibration could not produce a better model."""


class BagError(HandSogError):
    """A bag cannot be read or lacks a topic, CameraInfo or ground truth."""
