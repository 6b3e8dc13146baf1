"""Model selection for (nearly) intersecting joint axes: keep the exactly intersecting model when the
data do not support link offsets.

Why. When consecutive axes intersect (``a_l = 0``, ``d_l = 0``: a spherical wrist for L = 3) and the
joint angles are unknown, the axis directions, twists and mount rotations are undetermined: any axes
through the wrist point reproduce the same rotations (:mod:`dcc_fg.degeneracy`). With free link
offsets they become determined *in proportion to the offsets*: the general model can pair offsets of
a fraction of a millimetre with twists and mount rotations that move by up to radians, and that
bilinear freedom fits the corner noise. On the exactly intersecting 3-axis members of the random
family (``benchmarks/bench_random_mechanisms.py``) the general fit ends 13-19 chi-square units below the
fit started at the truth (two Gaussian-noise draws of one member) with per-snapshot ``T_ds`` errors at
~2x the Cramer-Rao bound (1.9-2.7x on the rendered images); the exactly intersecting fit of the same
images is at 0.4-1.0x (two rendered members). The linearized covariance of the general fit cannot see this (the bound
is local), so the choice is made by a test, not by the covariance.

Test. At the end of the global search (:func:`dcc_fg.global_fit.calibrate_global`), when its best
(general) solution holds directions by prior (the symptom of nearly intersecting axes) and no
``--nominal`` was given, the images are calibrated once more with the offsets held at zero (``--nominal
exactly-intersecting``), started from the general solution with its offsets set to zero. The general
model's gain ``2 (c_exact - c_general) / s^2`` (data costs, ``s^2`` the general fit's variance factor)
is compared with ``chi2.ppf(1 - ALPHA, p)``. A gain within the threshold keeps the exactly
intersecting solution: the images show no offsets.

Degrees of freedom. The general model does not only add the ``m`` offsets: each of the ``h``
directions the exact fit leaves undetermined beyond the gauge (its null space at the solution: 6 for
a spherical wrist, whose twists and mount rotations any axes through the wrist reproduce) becomes
determined in proportion to the offsets, so the extra fit is that of a bilinear model. Counting the
offsets and their products with those directions as free linear parameters bounds it:
``p = m (1 + h)`` (21 for a spherical wrist). The plain count ``m + h`` (9) is too small: on exactly
intersecting members the gains were 25-29 chi-square units (four members, rendered and simulated),
above its 99.9 % quantile (27.9) and near the mean of the largest squared singular value of a 3 x 6
Gaussian matrix plus the offsets' own 3 (~20), the bilinear picture. ``ALPHA`` = 1e-3 (threshold 46.8
for a spherical wrist). Offsets the images resolve fit far better (members of the family with
offsets of 3-8 mm: 123 and 415 chi-square units).

Only for L >= 3. Two intersecting axes leave one direction undetermined, not the free rotation part
of a spherical wrist, and the general model already reaches the bound on them (exactly intersecting
L = 2 members of the family: 1.02x / 0.97x); there the test only adds the risk of a false acceptance
(L = 2 member 28 of the family, offset 1.9 mm: gain 10.2 below the threshold of 13.8, the exact model
2.7x the bound with NEES 27, the general one 1.2x).

Measured on the random family (``bench_random_mechanisms.py --joints 2,3 --n 50 --snapshots 25``): the
10 exactly intersecting L = 3 members gained 11.1-29.0 chi-square units from free offsets (all kept
the exact model: pooled error 0.85x / 0.75x the bound, was 1.92x / 2.14x), the 40 others 123 and up
(all kept the general model).

Units: data costs in GTSAM's error units (``0.5 * sum`` of whitened squared residuals); gains in
chi-square units.
"""

from __future__ import annotations

import logging
from dataclasses import replace

import numpy as np
from scipy.stats import chi2

from dcc_fg.calibrate import CalibrationOptions, CalibrationResult, calibrate, data_cost
from dcc_fg.data import CalibrationDataset, with_joints
from dcc_fg.degeneracy import EXACT, offset_entries
from dcc_fg.model import GimbalCalibration
from dcc_fg.util.errors import EstimatorError

log = logging.getLogger("dcc_fg.model_selection")
ALPHA = 1e-3  # false-rejection probability of the exactly intersecting model (module docstring)
MIN_JOINTS = 3  # two intersecting axes leave one direction, not the bilinear freedom (module docstring)


def should_test(result: CalibrationResult, options: CalibrationOptions) -> bool:
    """Whether the exactly intersecting model is tried: encoderless, L >= ``MIN_JOINTS``, no
    ``--nominal``, and the general solution holds directions by prior."""
    return (
        options.mode == "encoderless"
        and result.calibration.n_joints >= MIN_JOINTS
        and options.nominal is None
        and bool(result.extra.get("held_by_prior"))
    )


def exact_start(result: CalibrationResult) -> GimbalCalibration:
    """The general solution's kinematics with the link offsets of :func:`offset_entries` set to zero."""
    cal = result.calibration
    kin = cal.kin.copy()
    kin[offset_entries(cal.n_joints)] = 0.0
    return GimbalCalibration(kin, cal.n_joints, cal.static_camera, cal.dynamic_camera)


def bilinear_dof(n_offsets: int, n_held: int) -> int:
    """Degrees of freedom of the test: the offsets and their products with the held directions
    (module docstring)."""
    return int(n_offsets * (1 + n_held))


def decide(gain_chi2: float, dof: int, alpha: float = ALPHA) -> tuple[bool, float]:
    """(keep the exactly intersecting model, threshold): ``gain <= chi2.ppf(1 - alpha, dof)``."""
    threshold = float(chi2.ppf(1.0 - alpha, max(int(dof), 1)))
    return bool(gain_chi2 <= threshold), threshold


def select_intersecting(
    data: CalibrationDataset, general: CalibrationResult, options: CalibrationOptions
) -> CalibrationResult:
    """Test the exactly intersecting model against the general solution (module docstring).

    ``data``: the images of the general fit (its joint angles become the guesses). Returns the kept
    result; its ``extra["model_selection"]`` (also on the general result's) says which model, the gain,
    the threshold and the degrees of freedom, or why the test was not made. A failure of the exact fit
    keeps the general solution and is reported."""
    base = {"tested": EXACT}
    if not should_test(general, options):
        reason = f"not tested (no held directions, --nominal, or L < {MIN_JOINTS})"
        report = {**base, "model": "general", "reason": reason}
        general.extra["model_selection"] = report
        return general
    guesses = with_joints(data, general.joint_angles)
    try:
        exact = calibrate(guesses, exact_start(general), replace(options, nominal=EXACT))
    except (EstimatorError, ValueError) as exc:
        report = {**base, "model": "general", "reason": f"the exactly intersecting fit failed: {exc}"}
        general.extra["model_selection"] = report
        return general
    vf = max(float(general.variance_factor), 1e-12)
    gain = 2.0 * (data_cost(exact) - data_cost(general)) / vf
    held = len(exact.extra.get("held_by_prior", []))
    n_undetermined = max(int(exact.null_space_dim) - int(exact.n_gauge_fixed), held)
    dof = bilinear_dof(len(offset_entries(general.calibration.n_joints)), n_undetermined)
    keep_exact, threshold = decide(gain, dof)
    report = {
        **base,
        "model": EXACT if keep_exact else "general",
        "gain_chi2": float(gain),
        "threshold_chi2": threshold,
        "dof": int(dof),
        "alpha": ALPHA,
        "data_cost_general": float(data_cost(general)),
        "data_cost_exact": float(data_cost(exact)),
    }
    general.extra["model_selection"] = report
    general.calibration.statistics["model_selection"] = report
    if not keep_exact:
        return general
    log.info(
        "the axes intersect within what the images resolve: the general model fits only %.1f chi2 better "
        "(threshold %.1f, %d dof); keeping the exactly intersecting model", gain, threshold, dof,
    )  # fmt: skip
    # the offsets are the model's, not measured: no standard deviation, not observable
    offsets = offset_entries(exact.calibration.n_joints)
    report["held_at_zero"] = [exact.calibration.names[i] for i in offsets]
    if exact.calibration.observable is not None:
        exact.calibration.observable[offsets] = False
    if exact.calibration.kin_std is not None:
        exact.calibration.kin_std[offsets] = np.nan
    exact.extra["model_selection"] = report
    # the search's report stays (its starts, its chosen general solution); its ambiguities were between
    # general-model solutions, which the kept model does not have
    note = "search of the general model; the exactly intersecting model was kept (model_selection)"
    dropped = {"ambiguity": None, "spread": None}  # between general-model solutions: not in the kept covariance
    if "global" in general.extra:
        exact.extra["global"] = {**general.extra["global"], **dropped, "ambiguous_solutions": 0,
                                 "plausible_solutions": 0, "note": note}  # fmt: skip
    if "global" in general.calibration.statistics:
        exact.calibration.statistics["global"] = {**general.calibration.statistics["global"], **dropped, "note": note}
    exact.calibration.statistics["model_selection"] = report
    return exact
