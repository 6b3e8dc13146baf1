"""GTSAM keys of the smoother's variables (``gtsam.symbol_shorthand``; lower-case characters).

Per keyframe k: ``pose_key(k)`` = x(k) Pose3 ``T_WI``; ``velocity_key(k)`` = v(k) velocity in W
(m/s); ``bias_key(k)`` = b(k) ``imuBias.ConstantBias``; ``theta_key(k)`` = t(k) joint angles
(Vector L, rad; ``dcc`` mode); ``camera_key(k)`` = c(k) Pose3 ``T_Wd`` of the gimbal camera
(``dcc`` with ``gimbal_factor='camera_pose'``, or any mode whose gimbal images are timed:
:mod:`.exposure`); ``static_camera_key(k)`` = s(k) Pose3 ``T_Ws`` of the static camera at its exposure
time (when its time offset is estimated or not zero); ``extra_camera_key(k, cam)`` = e(64 k + cam)
Pose3 ``T_Wc`` of further camera ``cam`` (run index >= 2) on a gimbal chain (``dcc``);
``chain_theta_key(k, slot)`` = u(64 k + slot) the joint angles of further chain ``slot`` >= 1 (Vector, rad;
:mod:`.chains`). ``offsets_key`` =
o(0) the time offsets ``[t_s, t_d]`` (Vector 2, s; one variable for the whole run, never marginalized).
Per landmark n: ``landmark_key(n)`` = l(n) Point3 in W.
"""

from __future__ import annotations

from gtsam.symbol_shorthand import B, C, E, L, O, S, T, U, V, X

#: Run indices of further cameras are below this (the per-keyframe stride of :func:`extra_camera_key`).
MAX_CAMERAS = 64

pose_key = X
velocity_key = V
bias_key = B
theta_key = T
camera_key = C
landmark_key = L
static_camera_key = S
offsets_key = O(0)


def extra_camera_key(k: int, cam: int) -> int:
    """e(64 k + cam): the pose ``T_Wc`` of further camera ``cam`` (run index 2..63) at keyframe ``k``."""
    if not 2 <= cam < MAX_CAMERAS:
        raise ValueError(f"run index {cam} of a further camera must be in 2..{MAX_CAMERAS - 1}")
    return int(E(k * MAX_CAMERAS + cam))


def chain_theta_key(k: int, slot: int) -> int:
    """u(64 k + slot): the joint angles of further chain ``slot`` (1..63) at keyframe ``k``."""
    if not 1 <= slot < MAX_CAMERAS:
        raise ValueError(f"slot {slot} of a further chain must be in 1..{MAX_CAMERAS - 1}")
    return int(U(k * MAX_CAMERAS + slot))


__all__ = [
    "bias_key",
    "camera_key",
    "chain_theta_key",
    "extra_camera_key",
    "landmark_key",
    "offsets_key",
    "pose_key",
    "static_camera_key",
    "theta_key",
    "velocity_key",
]
