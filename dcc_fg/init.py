"""Initial values for the calibration graph.

* :func:`pnp_pose` - target pose ``T_ct`` (target -> camera c) from one view by planar PnP
  (OpenCV IPPE on undistorted normalized points, then Levenberg-Marquardt refinement).
* hand-measured kinematics come from a ``gimbal.yaml`` (:func:`dcc_fg.model.load_calibration`).
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from factors.camera import CameraModel

FloatArray = NDArray[np.float64]


def pnp_pose(camera: CameraModel, p_t: FloatArray, uv: FloatArray) -> FloatArray:
    """Pose of the target in the camera frame, ``T_ct`` (4x4), from >= 4 corners.

    Args:
        camera: intrinsics of the camera.
        p_t: (N, 3) target points in the target frame, metres (planar, z = 0 for our targets).
        uv: (N, 2) measured pixels.
    """
    if p_t.shape[0] < 4:
        raise ValueError(f"PnP needs at least 4 corners, got {p_t.shape[0]}")
    xy = camera.undistort_points(uv)
    obj = np.ascontiguousarray(p_t, dtype=np.float64).reshape(-1, 1, 3)
    img = np.ascontiguousarray(xy, dtype=np.float64).reshape(-1, 1, 2)
    K = np.eye(3)
    planar = np.ptp(p_t[:, 2]) < 1e-9
    flag = cv2.SOLVEPNP_IPPE if planar else cv2.SOLVEPNP_ITERATIVE
    ok, rvec, tvec = cv2.solvePnP(obj, img, K, None, flags=flag)
    if not ok:
        raise ValueError("PnP failed")
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, None, rvec, tvec)
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(rvec)[0]
    T[:3, 3] = tvec.ravel()
    return T
