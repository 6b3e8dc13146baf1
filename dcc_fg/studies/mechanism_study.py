"""Issue 14's proof on a randomized family of mechanisms: global minimum, accuracy, honest covariance.

One *member* of the family (``seed``, ``L`` joints, ``K`` snapshots) goes through the real user path:

1. render: :func:`dcc_fg.sim.write_dataset.write_calibration_dataset` writes the image folder,
   ``camchain.yaml``, ``target.yaml`` and ``ground_truth.yaml`` of the random mechanism;
2. detect: :func:`dcc_fg.sources.dataset.load_dataset` with the reader defaults of ``dcc-fg
   calibrate`` (pairing tolerance 5 ms, >= 8 common corners; the study sits below the commands
   layer, so it calls the loader that ``load_calibration_data`` wraps). Snapshots whose target is not
   detected in both images are dropped; the kept ones are matched to the truth by timestamp;
3. calibrate twice with ``CalibrationOptions()`` (``pixel_sigma=None``: both whitened with the
   same sigma, so their costs compare): the system under test
   :func:`dcc_fg.global_fit.calibrate_global` (automatic start) and
   :func:`dcc_fg.calibrate.calibrate` started at the true kinematics and true joint angles, solved on
   with the projected solve when it holds directions (:func:`truth_start`; the search compares the
   bottoms of its valleys, so the reference is a bottom too);
4. score on gauge-invariant quantities (:mod:`dcc_fg.studies.calibration_accuracy`): per-snapshot
   ``T_ds`` errors ``[omega (rad), v (m)]``, their Cramer-Rao bound and the NEES of the reported
   ``T_ds`` covariances.

Criteria (issue 14), per L over the family:

* *global minimum*: ``cost_auto <= cost_truth * (1 + 1e-6) + 1e-9`` with the data costs (GTSAM's
  0.5 * sum of whitened squared pixel residuals, :func:`dcc_fg.global_fit.data_cost`; the weak priors
  on held directions sit at each start's own values, so the solvers' final errors, priors included,
  do not compare), i.e. the automatic result is within 1e-6 relative of the best of both starts
  (``strict_success``), or both runs give the same ``T_ds`` for every snapshot within 0.1 sigma
  (``SAME_T_DS_M2``: weakly determined directions held by weak priors at each start's own values
  end a few 1e-6 apart in cost with the same answer); both counts are reported;
  a failed automatic run is a failure; when only the start at the truth fails, the comparison has
  no reference and the record says so (``reference = "auto only"``). ``cost_auto`` is the data cost
  of the search's best solution of the general model (``search_data_cost``; the truth start fits that
  model too): when :mod:`dcc_fg.model_selection` then keeps the exactly intersecting model (a
  constrained model, whose cost is higher by construction), the criterion still judges the search,
  and accuracy and NEES judge the answer the user gets;
* *accuracy*: pooled RMS error / pooled RMS CRB <= 1.5 for rotation and translation over the
  members whose geometry is observable (finite, positive bound on T_ds; directions held by a weak
  prior, ``held_by_prior``, do not exclude a member: T_ds stays estimable) that reached the global
  minimum;
  the CRB uses the detector's corner noise measured against the true projections, per camera
  (``sigma_detector_camera_px``: the cameras differ in resolution and blur, so their detections
  differ in noise, by up to ~1.5x); the bound with the truth start's a-posteriori sigmas is reported too;
* *NEES*: each member's mean NEES over its snapshots (6 dof) is treated as ONE chi-square(6) draw
  (its snapshots share the kinematics, so their errors are not independent); the mean over M
  members then has the 95 % interval ``chi2.ppf([0.025, 0.975], 6 M) / M`` (first-order check).
  The interval that would hold for independent snapshots (``chi2(6 N) / N`` over all N snapshots)
  is reported for comparison only.
"""

from __future__ import annotations

import math
import time
import traceback
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.stats import chi2

from dcc_fg.calibrate import (
    CalibrationOptions,
    CalibrationResult,
    calibrate,
    continue_projected,
    corner_sigma,
    stopped_on_cap,
)
from dcc_fg.calibration_health import calibration_health
from dcc_fg.data import CalibrationDataset, with_joints
from dcc_fg.degeneracy import EXACT
from dcc_fg.global_fit import FURTHER_STEPS, T_ds_differences, calibrate_global, data_cost
from dcc_fg.io.outputs import plain
from dcc_fg.model import GimbalCalibration
from dcc_fg.sim.write_dataset import CalibrationSimSpec, load_ground_truth, write_calibration_dataset
from dcc_fg.sources.dataset import load_dataset
from dcc_fg.studies.calibration_accuracy import T_ds_errors, cramer_rao_bound, nees_T_ds
from dcc_fg.util.errors import EstimatorError

FloatArray = NDArray[np.float64]

#: Relative tolerance of the global-minimum criterion (issue 14).
COST_REL_TOL = 1e-6
#: Absolute slack of the cost comparison (round-off of GTSAM's error on costs of order 1e2-1e4).
COST_ABS_TOL = 1e-9
#: Two runs whose per-snapshot T_ds agree within 0.1 sigma (Mahalanobis^2 < 0.01 under the reported
#: covariance, every snapshot) reached the same minimum for every practical purpose, even when their
#: costs differ by more than COST_REL_TOL (flat, weakly determined directions held by the weak priors
#: of dcc_fg.degeneracy at each start's own values end a few 1e-6 apart in cost).
SAME_T_DS_M2 = 0.01
#: Largest pooled error / CRB ratio (issue 14).
CRB_RATIO_MAX = 1.5
#: Members that must reach the global minimum: 49 of 50.
SUCCESS_FRACTION = 49.0 / 50.0
#: Reader defaults of ``dcc-fg calibrate`` (dcc_fg.commands.calibrate.ReaderOptions).
SYNC_TOLERANCE_NS = 5_000_000
MIN_COMMON_POINTS = 8
#: Degrees of freedom of one T_ds error.
T_DS_DOF = 6


# ------------------------------------------------------------------ rendering


@dataclass(frozen=True)
class RenderedMember:
    """The files of one rendered member and what it is.

    Attributes:
        data: image folder (``cam0/``, ``cam1/``); camchain, target, ground_truth: the YAML files.
        description: the family's description of the member (``ground_truth.yaml``'s ``mechanism``:
            links m, twists deg, requested and achieved joint ranges deg, target, cameras, distances).
        render_time_s: wall time of simulating, rendering and writing the data set.
    """

    data: Path
    camchain: Path
    target: Path
    ground_truth: Path
    description: dict[str, Any]
    render_time_s: float


def render_member(seed: int, n_joints: int, n_snapshots: int, out_dir: Path) -> RenderedMember:
    """Render member ``seed`` of the family (:mod:`dcc_fg.sim.mechanism_family`) with ``n_joints``
    joints and ``n_snapshots`` image pairs into ``out_dir`` as ``dcc-fg simulate calibration
    --random-mechanism SEED --joints L --snapshots K --format folder --seed SEED`` does."""
    t0 = time.perf_counter()
    spec = CalibrationSimSpec(
        fmt="folder", seed=seed, n_snapshots=n_snapshots, n_joints=n_joints, random_mechanism=seed
    )
    out = write_calibration_dataset(out_dir, spec)
    elapsed = time.perf_counter() - t0
    raw = load_ground_truth(out.ground_truth).raw
    return RenderedMember(out.data, out.camchain, out.target, out.ground_truth, dict(raw.get("mechanism", {})), elapsed)


# ------------------------------------------------------------------ one member


@dataclass
class RunOutcome:
    """One calibration run of a member: its cost, time and, if it failed, why."""

    final_error: float = math.nan  # the solver's final error, priors included
    data_cost: float = math.nan  # pixel residuals only (dcc_fg.global_fit.data_cost)
    time_s: float = math.nan
    iterations: int = 0
    variance_factor: float = math.nan
    error: str = ""  # exception type and message of a refused or failed run; "" when it ran
    healthy: bool | None = None
    health_failures: list[str] = field(default_factory=list)


@dataclass
class MechanismRecord:
    """Everything the study measured on one member of the family.

    Units: errors and bounds in rad (rotation) and m (translation), RMS over the snapshots of the
    norm of each 3-vector; costs are GTSAM's 0.5 * sum of squared whitened residuals (sigma 1 px
    whitening scaled as ``calibrate`` does with ``pixel_sigma=None``); times in s; sigmas in px.
    """

    seed: int
    n_joints: int
    n_snapshots_requested: int
    description: dict[str, Any] = field(default_factory=dict)
    n_snapshots: int = 0  # used (target detected in both images)
    render_time_s: float = math.nan
    cpu_time_s: float = math.nan  # CPU time of this process for the whole member (the machine may be shared)
    detect_time_s: float = math.nan
    auto: RunOutcome = field(default_factory=RunOutcome)
    truth_start: RunOutcome = field(default_factory=RunOutcome)
    reference: str = ""  # "best of both" or "auto only" (the truth start failed)
    cost_rel_excess: float = math.nan  # (cost_auto - best) / best
    success: bool = False  # global-minimum criterion: strict cost criterion or the same T_ds as the best start
    strict_success: bool = False  # the cost criterion alone (final cost within 1e-6 relative of the best)
    # largest Mahalanobis^2 over the snapshots of T_ds(auto) - T_ds(truth start) under the automatic
    # result's reported T_ds covariance: < SAME_T_DS_M2 means both runs give the same answer
    T_ds_difference_m2_max: float = math.nan
    observable: bool = False  # the bound on T_ds is finite and positive (T_ds estimable from the data)
    rotation_rms: float = math.nan
    translation_rms: float = math.nan
    sigma_detector_px: float = math.nan  # corner noise against the true projections (RMS per axis, both cameras)
    sigma_detector_camera_px: Any = None  # [static, dynamic]: the same per camera (the bound uses these)
    sigma_posterior_px: float = math.nan  # a-posteriori sigma of the truth start (both cameras pooled)
    # (SS at the true parameters - SS at the truth start's minimum), whitened by each camera's a-posteriori
    # sigma: ~ chi2(truth_excess_dof)
    # when the detected corners are unbiased; far beyond it, the data disagree with the ground truth
    # (renderer / detector bias), which no estimator can fix
    truth_excess_chi2: float = math.nan
    truth_excess_dof: int = 0
    crb_rotation_rms: float = math.nan  # with sigma_detector_camera_px
    crb_translation_rms: float = math.nan
    crb_pooled_rotation_rms: float = math.nan  # with sigma_detector_px for both cameras (before per-camera bounds)
    crb_pooled_translation_rms: float = math.nan
    crb_posterior_rotation_rms: float = math.nan  # with the truth start's a-posteriori sigma of each camera
    crb_posterior_translation_rms: float = math.nan
    nees_mean: float = math.nan  # mean over snapshots of the per-snapshot T_ds NEES
    nees_dof: int = T_DS_DOF
    T_ds_std_rotation_median: float = math.nan  # reported 1-sigma (root trace of the 3x3 block)
    T_ds_std_translation_median: float = math.nan
    global_info: Any = None  # result.extra["global"] of the automatic run, if any
    held_by_prior: Any = None  # result.extra["held_by_prior"] of the automatic run, if any
    model_selection: Any = None  # result.extra["model_selection"] of the automatic run, if any
    # data cost of the automatic search's best general-model solution (= auto.data_cost unless the
    # exactly intersecting model was kept): what the global-minimum criterion compares
    search_data_cost: float = math.nan
    failure: str = ""  # cause when not a clean success (empty otherwise)

    @property
    def rotation_ratio(self) -> float:
        return self.rotation_rms / self.crb_rotation_rms if self.crb_rotation_rms > 0 else math.nan

    @property
    def translation_ratio(self) -> float:
        return self.translation_rms / self.crb_translation_rms if self.crb_translation_rms > 0 else math.nan

    @property
    def total_time_s(self) -> float:
        return float(np.nansum([self.render_time_s, self.detect_time_s, self.auto.time_s, self.truth_start.time_s]))

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-able mapping (non-finite numbers as None), with the ratios."""
        d = asdict(self)
        d["rotation_ratio"] = self.rotation_ratio
        d["translation_ratio"] = self.translation_ratio
        d["total_time_s"] = self.total_time_s
        return plain(d)

    @staticmethod
    def from_dict(d: dict[str, Any]) -> MechanismRecord:
        """Inverse of :meth:`to_dict` (None -> NaN for the float fields)."""
        d = {k: v for k, v in d.items() if k not in ("rotation_ratio", "translation_ratio", "total_time_s")}
        d.setdefault("strict_success", d.get("success", False))  # records written before both counts existed
        runs = {k: RunOutcome(**_nan_floats(d.pop(k), RunOutcome)) for k in ("auto", "truth_start")}
        return MechanismRecord(**_nan_floats(d, MechanismRecord), **runs)


def _nan_floats(d: dict[str, Any], cls: type) -> dict[str, Any]:
    floats = {k for k, f in cls.__dataclass_fields__.items() if f.type == "float"}
    return {k: (math.nan if v is None and k in floats else v) for k, v in d.items()}


def _error_text(exc: BaseException) -> str:
    return f"{type(exc).__name__}: {' '.join(str(exc).split())}"


def truth_residuals(
    data: CalibrationDataset, truth: GimbalCalibration, thetas: FloatArray, T_st: FloatArray
) -> tuple[FloatArray, NDArray[np.int64]]:
    """Per camera ``[static, dynamic]``: sum of squares (px^2) and number of values (2 per corner) of
    the detected corners minus their true projections (``T_st``: true target -> static camera poses,
    ``T_ds(thetas)`` the true static -> dynamic transforms)."""
    sq, n = np.zeros(2), np.zeros(2, dtype=np.int64)
    for s, th, T in zip(data.snapshots, thetas, T_st, strict=True):
        pairs = ((s.static, data.static_camera, T), (s.dynamic, data.dynamic_camera, truth.T_ds(th) @ T))
        for c, (obs, cam, T_ct) in enumerate(pairs):
            if len(obs.ids) == 0:
                continue
            p = data.target_points[obs.ids] @ T_ct[:3, :3].T + T_ct[:3, 3]
            uv, _ = cam.project(p, jacobian=False)
            sq[c] += float(np.sum((obs.pixels - uv) ** 2))
            n[c] += 2 * len(obs.ids)
    return sq, n


def truth_start(
    data: CalibrationDataset, truth: GimbalCalibration, thetas: FloatArray, opt: CalibrationOptions
) -> CalibrationResult:
    """The reference solution: :func:`dcc_fg.calibrate.calibrate` started at the true kinematics and joint
    angles (rad), solved on to the bottom of its valley with the projected solve when it holds directions
    by prior (:func:`dcc_fg.calibrate.continue_projected`), and on by ``FURTHER_STEPS`` more when that
    stopped on its cap, as the search does with its lowest solutions and its answer: bottoms are compared
    with bottoms."""
    res = calibrate(with_joints(data, thetas), truth, opt)
    if res.extra.get("held_by_prior") and not opt.project_held:
        res = continue_projected(data, res) or res
        if stopped_on_cap(res):
            res = continue_projected(data, res, FURTHER_STEPS) or res
    return res


def _run(fn: Any, data: CalibrationDataset, out: RunOutcome, health: bool) -> CalibrationResult | None:
    """Run ``fn()`` (a calibration), fill ``out``; a refusal or numerical failure is recorded, not raised."""
    t0 = time.perf_counter()
    try:
        res: CalibrationResult = fn()
    except (EstimatorError, ValueError, RuntimeError, ArithmeticError, np.linalg.LinAlgError) as exc:
        out.time_s = time.perf_counter() - t0
        out.error = _error_text(exc)
        return None
    out.time_s = time.perf_counter() - t0
    out.final_error = float(res.final_error)
    out.data_cost = data_cost(res)
    out.iterations = int(res.iterations)
    out.variance_factor = float(res.variance_factor)
    if health:
        try:
            report = calibration_health(res, data)
            out.healthy = report.healthy
            out.health_failures = [f"{c.name}: {c.message}" for c in report.failures]
        except (EstimatorError, ValueError, RuntimeError, ArithmeticError, np.linalg.LinAlgError) as exc:
            out.healthy = False
            out.health_failures = [f"health check crashed: {_error_text(exc)}"]
    return res


def study_member(
    seed: int,
    n_joints: int,
    n_snapshots: int,
    work_dir: str | Path,
    options: CalibrationOptions | None = None,
) -> MechanismRecord:
    """Render, detect, calibrate (automatic and truth starts) and score one member of the family.

    Never raises for a failed calibration: a refused or failed run, an unhealthy result, a missed
    global minimum are recorded in :attr:`MechanismRecord.failure`. ``work_dir`` receives the
    rendered data set.
    """
    opt = options or CalibrationOptions()
    rec = MechanismRecord(seed, n_joints, n_snapshots)
    cpu0 = time.process_time()
    try:
        _study(rec, Path(work_dir), opt)
    except Exception as exc:  # noqa: BLE001 - a study crash is itself a finding, recorded with its traceback
        tb = traceback.extract_tb(exc.__traceback__)[-1]
        rec.failure = (rec.failure + "; " if rec.failure else "") + (
            f"study crashed: {_error_text(exc)} at {Path(tb.filename).name}:{tb.lineno}"
        )
        rec.success = False
    rec.cpu_time_s = time.process_time() - cpu0
    return rec


def _study(rec: MechanismRecord, work_dir: Path, opt: CalibrationOptions) -> None:
    L = rec.n_joints
    member = render_member(rec.seed, L, rec.n_snapshots_requested, work_dir)
    rec.description, rec.render_time_s = member.description, member.render_time_s
    t0 = time.perf_counter()
    data = load_dataset(
        member.data,
        camchain=member.camchain,
        target=member.target,
        tolerance_ns=SYNC_TOLERANCE_NS,
        min_common_points=MIN_COMMON_POINTS,
        progress=False,
    )
    rec.detect_time_s = time.perf_counter() - t0
    rec.n_snapshots = len(data.snapshots)
    gt = load_ground_truth(member.ground_truth)
    stamps = np.array([s.timestamp_ns for s in data.snapshots], dtype=np.int64)
    thetas_true = gt.theta_at(stamps)
    index = {int(t): k for k, t in enumerate(gt.timestamps_ns)}
    T_st_true = gt.T_st[[index[int(t)] for t in stamps]]
    truth = GimbalCalibration(gt.kinematics.kin.copy(), L, data.static_camera, data.dynamic_camera)

    res_truth = _run(lambda: truth_start(data, truth, thetas_true, opt), data, rec.truth_start, False)
    res_auto = _run(lambda: calibrate_global(data, L, opt), data, rec.auto, True)
    if res_auto is not None:
        rec.global_info = plain(res_auto.extra.get("global"))
        rec.held_by_prior = plain(res_auto.extra.get("held_by_prior"))
        rec.model_selection = plain(res_auto.extra.get("model_selection"))
        rec.search_data_cost = float((rec.model_selection or {}).get("data_cost_general", rec.auto.data_cost))

    causes = []
    if res_auto is None:
        causes.append(f"automatic start failed: {rec.auto.error}")
    if res_truth is None:
        causes.append(f"truth start failed: {rec.truth_start.error}")
    if res_auto is not None:
        best = rec.search_data_cost if res_truth is None else min(rec.search_data_cost, rec.truth_start.data_cost)
        rec.reference = "auto only" if res_truth is None else "best of both"
        rec.cost_rel_excess = (rec.search_data_cost - best) / best if best > 0 else 0.0
        rec.strict_success = bool(rec.search_data_cost <= best * (1.0 + COST_REL_TOL) + COST_ABS_TOL)
        if res_truth is not None and res_auto.T_ds_covariances is not None:
            diff = T_ds_differences(res_auto, res_truth)
            covs = res_auto.T_ds_covariances
            m2 = [float(e @ np.linalg.lstsq(P, e, rcond=None)[0]) for e, P in zip(diff, covs, strict=True)]
            rec.T_ds_difference_m2_max = max(m2) if m2 else math.nan
        rec.success = rec.strict_success or bool(rec.T_ds_difference_m2_max < SAME_T_DS_M2)
        if not rec.success:
            causes.append(
                f"local minimum: data cost {rec.search_data_cost:.6g} vs truth start {rec.truth_start.data_cost:.6g} "
                f"(+{100 * rec.cost_rel_excess:.3g} %), T_ds apart by up to "
                f"{math.sqrt(rec.T_ds_difference_m2_max):.3g} sigma"
            )
        if rec.auto.healthy is False:
            causes.append("unhealthy: " + " | ".join(rec.auto.health_failures))
    ss_truth, n_values = truth_residuals(data, truth, thetas_true, T_st_true)
    rec.sigma_detector_px = math.sqrt(ss_truth.sum() / n_values.sum()) if n_values.sum() else math.nan
    sigma_cams = np.sqrt(ss_truth / np.maximum(n_values, 1))
    rec.sigma_detector_camera_px = [float(x) for x in sigma_cams]
    posterior = None
    if res_truth is not None:
        sig = corner_sigma(res_truth)
        posterior = (sig["static"], sig["dynamic"])
        rec.sigma_posterior_px = math.sqrt(
            (posterior[0] ** 2 * n_values[0] + posterior[1] ** 2 * n_values[1]) / max(n_values.sum(), 1)
        )
        per_camera = (res_truth.residuals_static, res_truth.residuals_dynamic)
        ss_min = [sum(float(np.sum(r * r)) for r in rs) for rs in per_camera]
        rec.truth_excess_chi2 = sum((ss_truth[c] - ss_min[c]) / posterior[c] ** 2 for c in range(2))
        K = rec.n_snapshots
        rec.truth_excess_dof = 12 + 3 * L - int(res_truth.n_gauge_fixed) + K * L + 6 * K
    # the bound of each camera's own corner noise (the detector's noise differs between cameras)
    if np.all(np.isfinite(sigma_cams)) and np.all(sigma_cams > 0):
        crb = cramer_rao_bound(data, truth, thetas_true, T_st_true, (float(sigma_cams[0]), float(sigma_cams[1])))
        rec.crb_rotation_rms, rec.crb_translation_rms = crb.rotation_rms, crb.translation_rms
        pooled = cramer_rao_bound(data, truth, thetas_true, T_st_true, rec.sigma_detector_px)
        rec.crb_pooled_rotation_rms, rec.crb_pooled_translation_rms = pooled.rotation_rms, pooled.translation_rms
        rec.observable = bool(np.all(np.isfinite(crb.T_ds)) and crb.rotation_rms > 0 and crb.translation_rms > 0)
    if posterior is not None and min(posterior) > 0:
        crb_post = cramer_rao_bound(data, truth, thetas_true, T_st_true, posterior)
        rec.crb_posterior_rotation_rms = crb_post.rotation_rms
        rec.crb_posterior_translation_rms = crb_post.translation_rms

    if res_auto is not None:
        err = T_ds_errors(truth, thetas_true, res_auto.calibration, res_auto.joint_angles)
        rec.rotation_rms = float(np.sqrt(np.mean(np.sum(err[:, :3] ** 2, axis=1))))
        rec.translation_rms = float(np.sqrt(np.mean(np.sum(err[:, 3:] ** 2, axis=1))))
        cov = res_auto.T_ds_covariances
        if cov is not None and len(cov) == len(err) and np.all(np.isfinite(cov)):
            rec.nees_mean = float(np.mean(nees_T_ds(err, cov)))
            rec.T_ds_std_rotation_median = float(np.median(np.sqrt(np.trace(cov[:, :3, :3], axis1=1, axis2=2))))
            rec.T_ds_std_translation_median = float(np.median(np.sqrt(np.trace(cov[:, 3:, 3:], axis1=1, axis2=2))))
        else:
            causes.append("no finite T_ds covariance reported")
    rec.failure = "; ".join(causes)


# ------------------------------------------------------------------ aggregation per L


def nees_interval(n_members: int, dof: int = T_DS_DOF, level: float = 0.95) -> tuple[float, float]:
    """Two-sided ``level`` interval of the mean of ``n_members`` independent chi-square(``dof``)
    variables: ``chi2.ppf([a, 1 - a], dof * n) / n`` with ``a = (1 - level) / 2``."""
    if n_members < 1:
        return math.nan, math.nan
    a = 0.5 * (1.0 - level)
    k = dof * n_members
    return float(chi2.ppf(a, k) / n_members), float(chi2.ppf(1.0 - a, k) / n_members)


def pooled_ratio(errors: Sequence[float], bounds: Sequence[float]) -> float:
    """sqrt(sum e^2 / sum b^2): pooled RMS error over pooled RMS bound (NaN when nothing is finite)."""
    e, b = np.asarray(errors, dtype=float), np.asarray(bounds, dtype=float)
    ok = np.isfinite(e) & np.isfinite(b) & (b > 0)
    return float(np.sqrt(np.sum(e[ok] ** 2) / np.sum(b[ok] ** 2))) if ok.any() else math.nan


@dataclass
class FamilySummary:
    """The issue-14 verdict for one L over the members studied.

    ``nees_interval`` is the first-order check described in the module docstring (each member's mean
    NEES one chi-square(6) draw); ``nees_interval_independent`` would hold if every snapshot's error
    were independent (reported only).
    """

    n_joints: int
    n: int
    successes: int
    strict_successes: int
    healthy: int
    n_observable: int
    n_held_by_prior: int
    rotation_ratio_pooled: float
    translation_ratio_pooled: float
    rotation_ratio_median: float
    rotation_ratio_max: float
    translation_ratio_median: float
    translation_ratio_max: float
    nees_mean: float
    nees_members: int
    nees_interval: tuple[float, float]
    nees_interval_independent: tuple[float, float]
    median_time_s: dict[str, float]
    failures: list[str]
    n_exact_model: int = 0  # members whose automatic run kept the exactly intersecting model

    @property
    def success_ok(self) -> bool:
        return self.n > 0 and self.successes >= math.ceil(SUCCESS_FRACTION * self.n - 1e-9)

    @property
    def crb_ok(self) -> bool:
        r = (self.rotation_ratio_pooled, self.translation_ratio_pooled)
        return all(np.isfinite(x) and x <= CRB_RATIO_MAX for x in r)

    @property
    def nees_ok(self) -> bool:
        lo, hi = self.nees_interval
        return bool(np.isfinite(self.nees_mean) and lo <= self.nees_mean <= hi)

    @property
    def passed(self) -> bool:
        return self.success_ok and self.crb_ok and self.nees_ok

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d.update(success_ok=self.success_ok, crb_ok=self.crb_ok, nees_ok=self.nees_ok, passed=self.passed)
        return plain(d)


def _nanmedian(x: Sequence[float]) -> float:
    a = np.asarray(x, dtype=float)
    a = a[np.isfinite(a)]
    return float(np.median(a)) if a.size else math.nan


def _median_max(x: Sequence[float]) -> tuple[float, float]:
    a = np.asarray(x, dtype=float)
    a = a[np.isfinite(a)]
    return (float(np.median(a)), float(a.max())) if a.size else (math.nan, math.nan)


def summarize(records: Sequence[MechanismRecord], n_joints: int) -> FamilySummary:
    """Aggregate the records with ``n_joints`` joints (see :class:`FamilySummary`).

    Ratios use the members whose geometry is observable and whose automatic run reached the global
    minimum (a local minimum is counted by the success criterion, not twice); NEES uses every member
    with a finite NEES and a successful automatic run.
    """
    recs = [r for r in records if r.n_joints == n_joints]
    good = [r for r in recs if r.success and r.observable]
    rot_mm = _median_max([r.rotation_ratio for r in good])
    tra_mm = _median_max([r.translation_ratio for r in good])
    nees = [r.nees_mean for r in recs if r.success and np.isfinite(r.nees_mean)]
    n_snap = sum(r.n_snapshots for r in recs if r.success and np.isfinite(r.nees_mean))
    times = {
        key: _nanmedian([getattr(r, attr) for r in recs])
        for key, attr in (
            ("render", "render_time_s"),
            ("detect", "detect_time_s"),
            ("total", "total_time_s"),
            ("cpu", "cpu_time_s"),
        )
    }
    for key in ("auto", "truth_start"):
        times[key] = _nanmedian([getattr(r, key).time_s for r in recs])
    return FamilySummary(
        n_joints=n_joints,
        n=len(recs),
        successes=sum(r.success for r in recs),
        strict_successes=sum(r.strict_success for r in recs),
        healthy=sum(r.auto.healthy is True for r in recs),
        n_observable=len(good),
        n_held_by_prior=sum(bool(r.held_by_prior) for r in recs),
        rotation_ratio_pooled=pooled_ratio([r.rotation_rms for r in good], [r.crb_rotation_rms for r in good]),
        translation_ratio_pooled=pooled_ratio([r.translation_rms for r in good], [r.crb_translation_rms for r in good]),
        rotation_ratio_median=rot_mm[0],
        rotation_ratio_max=rot_mm[1],
        translation_ratio_median=tra_mm[0],
        translation_ratio_max=tra_mm[1],
        nees_mean=float(np.mean(nees)) if nees else math.nan,
        nees_members=len(nees),
        nees_interval=nees_interval(len(nees)),
        nees_interval_independent=nees_interval(n_snap),
        median_time_s=times,
        failures=[f"seed {r.seed} (L={r.n_joints}): {r.failure}" for r in recs if r.failure],
        n_exact_model=sum((r.model_selection or {}).get("model") == EXACT for r in recs),
    )
