"""Shared test set-up: loopback-only DDS, a test ROS domain, one rclpy context per test.

The environment is fixed at import time, before any test module can import rclpy:
Fast DDS always uses the loopback-only profile shipped with the package, the
domain defaults to 73 (``make test`` sets it explicitly) and ``ROS_HOME`` points
at a throw-away directory, removed at exit, so tests never read or write the user's
``~/.ros`` (hand model, log files).
"""

from __future__ import annotations

import atexit
import os
import shutil
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Iterator

import pytest

if TYPE_CHECKING:
    from rclpy.context import Context

REPO = Path(__file__).resolve().parents[1]
LOOPBACK_PROFILE = REPO / "hand_sog_tracker" / "data" / "fastdds_loopback.xml"
TEST_DOMAIN_ID = "73"

os.environ["FASTRTPS_DEFAULT_PROFILES_FILE"] = str(LOOPBACK_PROFILE)
os.environ.setdefault("ROS_DOMAIN_ID", TEST_DOMAIN_ID)
os.environ.pop("ROS_LOCALHOST_ONLY", None)  # deprecated; the profile already keeps DDS local
os.environ.pop("ROS_AUTOMATIC_DISCOVERY_RANGE", None)
os.environ["ROS_HOME"] = tempfile.mkdtemp(prefix="hand_sog_tracker_ros_home_")
atexit.register(shutil.rmtree, os.environ["ROS_HOME"], ignore_errors=True)  # (logs of the run)


@pytest.fixture
def ros_context() -> Iterator["Context"]:
    """A fresh, initialised rclpy context, shut down after the test."""
    import rclpy
    from rclpy.context import Context

    ctx = Context()
    rclpy.init(context=ctx)
    try:
        yield ctx
    finally:
        rclpy.try_shutdown(context=ctx)
