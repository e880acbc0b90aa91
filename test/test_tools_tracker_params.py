"""Tracker settings for the tools: the node's params YAML, --set items, validation."""

from __future__ import annotations

from pathlib import Path

import pytest

from hand_sog_tracker.core.types import TrackerConfig
from hand_sog_tracker.errors import InputError
from hand_sog_tracker.tools.tracker_params import (
    node_only,
    parse_params_yaml,
    parse_set,
    read_params_file,
    tracker_config,
)

REPO = Path(__file__).resolve().parents[1]


def test_the_shipped_params_file_gives_the_default_config() -> None:
    values = read_params_file(REPO / "config" / "hand_sog_tracker.yaml")
    assert values["iterations"] == TrackerConfig().iterations == 7
    assert values["handedness"] == "right" and values["user_model_path"] == ""
    assert tracker_config(values) == TrackerConfig()
    assert {"user_model_path", "debug_image", "calibration_frames"} <= set(node_only(values))
    assert "near_mm" not in node_only(values) and "handedness" not in node_only(values)


def test_blocks_for_all_nodes_and_for_the_node_are_merged_in_order() -> None:
    text = (
        "/**:\n  ros__parameters:\n    iterations: 5\n    use_sim_time: false\n"
        "/robot/hand_sog_tracker:\n  ros__parameters:\n    iterations: 9\n    handedness: left\n"
        "other_node:\n  ros__parameters:\n    wiggle: 1\n"
    )
    values = parse_params_yaml(text)
    assert values == {"iterations": 9, "handedness": "left"}
    cfg = tracker_config(values)
    assert cfg.iterations == 9 and cfg.right_hand is False
    # a single block is used whatever the node is called
    assert parse_params_yaml("tracker:\n  ros__parameters:\n    far_mm: 800\n") == {"far_mm": 800}


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("near_mm: 100\n", "not a ROS 2 params file"),
        ("a: [1,\n", "not valid YAML"),
        ("hand_sog_tracker:\n  ros__parameters:\n    wiggle: 1\n", "unknown tracker parameter 'wiggle'"),
        ("hand_sog_tracker:\n  ros__parameters:\n    iterations: [1, 2]\n", "must be a single value"),
        ("a:\n  ros__parameters: {}\nb:\n  ros__parameters: {}\n", "no parameters for 'hand_sog_tracker'"),
    ],
)
def test_bad_params_files_are_clear_errors(text: str, match: str) -> None:
    with pytest.raises(InputError, match=match):
        parse_params_yaml(text)


def test_read_params_file_errors(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="cannot read params file"):
        read_params_file(tmp_path / "missing.yaml")


def test_set_items_are_typed_like_the_parameter() -> None:
    values = parse_set(["iterations=12", "far_mm=700", "debug_image=TRUE", "handedness=left", "iterations=13"])
    assert values == {"iterations": 13, "far_mm": 700.0, "debug_image": True, "handedness": "left"}
    assert isinstance(values["far_mm"], float)
    for item, match in [
        ("iterations", "expects name=value"),
        ("=3", "expects name=value"),
        ("wiggle=1", "unknown tracker parameter 'wiggle'"),
        ("iterations=1.5", "iterations must be int"),
        ("debug_image=yes", "debug_image must be bool"),
        ("far_mm=far", "far_mm must be float"),
    ]:
        with pytest.raises(InputError, match=match):
            parse_set([item])


def test_validation_is_the_node_s() -> None:
    with pytest.raises(InputError, match="near_mm"):
        tracker_config({"near_mm": 1500.0})
    with pytest.raises(InputError, match="outside"):
        tracker_config({"iterations": 0})
    with pytest.raises(InputError, match="handedness must be one of"):
        tracker_config({"handedness": "both"})
