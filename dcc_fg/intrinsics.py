"""Single-camera intrinsic calibration (``dcc-fg intrinsics``) for users without a camchain yet.

Models (Kalibr names):

* ``pinhole-radtan``: ``[fx, fy, cx, cy]`` + ``[k1, k2, p1, p2]``, solved by ``cv2.calibrateCamera``
  with ``k3`` fixed at 0 (Kalibr's radtan has 4 coefficients);
* ``pinhole-equidistant``: ``[fx, fy, cx, cy]`` + ``[k1, k2, k3, k4]`` (Kannala-Brandt), solved by
  ``cv2.fisheye.calibrate`` (zero skew).

Pixels are (u, v) in the distorted image, OpenCV's convention (the convention of
:mod:`factors.camera`, whose ``project`` reproduces OpenCV's projection for both models).

Statistics. The reprojection residuals are recomputed with :class:`factors.camera.CameraModel`
at the solution.  ``rms_px`` is OpenCV's figure, sqrt(mean |e|^2) over corners (per-corner error
norm); ``rms_per_axis_px`` is that over sqrt(2).  The standard deviation of every intrinsic
parameter is the square root of the diagonal of ``s^2 (J_I^T J_I - J_I^T J_P (J_P^T J_P)^-1
J_P^T J_I)^-1``: the Gauss-Newton covariance of the intrinsics with every view's pose eliminated
(Schur complement), with the a-posteriori corner variance ``s^2 = sum |e|^2 / (2 N - n_params)``.
Jacobians are OpenCV's analytic ones (``cv2.projectPoints`` / ``cv2.fisheye.projectPoints``).
This is a first-order, independent-Gaussian-corner figure: it does not include systematic
errors (an inadequate distortion model, a target that is not flat).
"""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray
from tqdm import tqdm

from dcc_fg.data import Observation
from dcc_fg.detection import detect_target
from dcc_fg.intrinsics_health import intrinsics_health
from dcc_fg.io.bags import BagTopicImages, is_bag
from dcc_fg.io.camchain import CamchainEntry, camchain_to_yaml, load_camchain
from dcc_fg.io.folders import IMAGE_SUFFIXES, list_timestamped, read_image
from dcc_fg.io.outputs import write_text_atomic
from dcc_fg.sources.parallel_detection import detect_images
from dcc_fg.targets import TargetGeometry
from dcc_fg.util.errors import stage
from dcc_fg.util.health import UnhealthyResultError
from factors.camera import CameraModel

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
MODELS = {"pinhole-radtan": "radtan", "pinhole-equidistant": "equidistant"}
PARAM_NAMES = {
    "radtan": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
    "equidistant": ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4"),
}
_CRITERIA = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)


@dataclass
class View:
    """The target corners seen in one image: timestamp (ns), observation, where it came from."""

    timestamp_ns: int
    observation: Observation
    source: str


@dataclass
class IntrinsicsResult:
    """A single-camera calibration.

    Attributes:
        camera: the estimated model.
        std: 1-sigma of each parameter (``fx, fy, cx, cy`` and the four distortion coefficients;
            pixels for the first four, unitless for the rest).
        rms_px: sqrt(mean squared per-corner reprojection error norm), pixels (OpenCV's ``rms``).
        rms_per_axis_px: ``rms_px / sqrt(2)``.
        per_view_rms_px: the same per view.
        T_ct: (V, 4, 4) target pose in the camera per view.
        views: the views used.
        n_images: images read; n_detected: images where the target was found with enough corners.
        source: data path (and camera) for messages.
    """

    camera: CameraModel
    std: dict[str, float]
    rms_px: float
    rms_per_axis_px: float
    per_view_rms_px: FloatArray
    T_ct: FloatArray
    views: list[View]
    n_images: int = 0
    n_detected: int = 0
    source: str = ""
    extra: dict[str, Any] = field(default_factory=dict)

    def summary(self) -> dict[str, Any]:
        """Plain dictionary of the results (for JSON and the printed table)."""
        names = PARAM_NAMES[self.camera.distortion_model]
        values = list(self.camera.intrinsics) + list(self.camera.distortion_coeffs)
        return {
            "source": self.source,
            "model": f"pinhole-{self.camera.distortion_model}",
            "resolution": list(self.camera.resolution),
            "parameters": {n: float(v) for n, v in zip(names, values, strict=True)},
            "std": dict(self.std),
            "rms_px": self.rms_px,
            "rms_per_axis_px": self.rms_per_axis_px,
            "views_used": len(self.views),
            "images_read": self.n_images,
            "images_with_target": self.n_detected,
            "corners": int(sum(len(v.observation) for v in self.views)),
        }


def intrinsics_table(result: IntrinsicsResult) -> str:
    """Text table: parameter, value, 1-sigma; then the reprojection error."""
    s = result.summary()
    lines = [f"intrinsics of {s['source']} ({s['model']}, {s['resolution'][0]}x{s['resolution'][1]})"]
    lines.append(f"  {'parameter':<10}{'value':>16}{'1-sigma':>14}")
    for name, value in s["parameters"].items():
        unit = " px" if name in ("fx", "fy", "cx", "cy") else ""
        lines.append(f"  {name:<10}{value:>16.6g}{s['std'][name]:>14.3g}{unit}")
    lines.append(
        f"  reprojection RMS {s['rms_px']:.3f} px ({s['rms_per_axis_px']:.3f} px per axis) over {s['corners']} "
        f"corners in {s['views_used']} views ({s['images_with_target']} of {s['images_read']} images had the target)"
    )
    return "\n".join(lines)


# ------------------------------------------------------------------ reading one camera


def camera_images(
    path: str | Path, camera: str, topic: str | None = None
) -> tuple[Iterator[tuple[int, NDArray[np.generic], str]], int, str]:
    """Stream one camera's images: ``(iterator of (stamp ns, image, where), count, description)``.

    ``path`` is a ROS1 bag / ROS2 bag folder (topic ``topic`` or ``/<camera>/image_raw``) or a
    folder with ``<camera>/<timestamp_ns>.<png|jpg|...>``.

    Raises:
        ValueError: naming the path: it does not exist, the camera folder is missing or holds no
            images, the topic is missing.
    """
    path = Path(path)
    if not path.exists():
        raise ValueError(f"{path}: no such file or folder")
    if is_bag(path):
        bag = BagTopicImages(path, topic or f"/{camera}/image_raw")
        return iter(bag), len(bag), f"{path}: topic {bag.topic}"
    if path.is_file():
        raise ValueError(f"{path}: not a ROS1 bag; expected a bag, a ROS2 bag folder or an image folder")
    folder = path / camera
    if not folder.is_dir():
        raise ValueError(f"{folder}: camera folder missing (image folder layout: {camera}/<timestamp_ns>.png)")
    files = list_timestamped(folder, IMAGE_SUFFIXES)
    if not files:
        raise ValueError(f"{folder}: no images named <timestamp_ns>.png (or .jpg, ...)")

    def gen() -> Iterator[tuple[int, NDArray[np.generic], str]]:
        for ts, p in sorted(files.items()):
            yield ts, read_image(p), str(p)

    return gen(), len(files), str(folder)


def detect_views(
    path: str | Path,
    camera: str,
    target: TargetGeometry,
    topic: str | None = None,
    every: int = 1,
    min_corners: int = 12,
    progress: bool = True,
    jobs: int = 1,
) -> tuple[list[View], tuple[int, int], int, str]:
    """Detect the target in one camera's images, streaming (only corners are kept), on ``jobs``
    processes (:mod:`dcc_fg.sources.parallel_detection`; the same views for any value).

    Returns:
        (views with >= ``min_corners`` corners, resolution (w, h), images read, description).

    Raises:
        ValueError: naming the data: no images, images of different sizes, the target found in
            none of them.
    """
    if every < 1:
        raise ValueError("every must be >= 1")
    images, count, where = camera_images(path, camera, topic)
    read: deque[tuple[int, str]] = deque()  # stamp and source of the images in flight
    size_of: dict[str, tuple[int, int]] = {}

    def every_nth() -> Iterator[NDArray[np.generic]]:
        for k, (ts, img, src) in enumerate(images):
            if k % every:
                continue
            size = (int(img.shape[1]), int(img.shape[0]))
            first = size_of.setdefault("first", size)
            if size != first:
                raise ValueError(f"{src}: image is {size[0]}x{size[1]}, earlier images of {where} are {first}")
            read.append((ts, src))
            yield img

    views: list[View] = []
    n_read = 0
    total = (count + every - 1) // every
    results = detect_images(every_nth(), target, detect_target, jobs)
    for obs in tqdm(results, total=total, desc=f"detect {camera}", disable=not progress):
        ts, src = read.popleft()
        n_read += 1
        if len(obs) >= min_corners:
            views.append(View(ts, obs, src))
    resolution = size_of.get("first")
    if resolution is None:
        raise ValueError(f"{where}: no images")
    if not views:
        kind = f"{target.target_type} {target.cols}x{target.rows}"
        raise ValueError(
            f"{where}: target ({kind}) not found with >= {min_corners} corners in any of {n_read} images "
            "(check target.yaml: targetCols/targetRows count inner corners, tagCols/tagRows count tags)"
        )
    return views, resolution, n_read, where


def select_views(views: list[View], max_views: int) -> list[View]:
    """At most ``max_views`` views, evenly spaced in recording order (all if there are fewer)."""
    if max_views <= 0 or len(views) <= max_views:
        return list(views)
    idx = np.unique(np.round(np.linspace(0, len(views) - 1, max_views)).astype(int))
    return [views[i] for i in idx]


# ------------------------------------------------------------------ calibration


def _object_image_points(views: list[View], target: TargetGeometry) -> tuple[list[FloatArray], list[FloatArray]]:
    P = target.points
    return [P[v.observation.ids].astype(np.float64) for v in views], [v.observation.pixels for v in views]


def calibrate_intrinsics(
    views: list[View],
    target: TargetGeometry,
    resolution: tuple[int, int],
    model: str = "pinhole-radtan",
    source: str = "",
) -> IntrinsicsResult:
    """Calibrate one camera from target views (see the module docstring).

    Args:
        views: target observations (pixels in the distorted image); >= 3 views.
        target: the target geometry (points in metres).
        resolution: image (width, height) in pixels.
        model: ``pinhole-radtan`` or ``pinhole-equidistant``.
        source: description for messages.

    Raises:
        ValueError: unknown model, too few views, or an optimizer failure (naming ``source``).
    """
    if model not in MODELS:
        raise ValueError(f"camera model '{model}' is not one of {', '.join(MODELS)}")
    if len(views) < 3:
        raise ValueError(f"{source}: {len(views)} views with the target; need at least 3 for intrinsics")
    dist_model = MODELS[model]
    obj, img = _object_image_points(views, target)
    w, h = resolution
    try:
        if dist_model == "radtan":
            _, K, dist, rvecs, tvecs = cv2.calibrateCamera(
                [o.astype(np.float32) for o in obj],
                [i.astype(np.float32) for i in img],
                (w, h),
                None,
                None,
                flags=cv2.CALIB_FIX_K3,
                criteria=_CRITERIA,
            )
            coeffs = np.asarray(dist, float).ravel()[:4]
        else:
            flags = _fisheye_flag("CALIB_RECOMPUTE_EXTRINSIC") | _fisheye_flag("CALIB_FIX_SKEW")
            # (1, N, C) point arrays: OpenCV 5's fisheye.calibrate rejects (N, 1, C)
            _, K, dist, rvecs, tvecs = cv2.fisheye.calibrate(
                [o.reshape(1, -1, 3) for o in obj],
                [i.reshape(1, -1, 2) for i in img],
                (w, h),
                np.eye(3),
                np.zeros(4),
                flags=flags,
                criteria=_CRITERIA,
            )
            coeffs = np.asarray(dist, float).ravel()[:4]
    except cv2.error as exc:
        raise ValueError(f"{source}: OpenCV could not calibrate the {model} model ({exc.err})") from None
    camera = CameraModel((K[0, 0], K[1, 1], K[0, 2], K[1, 2]), dist_model, tuple(float(c) for c in coeffs), (w, h))
    rv = [np.asarray(r, float).ravel() for r in rvecs]
    tv = [np.asarray(t, float).ravel() for t in tvecs]
    T_ct = np.array([_pose(r, t) for r, t in zip(rv, tv, strict=True)])
    residuals = [
        camera.project(o @ T[:3, :3].T + T[:3, 3], jacobian=False)[0] - i
        for o, i, T in zip(obj, img, T_ct, strict=True)
    ]
    if not all(np.all(np.isfinite(r)) for r in residuals):
        raise ValueError(f"{source}: the {model} calibration diverged (non-finite reprojection)")
    sq = np.concatenate([np.sum(r * r, axis=1) for r in residuals])
    rms = float(np.sqrt(sq.mean()))
    with stage("intrinsics covariance", hint="record views that cover the image and tilt the target"):
        std = intrinsics_std(camera, obj, rv, tv, residuals)
    return IntrinsicsResult(
        camera=camera,
        std=dict(zip(PARAM_NAMES[dist_model], std.tolist(), strict=True)),
        rms_px=rms,
        rms_per_axis_px=rms / np.sqrt(2.0),
        per_view_rms_px=np.array([np.sqrt(np.mean(np.sum(r * r, axis=1))) for r in residuals]),
        T_ct=T_ct,
        views=list(views),
        source=source,
    )


def _fisheye_flag(name: str) -> int:
    """A ``cv2.fisheye`` flag: ``cv2.fisheye.<name>`` in OpenCV 4, ``cv2.<name>`` in OpenCV 5."""
    return int(getattr(cv2.fisheye, name, None) or getattr(cv2, name))


def _pose(rvec: FloatArray, tvec: FloatArray) -> FloatArray:
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(rvec)[0]
    T[:3, 3] = tvec
    return T


def projection_jacobians(
    camera: CameraModel, p_t: FloatArray, rvec: FloatArray, tvec: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Projected pixels (N, 2) and the Jacobians of the stacked (u, v) rows (2N) with respect to
    the 8 intrinsics ``[fx, fy, cx, cy, d1..d4]`` (2N, 8) and the view pose ``[rvec, tvec]``
    (2N, 6), from OpenCV's analytic projection Jacobians."""
    K, d = camera.K, camera.opencv_dist
    p_t = np.ascontiguousarray(p_t, dtype=np.float64)  # OpenCV ignores the strides of a sliced array
    if camera.distortion_model == "equidistant":
        uv, J = cv2.fisheye.projectPoints(p_t.reshape(-1, 1, 3), rvec, tvec, K, d)
        return uv.reshape(-1, 2), J[:, 0:8], J[:, 8:14]  # columns f(2) c(2) k(4) om(3) T(3) alpha
    uv, J = cv2.projectPoints(p_t, rvec, tvec, K, d)
    return uv.reshape(-1, 2), J[:, 6:14], J[:, 0:6]  # columns om(3) T(3) f(2) c(2) dist(4)


def intrinsics_std(
    camera: CameraModel,
    obj: list[FloatArray],
    rvecs: list[FloatArray],
    tvecs: list[FloatArray],
    residuals: list[FloatArray],
) -> FloatArray:
    """1-sigma of the 8 intrinsics: Gauss-Newton covariance with the view poses eliminated,
    scaled by the a-posteriori corner variance (module docstring)."""
    S = np.zeros((8, 8))
    n_obs = 0
    for p, r, t in zip(obj, rvecs, tvecs, strict=True):
        _, J_i, J_p = projection_jacobians(camera, p, r, t)
        H_pp = J_p.T @ J_p
        H_ip = J_i.T @ J_p
        S += J_i.T @ J_i - H_ip @ np.linalg.solve(H_pp, H_ip.T)
        n_obs += J_i.shape[0]
    dof = n_obs - 8 - 6 * len(obj)
    if dof <= 0:
        return np.full(8, np.nan)
    s2 = float(sum(np.sum(r * r) for r in residuals)) / dof
    try:
        cov = np.linalg.inv(S) * s2
    except np.linalg.LinAlgError:
        return np.full(8, np.nan)
    return np.sqrt(np.maximum(np.diag(cov), 0.0))


# ------------------------------------------------------------------ output


def write_intrinsics_camchain(
    out: str | Path, camera_name: str, result: IntrinsicsResult, rostopic: str | None = None
) -> Path:
    """Write (or update) a Kalibr camchain YAML with ``camera_name``'s entry, atomically.

    An existing camchain at ``out`` keeps its other cameras (and this camera's pass-through
    fields such as ``T_cn_cnm1``), so cam0 and cam1 can be calibrated one after the other.
    """
    out = Path(out)
    entries: dict[str, CamchainEntry] = load_camchain(out) if out.exists() else {}
    old = entries.get(camera_name)
    extra = old.extra if old is not None else {}
    topic = rostopic if rostopic is not None else (old.rostopic if old is not None else None)
    entries[camera_name] = CamchainEntry(result.camera, topic, extra)
    write_text_atomic(out, camchain_to_yaml(dict(sorted(entries.items()))))
    return out


def run_intrinsics(
    data: str | Path,
    target: TargetGeometry,
    camera: str = "cam0",
    model: str = "pinhole-radtan",
    out: str | Path | None = None,
    topic: str | None = None,
    every: int = 1,
    max_views: int = 80,
    min_corners: int = 12,
    max_rms: float = 2.0,
    progress: bool = True,
    accept_unhealthy: bool = False,
    jobs: int = 1,
) -> IntrinsicsResult:
    """Detect, select views, calibrate, and (if ``out``) write the camchain entry.

    Args:
        data: bag, ROS2 bag folder, or folder with ``<camera>/<timestamp_ns>.png``.
        target: the calibration target.
        camera: camchain entry name and image sub-folder (``cam0`` / ``cam1``).
        model: ``pinhole-radtan`` | ``pinhole-equidistant``.
        out: camchain YAML to write or update (atomically); None writes nothing.
        topic: image topic in a bag (default ``/<camera>/image_raw``).
        every: use every n-th image.
        max_views: at most this many views (evenly spaced in time) enter the calibration.
        min_corners: a view needs at least this many corners.
        max_rms: a result whose RMS reprojection error exceeds this many pixels is unhealthy
            (wrong target dimensions or bad detections, not a camera); see
            :func:`dcc_fg.intrinsics_health.intrinsics_health` for every check.
        progress: tqdm progress bar over the images.
        accept_unhealthy: return (and write) a result that failed a health check; otherwise
            :class:`~dcc_fg.util.health.UnhealthyResultError` is raised and nothing is written. The
            report is in ``result.extra['health']``.
        jobs: processes detecting the target (same views for any value; 1: this process only).
    """
    if model not in MODELS:
        raise ValueError(f"camera model '{model}' is not one of {', '.join(MODELS)}")
    views, resolution, n_read, where = detect_views(data, camera, target, topic, every, min_corners, progress, jobs)
    used = select_views(views, max_views)
    result = calibrate_intrinsics(used, target, resolution, model, where)
    result.n_images, result.n_detected = n_read, len(views)
    health = intrinsics_health(result, max_rms)
    result.extra["health"] = health
    if not health.healthy and not accept_unhealthy:
        raise UnhealthyResultError(health)
    if out is not None:
        bag_topic = (topic or f"/{camera}/image_raw") if is_bag(Path(data)) else None
        write_intrinsics_camchain(out, camera, result, bag_topic)
    return result
