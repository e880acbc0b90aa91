"""The node's interface module (hand_sog_tracker.interface): one definition, no ROS imports."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from hand_sog_tracker import interface
from hand_sog_tracker.errors import InputError
from hand_sog_tracker.tools.bagio import DepthSample, write_depth_bag
from helpers import INTR

REPO = Path(__file__).resolve().parents[1]
#: Packages that need a ROS installation (or its PyPI wheels).
ROS_MODULES = ("rclpy", "sensor_msgs", "std_msgs", "geometry_msgs", "builtin_interfaces",
               "visualization_msgs", "diagnostic_msgs", "rcl_interfaces")

_READ_BAG = """
import json, sys
from hand_sog_tracker.tools.bagio import DepthBagReader
with DepthBagReader(sys.argv[1]) as r:
    frames = list(r.frames())
ros = sorted(m for m in sys.modules if m.split(".")[0] in {ros})
print(json.dumps({{"frames": len(frames), "ok": sum(f.error is None for f in frames),
                  "truth": sum(f.truth_mm is not None for f in frames), "ros": ros}}))
"""


@pytest.mark.parametrize("codec", [None, "png"])
def test_reading_a_bag_loads_no_ros_module(tmp_path: Path, codec: str | None) -> None:
    rng = np.random.default_rng(3)
    samples = [
        DepthSample(1_000_000_000 + i * 33_333_333, rng.uniform(300.0, 700.0, (INTR.height, INTR.width)),
                    INTR, np.full((5, 3), 400.0))
        for i in range(3)
    ]
    write_depth_bag(tmp_path / "b", samples, depth_codec=codec)  # type: ignore[arg-type]
    code = _READ_BAG.format(ros=set(ROS_MODULES))
    out = subprocess.run([sys.executable, "-c", code, str(tmp_path / "b")], cwd=REPO,
                         capture_output=True, text=True, timeout=120, check=True)
    got = json.loads(out.stdout.strip().splitlines()[-1])
    assert got == {"frames": 3, "ok": 3, "truth": 3, "ros": []}


def test_interface_imports_no_ros_module() -> None:
    code = ("import sys, hand_sog_tracker.interface, hand_sog_tracker.tools.bagio; "
            f"print(sorted(m for m in sys.modules if m.split('.')[0] in {set(ROS_MODULES)}))")
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True,
                         timeout=60, check=True)
    assert out.stdout.strip() == "[]"


def test_stamps_round_trip() -> None:
    ns = 1_700_000_000_123_456_789
    stamp = interface.ns_to_stamp(ns, SimpleNamespace)
    assert (stamp.sec, stamp.nanosec) == (1_700_000_000, 123_456_789)
    assert interface.stamp_to_ns(stamp) == ns
    with pytest.raises(InputError, match="negative"):
        interface.ns_to_stamp(-1, SimpleNamespace)


def test_image_to_depth_mm_on_a_duck_typed_message() -> None:
    depth = np.array([[0, 500], [1000, 65535]], dtype="<u2")
    msg = SimpleNamespace(height=2, width=2, encoding="16UC1", is_bigendian=0, step=4,
                          data=depth.tobytes())
    np.testing.assert_array_equal(interface.image_to_depth_mm(msg), depth.astype(np.float32))


def test_node_and_tools_use_the_one_definition() -> None:
    from hand_sog_tracker.ros import conversions, node
    from hand_sog_tracker.tools import bagio, node_harness

    assert conversions.image_to_depth_mm is interface.image_to_depth_mm
    assert conversions.camera_info_to_intrinsics is interface.camera_info_to_intrinsics
    assert conversions.stamp_to_ns is bagio.stamp_to_ns is interface.stamp_to_ns
    assert node.IMAGE_TOPIC == node_harness.DEPTH_TOPIC == interface.DEPTH_TOPIC
    assert bagio.DEPTH_TOPIC == "/" + interface.DEPTH_TOPIC == interface.BAG_DEPTH_TOPIC
    assert node.NODE_NAME == interface.NODE_NAME
    assert set(node_harness.COUNTER_KEYS) <= {k.removeprefix("frames_") for k in interface.DIAG_COUNTER_KEYS}
