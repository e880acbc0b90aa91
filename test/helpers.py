"""Values shared by several test modules (import as ``from helpers import INTR``).

pytest puts this directory on ``sys.path`` (rootdir-relative "prepend" import mode), so test
modules import it by its bare name, like ``test_ros_calibration`` imports ``test_ros_node``.
"""

from __future__ import annotations

import os

from hand_sog_tracker.core.types import Intrinsics

#: The suite's base DDS domain: ``TEST_DOMAIN_ID`` (``make test`` passes it as ``ROS_DOMAIN_ID``;
#: conftest defaults it to 73). Tests that need a domain of their own take :func:`test_domain`.
BASE_DOMAIN_ID = int(os.environ.get("ROS_DOMAIN_ID", "73"))


def test_domain(offset: int) -> int:
    """A DDS domain for one test module: the suite's base domain plus ``offset`` (1-9).

    Deriving every domain from the base keeps two suites run side by side with different
    ``TEST_DOMAIN_ID`` values apart (Fast DDS accepts domains 0-232).
    """
    return (BASE_DOMAIN_ID + offset) % 233


test_domain.__test__ = False  # type: ignore[attr-defined]  # not a pytest test

#: RealSense-like 320x240 depth intrinsics (px) with the principal point at (160, 120).
#: ``test_ros_node`` keeps its own with ``cx, cy = 159.5, 119.5`` (the exact image centre, as
#: :func:`hand_sog_tracker.synth.sequence.default_intrinsics` gives), ``test_core_realdata`` the
#: calibration of its recorded camera.
INTR = Intrinsics(fx=287.26, fy=287.26, cx=160.0, cy=120.0, width=320, height=240)


def read_setup_kwargs(colcon: bool = False) -> dict:
    """The keyword arguments setup.py passes to ``setuptools.setup`` (nothing is built).

    ``colcon``: as in a sourced ROS environment (``AMENT_PREFIX_PATH`` set), else as for pip.
    """
    import runpy
    from pathlib import Path

    import setuptools

    repo = Path(__file__).resolve().parents[1]
    captured: dict = {}
    original, cwd = setuptools.setup, Path.cwd()
    setuptools.setup = lambda **kw: captured.update(kw)
    ament = os.environ.pop("AMENT_PREFIX_PATH", None)
    if colcon:
        os.environ["AMENT_PREFIX_PATH"] = "/opt/ros/jazzy"
    try:
        os.chdir(repo)
        runpy.run_path(str(repo / "setup.py"), run_name="__main__")
    finally:
        os.chdir(cwd)
        setuptools.setup = original
        os.environ.pop("AMENT_PREFIX_PATH", None)
        if ament is not None:
            os.environ["AMENT_PREFIX_PATH"] = ament
    return captured
