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

from dcc_fg.calibration_graph import CalibrationProblem, SolutionArrays, snapshot_measurements, variable_dims
from dcc_fg.data import CalibrationDataset
from dcc_fg.gauss_newton import ordering_of, scaled_pseudo_inverse
from dcc_fg.util.errors import stage
from factors import chain
from factors.calibration import KinLayout, bundle_residuals, two_way_residuals

FloatArray = NDArray[np.float64]
COVARIANCE_CHUNK = 200  # snapshots per joint-marginal call (dense block: (nk + 200 L)^2 doubles)
COVARIANCE_UNAVAILABLE = "unavailable: the information matrix is too ill-conditioned for a Cholesky factorization"
DENSE_LIMIT = 4000  # unknowns up to which the dense fallback of dense_covariances is used
DENSE_REL_TOL = 1e-12  # scaled eigenvalues below this are dropped by the fallback's pseudo-inverse
COVARIANCE_DENSE = "ok (scaled pseudo-inverse: the information matrix is too ill-conditioned for Cholesky)"


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
    scale_out: FloatArray | None = None,
) -> FloatArray:
    """Information matrix of the *full* kinematic vector (12 + 3L) after eliminating the
    per-snapshot variables (joint angles when estimated, target poses in the bundle).

    Per snapshot the kinematic Jacobian is projected onto the orthogonal complement of the local
    variables' Jacobian (``J_k - Q Q^T J_k``, ``Q`` an orthonormal basis of ``J_x``), which equals the
    Schur complement ``J_k^T J_k - H_xk^T H_xx^-1 H_xk`` in exact arithmetic but stays positive
    semi-definite in floating point: where a kinematic direction is absorbed by the joint angles (a
    gauge, or the axes of a spherical wrist) the subtraction would cancel ~1e8 against ~1e8.

    ``scale_out``: when given (shape (12 + 3L,)), receives the square root of the diagonal of the
    information *before* elimination (each parameter's information if everything else were known):
    a scale for metres and radians that, unlike the diagonal of the result, does not vanish along
    the directions the elimination removes.
    """
    layout = KinLayout(np.asarray(kin, float), np.ones(chain.n_kin(n_joints), dtype=bool), n_joints)
    cams = (data.static_camera, data.dynamic_camera)
    n = chain.n_kin(n_joints)
    S = np.zeros((n, n))
    diag = np.zeros(n)
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
        diag += np.einsum("ij,ij->j", Jk, Jk)
        if local:
            Jx = (
                np.concatenate(
                    [np.concatenate([b[1][j].reshape(b[1][j].shape[0] * 2, -1) for j in local], axis=1) for b in blocks]
                )
                / sigma
            )
            Q = np.linalg.qr(Jx)[0]
            Jk = Jk - Q @ (Q.T @ Jk)
        S += Jk.T @ Jk
    if scale_out is not None:
        scale_out[:] = np.sqrt(diag)
    return 0.5 * (S + S.T)


def null_space(S: FloatArray, rel_tol: float = 1e-9, scale: FloatArray | None = None) -> FloatArray:
    """Orthonormal basis (n, k) of the numerical null space of a PSD matrix, in parameter space
    (scaled first so that metres and radians are treated alike: by ``scale``, e.g. the one
    :func:`information_schur` returns, else by the square root of the diagonal of ``S``)."""
    d = np.sqrt(np.maximum(np.diag(S), 1e-300)) if scale is None else np.maximum(np.asarray(scale, float), 1e-300)
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


def dense_covariances(
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    problem: CalibrationProblem,
    sol: SolutionArrays,
    observable: NDArray[np.bool_],
    variance_factor: float,
) -> Covariances | None:
    """Covariances from the dense information matrix of the linearized graph, for the problems whose
    information is too ill-conditioned for GTSAM's Cholesky (nearly degenerate mechanisms: directions
    whose information is a few 1e-8 of the largest). Jacobi-scaled, then a pseudo-inverse that drops
    the directions below ``DENSE_REL_TOL`` (they leave every ``T_ds`` unchanged). None when the
    problem has more than ``DENSE_LIMIT`` unknowns."""
    K, L, fixed = problem.n_snapshots, problem.n_joints, problem.fixed
    kin_key = problem.kin_key
    keys = variable_dims(problem)
    n = sum(d for _, d in keys)
    if n > DENSE_LIMIT or n == 0:
        return None
    offsets = {}
    at = 0
    for key, dim in keys:
        offsets[key] = (at, dim)
        at += dim
    with stage("marginal covariances", hint=COVARIANCE_HINT):
        H = graph.linearize(values).hessian(ordering_of(keys))[0]
        C = scaled_pseudo_inverse(H, DENSE_REL_TOL) * variance_factor

    def block(a: int, b: int) -> FloatArray:
        (ia, da), (ib, db) = offsets[a], offsets[b]
        return C[ia : ia + da, ib : ib + db]

    kin_std = np.full(len(sol.kin), np.nan)
    theta_std = np.full((K, L), np.nan)
    T_ds_cov = np.zeros((K, 6, 6))
    if kin_key is not None:
        kin_std[~fixed] = np.sqrt(np.maximum(np.diag(block(kin_key, kin_key)), 0.0))
    kin_std[~observable] = np.nan
    for i in range(K):
        Jk, Jt = chain.d_T_ds_tangent(sol.kin, sol.thetas[i], L)
        ks, Js = [], []
        if kin_key is not None:
            ks.append(kin_key)
            Js.append(Jk[:, ~fixed])
        if problem.estimate_theta:
            ks.append(J(i))
            Js.append(Jt)
            theta_std[i] = np.sqrt(np.maximum(np.diag(block(J(i), J(i))), 0.0))
        if ks:
            Cb = np.block([[block(a, b) for b in ks] for a in ks])
            Jf = np.concatenate(Js, axis=1)
            T_ds_cov[i] = Jf @ Cb @ Jf.T
    return Covariances(kin_std, theta_std, T_ds_cov, COVARIANCE_DENSE)
