"""Health checks of a calibration / validation result (see :mod:`dcc_fg.util.health`).

A calibration that estimates the pixel noise from its own residuals cannot judge its model with
them: a wrong model (too few joints, wrong pairing, joint readings in degrees) just estimates a
large noise. The checks here compare the result with a **noise floor that does not depend on the
kinematic model**: a free 6-DOF target pose per camera per snapshot (per-image PnP, refined on the
pixel error). Its residual sum of squares ``SS_floor`` has ``2N - 6`` degrees of freedom per image
and measures the corner noise plus whatever the intrinsics cannot fit. Every DCC model is a
constrained version of it (bundle: one target pose per snapshot, ``T_ds(theta)`` from the chain),
so under a correct model the extra sum of squares ``SS_model - SS_floor`` is ``sigma^2 chi2(q)``
with ``q = 6K - K L_est - n_kin_free + n_gauge_offsets`` (the parameters the model saves).

Checks (name: statistic, threshold):

* ``residuals.static`` / ``residuals.dynamic``: F-test of the extra sum of squares of the camera
  against the camera's floor variance (``F = (dSS / q) / s2``, limit the F quantile at
  :data:`~dcc_fg.util.health.FALSE_ALARM_PROBABILITY` with ``(q, 2N - 6K)`` degrees of freedom; one
  camera's share of the extra sum is at most all of it, so ``q`` is conservative), combined with an
  effect size: the camera's RMS residual must also exceed :data:`RMS_RATIO_LIMIT` times the floor
  (a systematic error at least sqrt(3) times the noise itself: real intrinsics misfit and slight
  non-rigidity stay below it, a wrong model is far above it).
* ``residuals.snapshots``: an outlier test of each snapshot against the others: ``dSS_i / v_i``
  against the chi-square quantile at :data:`SNAPSHOT_ALPHA` with ``6 - L_est`` degrees of freedom,
  plus the same RMS ratio, where ``v_i`` is the largest of the pooled floor variance, the
  snapshot's own floor variance and the model's pooled residual variance (a misfit every snapshot
  shares is the per-camera test's job; real intrinsics misfit the periphery, which a free pose
  absorbs better than the rig can); the number of failing snapshots against the binomial quantile
  of ``K`` trials at ``SNAPSHOT_ALPHA`` (at the false-alarm probability). A **warning**: a few
  outlier snapshots (bad detections, a board at the edge of poor intrinsics) leave the result usable
  and are listed by stamp; a model error shared by the snapshots fails the per-camera tests.
* ``residuals.pixel_sigma`` (only when the user gave ``pixel_sigma``): the whitened sum of squares
  against ``chi2(dof)`` of the model, with the same RMS-ratio margin over the given sigma.
* ``convergence``: non-finite cost; zero iterations with a cost above the noise (the initial
  values written as the result); the iteration cap reached while one more iteration would still
  lower the cost by more than one unit of chi-square (``dSS / s2 > 1``).
* ``finite``: kinematics, joint angles, target poses, standard deviations and ``T_ds`` covariances
  are finite (NaN standard deviations only for unobservable parameters), variances non-negative.
* ``joint_angles``: estimated joint angles finite (their circular span is reported);
  ``encoders`` mode: readings beyond +-2 pi (joints.csv in degrees instead of radians).
* ``pairing.shift``: the PnP ``T_ds`` of every snapshot re-paired with the neighbouring dynamic
  image (shift +-1) and the chain re-fitted at the pose level (:func:`dcc_fg.init.pose_level_refine`,
  joint angles free); the given pairing fails when a shift lowers the pose-level sum of squares by
  more than the F quantile (equal degrees of freedom) and by more than ``RMS_RATIO_LIMIT**2``.
* ``pairing.stamps`` (when the reader reports them): the median stamp gap between paired images
  against a quarter of the frame period, the median gap of nearest-neighbour pairing of two
  free-running (unsynchronized) cameras.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy import stats

from dcc_fg.calibrate import CalibrationResult
from dcc_fg.calibration_graph import gauge_fixed_joint_offsets, gauge_fixed_kin
from dcc_fg.data import CalibrationDataset
from dcc_fg.degeneracy import EXACT
from dcc_fg.init import mean_pose, pose_level_refine, tangent_error
from dcc_fg.noise_floor import NoiseFloor, noise_floor
from dcc_fg.util.health import FALSE_ALARM_PROBABILITY, HealthCheck, HealthReport
from factors import chain

FloatArray = NDArray[np.float64]

#: Effect size of the residual tests: a model fails only if its RMS residual per axis also exceeds
#: the noise floor by this factor (its systematic error is then at least sqrt(3) times the noise).
RMS_RATIO_LIMIT = 2.0
#: Level of the per-snapshot test; the count of failing snapshots is tested against Binomial(K, alpha).
SNAPSHOT_ALPHA = 1e-3
#: Full turn: joint angles (or readings) spanning more than this are outside any physical range.
FULL_TURN = 2.0 * np.pi
#: Pose-level whitening of the pairing check, rad and m (the same for every pairing compared).
PAIRING_SIGMA_ROT, PAIRING_SIGMA_TRANS = 1e-3, 1e-3
#: The pairing check uses at most this many consecutive snapshot triples (evenly spread), so its
#: cost does not grow with the data set; its pose-level fits stop at this relative cost decrease
#: (the compared sums of squares differ by factors, not by parts in 1e4) or iteration count.
PAIRING_MAX_PAIRS, PAIRING_REL_TOL, PAIRING_ITERATIONS = 30, 1e-4, 15
CAMERAS = ("static", "dynamic")


# ------------------------------------------------------------------ helpers


def _culprits(result: CalibrationResult) -> str:
    """What a model that does not fit its images most likely got wrong, by mode."""
    mode, L = result.options.mode, result.calibration.n_joints
    if mode == "validate":
        return (
            "the calibration does not fit these images (a different gimbal or camera mount, moved cameras, "
            "other intrinsics) or the images are paired with the wrong partner"
        )
    if mode == "encoders":
        return (
            "the joint readings do not fit the images: joints.csv / JointState may be in degrees (radians needed), "
            f"offset in time from the images, or the mechanism has more joints than {L}"
        )
    return f"the mechanism probably has more joints than --joints {L}, or the images are paired with the wrong partner"


def _hint(result: CalibrationResult) -> str:
    if result.options.mode == "validate":
        return (
            "check that --calibration belongs to this rig, the pairing of the images (--sync-tolerance) and "
            "the intrinsics"
        )
    if result.options.mode == "encoders":
        return "check the joint-angle units (radians), their time stamps, --joints, the intrinsics (--camchain)"
    return "check --joints, the pairing of the images (time sync, --sync-tolerance), the intrinsics (--camchain)"


def _n_model_parameters(result: CalibrationResult) -> tuple[int, int]:
    """(free kinematic entries minus held mean joint angles, joint angles estimated per snapshot)."""
    L, mode = result.calibration.n_joints, result.options.mode
    if mode == "validate":
        return 0, L
    fixed = gauge_fixed_kin(L, mode)
    n_free = int((~fixed).sum()) - len(gauge_fixed_joint_offsets(L, mode))
    return n_free, (L if mode == "encoderless" else 0)


def _model_ss(result: CalibrationResult) -> FloatArray:
    """(K, 2) residual sums of squares of the model, px^2, columns [static, dynamic]."""
    return np.array(
        [
            [float(np.sum(a * a)), float(np.sum(b * b))]
            for a, b in zip(result.residuals_static, result.residuals_dynamic, strict=True)
        ]
    )


# ------------------------------------------------------------------ residual checks


def _camera_f_tests(result: CalibrationResult, floor: NoiseFloor) -> list[tuple[float, float, int, float, float]]:
    """Per camera: (F statistic, its limit, q, RMS residual px, floor RMS px) of the extra sum of squares."""
    K = floor.ss.shape[0]
    ss_model = _model_ss(result)
    n_kin, L_est = _n_model_parameters(result)
    q = max(6 * K - K * L_est - n_kin, 1)
    out = []
    for c in range(2):
        s2 = max(floor.variance(c), 1e-18)
        n_obs = 2 * int(floor.n[:, c].sum())
        d_ss = max(float(ss_model[:, c].sum() - floor.ss[:, c].sum()), 0.0)
        F_lim = float(stats.f.ppf(1.0 - FALSE_ALARM_PROBABILITY, q, max(floor.dof(c), 1)))
        out.append((d_ss / q / s2, F_lim, q, float(np.sqrt(ss_model[:, c].sum() / n_obs)), float(np.sqrt(s2))))
    return out


def residuals_significant(result: CalibrationResult, floor: NoiseFloor) -> bool:
    """Whether either camera's extra sum of squares over the floor is statistically significant
    (the F-test alone, without the effect-size margin), or not finite."""
    return any(not (F <= lim) for F, lim, *_ in _camera_f_tests(result, floor))


def residual_checks(result: CalibrationResult, floor: NoiseFloor) -> list[HealthCheck]:
    """``residuals.static`` / ``residuals.dynamic``, ``residuals.snapshots`` and (when the user gave
    ``pixel_sigma``) ``residuals.pixel_sigma``; see the module docstring."""
    out = []
    K = floor.ss.shape[0]
    ss_model = _model_ss(result)
    n_kin, L_est = _n_model_parameters(result)
    p = FALSE_ALARM_PROBABILITY
    s2 = np.array([max(floor.variance(c), 1e-18) for c in range(2)])
    for c, (cam, (F, F_lim, q, rms, rms_floor)) in enumerate(zip(CAMERAS, _camera_f_tests(result, floor), strict=True)):
        ratio = rms / rms_floor
        passed = not (F > F_lim and ratio > RMS_RATIO_LIMIT) and np.isfinite(rms)
        text = (
            f"residuals {rms:.3g} px RMS per axis in the {cam} camera for a {rms_floor:.3g} px noise floor "
            f"(PnP of each image): {ratio:.1f}x the floor (limit {RMS_RATIO_LIMIT:g}x), F = {F:.3g} "
            f"(limit {F_lim:.3g}, {q} and {floor.dof(c)} degrees of freedom)"
        )
        if not passed:
            text += f": {_culprits(result)}"
        out.append(
            HealthCheck(f"residuals.{cam}", bool(passed), text, "" if passed else _hint(result), ratio, RMS_RATIO_LIMIT)
        )

    # per snapshot, an outlier test against the rest: both cameras' extra sum of squares over the
    # larger of the floor variance (pooled or the snapshot's own) and the model's pooled variance
    # (the misfit all snapshots share is the per-camera test's job)
    own = floor.ss / np.maximum(2 * floor.n - 6, 1)
    model_var = ss_model.sum(axis=0) / np.maximum(2 * floor.n.sum(axis=0), 1)
    var_ref = np.maximum(np.maximum(own, s2[None, :]), model_var[None, :])
    q_i = (np.maximum(ss_model - floor.ss, 0.0) / var_ref).sum(axis=1)
    dof_i = max(6 - L_est, 1)
    chi_lim = float(stats.chi2.ppf(1.0 - SNAPSHOT_ALPHA, dof_i))
    ratio_i = np.sqrt(((ss_model / np.maximum(2 * floor.n, 1)) / var_ref).max(axis=1))
    bad = np.flatnonzero((q_i > chi_lim) & (ratio_i > RMS_RATIO_LIMIT))
    allowed = int(stats.binom.ppf(1.0 - p, K, SNAPSHOT_ALPHA))
    passed = len(bad) <= allowed
    text = (
        f"{len(bad)} of {K} snapshots fit far worse than their per-image PnP and the other snapshots "
        f"(chi-square at {SNAPSHOT_ALPHA:g} with {dof_i} degrees of freedom and over {RMS_RATIO_LIMIT:g}x their "
        f"reference; at most {allowed} expected)"
    )
    if not passed:
        worst = bad[np.argsort(-q_i[bad])][:5]
        stamps = ", ".join(f"{int(i)} (t={int(result.timestamps_ns[i])} ns, {ratio_i[i]:.1f}x)" for i in worst)
        text += f"; worst: {stamps}: {_culprits(result)}, or wrong corner detections in those images"
    out.append(
        HealthCheck(
            "residuals.snapshots",
            bool(passed),
            text,
            ""
            if passed
            else _hint(result) + "; drop the listed images if only a few fail; --corners common if "
            "the intrinsics misfit the image periphery",
            float(len(bad)),
            float(allowed),
            severity="warning",
        )
    )

    sigma = result.options.pixel_sigma
    if sigma is not None:
        n_obs = 2 * int(floor.n.sum())
        dof = max(n_obs - (6 * K + K * L_est + n_kin), 1)
        chi = float(ss_model.sum()) / sigma**2
        lim = float(stats.chi2.ppf(1.0 - p, dof))
        rms = float(np.sqrt(ss_model.sum() / n_obs))
        passed = not (chi > lim and rms > RMS_RATIO_LIMIT * sigma)
        text = (
            f"residuals {rms:.3g} px RMS per axis for the given pixel_sigma {sigma:g} px: chi-square {chi:.4g} "
            f"(limit {lim:.4g}, {dof} degrees of freedom)"
        )
        if not passed:
            floor_rms = float(np.sqrt(floor.ss.sum() / max(floor.dof(0) + floor.dof(1), 1)))
            if floor_rms > RMS_RATIO_LIMIT * sigma:
                text += (
                    f": the per-image PnP floor is {floor_rms:.3g} px too, so the corner noise is larger than "
                    "--pixel-sigma"
                )
            else:
                text += f": {_culprits(result)}"
        out.append(
            HealthCheck(
                "residuals.pixel_sigma",
                bool(passed),
                text,
                "" if passed else "give a --pixel-sigma that matches the detector, or omit it to estimate it",
                rms / sigma,
                RMS_RATIO_LIMIT,
            )
        )
    return out


# ------------------------------------------------------------------ solver and ranges


def convergence_check(result: CalibrationResult, floor: NoiseFloor) -> HealthCheck:
    """``convergence``: finite cost, at least one iteration unless already at the noise, and no
    iteration cap reached while still descending by more than one chi-square unit per iteration."""
    solver = result.extra.get("solver", {})
    sigma = float(solver.get("sigma", result.options.pixel_sigma or 1.0))
    s2 = float(floor.ss.sum() / max(floor.dof(0) + floor.dof(1), 1))
    s2 = max(s2, 1e-18)
    hint = "check the initial values (--gimbal, or --init auto) and the solver options (max_iterations)"
    if not (np.isfinite(result.final_error) and np.isfinite(result.initial_error)):
        return HealthCheck(
            "convergence",
            False,
            f"the cost is not finite (initial {result.initial_error}, final {result.final_error})",
            hint,
        )
    K = floor.ss.shape[0]
    n_kin, L_est = _n_model_parameters(result)
    n_obs = 2 * int(floor.n.sum())
    dof = max(n_obs - (6 * K + K * L_est + n_kin), 1)
    ss_final = 2.0 * result.final_error * sigma**2  # px^2
    chi_final = ss_final / s2
    at_noise = chi_final <= float(stats.chi2.ppf(1.0 - FALSE_ALARM_PROBABILITY, dof)) * RMS_RATIO_LIMIT**2
    if result.iterations == 0 and not at_noise:
        return HealthCheck(
            "convergence",
            False,
            f"Levenberg-Marquardt ran 0 iterations with a cost {chi_final:.4g} times the noise floor variance "
            f"({dof} degrees of freedom): the result is the initial guess",
            hint,
            0.0,
            1.0,
        )
    cap = int(solver.get("max_iterations", result.options.max_iterations))
    next_dec = float(solver.get("next_decrease", np.nan))
    remaining = 2.0 * next_dec * sigma**2 / s2 if np.isfinite(next_dec) else 0.0
    if result.iterations >= cap and remaining > 1.0:
        return HealthCheck(
            "convergence",
            False,
            f"Levenberg-Marquardt stopped on its cap of {cap} iterations while still lowering the cost by "
            f"{remaining:.3g} chi-square units per iteration (limit 1): not converged",
            "raise max_iterations, or start closer (--gimbal with better values, --init auto)",
            remaining,
            1.0,
        )
    return HealthCheck(
        "convergence",
        True,
        f"{result.iterations} iterations (cap {cap}); remaining decrease {remaining:.3g} chi-square units",
    )


def finite_check(result: CalibrationResult) -> HealthCheck:
    """``finite``: estimates, standard deviations and covariances are finite numbers (NaN standard
    deviations only where a parameter is unobservable or covariances are unavailable)."""
    bad = []
    cal = result.calibration
    if not np.all(np.isfinite(cal.kin)):
        bad.append(
            "kinematic parameters "
            + ", ".join(n for n, v in zip(cal.names, cal.kin, strict=True) if not np.isfinite(v))
        )
    if not np.all(np.isfinite(result.joint_angles)):
        bad.append("joint angles")
    if not np.all(np.isfinite(result.T_st)):
        bad.append("target poses")
    if result.extra.get("covariance", "ok") == "ok":
        if result.options.mode != "validate" and cal.kin_std is not None and cal.observable is not None:
            fixed = cal.gauge_fixed if cal.gauge_fixed is not None else np.zeros(len(cal.kin), dtype=bool)
            need = cal.observable & ~fixed
            std = np.asarray(cal.kin_std)
            if not np.all(np.isfinite(std[need])) or np.any(std[np.isfinite(std)] < 0):
                bad.append("standard deviations of observable kinematic parameters")
        if result.options.mode != "encoders" and result.joint_angle_std.size:
            if not np.all(np.isfinite(result.joint_angle_std)):
                bad.append("joint-angle standard deviations")
        cov = result.T_ds_covariances
        if cov is not None and len(cov):
            diag = np.einsum("kii->ki", cov)
            if not np.all(np.isfinite(cov)) or np.any(diag < 0):
                bad.append("T_ds covariances (non-finite or negative variances)")
    if bad:
        return HealthCheck(
            "finite",
            False,
            "non-finite or negative values in: " + "; ".join(bad),
            "the problem is numerically degenerate: check the initial values and that every joint moves",
        )
    return HealthCheck("finite", True, "estimates, standard deviations and covariances are finite")


def circular_span(theta: FloatArray) -> FloatArray:
    """Per joint (columns of ``theta`` (K, L), rad), the length of the shortest arc that holds every
    angle modulo 2 pi (2 pi minus the largest gap between neighbouring wrapped angles): an estimate of
    -3.2 rad and one of 3.1 rad are 0.02 rad apart on the joint, not 6.3."""
    wrapped = np.sort(np.mod(theta, FULL_TURN), axis=0)
    gaps = np.diff(np.vstack([wrapped, wrapped[:1] + FULL_TURN]), axis=0)
    return FULL_TURN - gaps.max(axis=0)


def joint_angle_checks(result: CalibrationResult, data: CalibrationDataset) -> list[HealthCheck]:
    """``joint_angles``: estimated angles finite (their span is reported as the shortest arc holding them:
    a revolute joint's angles are defined modulo a turn); ``encoders`` mode: readings within +-2 pi
    (larger values are degrees, not radians)."""
    out = []
    th = np.asarray(result.joint_angles, float)
    L = result.calibration.n_joints
    if L == 0 or th.size == 0:
        return out
    if result.options.mode == "encoders":
        readings = np.array([np.asarray(s.joints, float) for s in data.snapshots if s.joints is not None])
        biggest = float(np.max(np.abs(readings))) if readings.size else 0.0
        passed = biggest <= FULL_TURN
        text = f"joint readings within +-{biggest:.4g} (limit {FULL_TURN:.4g} rad)"
        if not passed:
            text = (
                f"joint readings reach {biggest:.4g}, beyond a full turn ({FULL_TURN:.4g} rad): joints.csv / "
                "JointState is probably in degrees, but radians are needed"
            )
        out.append(
            HealthCheck(
                "joint_angles.readings",
                bool(passed),
                text,
                "" if passed else "convert the joint readings to radians (multiply degrees by pi/180)",
                biggest,
                FULL_TURN,
            )
        )
    span = circular_span(th) if np.all(np.isfinite(th)) else np.full(L, np.inf)
    worst = int(np.argmax(span))
    passed = bool(np.isfinite(span[worst]))
    text = (
        f"joint {worst + 1} covers {span[worst]:.4g} rad (the shortest arc holding every estimate; angles that "
        "differ by whole turns are the same)"
    )
    if not passed:
        text = "non-finite joint angles: the model probably does not fit the mechanism"
    out.append(
        HealthCheck(
            "joint_angles.range",
            passed,
            text,
            "" if passed else "check --joints and the initial joint angles",
            float(span[worst]),
            FULL_TURN,
        )
    )
    return out


# ------------------------------------------------------------------ pairing


def _pose_level_ss(
    result: CalibrationResult, T_ds: FloatArray, thetas0: FloatArray, cov: FloatArray
) -> tuple[float, int]:
    """Whitened pose-level sum of squares of the chain re-fitted to ``T_ds`` (K', 4, 4) and its
    degrees of freedom. L = 0: one constant transform (the mean), each error ``Log(T_ds_i mean^-1)``
    whitened by its PnP covariance ``cov`` (K', 6, 6); L >= 1: :func:`dcc_fg.init.pose_level_refine`
    with joint angles free and the kinematics from the result as the start (fixed 1 mrad / 1 mm
    whitening)."""
    L, n = result.calibration.n_joints, len(T_ds)
    if L == 0:
        mean = mean_pose(T_ds)
        e = np.array([tangent_error(T @ chain.inv_se3(mean), np.eye(4)) for T in T_ds])
        white = np.linalg.solve(cov, e[:, :, None])[:, :, 0]
        return float(np.sum(e * white)), 6 * n - 6
    validating = result.options.mode == "validate"
    fixed = np.ones(chain.n_kin(L), dtype=bool) if validating else gauge_fixed_kin(L, "encoderless")
    offsets = [] if validating else gauge_fixed_joint_offsets(L, "encoderless")
    _, _, rms = pose_level_refine(
        result.calibration.kin,
        L,
        T_ds,
        thetas0,
        ~fixed,
        offsets,
        True,
        PAIRING_SIGMA_ROT,
        PAIRING_SIGMA_TRANS,
        PAIRING_ITERATIONS,
        PAIRING_REL_TOL,
    )
    n_par = int((~fixed).sum()) - len(offsets) + n * L
    return float(rms**2 * 6 * n), max(6 * n - n_par, 1)


def pairing_shift_check(result: CalibrationResult, floor: NoiseFloor) -> HealthCheck | None:
    """``pairing.shift``: would pairing each static image with the neighbouring dynamic image fit the
    chain much better than the given pairing? (Module docstring.) None when too few snapshots."""
    K = floor.T_st.shape[0]
    L = result.calibration.n_joints
    idx = np.arange(1, K - 1)
    if len(idx) > PAIRING_MAX_PAIRS:
        idx = np.unique(np.linspace(1, K - 2, PAIRING_MAX_PAIRS).round().astype(np.int64))
    if len(idx) * (6 - L) < 12 + 3 * L:
        return None
    thetas = np.asarray(result.joint_angles, float).reshape(K, L)
    ss: dict[int, float] = {}
    dof = 1
    for shift in (0, 1, -1):
        T_ds = floor.T_dt[idx + shift] @ np.linalg.inv(floor.T_st[idx])
        cov = floor.T_ds_covariance(idx, idx + shift)
        ss[shift], dof = _pose_level_ss(result, T_ds, thetas[idx + shift], cov)
    best = min((1, -1), key=lambda h: ss[h])
    gain = ss[0] / max(ss[best], 1e-300)
    limit = max(float(stats.f.ppf(1.0 - FALSE_ALARM_PROBABILITY, dof, dof)), RMS_RATIO_LIMIT**2)
    passed = not gain > limit
    text = (
        f"pairing each static image with the dynamic image {best:+d} snapshot away fits {gain:.3g} times "
        f"{'better' if gain >= 1 else 'as well'} at the pose level (limit {limit:.3g})"
    )
    if not passed:
        text = (
            f"the static and dynamic images seem paired with the wrong partner (shifting by one fits {gain:.3g} times "
            f"better, limit {limit:.3g}): the cameras' stamps are probably offset by one frame period"
        )
    return HealthCheck(
        "pairing.shift",
        bool(passed),
        text,
        "" if passed else "check the time sync of the cameras / --sync-tolerance",
        gain,
        limit,
    )


def _finite_ms(d: dict[str, Any], key: str) -> float | None:
    """``d[key]`` as a float when it is a finite number (the reader's pairing statistics, ms)."""
    value = d.get(key)
    if isinstance(value, int | float) and not isinstance(value, bool) and np.isfinite(value):
        return float(value)
    return None


def pairing_stamp_check(reader_report: dict[str, Any] | None) -> HealthCheck | None:
    """``pairing.stamps``: the median stamp gap of the pairs against a quarter of the frame period
    (the median gap of nearest-neighbour pairing of free-running cameras); None without the numbers."""
    pairing = (reader_report or {}).get("pairing")
    if not isinstance(pairing, dict):
        return None
    gap = _finite_ms(pairing, "gap_median_ms")
    periods = [p for p in (_finite_ms(pairing, "period_static_ms"), _finite_ms(pairing, "period_dynamic_ms")) if p]
    period = min(periods) if periods else None
    if gap is None or period is None or not period > 0:
        return None
    limit = 0.25 * period
    passed = gap <= limit
    text = f"median stamp gap of the pairs {gap:.3g} ms for a frame period of {period:.3g} ms (limit {limit:.3g} ms)"
    if not passed:
        text += ": the cameras do not look synchronized, so the pairs show the target at different times"
    return HealthCheck(
        "pairing.stamps",
        bool(passed),
        text,
        ""
        if passed
        else "synchronize the cameras (hardware trigger) or hold the target still per snapshot; check --sync-tolerance",
        gap,
        limit,
    )


# ------------------------------------------------------------------ all of them


#: Measured on the random mechanism family (benchmarks/bench_random_mechanisms.py, L = 3, 50 members,
#: 25 snapshots, with the held-direction polish): with the linearized covariance alone the 40 members
#: with held directions had a mean T_ds NEES of 9.2 for 6 dof (7.1 without); with the global search's
#: covering of the other solutions that fit as well (dcc_fg.global_fit.covering_covariance) 6.2 (6.4
#: without), the worst members 9.9 and 10.1. After the model selection (dcc_fg.model_selection, same
#: study, --joints 2,3): the 30 members with held directions that kept the general model 6.68 (worst
#: 10.1), the 10 exactly intersecting ones that kept the exact model 6.52 (worst 13.6, member 36).
OPTIMISTIC_T_DS_STD = (
    "the reported T_ds 1-sigma is a linearization that is optimistic on such nearly degenerate mechanisms "
    "(random 3-joint family: mean NEES 9.2 for 6 dof, the actual error about 1.25x the reported 1-sigma); "
    "do not rely on it below that factor, or calibrate with the global search, whose 1-sigma covers the other "
    "solutions that fit as well"
)
COVERED_T_DS_STD = (
    "the reported T_ds 1-sigma includes the spread of the other solutions that fit the images as well "
    "(random 3-joint family, 30 members with held directions: mean NEES 6.7 for 6 dof, consistent on average; "
    "single members up to 10, the actual error up to 1.3x the reported 1-sigma)"
)

EXACT_MODEL_T_DS_STD = (
    "the axes intersect within what the images resolve, so the exactly intersecting model was kept "
    "(dcc_fg.model_selection: free link offsets fit only {gain:.3g} chi2 better, threshold {threshold:.3g}); in "
    "it these directions are exactly undetermined and leave every T_ds unchanged, so the reported T_ds 1-sigma "
    "is that model's own (10 exactly intersecting 3-joint members of the random family: mean NEES 6.5 for 6 dof, "
    "single members up to 13.6, the actual error up to 1.5x the reported 1-sigma)"
)


def _t_ds_std_text(result: CalibrationResult) -> str:
    """Which T_ds covariance a result with held directions reports (the health message's second half)."""
    sel = result.extra.get("model_selection") or {}
    if sel.get("model") == EXACT:
        return EXACT_MODEL_T_DS_STD.format(gain=sel["gain_chi2"], threshold=sel["threshold_chi2"])
    return COVERED_T_DS_STD if "global" in result.extra else OPTIMISTIC_T_DS_STD


def determination_checks(result: CalibrationResult) -> list[HealthCheck]:
    """Warnings about what the data did not decide: kinematic directions held by a weak prior
    (:mod:`dcc_fg.degeneracy`) and another minimum that fits as well (:mod:`dcc_fg.global_fit`)."""
    out = []
    held = result.extra.get("held_by_prior") or []
    if held:
        out.append(
            HealthCheck(
                "determined.kinematics",
                False,
                (result.extra.get("held_by_prior_text") or f"{len(held)} kinematic direction(s) held by a weak prior")
                + "; "
                + _t_ds_std_text(result),
                "per-snapshot T_ds are determined by the images; for the kinematics themselves give --nominal (if "
                "the gimbal's geometry is known) or record more snapshots over wider joint ranges",
                float(len(held)),
                0.0,
                severity="warning",
            )
        )
    amb = (result.extra.get("global") or {}).get("ambiguity")
    if amb:
        out.append(
            HealthCheck(
                "determined.unique",
                False,
                f"another solution (start '{amb.get('start')}') fits the images as well (cost difference "
                f"{amb['cost_difference_chi2']:.3g} < chi-square threshold {amb['threshold_chi2']:.3g}) and gives T_ds "
                f"{amb['rotation_rms_rad'] * 1e3:.3g} mrad / {amb['translation_rms_m'] * 1e3:.3g} mm (RMS) apart; the "
                "reported T_ds covariances include this difference",
                "record more snapshots over wider joint ranges, or give --nominal for a gimbal of known geometry",
                float(amb["rotation_rms_rad"]),
                0.0,
                severity="warning",
            )
        )
    return out


def calibration_health(
    result: CalibrationResult, data: CalibrationDataset, reader_report: dict[str, Any] | None = None
) -> HealthReport:
    """Every health check of ``result`` (estimated from ``data``; ``reader_report``: the reader's
    report of :func:`dcc_fg.commands.calibrate.load_calibration_data`, whose ``pairing`` block is used
    when present). The report's subject is ``calibration`` or ``validation``."""
    report = HealthReport("validation" if result.options.mode == "validate" else "calibration")
    report.add(finite_check(result))
    floor = result.extra.get("noise_floor")  # computed by calibrate from the same PnP poses, if it weighted by it
    if not isinstance(floor, NoiseFloor) or floor.ss.shape[0] != len(data.snapshots):
        floor = noise_floor(data, result.extra.get("pnp_T_st"), result.extra.get("pnp_T_dt"))
    report.extend(residual_checks(result, floor))
    report.add(convergence_check(result, floor))
    report.extend(joint_angle_checks(result, data))
    if not residuals_significant(result, floor):
        report.add(
            HealthCheck(
                "pairing.shift",
                True,
                "not run: the residuals are at the noise floor in both cameras (F-test passed), so no other pairing "
                "can fit much better",
            )
        )
    elif np.all(np.isfinite(result.joint_angles)) and np.all(np.isfinite(result.calibration.kin)):
        shift = pairing_shift_check(result, floor)
        if shift is not None:
            report.add(shift)
    stamps = pairing_stamp_check(reader_report)
    if stamps is not None:
        report.add(stamps)
    report.extend(determination_checks(result))
    return report
