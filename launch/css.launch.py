"""Launch css_node with config/css_node.yaml (real ROS 2 installs: ros2 launch css_ros css.launch.py)."""
from __future__ import annotations

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def generate_launch_description() -> LaunchDescription:
    share = get_package_share_directory("css_ros")
    args = [
        DeclareLaunchArgument("params_file", default_value=os.path.join(share, "config", "css_node.yaml"),
                              description="css_node parameter file"),
        # Relative paths are resolved by css_node against the working directory, share/css_ros and the source tree.
        DeclareLaunchArgument("model_path", default_value="bags/demo/model.ply",
                              description="3DGS PLY of the scene (map frame)"),
        DeclareLaunchArgument("class_file", default_value="bags/demo/classes.yaml", description="class YAML"),
        DeclareLaunchArgument("namespace", default_value="", description="namespace of the node"),
        # Input topic names (remappings of the node's relative inputs).
        DeclareLaunchArgument("image", default_value="image"),
        DeclareLaunchArgument("segmentation", default_value="segmentation"),
        DeclareLaunchArgument("segmentation_confidence", default_value="segmentation_confidence"),
        DeclareLaunchArgument("camera_info", default_value="camera_info"),
        DeclareLaunchArgument("pose", default_value="pose"),
        DeclareLaunchArgument("candidates", default_value="candidates"),
    ]
    node = Node(
        package="css_ros",
        executable="css_node",
        name="css_node",
        namespace=LaunchConfiguration("namespace"),
        output="screen",
        parameters=[LaunchConfiguration("params_file"),
                    {"model_path": LaunchConfiguration("model_path"),
                     "class_file": LaunchConfiguration("class_file")}],
        remappings=[(name, LaunchConfiguration(name)) for name in
                    ("image", "segmentation", "segmentation_confidence", "camera_info", "pose", "candidates")],
    )
    return LaunchDescription([*args, node])
