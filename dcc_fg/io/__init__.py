"""Readers and writers: ROS bags, image folders, detection folders, Kalibr YAML, CSV/TUM."""
