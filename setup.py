"""Packaging for hand_sog_tracker: a ROS 2 (Jazzy) ament_python package that also pip-installs.

* ``colcon build`` (ament_python) installs the console scripts into
  ``lib/hand_sog_tracker`` (see setup.cfg) so ``ros2 run hand_sog_tracker tracker_node`` works.
* ``pip install .`` into a venv installs the same console scripts into the venv's ``bin/``
  and pulls ROS 2 Jazzy's Python wheels (rclpy with Fast DDS, the common interfaces).
"""

import os
from glob import glob

from setuptools import find_packages, setup

PACKAGE = "hand_sog_tracker"
VERSION = "0.1.0"

# In a sourced ROS 2 environment (colcon workspace) rclpy and the message packages come from the
# ROS installation (see package.xml); only a plain pip install needs the wheels from PyPI.
_ROS_WHEELS = [] if os.environ.get("AMENT_PREFIX_PATH") else [
    "ros-jazzy-rclpy[fastrtps]",
    "ros-jazzy-common-interfaces",
]

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
    extras_require={"plot": ["matplotlib"], "test": ["pytest", "matplotlib", "ruff"]},
    zip_safe=False,
    entry_points={
        "console_scripts": [
            f"tracker_node = {PACKAGE}.ros.node:main",
            f"calibrate_hand = {PACKAGE}.ros.calibrate_client:main",
            f"evaluate_bag = {PACKAGE}.tools.evaluate_bag:main",
            f"replay_bag = {PACKAGE}.tools.replay_bag:main",
            f"make_sample_bags = {PACKAGE}.tools.make_sample_bags:main",
            f"make_scene_bags = {PACKAGE}.tools.make_scene_bags:main",
            f"scene_eval = {PACKAGE}.tools.scene_eval:main",
            f"benchmark = {PACKAGE}.tools.benchmark:main",
            f"calibration_benchmark = {PACKAGE}.tools.calibration_benchmark:main",
            f"demo = {PACKAGE}.tools.demo:main",
        ],
    },
)
