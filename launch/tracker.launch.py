"""Launch the hand tracker, optionally with a robot_state_publisher for the hand URDF.

    ros2 launch hand_sog_tracker tracker.launch.py
    ros2 launch hand_sog_tracker tracker.launch.py robot_state_publisher:=true \
        depth_topic:=/camera/camera/depth/image_rect_raw camera_info_topic:=/camera/camera/depth/camera_info

Arguments:
  params_file            parameters of the node (default: the installed config/hand_sog_tracker.yaml)
  depth_topic            depth image topic (also remaps its /compressedDepth sub-topic)
  camera_info_topic      CameraInfo topic
  robot_state_publisher  true: also start robot_state_publisher with the URDF (rooted at
                         hand_wrist), fed by hand/joint_states (default false)
  urdf                   the URDF file (default: the installed urdf/hand.urdf; urdf/hand_left.urdf
                         for a left hand, or one printed for a calibrated model by
                         python -m hand_sog_tracker.core.urdf --model ~/.ros/hand_sog_tracker/hand_model.yaml)
  publish_tf             the node broadcasts hand_wrist in the camera frame on /tf, which joins
                         the URDF's finger links to the camera (default: = robot_state_publisher)
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition
from launch.substitutions import Command, LaunchConfiguration
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue

PACKAGE = "hand_sog_tracker"


def generate_launch_description() -> LaunchDescription:
    share = get_package_share_directory(PACKAGE)
    depth = LaunchConfiguration("depth_topic")
    return LaunchDescription(
        [
            DeclareLaunchArgument(
                "params_file",
                default_value=os.path.join(share, "config", "hand_sog_tracker.yaml"),
                description="Parameters file of the tracker node",
            ),
            DeclareLaunchArgument("depth_topic", default_value="camera/depth/image_rect_raw"),
            DeclareLaunchArgument("camera_info_topic", default_value="camera/depth/camera_info"),
            DeclareLaunchArgument(
                "robot_state_publisher",
                default_value="false",
                description="Also start robot_state_publisher with urdf/hand.urdf",
            ),
            DeclareLaunchArgument(
                "urdf",
                default_value=os.path.join(share, "urdf", "hand.urdf"),
                description="URDF for robot_state_publisher",
            ),
            DeclareLaunchArgument(
                "publish_tf",
                default_value=LaunchConfiguration("robot_state_publisher"),
                description="Broadcast hand_wrist and the fingertips on /tf",
            ),
            Node(
                package=PACKAGE,
                executable="tracker_node",
                name="hand_sog_tracker",
                output="screen",
                parameters=[
                    LaunchConfiguration("params_file"),
                    {"publish_tf": ParameterValue(LaunchConfiguration("publish_tf"), value_type=bool)},
                ],
                remappings=[
                    ("camera/depth/image_rect_raw", depth),
                    ("camera/depth/image_rect_raw/compressedDepth", [depth, "/compressedDepth"]),
                    ("camera/depth/camera_info", LaunchConfiguration("camera_info_topic")),
                ],
            ),
            Node(
                package="robot_state_publisher",
                executable="robot_state_publisher",
                name="hand_state_publisher",
                output="screen",
                parameters=[
                    {
                        "robot_description": ParameterValue(
                            Command(["cat ", LaunchConfiguration("urdf")]), value_type=str
                        )
                    }
                ],
                remappings=[("joint_states", "hand/joint_states")],
                condition=IfCondition(LaunchConfiguration("robot_state_publisher")),
            ),
        ]
    )
