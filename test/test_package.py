"""Packaging and layering: package.xml vs setup.py, console scripts, the core without ROS."""

from __future__ import annotations

import configparser
import importlib
import re
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from helpers import read_setup_kwargs

REPO = Path(__file__).resolve().parents[1]

#: ``ros2 run`` names (colcon); a pip install puts them on the PATH as ``hand_sog_<name>``.
CONSOLE_SCRIPTS = {
    "tracker_node": "hand_sog_tracker.ros.node:main",
    "calibrate_hand": "hand_sog_tracker.ros.calibrate_client:main",
    "evaluate_bag": "hand_sog_tracker.tools.evaluate_bag:main",
    "replay_bag": "hand_sog_tracker.tools.replay_bag:main",
    "make_sample_bags": "hand_sog_tracker.tools.make_sample_bags:main",
    "benchmark": "hand_sog_tracker.tools.benchmark:main",
    "calibration_benchmark": "hand_sog_tracker.tools.calibration_benchmark:main",
    "demo": "hand_sog_tracker.tools.demo:main",
}


@pytest.fixture(scope="module")
def setup_kwargs() -> dict:
    """The keyword arguments setup.py passes to setuptools.setup (setup.py is not executed for real)."""
    return read_setup_kwargs()


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
    assert "python3-rosbags" in exec_deps  # the bag tools after rosdep install + colcon build


@pytest.mark.parametrize("colcon", [False, True])
def test_console_scripts_are_declared_and_resolve(colcon: bool) -> None:
    kwargs = read_setup_kwargs(colcon=colcon)
    declared = dict(
        (name.strip(), target.strip())
        for name, target in (s.split("=") for s in kwargs["entry_points"]["console_scripts"])
    )
    prefix = "" if colcon else "hand_sog_"  # on a PATH, no command named "demo" or "benchmark"
    assert declared == {prefix + name: target for name, target in CONSOLE_SCRIPTS.items()}
    for name, target in declared.items():
        module, func = target.split(":")
        assert callable(getattr(importlib.import_module(module), func)), name


def test_versions_agree_with_the_newest_changelog_entry(setup_kwargs: dict) -> None:
    text = (REPO / "CHANGELOG.rst").read_text()
    entries = re.findall(r"^(\d+\.\d+\.\d+) \((\d{4}-\d\d-\d\d)\)\n-+$", text, flags=re.M)
    assert entries, "CHANGELOG.rst has no 'X.Y.Z (YYYY-MM-DD)' entries"
    versions = [tuple(int(v) for v in version.split(".")) for version, _ in entries]
    assert versions == sorted(versions, reverse=True), "newest entry first"
    dates = [date for _, date in entries]
    assert dates == sorted(dates, reverse=True)
    newest = entries[0][0]
    assert ET.parse(REPO / "package.xml").getroot().findtext("version") == setup_kwargs["version"] == newest
    assert not (REPO / "CHANGELOG.md").exists()
    assert "Apache License" in (REPO / "LICENSE").read_text() and "Version 2.0" in (REPO / "LICENSE").read_text()


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
