"""Values shared by several test modules (import as ``from helpers import INTR``).

pytest puts this directory on ``sys.path`` (rootdir-relative "prepend" import mode), so test
modules import it by its bare name, like ``test_ros_calibration`` imports ``test_ros_node``.
"""

from __future__ import annotations

from hand_sog_tracker.core.types import Intrinsics

#: RealSense-like 320x240 depth intrinsics (px) with the principal point at (160, 120).
#: ``test_ros_node`` keeps its own with ``cx, cy = 159.5, 119.5`` (the exact image centre, as
#: :func:`hand_sog_tracker.synth.sequence.default_intrinsics` gives), ``test_core_realdata`` the
#: calibration of its recorded camera.
INTR = Intrinsics(fx=287.26, fy=287.26, cx=160.0, cy=120.0, width=320, height=240)
