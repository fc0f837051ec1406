"""``css_map``: inspect, merge and transfer saved semantic maps (ROS-free; the maths is in the engine)."""
