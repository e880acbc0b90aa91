"""Packaging and layering: package.xml vs setup.py, console scripts, the core without ROS."""

from __future__ import annotations

import configparser
import importlib
import os
import re
import runpy
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
import setuptools

REPO = Path(__file__).resolve().parents[1]

CONSOLE_SCRIPTS = {
    "tracker_node": "hand_sog_tracker.ros.node:main",
    "calibrate_hand": "hand_sog_tracker.ros.calibrate_client:main",
    "evaluate_bag": "hand_sog_tracker.tools.evaluate_bag:main",
    "replay_bag": "hand_sog_tracker.tools.replay_bag:main",
    "make_sample_bags": "hand_sog_tracker.tools.make_sample_bags:main",
    "make_scene_bags": "hand_sog_tracker.tools.make_scene_bags:main",
    "scene_eval": "hand_sog_tracker.tools.scene_eval:main",
    "benchmark": "hand_sog_tracker.tools.benchmark:main",
    "calibration_benchmark": "hand_sog_tracker.tools.calibration_benchmark:main",
    "demo": "hand_sog_tracker.tools.demo:main",
}


@pytest.fixture(scope="module")
def setup_kwargs() -> dict:
    """The keyword arguments setup.py passes to setuptools.setup (setup.py is not executed for real)."""
    captured: dict = {}
    original = setuptools.setup
    setuptools.setup = lambda **kw: captured.update(kw)
    cwd = Path.cwd()
    try:
        os.chdir(REPO)
        runpy.run_path(str(REPO / "setup.py"), run_name="__main__")
    finally:
        os.chdir(cwd)
        setuptools.setup = original
    return captured


def test_core_never_imports_rclpy() -> None:
    code = (
        "import importlib, pkgutil, sys\n"
        "import hand_sog_tracker\n"  # the front door (__init__) imports the core only
        "assert hand_sog_tracker.Tracker is not None\n"
        "import hand_sog_tracker.core as core\n"
        "names = [m.name for m in pkgutil.iter_modules(core.__path__, 'hand_sog_tracker.core.')]\n"
        "for n in names: importlib.import_module(n)\n"
        "bad = sorted(m for m in sys.modules if m.split('.')[0] in ('rclpy', 'rosbags', 'sensor_msgs'))\n"
        "assert len(names) >= 8, names\n"
        "assert not bad, bad\n"
        "print(len(names))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert int(out.stdout) >= 8


def test_package_xml_and_setup_agree(setup_kwargs: dict) -> None:
    root = ET.parse(REPO / "package.xml").getroot()
    assert root.tag == "package" and root.get("format") == "3"
    assert root.findtext("name") == setup_kwargs["name"] == "hand_sog_tracker"
    assert root.findtext("version") == setup_kwargs["version"]
    assert root.findtext("export/build_type") == "ament_python"
    exec_deps = {e.text for e in root.findall("exec_depend")}
    assert {"rclpy", "sensor_msgs", "geometry_msgs", "visualization_msgs", "std_srvs", "diagnostic_msgs",
            "python3-numpy", "python3-opencv"} <= exec_deps
    assert "tests_require" not in setup_kwargs
    assert setup_kwargs["extras_require"]["test"] == ["pytest", "matplotlib", "ruff"]
    assert setup_kwargs["extras_require"]["plot"] == ["matplotlib"]
    reqs = set(setup_kwargs["install_requires"])
    assert {"numpy", "opencv-python-headless", "rosbags"} <= reqs


def test_console_scripts_are_declared_and_resolve(setup_kwargs: dict) -> None:
    declared = dict(
        (name.strip(), target.strip())
        for name, target in (s.split("=") for s in setup_kwargs["entry_points"]["console_scripts"])
    )
    assert declared == CONSOLE_SCRIPTS
    for name, target in declared.items():
        module, func = target.split(":")
        assert callable(getattr(importlib.import_module(module), func)), name


def test_installed_files(setup_kwargs: dict) -> None:
    data = {dest: list(files) for dest, files in setup_kwargs["data_files"]}
    assert data["share/ament_index/resource_index/packages"] == ["resource/hand_sog_tracker"]
    assert (REPO / "resource" / "hand_sog_tracker").is_file()
    assert data["share/hand_sog_tracker"] == ["package.xml"]
    assert "config/hand_sog_tracker.yaml" in data["share/hand_sog_tracker/config"]
    assert setup_kwargs["package_data"]["hand_sog_tracker"] == ["data/*.xml", "data/webxr_hand/*"]
    for name in ("right.glb", "left.glb", "LICENSE.md"):  # the mesh hand of synth.mesh (MIT)
        assert (REPO / "hand_sog_tracker" / "data" / "webxr_hand" / name).is_file()
    cfg = configparser.ConfigParser()
    cfg.read(REPO / "setup.cfg")
    assert cfg["develop"]["script_dir"] == "$base/lib/hand_sog_tracker"
    assert cfg["install"]["install_scripts"] == "$base/lib/hand_sog_tracker"


def test_shipped_dds_profile_is_loopback_only() -> None:
    path = REPO / "hand_sog_tracker" / "data" / "fastdds_loopback.xml"
    root = ET.parse(path).getroot()
    ns = {"f": "http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"}
    addresses = [a.text for a in root.iter("{%s}address" % ns["f"])]
    assert len(addresses) >= 4 and set(addresses) == {"127.0.0.1"}
    assert root.find(".//f:useBuiltinTransports", ns).text == "false"
    participant = root.find("f:participant", ns)
    assert participant.get("is_default_profile") == "true"
    types = {t.text for t in root.iter("{%s}type" % ns["f"])}
    assert types <= {"UDPv4", "SHM"}


def test_launch_file_compiles_and_names_only_what_exists(setup_kwargs: dict) -> None:
    """The launch file cannot run here (no launch / launch_ros on PyPI): check what it names."""
    import ast
    import py_compile

    path = REPO / "launch" / "tracker.launch.py"
    py_compile.compile(str(path), doraise=True)
    tree = ast.parse(path.read_text())
    data = {dest: list(files) for dest, files in setup_kwargs["data_files"]}
    assert "launch/tracker.launch.py" in data["share/hand_sog_tracker/launch"]
    assert "urdf/hand.urdf" in data["share/hand_sog_tracker/urdf"]
    assert any(isinstance(n, ast.FunctionDef) and n.name == "generate_launch_description" for n in tree.body)
    consts = {
        t.id: n.value.value
        for n in tree.body
        if isinstance(n, ast.Assign) and isinstance(n.value, ast.Constant)
        for t in n.targets
    }

    def value(node: ast.expr) -> str:
        return consts[node.id] if isinstance(node, ast.Name) else ast.literal_eval(node)

    nodes = {}
    for call in ast.walk(tree):
        if isinstance(call, ast.Call) and getattr(call.func, "id", None) == "Node":
            kw = {k.arg: k.value for k in call.keywords}
            nodes[value(kw["package"])] = value(kw["executable"])
    scripts = {s.split("=")[0].strip() for s in setup_kwargs["entry_points"]["console_scripts"]}
    assert nodes["hand_sog_tracker"] in scripts
    assert nodes == {"hand_sog_tracker": "tracker_node", "robot_state_publisher": "robot_state_publisher"}
    # Files it joins under the share directory exist in the source tree and are installed there.
    joined = [
        tuple(value(a) for a in call.args[1:])
        for call in ast.walk(tree)
        if isinstance(call, ast.Call) and getattr(call.func, "attr", None) == "join"
    ]
    assert ("urdf", "hand.urdf") in joined and ("config", "hand_sog_tracker.yaml") in joined
    for parts in joined:
        rel = "/".join(parts)
        assert (REPO / rel).is_file(), rel
        assert rel in data[f"share/hand_sog_tracker/{parts[0]}"], rel
    # Its dependencies are declared for rosdep.
    exec_deps = {e.text for e in ET.parse(REPO / "package.xml").getroot().findall("exec_depend")}
    assert {"launch", "launch_ros", "ament_index_python", "robot_state_publisher"} <= exec_deps
    # Every parameter it sets is a node parameter.
    from hand_sog_tracker.ros.params import PARAM_NAMES

    set_names = {
        k.value
        for d in ast.walk(tree)
        if isinstance(d, ast.Dict)
        for k in d.keys
        if isinstance(k, ast.Constant)
    }
    assert set_names - {"robot_description"} <= set(PARAM_NAMES)


def test_package_xml_lists_every_ros_package_imported() -> None:
    """rosdep installs what package.xml names: every ROS package the code imports is there."""
    import ast

    ros_names = {"rclpy", "launch", "launch_ros", "ament_index_python"}
    imported = set()
    for path in [*(REPO / "hand_sog_tracker").rglob("*.py"), *(REPO / "launch").glob("*.py")]:
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else (
                [node.module] if isinstance(node, ast.ImportFrom) and node.module and not node.level else []
            )
            for name in names:
                top = name.split(".")[0]
                if top in ros_names or top.endswith(("_msgs", "_srvs", "_interfaces")):
                    imported.add(top)
    deps = {e.text for e in ET.parse(REPO / "package.xml").getroot().iter() if e.tag.endswith("depend")}
    assert {"rclpy", "sensor_msgs", "std_msgs", "builtin_interfaces", "rcl_interfaces"} <= imported
    assert imported <= deps, sorted(imported - deps)


def test_every_test_domain_derives_from_the_suite_domain() -> None:
    """Two suites run side by side with different TEST_DOMAIN_ID values must never share a DDS
    domain: no test module may fix a domain of its own (helpers.test_domain derives them)."""
    fixed = re.compile(r"(DOMAIN(_ID)?\s*=\s*\"?\d+|ROS_DOMAIN_ID\",\s*\"[1-9]\d*\"|domain_id=\d+)")
    offenders = [
        f"{path.name}:{n}"
        for path in sorted((REPO / "test").glob("*.py"))
        for n, line in enumerate(path.read_text().splitlines(), 1)
        if fixed.search(line) and path.name not in {"conftest.py", "helpers.py", "test_package.py"}
    ]
    assert not offenders, f"fixed DDS domains in tests: {offenders}"
