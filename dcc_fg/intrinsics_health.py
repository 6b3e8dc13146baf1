"""Health checks of a single-camera (intrinsics) calibration (see :mod:`dcc_fg.util.health`).

Checks (name: statistic, threshold):

* ``finite``: focal lengths positive, every parameter and standard deviation finite.
* ``residuals.rms``: the RMS reprojection error (OpenCV's per-corner norm, pixels) against
  ``max_rms`` (default 2 px: sub-pixel corner detectors on a sharp target reach a few tenths of a
  pixel, so a larger error means wrong target dimensions, a wrong model or bad detections).
* ``residuals.views``: each view's mean squared error against the pooled one, as an F-type outlier
  test at :data:`VIEW_ALPHA` (``2 N_v - 6`` and the pooled degrees of freedom) with an RMS ratio of
  :data:`~dcc_fg.calibration_health.RMS_RATIO_LIMIT`; the count against the binomial quantile at the
  false-alarm probability. A **warning**: a few bad views leave the camera usable.
* ``principal_point``: inside the image.
* ``distortion.fold``: the distortion map is one-to-one over the whole image: the distorted radius
  where the determinant of its Jacobian first stops being positive lies beyond the image corners (a
  polynomial that folds inside the image has been fitted to too few views near the image border).
  An error when the fold lies inside the observed corners, a warning when only beyond them.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

import numpy as np
from numpy.typing import NDArray
from scipy import stats

from dcc_fg.calibration_health import RMS_RATIO_LIMIT
from dcc_fg.util.health import FALSE_ALARM_PROBABILITY, HealthCheck, HealthReport
from factors.camera import CameraModel


class _Observation(Protocol):
    pixels: NDArray[np.float64]

    def __len__(self) -> int: ...


class _View(Protocol):
    observation: _Observation
    source: str


class IntrinsicsResult(Protocol):
    """What the checks read of :class:`dcc_fg.intrinsics.IntrinsicsResult` (which calls them)."""

    camera: CameraModel
    std: dict[str, float]
    rms_px: float
    per_view_rms_px: NDArray[np.float64]
    views: Sequence[_View]


#: Level of the per-view outlier test; the count of failing views is tested against Binomial(V, alpha).
VIEW_ALPHA = 1e-3
#: Directions and radii (x4, geometric) along which the distortion fold is searched.
FOLD_DIRECTIONS, FOLD_RADII = 16, 200


def finite_check(result: IntrinsicsResult) -> HealthCheck:
    """``finite``: focal lengths positive; parameters and standard deviations finite."""
    cam = result.camera
    params = np.r_[np.asarray(cam.intrinsics, dtype=float), np.asarray(cam.distortion_coeffs, dtype=float)]
    std = np.array([float(v) for v in result.std.values()], dtype=float)
    problems = []
    if not np.all(np.isfinite(params)):
        problems.append("non-finite parameters")
    elif not (cam.intrinsics[0] > 0 and cam.intrinsics[1] > 0):
        problems.append(f"focal lengths {cam.intrinsics[0]:.4g}, {cam.intrinsics[1]:.4g} px are not positive")
    if std.size and not np.all(np.isfinite(std)):
        problems.append("non-finite standard deviations (the views do not determine every parameter)")
    passed = not problems
    text = "parameters and standard deviations finite" if passed else "; ".join(problems)
    hint = "" if passed else "record more views, tilted and spread over the whole image"
    return HealthCheck("finite", passed, text, hint)


def rms_check(result: IntrinsicsResult, max_rms: float) -> HealthCheck:
    """``residuals.rms``: OpenCV's RMS (per-corner norm, px) against ``max_rms``."""
    passed = bool(np.isfinite(result.rms_px) and result.rms_px <= max_rms)
    worst = int(np.argmax(result.per_view_rms_px)) if len(result.per_view_rms_px) else -1
    text = f"RMS reprojection error {result.rms_px:.3g} px (limit {max_rms:g} px)"
    if not passed and worst >= 0:
        text += f"; worst view {result.views[worst].source} at {result.per_view_rms_px[worst]:.3g} px"
    hint = "" if passed else "check the target dimensions in target.yaml, the camera model (--model) and the detections"
    return HealthCheck("residuals.rms", passed, text, hint, float(result.rms_px), float(max_rms))


def view_check(result: IntrinsicsResult) -> HealthCheck:
    """``residuals.views``: per-view outlier count (a warning; see the module docstring)."""
    n = np.array([len(v.observation) for v in result.views], dtype=float)
    ms = result.per_view_rms_px**2 / 2.0  # mean squared error per axis of each view
    dof_v = np.maximum(2.0 * n - 6.0, 1.0)
    pooled = float(np.sum(ms * 2.0 * n) / max(np.sum(dof_v), 1.0))
    dof_pooled = max(float(np.sum(dof_v)), 1.0)
    F = ms * 2.0 * n / dof_v / max(pooled, 1e-18)
    limit = stats.f.ppf(1.0 - VIEW_ALPHA, dof_v, dof_pooled)
    bad = np.flatnonzero((F > limit) & (np.sqrt(ms / max(pooled, 1e-18)) > RMS_RATIO_LIMIT))
    allowed = int(stats.binom.ppf(1.0 - FALSE_ALARM_PROBABILITY, len(n), VIEW_ALPHA))
    passed = len(bad) <= allowed
    text = f"{len(bad)} of {len(n)} views fit far worse than the others (at most {allowed} expected)"
    if not passed:
        text += ": " + ", ".join(result.views[i].source for i in bad[:5])
    hint = "" if passed else "drop those images (wrong detections, motion blur) and calibrate again"
    return HealthCheck("residuals.views", passed, text, hint, float(len(bad)), float(allowed), severity="warning")


def principal_point_check(camera: CameraModel) -> HealthCheck:
    """``principal_point``: (cx, cy) inside the image."""
    cx, cy = float(camera.intrinsics[2]), float(camera.intrinsics[3])
    w, h = camera.resolution
    passed = bool(0.0 <= cx <= w and 0.0 <= cy <= h)
    text = f"principal point ({cx:.1f}, {cy:.1f}) px in a {w}x{h} image"
    if not passed:
        text += ": outside the image"
    hint = "" if passed else "record views that cover the whole image, tilted in both directions"
    return HealthCheck("principal_point", passed, text, hint)


def field_radius(camera: CameraModel) -> float:
    """Distorted normalized radius of the farthest image corner: the pinhole inverse of the corner
    pixels (``K^-1 u`` is exactly the distorted normalized coordinate)."""
    fx, fy, cx, cy = (float(v) for v in camera.intrinsics)
    w, h = camera.resolution
    corners = np.array([[0.0, 0.0], [w, 0.0], [0.0, h], [w, h]])
    xy = (corners - [cx, cy]) / [fx, fy]
    return float(np.max(np.linalg.norm(xy, axis=1)))


def observed_radius(camera: CameraModel, pixels: NDArray[np.float64]) -> float:
    """Largest distorted normalized radius of the corners the views observed (``K^-1 u``)."""
    if len(pixels) == 0:
        return 0.0
    fx, fy, cx, cy = (float(v) for v in camera.intrinsics)
    xy = (np.asarray(pixels, dtype=float) - [cx, cy]) / [fx, fy]
    return float(np.max(np.linalg.norm(xy, axis=1)))


def fold_radius(camera: CameraModel) -> float:
    """Distorted normalized radius where the distortion map first stops being one-to-one (the
    determinant of its Jacobian is no longer positive) along any of :data:`FOLD_DIRECTIONS` rays,
    out to 87 deg off the axis; ``inf`` without a fold."""
    ang = np.linspace(0.0, 2.0 * np.pi, FOLD_DIRECTIONS, endpoint=False)
    r = np.geomspace(1e-3, 20.0, 4 * FOLD_RADII)
    dirs = np.stack([np.cos(ang), np.sin(ang)], axis=1)
    xy_d, J = camera.distort((r[:, None, None] * dirs[None]).reshape(-1, 2))
    ok = (np.linalg.det(J) > 0).reshape(len(r), len(ang))
    rd = np.linalg.norm(xy_d, axis=1).reshape(len(r), len(ang))
    reach = np.inf
    for j in range(len(ang)):
        bad = np.flatnonzero(~ok[:, j])
        if bad.size:
            reach = min(reach, float(np.max(rd[: max(bad[0], 1), j])))
    return reach


def fold_check(camera: CameraModel, observed: float = 0.0) -> HealthCheck:
    """``distortion.fold``: the model must be one-to-one over the image. A fold inside the observed
    corners' radius ``observed`` (distorted normalized) is an error: the model contradicts its own
    data; a fold between them and the image corners is a warning: the model is valid where the views
    saw the target, but pixels near the image corners have no undistorted direction."""
    corners = field_radius(camera)
    reach = fold_radius(camera)
    passed = bool(corners < reach)
    severity = "error" if reach <= observed else "warning"
    if passed:
        text = f"distortion one-to-one out to the image corners (distorted normalized radius {corners:.3g}" + (
            f"; the model folds at {reach:.3g})" if np.isfinite(reach) else "; no fold)"
        )
    else:
        text = (
            f"the distortion folds at distorted normalized radius {reach:.3g}, inside the image (corners at "
            f"{corners:.3g}, farthest observed corner at {observed:.3g}): pixels beyond it have no undistorted "
            "direction"
        )
    hint = "" if passed else "record views with the target near the image corners and borders, or a simpler model"
    return HealthCheck("distortion.fold", passed, text, hint, float(corners), float(reach), severity=severity)


def intrinsics_health(result: IntrinsicsResult, max_rms: float = 2.0) -> HealthReport:
    """Every health check of the single-camera calibration ``result`` (subject ``intrinsics``)."""
    report = HealthReport("intrinsics")
    report.add(finite_check(result))
    report.add(rms_check(result, max_rms))
    if len(result.views) > 1:
        report.add(view_check(result))
    if np.all(np.isfinite(result.camera.intrinsics)) and result.camera.intrinsics[0] > 0:
        report.add(principal_point_check(result.camera))
        pixels = [np.asarray(v.observation.pixels, dtype=float) for v in result.views]
        observed = observed_radius(result.camera, np.concatenate(pixels) if pixels else np.zeros((0, 2)))
        report.add(fold_check(result.camera, observed))
    return report
