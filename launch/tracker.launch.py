"""Launch the hand tracker on a depth camera.

    ros2 launch hand_sog_tracker tracker.launch.py depth_topic:=/camera/camera/depth/image_rect_raw
    ros2 launch hand_sog_tracker tracker.launch.py namespace:=left_hand handedness:=left \
        frame_prefix:=left_ publish_tf:=true

``ros2 launch hand_sog_tracker tracker.launch.py --show-args`` lists the arguments with their
descriptions (:data:`ARGUMENTS`).  The node publishes the description of the hand model it uses
on ``hand/robot_description`` in its namespace and, with ``publish_tf``, the hand's frames on
/tf itself: no robot_state_publisher and no static URDF are needed.
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

PACKAGE = "hand_sog_tracker"
EXECUTABLE = "tracker_node"
NODE_NAME = "hand_sog_tracker"

#: (name, default, description) of every launch argument; "" for params_file is the installed
#: config/hand_sog_tracker.yaml.
ARGUMENTS = (
    ("namespace", "", "Namespace of the node and of its topics, e.g. left_hand (default: none)"),
    ("handedness", "right", "Which hand is tracked: right or left (overrides the params file)"),
    ("depth_topic", "camera/depth/image_rect_raw",
     "Depth image topic (16UC1 mm or 32FC1 m); its /compressedDepth sub-topic is remapped with it"),
    ("camera_info_topic", "",
     "CameraInfo topic of the depth image; empty: camera_info beside depth_topic "
     "(/camera/camera/depth/image_rect_raw -> /camera/camera/depth/camera_info)"),
    ("params_file", "", "Parameters file of the node; empty: the installed config/hand_sog_tracker.yaml"),
    ("publish_tf", "false", "true: the node broadcasts the hand's frames on /tf (for RViz's RobotModel display)"),
    ("frame_prefix", "", "Put in front of every frame the node names (TF and URDF links), e.g. left_"),
    ("use_sim_time", "false", "true: use the /clock topic (replaying a bag with --clock)"),
)


def camera_info_topic(depth_topic: str) -> str:
    """The CameraInfo topic a camera driver publishes beside ``depth_topic``."""
    parent = depth_topic.rstrip("/").rpartition("/")[0]
    return f"{parent}/camera_info" if parent else "camera_info"


def _as_bool(text: str) -> bool:
    if text.lower() not in ("true", "false"):
        raise ValueError(f"expected true or false, got {text!r}")
    return text.lower() == "true"


def _tracker_node(context, *_args, **_kwargs):
    arg = {name: LaunchConfiguration(name).perform(context) for name, _, _ in ARGUMENTS}
    depth = arg["depth_topic"]
    params_file = arg["params_file"] or os.path.join(
        get_package_share_directory(PACKAGE), "config", "hand_sog_tracker.yaml"
    )
    overrides = {
        "handedness": arg["handedness"],
        "publish_tf": _as_bool(arg["publish_tf"]),
        "frame_prefix": arg["frame_prefix"],
        "use_sim_time": _as_bool(arg["use_sim_time"]),
    }
    return [
        Node(
            package=PACKAGE,
            executable=EXECUTABLE,
            name=NODE_NAME,
            namespace=arg["namespace"],
            output="screen",
            parameters=[params_file, overrides],
            remappings=[
                ("camera/depth/image_rect_raw", depth),
                ("camera/depth/image_rect_raw/compressedDepth", f"{depth}/compressedDepth"),
                ("camera/depth/camera_info", arg["camera_info_topic"] or camera_info_topic(depth)),
            ],
        )
    ]


def generate_launch_description() -> LaunchDescription:
    return LaunchDescription(
        [DeclareLaunchArgument(name, default_value=default, description=text) for name, default, text in ARGUMENTS]
        + [OpaqueFunction(function=_tracker_node)]
    )
