"""IMU propagation: input checks, preintegration between keyframes, standstill initial state.

The IMU frame I is the body frame; W has gravity along -z (``ImuConfig.gravity``, m/s^2).
Accelerometer samples are specific forces in m/s^2, gyroscope samples rates in rad/s, times in ns.
"""

from __future__ import annotations

import gtsam
import numpy as np

from dcc_fg.data.vio import ImuConfig, ImuSamples
from dcc_fg.vio.backend.options import NS, FloatArray, InitialState


def validate_imu(imu: ImuSamples, source: str = "imu") -> None:
    """Raise ValueError for IMU data the smoother cannot use (naming the field at fault)."""
    n = len(imu)
    if imu.acc.shape != (n, 3) or imu.gyro.shape != (n, 3):
        raise ValueError(f"{source}: acc and gyro must be (N, 3) arrays matching t_ns ({n} samples)")
    if n < 2:
        raise ValueError(f"{source}: at least two IMU samples are needed, got {n}")
    dt = np.diff(imu.t_ns)
    if np.any(dt <= 0):
        k = int(np.argmax(dt <= 0))
        raise ValueError(
            f"{source}: t_ns not strictly increasing at sample {k + 1} ({imu.t_ns[k]} -> {imu.t_ns[k + 1]})"
        )
    for name, arr in (("acc", imu.acc), ("gyro", imu.gyro)):
        bad = ~np.all(np.isfinite(arr), axis=1)
        if np.any(bad):
            k = int(np.argmax(bad))
            raise ValueError(f"{source}: {name} is not finite at sample {k} (t_ns {imu.t_ns[k]})")


def preintegration_params(cfg: ImuConfig) -> gtsam.PreintegrationCombinedParams:
    """Combined preintegration parameters from Kalibr continuous-time noise densities, gravity -z."""
    p = gtsam.PreintegrationCombinedParams.MakeSharedU(cfg.gravity)
    I3 = np.eye(3)
    p.setAccelerometerCovariance(I3 * cfg.accelerometer_noise_density**2)
    p.setGyroscopeCovariance(I3 * cfg.gyroscope_noise_density**2)
    p.setIntegrationCovariance(I3 * 1e-8)
    p.setBiasAccCovariance(I3 * cfg.accelerometer_random_walk**2)
    p.setBiasOmegaCovariance(I3 * cfg.gyroscope_random_walk**2)
    return p


def integrate_imu(pim: gtsam.PreintegratedCombinedMeasurements, imu: ImuSamples, t0_ns: int, t1_ns: int) -> None:
    """Integrate the IMU over [t0, t1]: each sample interval contributes its midpoint average,
    clipped to the interval (samples before t0 / after t1 are held)."""
    t = imu.t_ns
    i0 = max(int(np.searchsorted(t, t0_ns, side="right")) - 1, 0)
    i1 = min(int(np.searchsorted(t, t1_ns, side="left")), len(t) - 1)
    for i in range(i0, i1):
        a = max(t[i], t0_ns)
        b = min(t[i + 1], t1_ns)
        if b <= a:
            continue
        acc = 0.5 * (imu.acc[i] + imu.acc[i + 1])
        gyro = 0.5 * (imu.gyro[i] + imu.gyro[i + 1])
        pim.integrateMeasurement(acc, gyro, (b - a) / NS)
    if t1_ns > t[-1]:  # hold the last sample
        pim.integrateMeasurement(imu.acc[-1], imu.gyro[-1], (t1_ns - max(t[-1], t0_ns)) / NS)


def preintegrate(
    params: gtsam.PreintegrationCombinedParams,
    bias: gtsam.imuBias.ConstantBias,
    imu: ImuSamples,
    t0_ns: int,
    t1_ns: int,
) -> gtsam.PreintegratedCombinedMeasurements:
    """Preintegrated measurements over [t0, t1] (:func:`integrate_imu`) linearized at ``bias``."""
    pim = gtsam.PreintegratedCombinedMeasurements(params, bias)
    integrate_imu(pim, imu, t0_ns, t1_ns)
    return pim


def up_to_z_rotation(up_I: FloatArray) -> FloatArray:
    """``R_WI`` turning the body direction ``up_I`` (any length) onto +z of W by the least rotation
    (yaw left as it is): gravity along -z of W when ``up_I`` is the specific force at rest."""
    u = np.asarray(up_I, float) / np.linalg.norm(up_I)
    ez = np.array([0.0, 0.0, 1.0])
    axis = np.cross(u, ez)
    s, c = np.linalg.norm(axis), float(np.dot(u, ez))
    rotvec = np.zeros(3) if s < 1e-12 else axis / s * np.arctan2(s, c)
    return gtsam.Rot3.Expmap(rotvec).matrix()


def standstill_state(imu: ImuSamples, t0_ns: int, window: float, gravity: float, n_joints: int) -> InitialState:
    """Gravity-aligned initial state from IMU samples in [t0, t0 + window] (body assumed at rest).

    Roll and pitch rotate the mean specific force onto +z of W; yaw is 0; the gyroscope bias is
    the mean rate; raises ValueError if the body is clearly moving.
    """
    sel = (imu.t_ns >= t0_ns) & (imu.t_ns <= t0_ns + int(window * NS))
    if sel.sum() < 5:
        raise ValueError(f"standstill initialization needs IMU samples in the first {window} s after the first frame")
    f = imu.acc[sel].mean(axis=0)
    spread = np.linalg.norm(imu.acc[sel] - f, axis=1).max()
    if abs(np.linalg.norm(f) - gravity) > 0.5 or spread > 3.0:
        raise ValueError(
            f"standstill initialization: the IMU is not at rest at the start (|mean acc| = {np.linalg.norm(f):.2f} "
            f"m/s^2, spread {spread:.2f}); pass an initial state instead"
        )
    T = np.eye(4)
    T[:3, :3] = up_to_z_rotation(f)
    return InitialState(t0_ns, T, np.zeros(3), np.zeros(3), imu.gyro[sel].mean(axis=0), np.zeros(n_joints))
