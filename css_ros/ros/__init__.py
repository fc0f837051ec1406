"""The ROS 2 layer: the `css_node` node and its parts (rclpy is imported by these modules)."""
