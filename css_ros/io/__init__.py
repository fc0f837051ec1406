"""ROS-free input/output: message <-> array conversion, frame decoding, synchronisation, topics, bags."""
