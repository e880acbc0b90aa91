"""Node parameters: specs, shipped YAML, validation on set (in-process rclpy, loopback DDS)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
from rclpy.exceptions import InvalidParameterValueException
from rclpy.parameter import Parameter

from hand_sog_tracker.core.types import TrackerConfig
from hand_sog_tracker.errors import InputError
from hand_sog_tracker.ros.node import TrackerNode
from hand_sog_tracker.ros.params import PARAM_NAMES, PARAM_SPECS, params_yaml, settings_from_values

REPO = Path(__file__).resolve().parents[1]
CONFIG = REPO / "config" / "hand_sog_tracker.yaml"


def test_every_tracker_setting_is_a_parameter_with_the_core_default() -> None:
    fields = {f.name for f in dataclasses.fields(TrackerConfig)} - {"right_hand"}
    node_only = {"handedness", "user_model_path", "debug_image", "calibration_frames", "auto_calibrate",
                 "input_transport", "publish_wrist_joints", "publish_tf", "frame_prefix", "max_hands",
                 "max_image_pixels", "frame_budget_ms", "max_lag_ms"}
    assert fields | node_only == set(PARAM_NAMES)
    defaults = TrackerConfig()
    spec = {s.name: s for s in PARAM_SPECS}
    for name in fields:
        assert spec[name].default == getattr(defaults, name), name
        assert type(spec[name].default) is type(getattr(defaults, name)), name
        assert spec[name].description
    assert settings_from_values({}).tracker == defaults


def test_shipped_yaml_lists_every_parameter_at_its_default() -> None:
    assert CONFIG.read_text() == params_yaml(), "regenerate config/hand_sog_tracker.yaml from params_yaml()"


@pytest.mark.parametrize(
    "values, match",
    [
        ({"near_mm": 1200.0}, "near_mm < far_mm"),
        ({"median_kernel": 2}, "median_kernel"),
        ({"handedness": "up"}, "handedness must be one of right, left"),
        ({"iterations": 2.5}, "iterations must be int"),
        ({"debug_image": 1}, "debug_image must be bool"),
        ({"far_mm": 1e6}, r"far_mm=1000000.0 is outside"),
        ({"calibration_frames": 0}, "calibration_frames"),
    ],
)
def test_invalid_values_are_rejected_naming_the_parameter(values, match) -> None:
    with pytest.raises(InputError, match=match):
        settings_from_values(values)


def test_settings_freeze_handedness_and_model_path(tmp_path: Path) -> None:
    s = settings_from_values({"handedness": "left", "user_model_path": str(tmp_path / "m.yaml"), "far_mm": 700})
    assert s.tracker.right_hand is False and s.tracker.far_mm == 700.0
    assert s.user_model_path == tmp_path / "m.yaml"


def test_node_loads_the_shipped_params_file_and_overrides(ros_context, tmp_path: Path) -> None:
    node = TrackerNode(
        context=ros_context,
        cli_args=["--ros-args", "--params-file", str(CONFIG), "-p", "iterations:=7"],
        parameter_overrides=[Parameter("user_model_path", value=str(tmp_path / "m.yaml"))],
    )
    try:
        assert node.settings.tracker == dataclasses.replace(TrackerConfig(), iterations=7)
        assert node.settings.user_model_path == tmp_path / "m.yaml"
        desc = node.describe_parameter("near_mm")
        assert desc.floating_point_range[0].from_value == 10.0 and "mm" in desc.description
        assert node.describe_parameter("user_model_path").read_only
        assert node.has_parameter("qos_overrides./camera/depth/image_rect_raw.subscription.depth")
    finally:
        node.destroy_node()


def test_on_set_callback_rejects_with_a_reason_and_accepts_valid_changes(ros_context, tmp_path: Path) -> None:
    node = TrackerNode(
        context=ros_context, parameter_overrides=[Parameter("user_model_path", value=str(tmp_path / "m.yaml"))]
    )
    try:
        results = node.set_parameters(
            [
                Parameter("near_mm", value=1200.0),
                Parameter("median_kernel", value=4),
                Parameter("far_mm", value=50000.0),
                Parameter("handedness", value="both"),
                Parameter("user_model_path", value="/tmp/x.yaml"),
            ]
        )
        assert [r.successful for r in results] == [False] * 5
        assert "near_mm < far_mm" in results[0].reason
        assert "median_kernel" in results[1].reason
        assert "far_mm" in results[2].reason  # range from the descriptor
        assert "handedness" in results[3].reason
        assert "read-only" in results[4].reason
        assert node.settings.tracker == TrackerConfig()
        ok = node.set_parameters_atomically(
            [Parameter("near_mm", value=200.0), Parameter("far_mm", value=900.0), Parameter("handedness", value="left")]
        )
        assert ok.successful, ok.reason
        assert (node.settings.tracker.near_mm, node.settings.tracker.far_mm) == (200.0, 900.0)
        assert node.settings.tracker.right_hand is False
    finally:
        node.destroy_node()


def test_invalid_start_up_parameters_raise(ros_context) -> None:
    with pytest.raises(InputError, match="near_mm < far_mm"):
        TrackerNode(context=ros_context, parameter_overrides=[Parameter("near_mm", value=1050.0)])
    with pytest.raises(InvalidParameterValueException):
        TrackerNode(context=ros_context, parameter_overrides=[Parameter("iterations", value=0)])
