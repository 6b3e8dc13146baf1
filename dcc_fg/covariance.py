"""Observability and covariances of a calibration (frames and conventions: docs/architecture.md).

* Observability: the information matrix of the *full* kinematic vector (12 + 3L, no gauge), with
  the per-snapshot variables eliminated (Schur complement), and its null space
  (:func:`information_schur`, :func:`null_space`, :func:`observable_mask`).
* Covariances: GTSAM marginals of the solved graph, scaled by the a-posteriori variance factor,
  for the free kinematic entries, the joint angles and each snapshot's ``T_ds`` (6x6, tangent
  ``[omega, v]`` in rad and m, gtsam's right perturbation; :func:`marginal_covariances`).
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np
from gtsam.symbol_shorthand import J
from numpy.typing import NDArray

from dcc_fg.calibration_graph import CalibrationProblem, SolutionArrays, snapshot_measurements
from dcc_fg.data import CalibrationDataset
from dcc_fg.util.errors import stage
from factors import chain
from factors.calibration import KinLayout, bundle_residuals, two_way_residuals

FloatArray = NDArray[np.float64]
COVARIANCE_CHUNK = 200  # snapshots per joint-marginal call (dense block: (nk + 200 L)^2 doubles)
COVARIANCE_UNAVAILABLE = "unavailable: the information matrix is too ill-conditioned for a Cholesky factorization"


# ------------------------------------------------------------------ observability


def information_schur(
    data: CalibrationDataset,
    kin: FloatArray,
    n_joints: int,
    thetas: FloatArray,
    T_st: FloatArray,
    mode: str,
    formulation: str,
    sigma: float,
    pnp: list[tuple[FloatArray, FloatArray]] | None = None,
) -> FloatArray:
    """Information matrix of the *full* kinematic vector (12 + 3L) after eliminating the
    per-snapshot variables (joint angles when estimated, target poses in the bundle)."""
    layout = KinLayout(np.asarray(kin, float), np.ones(chain.n_kin(n_joints), dtype=bool), n_joints)
    cams = (data.static_camera, data.dynamic_camera)
    n = chain.n_kin(n_joints)
    S = np.zeros((n, n))
    for i, s in enumerate(data.snapshots):
        meas = snapshot_measurements(data, s)
        if formulation == "bundle":
            blocks = bundle_residuals(layout, kin, thetas[i], T_st[i], meas, cams, True)
            local = [1, 2] if mode == "encoderless" else [2]
        else:
            assert pnp is not None
            P_s, P_d = pnp[i]
            blocks = two_way_residuals(layout, kin, thetas[i], P_s, meas.z_dynamic, P_d, meas.z_static, cams, True)
            local = [1] if mode == "encoderless" else []
        Jk = np.concatenate([b[1][0].reshape(-1, n) for b in blocks]) / sigma
        if local:
            Jx = (
                np.concatenate(
                    [np.concatenate([b[1][j].reshape(b[1][j].shape[0] * 2, -1) for j in local], axis=1) for b in blocks]
                )
                / sigma
            )
            Hxx = Jx.T @ Jx
            Hxk = Jx.T @ Jk
            S += Jk.T @ Jk - Hxk.T @ np.linalg.solve(Hxx, Hxk)
        else:
            S += Jk.T @ Jk
    return S


def null_space(S: FloatArray, rel_tol: float = 1e-9) -> FloatArray:
    """Orthonormal basis (n, k) of the numerical null space of a PSD matrix, in parameter space
    (Jacobi-scaled first so that metres and radians are treated alike)."""
    d = np.sqrt(np.maximum(np.diag(S), 1e-300))
    Sn = S / np.outer(d, d)
    w, V = np.linalg.eigh(Sn)
    N = V[:, w < rel_tol * w.max()]
    return N


def observable_mask(N: FloatArray, tol: float = 1e-6) -> NDArray[np.bool_]:
    """A parameter is observable when no null-space direction moves it."""
    if N.shape[1] == 0:
        return np.ones(N.shape[0], dtype=bool)
    return np.max(np.abs(N), axis=1) < tol


# ------------------------------------------------------------------ covariances


@dataclass
class Covariances:
    """What a calibration reports about its uncertainty: 1-sigma of the kinematic entries (NaN where
    held, unobservable or not computed) and of the joint angles (K, L) in rad (NaN when not
    estimated), the (K, 6, 6) covariances of ``T_ds`` (None when not computed) and a note ("ok",
    "not computed" or why they are unavailable)."""

    kin_std: FloatArray
    theta_std: FloatArray
    T_ds: FloatArray | None
    note: str


COVARIANCE_HINT = "run without covariances (compute_covariance: false)"


def graph_marginals(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> gtsam.Marginals:
    """GTSAM marginals at the solution. Raises :class:`~dcc_fg.util.errors.EstimatorError` of the stage
    "marginal covariances" when the information matrix cannot be factorized (an ill-posed graph)."""
    with stage("marginal covariances", hint=COVARIANCE_HINT):
        return gtsam.Marginals(graph, values)


def marginal_covariances(
    marginals: gtsam.Marginals,
    problem: CalibrationProblem,
    sol: SolutionArrays,
    observable: NDArray[np.bool_],
    variance_factor: float,
) -> Covariances:
    """Covariances of the kinematics, joint angles and each snapshot's ``T_ds`` from the marginals,
    scaled by ``variance_factor``.

    One joint marginal per chunk of ``COVARIANCE_CHUNK`` snapshots instead of two per snapshot: each
    GTSAM marginal call costs about as much as a joint one over many keys (the mean prior on the
    reference snapshots' joint angles puts them in one clique), so per-snapshot calls made this
    O(K^2) (~70 s of covariances at K = 300). Chunks bound the dense block.
    """
    K, L, fixed = problem.n_snapshots, problem.n_joints, problem.fixed
    kin_key, estimate_theta = problem.kin_key, problem.estimate_theta
    kin_std = np.full(len(sol.kin), np.nan)
    theta_std = np.full((K, L), np.nan)
    T_ds_cov = np.zeros((K, 6, 6))
    with stage("marginal covariances", hint=COVARIANCE_HINT):
        if kin_key is not None:
            cov = marginals.marginalCovariance(kin_key) * variance_factor
            kin_std[~fixed] = np.sqrt(np.diag(cov))
        kin_std[~observable] = np.nan
        for start in range(0, K, COVARIANCE_CHUNK):
            chunk = range(start, min(K, start + COVARIANCE_CHUNK))
            keys = ([kin_key] if kin_key is not None else []) + ([J(i) for i in chunk] if estimate_theta else [])
            if not keys:
                break
            kv = gtsam.KeyVector()
            for k in keys:
                kv.append(k)
            joint = marginals.jointMarginalCovariance(kv)
            for i in chunk:
                Jk, Jt = chain.d_T_ds_tangent(sol.kin, sol.thetas[i], L)
                keys_i, blocks_J = [], []
                if kin_key is not None:
                    keys_i.append(kin_key)
                    blocks_J.append(Jk[:, ~fixed])
                if estimate_theta:
                    keys_i.append(J(i))
                    blocks_J.append(Jt)
                C = np.block([[joint.at(a, b) for b in keys_i] for a in keys_i]) * variance_factor
                if estimate_theta:
                    theta_std[i] = np.sqrt(np.diag(joint.at(J(i), J(i))) * variance_factor)
                Jf = np.concatenate(blocks_J, axis=1)
                T_ds_cov[i] = Jf @ C @ Jf.T
    return Covariances(kin_std, theta_std, T_ds_cov, "ok")
