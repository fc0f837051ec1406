"""The demo: procedural scene, trajectory, segmentation noise, bag generator and live player."""
