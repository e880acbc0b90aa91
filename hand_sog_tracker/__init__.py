"""Sum-of-Gaussians hand tracking from depth images; the tracker needs no ROS.

The front door for Python users::

    from hand_sog_tracker import Intrinsics, Tracker, TrackerConfig

    tracker = Tracker(TrackerConfig())
    result = tracker.process(depth_mm, Intrinsics(fx=287.26, fy=287.26, cx=159.5, cy=119.5,
                                                  width=320, height=240))
    result.fingertips_mm  # (5, 3) mm, thumb .. little, or None

The names below come from :mod:`hand_sog_tracker.core` (NumPy only, never rclpy) and are
loaded on first use, so importing a subpackage (``hand_sog_tracker.ros``, ``.tools``) does
not load the tracker.  Subpackages: ``core`` (tracker, model, calibration), ``ros`` (the node),
``synth`` (synthetic depth), ``tools`` (bag tools); ``interface`` (the node's topics and message
conversions, no ROS imports), ``errors`` (every exception of the package).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from hand_sog_tracker.core.hand_model import HandModel, HandShape, default_hand_model
    from hand_sog_tracker.core.tracker import Tracker
    from hand_sog_tracker.core.types import Intrinsics, TrackerConfig, TrackerStatus, TrackResult

__all__ = [
    "Tracker",
    "TrackerConfig",
    "Intrinsics",
    "TrackResult",
    "TrackerStatus",
    "HandModel",
    "HandShape",
    "default_hand_model",
]

#: Public name -> the core module that defines it.
_HOMES = {
    "Tracker": "hand_sog_tracker.core.tracker",
    "TrackerConfig": "hand_sog_tracker.core.types",
    "Intrinsics": "hand_sog_tracker.core.types",
    "TrackResult": "hand_sog_tracker.core.types",
    "TrackerStatus": "hand_sog_tracker.core.types",
    "HandModel": "hand_sog_tracker.core.hand_model",
    "HandShape": "hand_sog_tracker.core.hand_model",
    "default_hand_model": "hand_sog_tracker.core.hand_model",
}


def __getattr__(name: str) -> Any:
    """Load a public name from the core on first use (PEP 562)."""
    home = _HOMES.get(name)
    if home is None:
        raise AttributeError(f"module 'hand_sog_tracker' has no attribute {name!r}")
    value = getattr(importlib.import_module(home), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
