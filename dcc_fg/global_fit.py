"""Global strategy of the encoderless calibration: several starts, the lowest cost wins, ambiguity reported.

The corner-level problem has local minima, most of them from the discrete ambiguities of the axis
fit (which joint's axis is which, the branch of a twist) and, for L = 3, from the flat valleys of
mechanisms whose axes nearly intersect. :func:`calibrate_global` therefore solves the complete
problem (:func:`dcc_fg.calibrate.calibrate`) from every distinct start it has:

* the hand-measured kinematics (``--gimbal``), when given;
* each of the automatic initialization's distinct pose-level minima
  (:func:`dcc_fg.auto_init.auto_initial_candidates`: one for L <= 1, the axis-plane fits for L = 2,
  the best axis-search minima for L = 3, and the deeper minima of the whitened pose-level cost
  that :func:`dcc_fg.auto_init.whitened_hops` finds);

and keeps the solution with the lowest *data* cost (pixel residuals only: the weak priors of
:mod:`dcc_fg.degeneracy` sit at each start's own values, so they do not take part in the
comparison). Solutions that hold directions by the weak prior stop in the curved valley of those
directions short of its bottom, so before they are compared the ``N_PROJECTED`` lowest are solved on
from where they stopped with the projected solve (:func:`projected_continuation`,
:func:`dcc_fg.calibrate.continue_projected`, :mod:`dcc_fg.projection`). Bottoms, not stopping points,
must be compared, for the choice and for the uniqueness check below: on random L = 3 member 35 the
joint solves of all seven starts stop on the iteration cap; the best one's continuation ends at 1.41799,
and a valley whose bottom lies 8.2 chi-square units above it (its T_ds 0.9 mrad / 1.7 mm from the best
one's, closer to the truth) stopped 45 units above, outside the threshold, so the reported covariance
ignored it (NEES 57). Only the best solution was continued before (random L = 3 family: 40 of 50
members, all ended lower, by a median 2.7e-5 and at most 2.5e-3 of the data cost). The answer, the
lowest solution after those continuations, is continued once more by ``FURTHER_STEPS`` projected steps
when its continuation stopped on the step cap still descending (:func:`dcc_fg.calibrate.stopped_on_cap`):
on random L = 3 members 14 and 29 it stopped there 1.8e-4 and 1.5e-6 of the data cost above the truth
start's continuation, in the same valley (T_ds 0.32 and 0.11 sigma apart).

Uniqueness. Another solution whose data cost is within the chi-square threshold of the best one,
``2 (c_j - c_best) / s^2 < chi2_0.95(p)`` (``s^2`` the a-posteriori variance factor), fits the images
as well: it lies inside the likelihood-ratio confidence region of the kinematics. ``p``
(:func:`determined_parameters`) is the number of free kinematic parameters less the directions the data
leave exactly undetermined beyond the gauge; directions held by the weak prior because the data determine
them only weakly count, since the data cost does change along them (on nearly intersecting 3-axis
chains, solutions along those directions differ by 5-25 chi-square units).

* Every solution in that region is a plausible answer, so the reported ``T_ds`` covariance covers
  them (:func:`covering_covariance`): each snapshot's covariance gets the scatter ``S = sum_j d_j d_j^T``
  of the ``T_ds`` differences ``d_j`` to those solutions added, scaled so that the one farthest in it
  lies at one sigma: ``S max_j d_j^T S^+ d_j``. One solution adds ``d d^T``, the same one twice too;
  solutions in different directions are each covered.
  ``extra["global"]["spread"]`` names the farthest one (mean Mahalanobis^2 in the best one's
  covariance) and ``plausible_solutions`` counts them. Solutions that converge to the best one add
  nothing.
* When such a solution's ``T_ds`` differs from the best one by more than the reported uncertainty
  (Mahalanobis^2 above ``chi2_0.95(6)`` in some snapshot), the data do not decide between the two: the
  result carries ``extra["global"]["ambiguity"]`` (the two solutions' ``T_ds`` difference, rad and m)
  and the health report warns; with the difference added, the 1-sigma a user reads is never smaller
  than the ambiguity.

Model. The search fits the general model (free link offsets). When its best solution holds directions
by prior (nearly intersecting axes), :func:`dcc_fg.model_selection.select_intersecting` then tests the
exactly intersecting model against it and keeps that one when the offsets do not fit the images
significantly better (a spherical wrist's general fit spends the offsets on the corner noise).

Why the spread and not the best solution's covariance alone: on nearly intersecting 3-axis chains the
kinematics slide along weakly determined directions that leave ``T_ds`` unchanged only to first order,
so the linearized covariance misses part of the spread of the solutions that fit as well (random
L = 3 family, benchmarks/bench_random_mechanisms.py: NEES 8.05 with the linearized covariance alone,
7.22 with the farthest plausible solution's outer product added, 6.10 with the covering; 95 % interval
5.04-7.04).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import gtsam
import numpy as np
from numpy.typing import NDArray
from scipy.stats import chi2

from dcc_fg.auto_init import auto_initial_candidates
from dcc_fg.calibrate import (
    CalibrationOptions,
    CalibrationResult,
    calibrate,
    continue_projected,
    data_cost,
    stopped_on_cap,
)
from dcc_fg.data import CalibrationDataset, with_joints
from dcc_fg.model import GimbalCalibration
from dcc_fg.model_selection import select_intersecting
from dcc_fg.projection import MAX_STEPS
from dcc_fg.util.errors import EstimatorError

FloatArray = NDArray[np.float64]
log = logging.getLogger("dcc_fg.global_fit")
AMBIGUITY_PROBABILITY = 0.95  # chi-square quantile of "fits as well"
N_PROJECTED = 3  # the lowest-cost solutions solved on with the projected solve when they hold directions
FURTHER_STEPS = 900  # more projected steps for the chosen solution when its continuation stopped on the cap
AMBIGUITY_NEES = 12.59  # chi2_0.95(6): a T_ds difference beyond this (Mahalanobis^2) is a different answer


@dataclass
class Start:
    """One start of the global strategy: its name, kinematics and the data with its joint-angle guesses."""

    name: str
    initial: GimbalCalibration
    data: CalibrationDataset
    pose_level_rms: float = float("nan")


def T_ds_differences(a: CalibrationResult, b: CalibrationResult) -> FloatArray:
    """(K, 6) ``Log(T_ds_a^-1 T_ds_b)`` per snapshot, [omega rad, v m] (gtsam Pose3 local coordinates)."""
    return np.array(
        [gtsam.Pose3(a.T_ds(i)).localCoordinates(gtsam.Pose3(b.T_ds(i))) for i in range(len(a.timestamps_ns))]
    )


def starts_of(
    data: CalibrationDataset,
    n_joints: int,
    mode: str,
    initial: GimbalCalibration | None,
    automatic: bool,
    report: list[dict[str, Any]],
    initial_name: str = "gimbal.yaml",
) -> list[Start]:
    """The starts: ``initial`` (with the snapshots' own joint guesses), then the automatic candidates
    (with their joint angles as the guesses, except in ``encoders`` mode). When ``initial`` is given,
    a failure of the automatic initialization (e.g. images in which a joint never moves) is recorded
    in ``report`` and the search goes on from ``initial`` alone."""
    starts = []
    if initial is not None:
        starts.append(Start(initial_name, initial, data))
    if automatic:
        try:
            candidates = auto_initial_candidates(data, n_joints)
        except (EstimatorError, ValueError) as exc:
            if initial is None:
                raise
            report.append({"start": "automatic", "error": str(exc)})
            candidates = []
        for k, (cal, thetas, rms) in enumerate(candidates):
            d = data
            if mode != "encoders":
                d = with_joints(data, thetas)
            starts.append(Start(f"automatic {k + 1}", cal, d, float(rms)))
    return starts


def determined_parameters(result: CalibrationResult) -> int:
    """Degrees of freedom of the likelihood-ratio test between two solutions: the free (not
    gauge-fixed) kinematic parameters less the null-space directions at the solution beyond the gauge
    (at least 1). Weakly determined directions (held by prior) count: the data cost changes along them."""
    fixed = result.calibration.gauge_fixed
    n_free = len(result.calibration.kin) - (int(np.sum(fixed)) if fixed is not None else 0)
    extra_null = max(int(result.null_space_dim) - int(result.n_gauge_fixed), 0)
    return max(n_free - extra_null, 1)


def fits_as_well(best: CalibrationResult, other: CalibrationResult) -> tuple[bool, float, float]:
    """(inside the 95 % likelihood-ratio region of the best solution, cost difference in chi-square
    units, threshold): ``2 (c_other - c_best) / s^2 <= chi2_0.95(p)`` (module docstring)."""
    vf = max(float(best.variance_factor), 1e-12)
    delta = 2.0 * (data_cost(other) - data_cost(best)) / vf
    threshold = float(chi2.ppf(AMBIGUITY_PROBABILITY, determined_parameters(best)))
    return delta <= threshold, float(delta), threshold


def solution_difference(best: CalibrationResult, other: CalibrationResult) -> dict[str, Any]:
    """How far ``other``'s per-snapshot ``T_ds`` is from ``best``'s: RMS and max rotation (rad) and
    translation (m), and the Mahalanobis^2 in ``best``'s reported covariance (max and mean over the
    snapshots; NaN without covariances). ``_diff``: the (K, 6) differences."""
    diff = T_ds_differences(best, other)
    if best.T_ds_covariances is not None:
        covs = best.T_ds_covariances
        m2 = np.array([e @ np.linalg.lstsq(P, e, rcond=None)[0] for e, P in zip(diff, covs, strict=True)])
    else:
        m2 = np.full(len(diff), np.nan)
    finite = bool(np.any(np.isfinite(m2)))
    return {
        "rotation_rms_rad": float(np.sqrt(np.mean(np.sum(diff[:, :3] ** 2, axis=1)))),
        "translation_rms_m": float(np.sqrt(np.mean(np.sum(diff[:, 3:] ** 2, axis=1)))),
        "rotation_max_rad": float(np.max(np.linalg.norm(diff[:, :3], axis=1))),
        "translation_max_m": float(np.max(np.linalg.norm(diff[:, 3:], axis=1))),
        "max_mahalanobis2": float(np.nanmax(m2)) if finite else float("nan"),
        "mean_mahalanobis2": float(np.nanmean(m2)) if finite else float("nan"),
        "_diff": diff,
    }


def is_ambiguous(difference: dict[str, Any]) -> bool:
    """Whether a :func:`solution_difference` is a different answer: Mahalanobis^2 at or above
    ``chi2_0.95(6)`` in some snapshot, or no covariance to tell (NaN)."""
    return not difference["max_mahalanobis2"] < AMBIGUITY_NEES


def ambiguity_of(best: CalibrationResult, other: CalibrationResult) -> dict[str, Any] | None:
    """The ambiguity between two solutions (module docstring), or None when ``other`` fits clearly
    worse or gives the same ``T_ds`` within the best one's reported uncertainty."""
    inside, delta, threshold = fits_as_well(best, other)
    if not inside:
        return None
    amb = solution_difference(best, other)
    return {"cost_difference_chi2": delta, "threshold_chi2": threshold, **amb} if is_ambiguous(amb) else None


def covering_covariance(diffs: FloatArray) -> FloatArray:
    """(K, 6, 6) per snapshot: the smallest multiple of the scatter ``S = sum_j d_j d_j^T`` of the
    differences ``diffs`` (n, K, 6) that has every ``d_j`` within one sigma: ``c S`` with
    ``c = max_j d_j^T S^+ d_j`` (the leverages, at most 1), since ``d_j^T (c S)^+ d_j`` is the leverage
    over ``c``; zero where all differences vanish."""
    K = diffs.shape[1]
    out = np.zeros((K, 6, 6))
    for k in range(K):
        D = diffs[:, k, :]
        S = D.T @ D
        if not np.any(S):
            continue
        leverage = np.einsum("ji,il,jl->j", D, np.linalg.pinv(S, rcond=1e-12, hermitian=True), D)
        out[k] = S * float(np.max(leverage))
    return out


def _farthest(amb: dict[str, Any]) -> tuple[float, float]:
    """Sort key of ambiguities: the mean Mahalanobis^2 of the T_ds difference in the best solution's
    reported covariance (RMS difference in rad + m when there is no covariance)."""
    m2 = amb["mean_mahalanobis2"]
    return (m2 if np.isfinite(m2) else -1.0, amb["rotation_rms_rad"] + amb["translation_rms_m"])


def projected_continuation(
    start: Start, res: CalibrationResult, report: list[dict[str, Any]], max_steps: int = MAX_STEPS
) -> CalibrationResult:
    """``res`` solved on from where it stopped with the projected solve (at most ``max_steps`` steps,
    :func:`dcc_fg.calibrate.continue_projected`): the joint solve stops in the curved valley of the held
    directions short of its bottom, and the search must compare bottoms. The continuation replaces
    ``res`` when it lowers the data cost; recorded in ``report`` either way."""
    name = f"{start.name}, projected" if max_steps == MAX_STEPS else f"{start.name}, projected on ({max_steps} steps)"
    try:
        cont = continue_projected(start.data, res, max_steps)
    except (EstimatorError, ValueError) as exc:
        report.append(start_entry(name, start, error=exc))
        return res
    if cont is None:
        report.append({"start": name, "pose_level_rms": start.pose_level_rms, "projection": "did not lower the cost"})
        return res
    report.append({**start_entry(name, start, cont), "projection": cont.extra.get("held_projection")})
    return cont


def start_entry(
    name: str, start: Start, res: CalibrationResult | None = None, error: Exception | None = None
) -> dict[str, Any]:
    """One line of ``extra["global"]["starts"]``: the start's name and pose-level RMS, then its solve's
    data cost, final error, iterations and time, or its ``error``."""
    entry: dict[str, Any] = {"start": name, "pose_level_rms": start.pose_level_rms}
    if error is not None:
        return {**entry, "error": str(error)}
    assert res is not None
    return {
        **entry,
        "data_cost": data_cost(res),
        "final_error": float(res.final_error),
        "iterations": int(res.iterations),
        "time_s": float(res.solve_time_s),
    }


def calibrate_global(
    data: CalibrationDataset,
    n_joints: int,
    options: CalibrationOptions | None = None,
    initial: GimbalCalibration | None = None,
    automatic: bool = True,
    initial_name: str = "gimbal.yaml",
) -> CalibrationResult:
    """Calibration that searches for the global minimum (module docstring).

    Args:
        data: the snapshots (``joints`` are guesses in encoderless mode, readings with encoders).
        n_joints: L.
        options: solver options (mode ``encoderless`` or ``encoders``).
        initial: hand-measured kinematics (``--gimbal``), one more start; None: automatic starts only.
        automatic: add the automatic initialization's starts (always, when ``initial`` is None).
        initial_name: how ``initial`` is named in the report (default ``gimbal.yaml``).

    Returns:
        the solution with the lowest data cost, or the exactly intersecting solution when the data do not
        support link offsets (:mod:`dcc_fg.model_selection`, reported in ``extra["model_selection"]``);
        ``extra["global"]`` lists every start of the search (name, pose-level RMS, final data cost,
        iterations, or its error) and the ambiguity, if any.

    Raises:
        the first start's error when every start fails.
    """
    opt = options or CalibrationOptions()
    if opt.mode == "validate":
        raise ValueError("calibrate_global calibrates; validate with dcc_fg.calibrate.calibrate(mode='validate')")
    report: list[dict[str, Any]] = []
    starts = starts_of(data, n_joints, opt.mode, initial, automatic or initial is None, report, initial_name)
    results: list[tuple[Start, CalibrationResult]] = []
    first_error: Exception | None = None
    for start in starts:
        try:
            res = calibrate(start.data, start.initial, opt)
        except (EstimatorError, ValueError) as exc:
            first_error = first_error or exc
            report.append(start_entry(start.name, start, error=exc))
            continue
        results.append((start, res))
        report.append(start_entry(start.name, start, res))
    if not results:
        assert first_error is not None
        raise first_error
    if not opt.project_held:  # the lowest ones solved on to the bottoms of their valleys (module docstring)
        for j in sorted(range(len(results)), key=lambda j: data_cost(results[j][1]))[:N_PROJECTED]:
            start, res = results[j]
            if res.extra.get("held_by_prior"):
                results[j] = (start, projected_continuation(start, res, report))
    j_best = min(range(len(results)), key=lambda j: data_cost(results[j][1]))
    if not opt.project_held and stopped_on_cap(results[j_best][1]):  # the answer is solved on to its bottom
        start, res = results[j_best]
        results[j_best] = (start, projected_continuation(start, res, report, FURTHER_STEPS))
    best_start, best = results[j_best]
    plausible = []  # the other solutions inside the likelihood-ratio region, with their T_ds difference
    for start, res in results:
        if res is best:
            continue
        inside, delta, threshold = fits_as_well(best, res)
        if inside:
            plausible.append({"start": start.name, "cost_difference_chi2": delta, "threshold_chi2": threshold,
                              **solution_difference(best, res)})  # fmt: skip
    spread = max(plausible, key=_farthest, default=None)
    if plausible and best.T_ds_covariances is not None:
        best.T_ds_covariances = best.T_ds_covariances + covering_covariance(np.array([a["_diff"] for a in plausible]))
    for amb in plausible:
        amb.pop("_diff")
    ambiguities = [a for a in plausible if is_ambiguous(a)]
    worst = max(ambiguities, key=_farthest, default=None)
    if worst is not None:
        log.warning(
            "another solution (start %s) fits the images as well but gives T_ds %.3g mrad / %.3g mm (RMS) apart; "
            "the reported T_ds covariances include the difference",
            worst["start"], worst["rotation_rms_rad"] * 1e3, worst["translation_rms_m"] * 1e3,
        )  # fmt: skip
    best.extra["global"] = {
        "starts": report,
        "chosen": best_start.name,
        "ambiguity": worst,
        "ambiguous_solutions": len(ambiguities),
        "spread": spread,
        "plausible_solutions": len(plausible),
    }
    best.calibration.statistics["global"] = {
        "solved": len(results),
        "chosen": best_start.name,
        "ambiguity": worst,
        "spread": spread,
        "starts": report,
    }
    return select_intersecting(data, best, opt)
