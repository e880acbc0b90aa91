"""Packaging for hand_sog_tracker: a ROS 2 (Jazzy) ament_python package that also pip-installs.

* ``colcon build`` (ament_python) installs the console scripts into
  ``lib/hand_sog_tracker`` (see setup.cfg) so ``ros2 run hand_sog_tracker tracker_node`` works.
* ``pip install .`` into a venv installs the same console scripts into the venv's ``bin/``
  with the prefix ``hand_sog_`` (``hand_sog_tracker_node``, ``hand_sog_demo`` ...: names that
  cannot collide with other commands on a PATH) and pulls ROS 2 Jazzy's Python wheels (rclpy
  with Fast DDS, the common interfaces).
"""

import os
from glob import glob

from setuptools import find_packages, setup

PACKAGE = "hand_sog_tracker"
VERSION = "0.20.0"

# In a sourced ROS 2 environment (colcon workspace) rclpy and the message packages come from the
# ROS installation (see package.xml); only a plain pip install needs the wheels from PyPI.
_ROS_WHEELS = [] if os.environ.get("AMENT_PREFIX_PATH") else [
    "ros-jazzy-rclpy[fastrtps]",
    "ros-jazzy-common-interfaces",
]

# The commands: ``ros2 run`` name -> entry point.  lib/hand_sog_tracker is the package's own
# folder, so the short names stay there; on a PATH (pip) they carry the package's prefix.
_SCRIPTS = {
    "tracker_node": f"{PACKAGE}.ros.node:main",
    "calibrate_hand": f"{PACKAGE}.ros.calibrate_client:main",
    "evaluate_bag": f"{PACKAGE}.tools.evaluate_bag:main",
    "replay_bag": f"{PACKAGE}.tools.replay_bag:main",
    "make_sample_bags": f"{PACKAGE}.tools.make_sample_bags:main",
    "make_scene_bags": f"{PACKAGE}.tools.make_scene_bags:main",
    "scene_eval": f"{PACKAGE}.tools.scene_eval:main",
    "benchmark": f"{PACKAGE}.tools.benchmark:main",
    "calibration_benchmark": f"{PACKAGE}.tools.calibration_benchmark:main",
    "demo": f"{PACKAGE}.tools.demo:main",
}
_SCRIPT_PREFIX = "" if os.environ.get("AMENT_PREFIX_PATH") else "hand_sog_"

setup(
    name=PACKAGE,
    version=VERSION,
    description="Real-time 26-DOF hand tracking from depth with Sum of Gaussians (ROS 2 node)",
    license="Apache-2.0",
    python_requires=">=3.10",
    packages=find_packages(exclude=["test", "test.*"]),
    package_data={PACKAGE: ["data/*.xml", "data/webxr_hand/*"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", sorted(glob("config/*.yaml"))),
        (f"share/{PACKAGE}/launch", sorted(glob("launch/*.launch.py"))),
        (f"share/{PACKAGE}/urdf", sorted(glob("urdf/*.urdf"))),
    ],
    install_requires=_ROS_WHEELS + [
        "numpy",
        "opencv-python-headless",
        "rosbags",
    ],
    extras_require={
        "plot": ["matplotlib"],
        "test": ["pytest", "matplotlib", "ruff"],
        "docs": ["sphinx", "myst-parser", "sphinx-argparse"],  # make docs (doc/conf.py)
    },
    zip_safe=False,
    entry_points={
        "console_scripts": [f"{_SCRIPT_PREFIX}{name} = {target}" for name, target in _SCRIPTS.items()],
    },
)
