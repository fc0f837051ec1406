"""Importers: turn the outputs of 3DGS trainers (INRIA cameras.json, nerfstudio transforms.json, COLMAP
sparse models) plus a folder of label PNGs into the bag layout css_replay and css_demo read (ROS-free)."""
