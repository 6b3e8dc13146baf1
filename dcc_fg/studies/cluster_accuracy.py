"""Accuracy of the cluster calibration against the simulator's truth and the Cramer-Rao bound.

Gauge-invariant quantity: every camera's ``T_cs(theta_i)`` (s = cam0 -> camera c at snapshot i's joint
angles); its error ``xi = Log(T_true^-1 T_est) = [omega, v]`` (rad, m; gtsam Pose3 local coordinates
at the truth). The bound is :func:`dcc_fg.cluster_calibration.T_cs_bound` at the true values for the
simulation's pixel sigma (the information of the full parameterization, gauge directions dropped).
RMS values: ``sqrt(mean ||omega||^2)`` and ``sqrt(mean ||v||^2)`` over snapshots (and seeds); the
bound's ``sqrt(mean trace)`` of the rotation / translation blocks.
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np
from numpy.typing import NDArray

from dcc_fg.cluster_calibration import ClusterCalibrationResult, ClusterKinematics, T_cs_bound, problem_at
from dcc_fg.sim.cluster_scene import SimulatedCluster

FloatArray = NDArray[np.float64]


@dataclass
class CameraAccuracy:
    """Per camera: errors (n, 6) and bound covariances (n, 6, 6) over the snapshots where T_cs exists."""

    errors: FloatArray
    bound: FloatArray

    @staticmethod
    def rms(e: FloatArray) -> tuple[float, float]:
        return float(np.sqrt(np.mean(np.sum(e[:, :3] ** 2, axis=1)))), float(np.sqrt(np.mean(np.sum(e[:, 3:] ** 2, 1))))

    @staticmethod
    def bound_rms(P: FloatArray) -> tuple[float, float]:
        return (
            float(np.sqrt(np.mean(np.trace(P[:, :3, :3], axis1=1, axis2=2)))),
            float(np.sqrt(np.mean(np.trace(P[:, 3:, 3:], axis1=1, axis2=2)))),
        )


def true_thetas(sim: SimulatedCluster, i: int) -> dict[str, FloatArray]:
    return {ch: sim.joints[ch][i] for ch in sim.truth.chain_names}


def cluster_accuracy(sim: SimulatedCluster, result: ClusterCalibrationResult) -> dict[str, CameraAccuracy]:
    """Camera (all but cam0) -> errors of ``result`` against the truth and the Cramer-Rao bound."""
    problem, state = problem_at(
        sim.data, ClusterKinematics.from_cluster(sim.truth), sim.joints, sim.T_st, sim.config.pixel_sigma
    )
    bound = T_cs_bound(problem, state)
    used = result.snapshot_index
    if len(used) != problem.n_snapshots:
        raise ValueError("the result and the truth use different snapshots")
    out = {}
    for c in sim.truth.camera_names[1:]:
        ch = sim.truth.camera(c).chain
        errs, covs = [], []
        for k, i in enumerate(used):
            if ch is not None and not np.all(np.isfinite(result.joint_angles[ch][k])):
                continue
            T_true = sim.truth.T_cs(c, true_thetas(sim, int(i)))
            errs.append(gtsam.Pose3(T_true).localCoordinates(gtsam.Pose3(result.T_cs(c, k))))
            covs.append(bound[c][k])
        out[c] = CameraAccuracy(np.array(errs), np.array(covs))
    return out
