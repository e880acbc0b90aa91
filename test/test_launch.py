"""The launch file: its arguments, what it starts and how it derives the CameraInfo topic.

``launch`` and ``launch_ros`` have no PyPI wheels, so the file is run here against small
stand-ins for the few classes it uses, which record what it asks for; where the real packages
are importable the LaunchDescription itself is inspected too.
"""

from __future__ import annotations

import ast
import importlib.util
import sys
import types
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import pytest

from hand_sog_tracker.ros.params import PARAM_NAMES, PARAM_SPECS
from helpers import read_setup_kwargs

REPO = Path(__file__).resolve().parents[1]
LAUNCH = REPO / "launch" / "tracker.launch.py"
NEEDED = {"namespace", "handedness", "depth_topic", "camera_info_topic", "use_sim_time", "params_file",
          "publish_tf", "frame_prefix"}


class _Recorded:
    """Stands in for a launch class: keeps its arguments."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.args, self.kwargs = args, kwargs


class _Config(_Recorded):
    def perform(self, context: dict[str, str]) -> str:
        return context[self.args[0]]


def _load_with_stand_ins(monkeypatch) -> types.ModuleType:
    stand_ins = {
        "launch": {"LaunchDescription": _Recorded},
        "launch.actions": {"DeclareLaunchArgument": _Recorded, "OpaqueFunction": _Recorded},
        "launch.substitutions": {"LaunchConfiguration": _Config},
        "launch_ros": {},
        "launch_ros.actions": {"Node": _Recorded},
        "ament_index_python": {},
        "ament_index_python.packages": {"get_package_share_directory": lambda pkg: f"/opt/share/{pkg}"},
    }
    for name, attrs in stand_ins.items():
        mod = types.ModuleType(name)
        for key, value in attrs.items():
            setattr(mod, key, value)
        monkeypatch.setitem(sys.modules, name, mod)
    spec = importlib.util.spec_from_file_location("tracker_launch", LAUNCH)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _run(monkeypatch, **given: str) -> tuple[list[_Recorded], _Recorded]:
    """The declared arguments and the Node the launch file starts with ``given`` arguments."""
    module = _load_with_stand_ins(monkeypatch)
    ld = module.generate_launch_description()
    entities = ld.args[0]
    declared = [e for e in entities if "default_value" in e.kwargs]
    opaque = [e for e in entities if "function" in e.kwargs]
    assert len(opaque) == 1 and len(declared) + 1 == len(entities)
    context = {d.args[0]: d.kwargs["default_value"] for d in declared} | given
    (node,) = opaque[0].kwargs["function"](context)
    return declared, node


def test_every_argument_is_declared_and_described(monkeypatch) -> None:
    declared, _ = _run(monkeypatch)
    names = [d.args[0] for d in declared]
    assert NEEDED <= set(names) and len(names) == len(set(names))
    for d in declared:
        assert len(d.kwargs["description"]) > 15, d.args[0]


def test_the_node_gets_the_installed_params_and_the_default_topics(monkeypatch, setup_kwargs: dict) -> None:
    _, node = _run(monkeypatch)
    kw = node.kwargs
    assert (kw["package"], kw["name"], kw["namespace"]) == ("hand_sog_tracker", "hand_sog_tracker", "")
    ros_scripts = {s.split("=")[0].strip() for s in setup_kwargs["entry_points"]["console_scripts"]}
    assert kw["executable"] in ros_scripts
    params_file, overrides = kw["parameters"]
    assert params_file == "/opt/share/hand_sog_tracker/config/hand_sog_tracker.yaml"
    data = {dest: list(files) for dest, files in setup_kwargs["data_files"]}
    assert "config/hand_sog_tracker.yaml" in data["share/hand_sog_tracker/config"]
    assert set(overrides) - {"use_sim_time"} <= set(PARAM_NAMES)
    assert overrides == {"handedness": "right", "publish_tf": False, "frame_prefix": "", "use_sim_time": False}
    assert dict(kw["remappings"]) == {
        "camera/depth/image_rect_raw": "camera/depth/image_rect_raw",
        "camera/depth/image_rect_raw/compressedDepth": "camera/depth/image_rect_raw/compressedDepth",
        "camera/depth/camera_info": "camera/depth/camera_info",
    }


def test_camera_info_follows_the_depth_topic(monkeypatch) -> None:
    _, node = _run(monkeypatch, depth_topic="/camera/camera/depth/image_rect_raw", namespace="left_hand",
                   handedness="left", use_sim_time="true", frame_prefix="left_")
    remaps = dict(node.kwargs["remappings"])
    assert remaps["camera/depth/camera_info"] == "/camera/camera/depth/camera_info"
    compressed = "/camera/camera/depth/image_rect_raw/compressedDepth"
    assert remaps["camera/depth/image_rect_raw/compressedDepth"] == compressed
    assert node.kwargs["namespace"] == "left_hand"
    overrides = node.kwargs["parameters"][1]
    assert overrides["handedness"] == "left" and overrides["use_sim_time"] is True
    assert overrides["frame_prefix"] == "left_"
    choices = {s.name: s.choices for s in PARAM_SPECS}["handedness"]
    assert overrides["handedness"] in choices
    # ... unless given explicitly.
    _, node = _run(monkeypatch, depth_topic="/cam/depth", camera_info_topic="/cam/info")
    assert dict(node.kwargs["remappings"])["camera/depth/camera_info"] == "/cam/info"


def test_no_shell_no_static_description_no_root_robot_description() -> None:
    tree = ast.parse(LAUNCH.read_text())
    names = {n.id for n in ast.walk(tree) if isinstance(n, ast.Name)} | {
        a.name for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) for a in n.names
    }
    assert not names & {"Command", "ExecuteProcess", "FindExecutable", "PythonExpression"}
    code = ast.Module(body=tree.body[1:], type_ignores=[])  # without the module docstring
    strings = {n.value for n in ast.walk(code) if isinstance(n, ast.Constant) and isinstance(n.value, str)}
    assert not any("robot_state_publisher" in s or ".urdf" in s or "robot_description" == s for s in strings)
    deps = {e.text for e in ET.parse(REPO / "package.xml").getroot().findall("exec_depend")}
    assert {"launch", "launch_ros", "ament_index_python"} <= deps


@pytest.mark.skipif(importlib.util.find_spec("launch_ros") is None, reason="launch_ros is not installed (no wheel)")
def test_the_real_launch_description_declares_the_arguments() -> None:  # pragma: no cover
    from launch.actions import DeclareLaunchArgument

    spec = importlib.util.spec_from_file_location("tracker_launch_real", LAUNCH)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    ld = module.generate_launch_description()
    declared = {a.name: a for a in ld.entities if isinstance(a, DeclareLaunchArgument)}
    assert NEEDED <= set(declared)
    assert all(a.description and a.description != "no description given" for a in declared.values())


@pytest.fixture(scope="module")
def setup_kwargs() -> dict:
    return read_setup_kwargs(colcon=True)  # where launch files run
