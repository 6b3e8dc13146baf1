"""Predicted T_ds accuracy over a range (dcc_fg.planning.predict): Jacobians against numerical
differentiation and against the factors' own Jacobians, the kinematics' covariance against the
calibration's, and the predicted covariance against true errors at held-out joint angles (NEES)."""

from __future__ import annotations

from dataclasses import replace
from functools import lru_cache

import gtsam
import numpy as np
import pytest
from scipy.stats import chi2

from dcc_fg.calibrate import CalibrationOptions, CalibrationResult, calibrate
from dcc_fg.data import CalibrationDataset, Observation, Snapshot
from dcc_fg.planning.predict import (
    MAX_OBLIQUE_DEG,
    POSE_TILT_DIRECTIONS,
    POSE_TILTS_DEG,
    KinematicsInformation,
    ViewModel,
    accuracy_over_range,
    accuracy_table,
    candidate_poses,
    kinematics_information,
    place_targets,
    placement_at,
    predict,
    range_grid,
    view_information,
)
from dcc_fg.sim.calibration_scene import SceneConfig, SimulatedCalibration, simulate_calibration, true_kinematics
from dcc_fg.sim.mechanism_family import family_member
from factors import chain
from factors.calibration import KinLayout, SnapshotMeasurements, bundle_residuals

DEG = np.pi / 180.0


def pinned_view(sigma: float = 0.4) -> ViewModel:
    truth = true_kinematics(2)
    assert truth.static_camera is not None and truth.dynamic_camera is not None
    pts = SceneConfig().target.points
    return ViewModel(truth.static_camera, truth.dynamic_camera, pts, 0.9, (0.6, 1.2), sigma)


def _pose_exp(T: np.ndarray, xi: np.ndarray) -> np.ndarray:
    return T @ gtsam.Pose3.Expmap(xi).matrix()


def test_view_information_matches_numerical_differentiation() -> None:
    """The analytic information on xi (target pose eliminated) equals the one from central differences
    of the corner projections with respect to T_ds Exp(xi) and T_st Exp(eta)."""
    truth = true_kinematics(2)
    view = pinned_view()
    T_ds = truth.T_ds(np.array([95.0, 5.0]) * DEG)[None]
    pl = place_targets(view, T_ds)
    assert pl.ok[0] and pl.full[0]
    T_st = pl.T_st[0]
    pts = view.target_points

    def corners(xi: np.ndarray, eta: np.ndarray) -> np.ndarray:
        Tst = _pose_exp(T_st, eta)
        Tds = _pose_exp(T_ds[0], xi)
        p_s = pts @ Tst[:3, :3].T + Tst[:3, 3]
        p_d = p_s @ Tds[:3, :3].T + Tds[:3, 3]
        return np.concatenate([view.static_camera.project(p_s, False)[0], view.dynamic_camera.project(p_d, False)[0]])

    h = 1e-6
    J = np.zeros((2 * 2 * len(pts), 12))
    for k in range(12):
        d = np.zeros(12)
        d[k] = h
        J[:, k] = (corners(d[:6], d[6:]) - corners(-d[:6], -d[6:])).ravel() / (2 * h)
    H = J.T @ J / view.pixel_sigma**2
    expected = H[:6, :6] - H[:6, 6:] @ np.linalg.solve(H[6:, 6:], H[6:, :6])
    got = view_information(view, T_ds, pl)[0]
    assert np.allclose(got, expected, rtol=1e-5, atol=1e-6 * np.abs(expected).max())


@pytest.mark.parametrize("seed", range(6))
def test_candidate_poses_show_the_whole_board_to_both_cameras(seed: int) -> None:
    """Every pose the planner may propose (random family members, random joint angles in their range)
    shows every corner inside both images, is seen at most MAX_OBLIQUE_DEG off its normal by each
    camera and belongs to the T_ds it was made for; the facing pose (place_targets' at the preferred
    distance) is among them; at most the documented number per T_ds."""
    member = family_member(seed, None, 20)
    truth = member.truth
    assert truth.static_camera is not None and truth.dynamic_camera is not None
    rng = np.random.default_rng(seed)
    th = member.ranges[:, 0] + rng.uniform(size=(12, truth.n_joints)) * np.ptp(member.ranges, axis=1)
    T_ds = chain.T_ds_batch(truth.kin, th, truth.n_joints)
    near, far = member.scene.distance_range
    view = ViewModel(
        truth.static_camera, truth.dynamic_camera, member.scene.target.points, 0.5 * (near + far), (near, far), 0.3
    )
    pl, owner = candidate_poses(view, T_ds)
    assert len(owner) == len(pl.T_st) and (len(owner) == 0 or owner.max() < len(T_ds))
    per_view = 2 * (1 + len(POSE_TILTS_DEG) * POSE_TILT_DIRECTIONS)
    assert np.all(np.bincount(owner, minlength=len(T_ds)) <= per_view)
    again = placement_at(view, pl.T_st, T_ds[owner])  # recomputed from the poses alone
    assert again.full.all() and np.allclose(again.centre, pl.centre) and np.allclose(again.distance, pl.distance)
    assert np.allclose(np.linalg.norm(pl.centre, axis=1), pl.distance)
    for c, T in zip(pl.centre, pl.T_st, strict=True):
        assert np.allclose(T[:3, :3] @ view.target_points.mean(axis=0) + T[:3, 3], c)
        assert np.allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-12) and np.linalg.det(T[:3, :3]) > 0
    n = pl.T_st[:, :3, 2]
    c_d = -np.einsum("gji,gj->gi", T_ds[owner, :3, :3], T_ds[owner, :3, 3])
    for ray in (pl.centre, pl.centre - c_d):
        cosang = np.einsum("gi,gi->g", n, ray) / np.linalg.norm(ray, axis=1)
        assert np.all(cosang >= np.cos(np.radians(MAX_OBLIQUE_DEG)) - 1e-12)
    facing = place_targets(view, T_ds)
    full = np.flatnonzero(facing.full)
    assert full.size and all(np.any(owner == g) for g in full)  # a whole-board view has candidates
    found = [np.any(np.all(np.isclose(pl.T_st[owner == g], facing.T_st[g], atol=1e-12), axis=(1, 2))) for g in full]
    assert sum(found) >= 1  # (place_targets may have taken an intermediate distance, not a candidate's)


def test_a_view_with_no_corner_seen_has_no_information() -> None:
    """Joint angles where no target pose shows a corner to either camera (e.g. a held-out angle just
    beyond the range): zero information for that view, not a singular-matrix error (it crashed
    bench_plan.py's member 2); the other views are unchanged."""
    truth = true_kinematics(2)
    view = pinned_view()
    T_ds = np.stack([truth.T_ds(np.array(a) * DEG) for a in ([95.0, 5.0], [100.0, 0.0])])
    pl = place_targets(view, T_ds)
    both = view_information(view, T_ds, pl)
    blind = replace(pl, seen_s=pl.seen_s.copy(), seen_d=pl.seen_d.copy())
    blind.seen_s[1] = False
    blind.seen_d[1] = False
    got = view_information(view, T_ds, blind)
    assert np.all(got[1] == 0.0)
    assert np.allclose(got[0], both[0], rtol=1e-12, atol=0.0)


@pytest.mark.parametrize("L", [1, 2, 3])
def test_snapshot_information_matches_the_factor_jacobians(L: int) -> None:
    """J^T Lambda J through d T_ds / d(kin, theta) (factors.chain, batched) equals the information of a
    snapshot on (kin, theta) from the calibration factor's Jacobians (factors.calibration), target pose
    eliminated: the prediction uses the same model as the calibration."""
    truth = true_kinematics(L)
    view = pinned_view()
    theta = truth.T_ds  # noqa: F841 - the chain is the truth's
    th = np.array([95.0, 4.0, -80.0][:L]) * DEG if L < 3 else np.array([90.0, -90.0, 20.0]) * DEG
    pred = predict(
        KinematicsInformation(truth.kin, L, np.ones(len(truth.kin), bool), np.eye(len(truth.kin)), view, th[None]),
        th[None],
    )
    assert pred.placement.ok[0]
    Jx = np.concatenate([pred.J_kin[0], pred.J_theta[0]], axis=1)
    ours = Jx.T @ pred.view_info[0] @ Jx
    T_st = pred.placement.T_st[0]
    seen_s, seen_d = pred.placement.seen_s[0], pred.placement.seen_d[0]
    pts = view.target_points
    p_s = pts @ T_st[:3, :3].T + T_st[:3, 3]
    p_d = p_s @ truth.T_ds(th)[:3, :3].T + truth.T_ds(th)[:3, 3]
    meas = SnapshotMeasurements(
        pts[seen_s],
        view.static_camera.project(p_s[seen_s], False)[0],
        pts[seen_d],
        view.dynamic_camera.project(p_d[seen_d], False)[0],
    )
    layout = KinLayout(truth.kin, np.ones(len(truth.kin), bool), L)
    blocks = bundle_residuals(layout, truth.kin, th, T_st, meas, (view.static_camera, view.dynamic_camera), True)
    J = np.concatenate([np.concatenate([b[1][k].reshape(-1, b[1][k].shape[2]) for k in range(3)], 1) for b in blocks])
    J = J / view.pixel_sigma
    H = J.T @ J
    n = Jx.shape[1]
    expected = H[:n, :n] - H[:n, n:] @ np.linalg.solve(H[n:, n:], H[n:, :n])
    scale = np.sqrt(np.outer(np.diag(expected), np.diag(expected))) + 1e-300
    assert np.max(np.abs(ours - expected) / scale) < 1e-7


def test_tangent_jacobians_match_numerical_differentiation() -> None:
    """The batched T_ds Jacobians the predictions propagate through, against central differences of
    Log(T_ds(x)^-1 T_ds(x + dx))."""
    truth = true_kinematics(3)
    th = np.array([[88.0, -95.0, 30.0], [80.0, -75.0, -40.0]]) * DEG
    T, Jk, Jt = chain.d_T_ds_tangent_batch(truth.kin, th, 3)
    h = 1e-6
    for g in range(2):
        x = np.concatenate([truth.kin, th[g]])
        num = np.zeros((6, len(x)))
        for k in range(len(x)):
            d = np.zeros(len(x))
            d[k] = h
            Tp = chain.T_ds((x + d)[: len(truth.kin)], (x + d)[len(truth.kin) :], 3)
            Tm = chain.T_ds((x - d)[: len(truth.kin)], (x - d)[len(truth.kin) :], 3)
            num[:, k] = gtsam.Pose3(T[g]).localCoordinates(gtsam.Pose3(Tp)) - gtsam.Pose3(T[g]).localCoordinates(
                gtsam.Pose3(Tm)
            )
        num /= 2 * h
        assert np.allclose(np.concatenate([Jk[g], Jt[g]], axis=1), num, atol=1e-7)


@lru_cache(maxsize=4)
def _calibrated(L: int, mode: str, formulation: str) -> tuple[SimulatedCalibration, CalibrationResult]:
    sim = simulate_calibration(3, SceneConfig(n_joints=L, n_calibration=16, n_validation=0))
    data = sim.calibration_set
    if mode == "encoders":
        snaps = [
            Snapshot(s.timestamp_ns, s.static, s.dynamic, sim.joints_calibration[i])
            for i, s in enumerate(data.snapshots)
        ]
        data = CalibrationDataset(data.static_camera, data.dynamic_camera, data.target_points, snaps, data.source)
        sim.calibration_set = data
    return sim, calibrate(data, sim.initial, CalibrationOptions(mode=mode, formulation=formulation))


@pytest.mark.parametrize(
    ("L", "mode", "formulation"),
    [
        (1, "encoderless", "bundle"),
        (2, "encoderless", "bundle"),
        (2, "encoders", "bundle"),
        (2, "encoderless", "two_way"),
    ],
)
def test_kinematic_covariance_equals_the_calibrations(L: int, mode: str, formulation: str) -> None:
    """The pseudo-inverse of the rebuilt information (gauge-fixed, mean prior as a hard constraint,
    measured sigma) reproduces the 1-sigma the calibration reports from GTSAM's marginals."""
    sim, res = _calibrated(L, mode, formulation)
    info = kinematics_information(res, sim.calibration_set)
    ours, theirs = info.kin_std, res.calibration.kin_std
    assert theirs is not None
    have = np.isfinite(theirs)  # the observable entries (gauge-dependent ones are reported as NaN)
    assert have.sum() >= 2
    assert np.allclose(ours[have], theirs[have], rtol=1e-4)
    assert np.all(np.isnan(ours[~info.free]))


def test_information_file_round_trip(tmp_path) -> None:  # type: ignore[no-untyped-def]
    sim, res = _calibrated(2, "encoderless", "bundle")
    info = kinematics_information(res, sim.calibration_set)
    back = KinematicsInformation.load(info.save(tmp_path / "k.npz"))
    assert np.array_equal(back.kin, info.kin) and np.array_equal(back.information, info.information)
    assert back.view.static_camera == info.view.static_camera and back.view.pixel_sigma == info.view.pixel_sigma
    with pytest.raises(ValueError, match="not a kinematics information file"):
        (tmp_path / "bad.npz").write_bytes(b"nope")
        KinematicsInformation.load(tmp_path / "bad.npz")


def test_accuracy_over_range_grid_table_and_summary() -> None:
    sim, res = _calibrated(2, "encoderless", "bundle")
    info = kinematics_information(res, sim.calibration_set)
    acc = accuracy_over_range(info)
    pts, axes = range_grid(acc.ranges)
    assert len(acc.prediction.thetas) == 15 * 15 and np.allclose(axes[0][[0, -1]], acc.ranges[0])
    s = acc.summary()
    for mode in ("snapshot", "calibration", "kinematics"):
        assert s[mode]["worst_rotation_mrad"] >= s[mode]["mean_rotation_mrad"] > 0
    # the snapshot prediction adds the snapshot's own noise to the calibration's share
    assert s["snapshot"]["worst_rotation_mrad"] >= s["calibration"]["worst_rotation_mrad"]
    # the uncertainty grows away from the data: the worst point is on the border of the range
    worst = np.radians(s["kinematics"]["worst_translation_at_deg"])
    assert np.any(np.isclose(worst[:, None], acc.ranges, atol=1e-9))
    assert "kinematics alone" in accuracy_table(acc)


def _heldout_snapshot(
    sim: SimulatedCalibration, view: ViewModel, theta: np.ndarray, rng: np.random.Generator
) -> CalibrationDataset | None:
    """One snapshot at the true joint angles with the target where the planner would hold it, noisy corners."""
    T_ds = sim.truth.T_ds(theta)
    pl = place_targets(view, T_ds[None])
    if not pl.full[0]:
        return None
    T_st, pts, sig = pl.T_st[0], view.target_points, sim.config.pixel_sigma
    p_s = pts @ T_st[:3, :3].T + T_st[:3, 3]
    p_d = p_s @ T_ds[:3, :3].T + T_ds[:3, 3]
    ids = np.arange(len(pts))
    uv_s = view.static_camera.project(p_s, False)[0] + rng.normal(scale=sig, size=(len(pts), 2))
    uv_d = view.dynamic_camera.project(p_d, False)[0] + rng.normal(scale=sig, size=(len(pts), 2))
    snap = Snapshot(0, Observation(ids, uv_s), Observation(ids, uv_d), None)
    return CalibrationDataset(view.static_camera, view.dynamic_camera, pts, [snap], "held-out")


def heldout_nees(cases: tuple[tuple[int, int], ...], reps: int) -> tuple[np.ndarray, np.ndarray]:
    """Monte Carlo over calibrations of random mechanisms (family members ``(seed, L)``, corner level,
    0.3 px, 14 snapshots): per repetition one held-out snapshot at random joint angles in the calibrated
    range, not used by the calibration, its joint angles estimated with the kinematics held (as dcc-fg
    validate does); its T_ds error against the truth scored with the predicted snapshot covariance.
    Returns the NEES (6 dof) and the ratio squared rotation error / predicted rotation variance."""
    nees, rot_ratio = [], []
    for seed, L in cases:
        member = family_member(seed, L, 14)
        for rep in range(reps):
            rng = np.random.default_rng(1000 * seed + rep)
            sim = simulate_calibration(100 * seed + rep, member.scene, mechanism=(member.truth, member.ranges))
            lo, hi = sim.joints_calibration.min(axis=0), sim.joints_calibration.max(axis=0)
            data = sim.calibration_set
            res = calibrate(data, sim.truth, CalibrationOptions())
            info = kinematics_information(res, data)
            held, theta = None, lo
            for _ in range(50):
                theta = lo + rng.uniform(size=L) * (hi - lo)
                held = _heldout_snapshot(sim, info.view, theta, rng)
                if held is not None:
                    break
            assert held is not None
            opt = CalibrationOptions(mode="validate", pixel_sigma=info.view.pixel_sigma)
            th_hat = calibrate(held, res.calibration, opt).joint_angles[0]
            err = gtsam.Pose3(sim.truth.T_ds(theta)).localCoordinates(gtsam.Pose3(res.calibration.T_ds(th_hat)))
            cov = predict(info, th_hat[None]).snapshot[0]
            nees.append(float(err @ np.linalg.solve(cov, err)))
            rot_ratio.append(float(np.linalg.norm(err[:3]) ** 2 / np.trace(cov[:3, :3])))
    return np.array(nees), np.array(rot_ratio)


def _check_nees(nees: np.ndarray) -> None:
    """Independent repetitions: the mean NEES lies in chi2.ppf([0.025, 0.975], 6 N) / N."""
    n = len(nees)
    lo_b, hi_b = chi2.ppf([0.025, 0.975], 6 * n) / n
    print(f"held-out NEES: mean {nees.mean():.3f} over {n} (95% interval {lo_b:.3f}-{hi_b:.3f})")
    assert lo_b <= nees.mean() <= hi_b, (nees.mean(), lo_b, hi_b)


def test_predicted_sigma_agrees_with_true_errors_at_heldout_angles_fast() -> None:
    nees, _ = heldout_nees(((5, 2),), 8)
    _check_nees(nees)


@pytest.mark.slow
def test_predicted_sigma_agrees_with_true_errors_at_heldout_angles() -> None:
    """Three random mechanisms (L = 1, 2, 2), 12 calibrations each (see :func:`heldout_nees`)."""
    nees, rot_ratio = heldout_nees(((2, 1), (5, 2), (8, 2)), 12)
    _check_nees(nees)
    # the rotation 1-sigma alone (what the range figure shows) is neither over- nor under-stated
    print(f"rotation error^2 / predicted variance: mean {rot_ratio.mean():.3f}")
    assert 0.5 < rot_ratio.mean() < 1.6
