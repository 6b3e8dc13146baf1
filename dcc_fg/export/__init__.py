"""Exports of a calibration for the rest of a robot's software (``dcc-fg export``).

* :mod:`~dcc_fg.export.urdf`: the cluster as a URDF (static camera link, one revolute joint per DH
  link, gimbal camera link; ROS optical frames), for ``robot_state_publisher``;
* :mod:`~dcc_fg.export.kalibr`: the cluster frozen at given joint angles as a Kalibr camchain
  (and camchain-imucam) YAML, for tools that only accept static rigs;
* :mod:`~dcc_fg.export.joint_states`: a ``joint_angles.csv`` as ``sensor_msgs/JointState`` in a
  ROS1 / ROS2 bag, to play the estimated angles back with the URDF;
* :mod:`~dcc_fg.export.naming`: the link and joint names the URDF and the bag share.

Frames and units as in docs/architecture.md: ``T_ds(theta)`` maps static-camera points into the
gimbal camera; metres, radians, integer nanoseconds.
"""
