"""Ground-truth evaluation of a calibration on gauge-invariant quantities, and the Cramer-Rao bound.

Gauge-invariant quantities (docs/architecture.md):

* per snapshot, ``T_ds(theta_i)``; its error is ``xi_i = Log(T_ds_true^-1 T_ds_est) = [omega, v]``
  (rad, m), the gtsam Pose3 local coordinates at the true value;
* joint angles after removing the unobservable constant offset per joint:
  ``theta_i,l - mean_k theta_k,l``;
* kinematic parameters only where the information matrix says they are observable.

The Cramer-Rao bound is ``G H^+ G^T``: ``H`` the information matrix of the bundle formulation
(maximum likelihood) at the true parameters for the pixel sigma of the simulation, ``G`` the
Jacobian of a gauge-invariant quantity with respect to all parameters. Both quantities are
estimable (orthogonal to the null space of H), so the pseudo-inverse gives the bound.
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np
from numpy.typing import NDArray

from dcc_fg.calibrate import CalibrationResult
from dcc_fg.calibration_graph import snapshot_measurements
from dcc_fg.data import CalibrationDataset
from dcc_fg.model import GimbalCalibration
from factors import chain
from factors.calibration import KinLayout, bundle_residuals, camera_sigmas

FloatArray = NDArray[np.float64]
# Relative eigenvalue below which a direction of the (Jacobi-scaled) information matrix counts as an
# exact gauge direction. Exact gauge directions sit at ~1e-16 of the largest eigenvalue (round-off);
# weakly informative directions of a nearly degenerate mechanism (L = 3: ~6e-10) must be kept, or
# the bound would silently ignore their uncertainty.
PINV_REL_TOL = 1e-12


def T_ds_errors(
    truth: GimbalCalibration, thetas_true: FloatArray, est: GimbalCalibration, thetas_est: FloatArray
) -> FloatArray:
    """(K, 6) tangent errors ``[omega, v]`` of T_ds per snapshot (rad, m)."""
    out = np.zeros((len(thetas_true), 6))
    for i, (tt, te) in enumerate(zip(thetas_true, thetas_est, strict=True)):
        out[i] = gtsam.Pose3(truth.T_ds(tt)).localCoordinates(gtsam.Pose3(est.T_ds(te)))
    return out


def offset_free_joint_errors(thetas_true: FloatArray, thetas_est: FloatArray) -> FloatArray:
    """(K, L) joint-angle errors with the mean error of each joint removed, radians."""
    d = np.asarray(thetas_est) - np.asarray(thetas_true)
    d = np.arctan2(np.sin(d), np.cos(d))
    return d - d.mean(axis=0)


@dataclass
class GroundTruthErrors:
    """Errors of one calibration (or validation) run against the simulator's truth."""

    T_ds: FloatArray  # (K, 6)
    joints: FloatArray  # (K, L) offset-free
    kin_observable: dict[str, float]  # parameter -> error (rad or m), observable ones only

    @property
    def rotation_rms(self) -> float:
        return float(np.sqrt(np.mean(np.sum(self.T_ds[:, :3] ** 2, axis=1))))

    @property
    def translation_rms(self) -> float:
        return float(np.sqrt(np.mean(np.sum(self.T_ds[:, 3:] ** 2, axis=1))))

    @property
    def joint_rms(self) -> FloatArray:
        return np.sqrt(np.mean(self.joints**2, axis=0))

    def as_dict(self) -> dict[str, object]:
        rot = np.linalg.norm(self.T_ds[:, :3], axis=1)
        tra = np.linalg.norm(self.T_ds[:, 3:], axis=1)
        absj = np.abs(self.joints)
        return {
            "T_ds_rotation_rad": {"mean": float(rot.mean()), "std": float(rot.std()), "rms": self.rotation_rms},
            "T_ds_translation_m": {"mean": float(tra.mean()), "std": float(tra.std()), "rms": self.translation_rms},
            "joint_offset_free_rad": [
                {"mean": float(absj[:, j].mean()), "std": float(absj[:, j].std()), "rms": float(self.joint_rms[j])}
                for j in range(self.joints.shape[1])
            ],
            "kinematic_errors_observable": self.kin_observable,
        }


def evaluate_against_truth(
    result: CalibrationResult, truth: GimbalCalibration, thetas_true: FloatArray
) -> GroundTruthErrors:
    """Gauge-invariant errors of ``result`` against the simulator's truth."""
    est = result.calibration
    kin_err = {}
    if est.observable is not None:
        for k, name in enumerate(est.names):
            if est.observable[k]:
                d = est.kin[k] - truth.kin[k]
                if chain.kin_is_angle(est.n_joints)[k]:
                    d = float(np.arctan2(np.sin(d), np.cos(d)))
                kin_err[name] = float(d)
    return GroundTruthErrors(
        T_ds=T_ds_errors(truth, thetas_true, est, result.joint_angles),
        joints=offset_free_joint_errors(thetas_true, result.joint_angles),
        kin_observable=kin_err,
    )


@dataclass
class CramerRaoBound:
    """Lower bounds on the covariance of the gauge-invariant quantities.

    Attributes:
        T_ds: (K, 6, 6) bound on the covariance of each snapshot's T_ds tangent error.
        joints: (K, L) bound on the variance of each offset-free joint angle.
    """

    T_ds: FloatArray
    joints: FloatArray

    @property
    def rotation_rms(self) -> float:
        return float(np.sqrt(np.mean(np.trace(self.T_ds[:, :3, :3], axis1=1, axis2=2))))

    @property
    def translation_rms(self) -> float:
        return float(np.sqrt(np.mean(np.trace(self.T_ds[:, 3:, 3:], axis1=1, axis2=2))))

    @property
    def joint_rms(self) -> FloatArray:
        return np.sqrt(np.mean(self.joints, axis=0))


def cramer_rao_bound(
    data: CalibrationDataset,
    truth: GimbalCalibration,
    thetas_true: FloatArray,
    T_st_true: FloatArray,
    pixel_sigma: float | tuple[float, float],
) -> CramerRaoBound:
    """CRB of T_ds(theta_i) and offset-free joint angles for encoderless calibration (bundle model).

    ``pixel_sigma``: the corner noise (px, 1 sigma per axis), one for both cameras or
    ``(static, dynamic)`` when the cameras' detections differ (the bound of the detector's actual noise).
    Parameter order: [kin (12+3L), theta_1..theta_K (L each), xi_1..xi_K (6 each, Pose3 of T_st)].
    """
    sigmas = camera_sigmas(pixel_sigma)
    L = truth.n_joints
    K = len(data.snapshots)
    nk = chain.n_kin(L)
    n = nk + K * L + 6 * K
    H = np.zeros((n, n))
    layout = KinLayout(truth.kin.copy(), np.ones(nk, dtype=bool), L)
    cams = (data.static_camera, data.dynamic_camera)
    for i, s in enumerate(data.snapshots):
        blocks = bundle_residuals(
            layout, truth.kin, thetas_true[i], T_st_true[i], snapshot_measurements(data, s), cams, True
        )
        for (_, (Jk, Jt, Jp)), sigma in zip(blocks, sigmas, strict=True):  # static, then dynamic camera
            rows = Jk.shape[0] * 2
            Jb = np.zeros((rows, n))
            Jb[:, :nk] = Jk.reshape(rows, -1)
            Jb[:, nk + i * L : nk + (i + 1) * L] = Jt.reshape(rows, -1)
            Jb[:, nk + K * L + 6 * i : nk + K * L + 6 * (i + 1)] = Jp.reshape(rows, -1)
            H += Jb.T @ Jb / float(sigma) ** 2
    # Jacobi scaling, then a pseudo-inverse that drops the exact null space
    d = np.sqrt(np.diag(H))
    Hn = H / np.outer(d, d)
    w, V = np.linalg.eigh(Hn)
    keep = w > PINV_REL_TOL * w.max()
    Hn_pinv = (V[:, keep] / w[keep]) @ V[:, keep].T
    C = Hn_pinv / np.outer(d, d)

    cov_T = np.zeros((K, 6, 6))
    for i in range(K):
        Jk, Jt = chain.d_T_ds_tangent(truth.kin, thetas_true[i], L)
        G = np.zeros((6, n))
        G[:, :nk] = Jk
        G[:, nk + i * L : nk + (i + 1) * L] = Jt
        cov_T[i] = G @ C @ G.T
    var_j = np.zeros((K, L))
    for j in range(L):
        idx = nk + np.arange(K) * L + j
        Cj = C[np.ix_(idx, idx)]
        P = np.eye(K) - np.full((K, K), 1.0 / K)  # remove the mean
        var_j[:, j] = np.diag(P @ Cj @ P.T)
    return CramerRaoBound(T_ds=cov_T, joints=var_j)


def nees_T_ds(errors: FloatArray, covariances: FloatArray) -> FloatArray:
    """Normalized estimation error squared of each snapshot's T_ds (6 dof each)."""
    return np.array([e @ np.linalg.solve(P, e) for e, P in zip(errors, covariances, strict=True)])
