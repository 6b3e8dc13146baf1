"""``dcc-fg calibrate DATA --cluster CLUSTER.yaml``: an N-camera cluster calibrated in one graph.

The cameras and their mounts come from one of

* ``--cluster CLUSTER.yaml``: the ``cameras:`` / ``chains:`` form (:mod:`dcc_fg.cluster`) with every
  camera's intrinsics; its kinematic values (static ``T_cs``, chains' ``tau_s`` / ``dh``, cameras'
  ``tau_d``) are the hand-measured start used by ``--init file``;
* ``--camchain camchain.yaml --mounts cam2=gimbal:2[,cam3=gimbal]``: a Kalibr camchain for the
  intrinsics (``cam0 .. camN-1``) and the cameras on chains as ``camN=CHAIN:L`` (L joints; ``:L``
  may be left out when another camera on the chain gives it); every other camera is static. There are
  no kinematic values then, so only ``--init auto`` is possible.

``--init auto`` (default) starts from :func:`dcc_fg.cluster_init.auto_initialize_cluster` (only the
mounts and joint counts are used), ``--init file`` (or ``gimbal``) from the ``--cluster`` file's values.
DATA is an N-camera detection folder (``camK/<timestamp_ns>.csv`` in yac's layout, what ``dcc-fg
simulate calibration --cluster`` writes; :func:`dcc_fg.cluster_data.read_cluster_detections`); image
folders and bags are refused for now (named).

Frames (docs/architecture.md): ``s`` = cam0, the reference static camera; ``T_cs`` maps points of s
into camera c (metres); angles in radians; stamps integer nanoseconds; pixels where a name says so.

Outputs (one :class:`~dcc_fg.io.output_set.OutputSet`, written only when the result is healthy or
``--accept-unhealthy``):

* ``calibration.yaml``: the cluster form with the estimates, their 1-sigma (``chains.K.tau_s_std``,
  ``chains.K.dh_std``, ``cameras.camN.tau_d_std``; null where the gauge holds a value) and intrinsics;
  ``statistics`` holds what the schema has no field for: the static cameras' ``T_cs`` 1-sigma
  (tangent ``[omega, v]``, rad and m), the observability report and gauge-fixed parameters, the
  per-camera ``T_cs(theta_i)`` 1-sigma and the reprojection errors;
* ``joint_angles.csv``: ``timestamp_ns,theta_1..theta_J``: every chain's joints in the flat order
  (chains in file order, ``statistics.joint_columns`` names them), NaN where no camera of a chain saw
  the target;
* ``summary.json``: provenance, the statistics and the ``health`` block (:func:`cluster_health`).
"""

from __future__ import annotations

import argparse
import dataclasses
import io
import json
import logging
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import NDArray
from scipy import stats

from dcc_fg.calibration_health import FULL_TURN, RMS_RATIO_LIMIT, circular_span
from dcc_fg.cluster import CAMERA_NAME, CHAIN_NAME_RULE, TAU_NAMES, CameraCluster, ChainSpec, valid_chain_name
from dcc_fg.cluster_calibration import ClusterCalibrationResult, ClusterOptions, calibrate_cluster
from dcc_fg.cluster_data import ClusterDataset, read_cluster_detections
from dcc_fg.cluster_init import auto_initialize_cluster
from dcc_fg.commands import common
from dcc_fg.init import pnp_pose
from dcc_fg.io.bags import is_bag
from dcc_fg.io.camchain import load_camchain
from dcc_fg.io.detections import is_detection_csv, read_detection_table
from dcc_fg.io.folders import IMAGE_SUFFIXES, list_timestamped
from dcc_fg.io.output_set import OutputSet
from dcc_fg.io.outputs import plain, write_text_atomic
from dcc_fg.model import GimbalCalibration, load_calibration
from dcc_fg.noise_floor import refine_poses
from dcc_fg.targets import TargetGeometry, load_target
from dcc_fg.util.config import apply_overrides, load_yaml_config
from dcc_fg.util.errors import stage
from dcc_fg.util.health import FALSE_ALARM_PROBABILITY, HealthCheck, HealthReport
from dcc_fg.util.provenance import run_record
from factors.camera import CameraModel

FloatArray = NDArray[np.float64]

log = logging.getLogger(__name__)

REFERENCE = "cam0"
POSE_NAMES = ("wx", "wy", "wz", "vx", "vy", "vz")
#: A camera centre farther than this from cam0 (m) is outside any physical cluster.
MAX_CAMERA_DISTANCE_M = 10.0
#: ``section.key`` options of ``calibrate`` that an N-camera calibration uses (same meaning).
CLUSTER_OPTIONS = (
    "init.method",
    "reader.sync_tolerance_ms",
    "solver.pixel_sigma",
    "solver.robust",
    "solver.robust_k",
    "output.accept_unhealthy",
)
#: The flags of the other ``calibrate`` options, for messages (an unknown one is shown by its option name).
FLAG_OF = {
    "init.joints": "--joints",
    "init.search": "--search",
    "solver.nominal": "--nominal",
    "solver.mode": "--mode",
    "solver.formulation": "--formulation",
    "solver.corner_noise": "--corner-noise",
    "reader.sync": "--sync",
    "reader.time_offsets": "--time-offsets",
    "reader.fix_time_offsets": "--fix-time-offsets",
    "reader.max_snapshots": "--max-snapshots",
    "reader.jobs": "--jobs",
    "reader.min_common_points": "--min-common-points",
    "reader.corners": "--corners",
    "output.report": "--report",
}

CLUSTER_HELP = (
    "N-camera cluster: a cameras:/chains: YAML (every camera's intrinsics, mounts, chains with joint counts; its "
    "kinematic values are the start of --init file). DATA is then a detection folder cam0/ .. camN-1/ "
    "(<timestamp_ns>.csv, yac layout). Writes calibration.yaml (cluster form with 1-sigma), joint_angles.csv "
    "(every chain's joints, NaN where unseen) and summary.json"
)
MOUNTS_HELP = (
    "N-camera cluster from --camchain (intrinsics of cam0 .. camN-1): the cameras on gimbal chains as "
    "camN=CHAIN:L[,camM=CHAIN[:L]] (L joints of the chain; every other camera static), e.g. cam2=gimbal:2; "
    "the start is the automatic initialization (--init auto)"
)


# ------------------------------------------------------------------------------------------- options


@dataclass
class ClusterInitOptions:
    """``method``: ``auto`` (the automatic initialization, default) or ``file`` (the ``--cluster``
    file's kinematic values; ``gimbal`` is read as ``file``)."""

    method: str = "auto"

    def __post_init__(self) -> None:
        if self.method == "gimbal":
            self.method = "file"
        if self.method not in ("auto", "file"):
            raise ValueError(f"method must be auto or file, got {self.method!r}")


@dataclass
class ClusterReaderOptions:
    """``sync_tolerance_ms``: frames of different cameras within this many milliseconds of each other
    form one snapshot (:func:`dcc_fg.cluster_data.read_cluster_detections`)."""

    sync_tolerance_ms: float = 5.0

    def __post_init__(self) -> None:
        if not (np.isfinite(self.sync_tolerance_ms) and self.sync_tolerance_ms > 0):
            raise ValueError(f"sync_tolerance_ms must be a positive number of ms, got {self.sync_tolerance_ms}")


@dataclass
class ClusterSolverOptions:
    """``pixel_sigma``: corner noise (px, 1 sigma; None: estimated); ``robust`` / ``robust_k``: per-corner
    loss (None, ``huber``, ``cauchy``) and its threshold (px); ``max_iterations`` of Levenberg-Marquardt."""

    pixel_sigma: float | None = None
    robust: str | None = None
    robust_k: float = 2.0
    max_iterations: int = 500

    def __post_init__(self) -> None:
        if self.robust not in (None, "huber", "cauchy"):
            raise ValueError(f"robust must be huber or cauchy, got {self.robust!r}")
        ClusterOptions(self.pixel_sigma, self.robust, self.robust_k, self.max_iterations)  # its own checks

    def options(self) -> ClusterOptions:
        return ClusterOptions(self.pixel_sigma, self.robust, self.robust_k, self.max_iterations)


@dataclass
class ClusterOutputOptions:
    """``accept_unhealthy``: write a result that failed its health checks (``health.healthy: false``)."""

    accept_unhealthy: bool = False


@dataclass
class ClusterCalibrateConfig:
    """Every option of ``dcc-fg calibrate --cluster`` (sections of the ``--config`` YAML)."""

    init: ClusterInitOptions = field(default_factory=ClusterInitOptions)
    reader: ClusterReaderOptions = field(default_factory=ClusterReaderOptions)
    solver: ClusterSolverOptions = field(default_factory=ClusterSolverOptions)
    output: ClusterOutputOptions = field(default_factory=ClusterOutputOptions)


@dataclass(frozen=True)
class ClusterInputs:
    """Input files of an N-camera run: DATA, and either ``cluster`` or ``camchain`` + ``mounts``."""

    data: str
    cluster: str | None = None
    camchain: str | None = None
    mounts: str | None = None
    target: str | None = None

    def by_option(self, config_file: str | Path | None = None) -> dict[str, str | Path | None]:
        """The input paths by the option that gave them, for the output checks."""
        return {
            "DATA": self.data,
            "--cluster": self.cluster,
            "--camchain": self.camchain,
            "--target": self.target,
            "--config": config_file,
        }

    def paths(self) -> dict[str, str | None]:
        return {"data": self.data, "cluster": self.cluster, "camchain": self.camchain, "target": self.target}


@dataclass
class ClusterSetup:
    """The cameras and mounts of a run.

    Attributes:
        source: the file that described them (messages).
        cameras: camera name -> intrinsics, ``cam0 .. camN-1``.
        mounts: camera -> chain name (None: static).
        joints: chain -> L, in the order of the flat joint-angle vector.
        start: the file's cluster (``--cluster``; its kinematics are the ``--init file`` start), else None.
        rostopics: camera -> image topic, where the file gives one.
    """

    source: str
    cameras: dict[str, CameraModel]
    mounts: dict[str, str | None]
    joints: dict[str, int]
    start: CameraCluster | None = None
    rostopics: dict[str, str] = field(default_factory=dict)


@dataclass
class ClusterRun:
    """What :func:`run_calibrate_cluster` produced: the result, the data, the health and the files."""

    result: ClusterCalibrationResult
    data: ClusterDataset
    health: HealthReport
    paths: list[Path]


# ------------------------------------------------------------------------------------------- inputs


def parse_mounts(text: str, cameras: list[str], source: str) -> tuple[dict[str, str], dict[str, int]]:
    """``--mounts camN=CHAIN:L,...`` -> (camera -> chain, chain -> L in order of first appearance).

    Raises:
        ValueError: naming ``--mounts`` and the item: malformed items, a camera not in ``cameras`` (of
            ``source``) or given twice, cam0 on a chain, a bad chain name, a chain without L or with two.
    """
    mounts: dict[str, str] = {}
    joints: dict[str, int | None] = {}
    items = [s.strip() for s in text.split(",")]
    for item in items:
        cam, sep, rest = item.partition("=")
        cam, rest = cam.strip(), rest.strip()
        if not sep or not cam or not rest:
            raise ValueError(f"--mounts {text!r}: item {item!r}: expected camN=CHAIN:L (e.g. cam2=gimbal:2)")
        name, colon, count = rest.partition(":")
        name = name.strip()
        if not CAMERA_NAME.match(cam):
            raise ValueError(f"--mounts {text!r}: item {item!r}: cameras are named cam0, cam1, ... (Kalibr's names)")
        if cam not in cameras:
            raise ValueError(f"--mounts {text!r}: camera {cam} is not in {source} (cameras: {', '.join(cameras)})")
        if cam == REFERENCE:
            raise ValueError(f"--mounts {text!r}: cam0 is the reference static camera s; it cannot sit on a chain")
        if cam in mounts:
            raise ValueError(f"--mounts {text!r}: camera {cam} is given twice")
        if not valid_chain_name(name):
            raise ValueError(f"--mounts {text!r}: item {item!r}: chain name {name!r}: {CHAIN_NAME_RULE}")
        L: int | None = None
        if colon:
            try:
                L = int(count.strip())
            except ValueError:
                raise ValueError(f"--mounts {text!r}: item {item!r}: L must be a joint count 0..6") from None
            if not 0 <= L <= 6:
                raise ValueError(f"--mounts {text!r}: item {item!r}: L must be a joint count 0..6, got {L}")
        previous = joints.get(name)
        if previous is not None and L is not None and previous != L:
            raise ValueError(f"--mounts {text!r}: chain {name} given {previous} and {L} joints")
        joints[name] = L if L is not None else previous
        mounts[cam] = name
    missing = [ch for ch, L in joints.items() if L is None]
    if missing:
        raise ValueError(f"--mounts {text!r}: no joint count for chain(s) {', '.join(missing)} (write camN=CHAIN:L)")
    return mounts, {ch: int(L) for ch, L in joints.items() if L is not None}


def cluster_setup(inputs: ClusterInputs) -> ClusterSetup:
    """The cameras, intrinsics and mounts of ``inputs`` (``--cluster``, or ``--camchain`` + ``--mounts``).

    Raises:
        ValueError: naming the file and field: a two-camera ``gimbal.yaml`` given to ``--cluster``, a
            camera without intrinsics, a bad ``--mounts``.
    """
    if inputs.cluster is not None:
        path = Path(inputs.cluster)
        if not path.is_file():
            raise FileNotFoundError(f"--cluster {path}: no such file")
        cal = load_calibration(path)
        if cal.layout is None:
            raise ValueError(
                f"{path}: a two-camera gimbal file (joints, tau_s, tau_d, dh), not the cameras:/chains: cluster form "
                "that --cluster needs (give it with --gimbal for two cameras, or describe every camera under "
                "cameras: and the chains under chains:)"
            )
        cluster = cal.cluster()
        lacking = [c.name for c in cluster.cameras if c.camera is None]
        if lacking:
            raise ValueError(
                f"{path}: cameras.{lacking[0]}: no intrinsics (camera_model, intrinsics, distortion_model, "
                f"distortion_coeffs, resolution){' (also ' + ', '.join(lacking[1:]) + ')' if lacking[1:] else ''}; "
                "the cluster file must give every camera's intrinsics"
            )
        cameras = {c.name: c.camera for c in cluster.cameras if c.camera is not None}
        return ClusterSetup(
            str(path),
            cameras,
            {c.name: c.chain for c in cluster.cameras},
            {ch.name: ch.n_joints for ch in cluster.chains},
            cluster,
            {c.name: c.rostopic for c in cluster.cameras if c.rostopic is not None},
        )
    assert inputs.camchain is not None and inputs.mounts is not None
    entries = load_camchain(inputs.camchain)
    names = list(entries)
    bad = [c for c in names if not CAMERA_NAME.match(c)]
    if bad:
        raise ValueError(f"{inputs.camchain}: camera entries must be named cam0, cam1, ... got {', '.join(bad)}")
    names.sort(key=lambda c: int(c[3:]))
    if names != [f"cam{k}" for k in range(len(names))]:
        raise ValueError(f"{inputs.camchain}: cameras must be cam0 .. cam{len(names) - 1} without gaps, got "
                         f"{', '.join(names)}")  # fmt: skip
    on_chain, joints = parse_mounts(inputs.mounts, names, inputs.camchain)
    mounts: dict[str, str | None] = {c: on_chain.get(c) for c in names}
    return ClusterSetup(
        str(inputs.camchain),
        {c: entries[c].camera for c in names},
        mounts,
        joints,
        None,
        {c: e.rostopic for c, e in entries.items() if e.rostopic is not None},
    )


def check_detection_folder(data: Path, cameras: list[str], source: str) -> None:
    """DATA must be an N-camera detection folder holding exactly the folders ``cameras`` (of ``source``).

    Raises:
        ValueError: naming the path: no such folder, a bag or image folder (not supported for N cameras
            yet), a camera folder missing or not described by ``source``, CSV files not in yac's layout.
    """
    if not data.exists():
        raise ValueError(f"{data}: no such file or folder")
    if is_bag(data):
        raise ValueError(
            f"{data}: a bag; dcc-fg calibrate --cluster reads N-camera detection folders only for now (camK/"
            "<timestamp_ns>.csv in yac's layout): detect the target in each camera's images first"
        )
    if not data.is_dir():
        raise ValueError(f"{data}: not a folder; --cluster expects a detection folder cam0/ .. camN-1/")
    present = sorted((p.name for p in data.iterdir() if p.is_dir() and CAMERA_NAME.match(p.name)),
                     key=lambda c: int(c[3:]))  # fmt: skip
    if not present:
        raise ValueError(f"{data}: no camera folders cam0/ .. camN-1/ (an N-camera detection folder holds "
                         "camK/<timestamp_ns>.csv)")  # fmt: skip
    for cam in present:
        files = [p for p in (data / cam).iterdir() if p.is_file()]
        if any(p.suffix.lower() in IMAGE_SUFFIXES for p in files):
            raise ValueError(
                f"{data / cam}: holds images; dcc-fg calibrate --cluster reads detection folders only for now (camK/"
                "<timestamp_ns>.csv in yac's layout): detect the target in each camera's images first"
            )
        csvs = sorted(p for p in files if p.suffix.lower() == ".csv")
        if csvs and not is_detection_csv(csvs[0]):
            raise ValueError(f"{csvs[0]}: CSV without yac's detection header (#ts,tag_rows,...,tag_id,corner_idx)")
    missing = [c for c in cameras if c not in present]
    if missing:
        raise ValueError(
            f"{data}: no camera folder {', '.join(c + '/' for c in missing)} for camera(s) "
            f"{', '.join(f'cameras.{c}' for c in missing)} of {source}; the folder has {', '.join(present)}"
        )
    extra = [c for c in present if c not in cameras]
    if extra:
        raise ValueError(
            f"{data / extra[0]}: camera folder of a camera {source} does not describe (its cameras: "
            f"{', '.join(cameras)}); describe {', '.join(extra)} there or move the folder away"
        )


def target_of(inputs: ClusterInputs, data: Path, cameras: list[str]) -> TargetGeometry:
    """``--target``, else the AprilGrid of the first detection file with rows."""
    if inputs.target is not None:
        return load_target(inputs.target)
    for cam in cameras:
        for _, path in sorted(list_timestamped(data / cam, (".csv",)).items()):
            table = read_detection_table(path)
            if table.grid is not None:
                rows, cols, size, spacing = table.grid
                return TargetGeometry.aprilgrid(cols, rows, size, spacing)
    raise ValueError(f"{data}: no detection file with corners; nothing to calibrate from")


# ------------------------------------------------------------------------------------------- health


def _parameter_counts(result: ClusterCalibrationResult) -> tuple[int, int, int]:
    """(free constant parameters, joint-angle unknowns, held mean angles) of the graph."""
    fixed = set(result.gauge_fixed)
    n_global = sum(1 for n in result.parameter_std if n not in fixed)
    n_theta = sum(int(np.isfinite(th).all(axis=1).sum()) * th.shape[1] for th in result.joint_angles.values())
    n_offsets = sum(1 for n in result.gauge_fixed if n.endswith(".mean"))
    return n_global, n_theta, n_offsets


def camera_floors(data: ClusterDataset, result: ClusterCalibrationResult) -> dict[str, tuple[float, int, float, int]]:
    """Per camera, the model-independent noise floor over the used snapshots (a free target pose per
    image, PnP refined on the pixels; :func:`dcc_fg.calibration_health.refine_poses`): camera ->
    (floor sum of squares px^2, its degrees of freedom 2N - 6 per image, the model's sum of squares px^2,
    corner count N)."""
    out = {}
    for cam, blocks in result.residuals.items():
        if not blocks:
            continue
        p_t, uv = [], []
        for pos, _ in blocks:
            obs = data.snapshots[int(result.snapshot_index[pos])].observations[cam]
            p_t.append(data.target_points[obs.ids])
            uv.append(obs.pixels)
        T0 = np.array([pnp_pose(data.cameras[cam], p, z) for p, z in zip(p_t, uv, strict=True)])
        _, ss, _ = refine_poses(data.cameras[cam], p_t, uv, T0)
        n = np.array([len(z) for z in uv])
        ss_model = float(sum(float(np.sum(r * r)) for _, r in blocks))
        out[cam] = (float(ss.sum()), int(np.sum(np.maximum(2 * n - 6, 0))), ss_model, int(n.sum()))
    return out


def cluster_health(result: ClusterCalibrationResult, data: ClusterDataset, max_iterations: int) -> HealthReport:
    """Health checks of an N-camera calibration (as :mod:`dcc_fg.calibration_health` for two cameras).

    * ``residuals.camN``: per camera, the RMS residual against the camera's noise floor (per-image PnP,
      model independent): fails when the extra sum of squares is significant (F-test at the false-alarm
      probability with the parameters the model saves over the floor) and the RMS exceeds
      :data:`~dcc_fg.calibration_health.RMS_RATIO_LIMIT` times the floor's;
    * ``residuals.pixel_sigma`` (with a given pixel sigma): whitened chi-square and the same RMS margin;
    * ``convergence``: finite costs, not stopped on the iteration cap, at least one iteration unless at
      the noise already;
    * ``finite``: estimates and the 1-sigma of the estimated parameters are finite;
    * ``joint_angles.range``: each chain's estimated angles finite (span: the shortest arc holding them);
    * ``geometry.distances``: every camera centre within :data:`MAX_CAMERA_DISTANCE_M` of cam0.
    """
    report = HealthReport("calibration")
    p = FALSE_ALARM_PROBABILITY
    floors = camera_floors(data, result)
    n_global, n_theta, n_offsets = _parameter_counts(result)
    n_images = sum(len(b) for b in result.residuals.values())
    K = len(result.snapshot_index)
    q = 6 * n_images - (6 * K + n_theta + n_global - n_offsets)
    hint_model = "check the --cluster mounts and joint counts, the intrinsics and the target description"
    for cam, (ss_floor, dof, ss_model, n) in floors.items():
        s2 = max(ss_floor / max(dof, 1), 1e-18)
        rms = float(np.sqrt(ss_model / max(2 * n, 1)))
        rms_floor = float(np.sqrt(s2))
        ratio = rms / rms_floor
        if q > 0 and dof > 0:
            F = max(ss_model - ss_floor, 0.0) / q / s2
            F_lim = float(stats.f.ppf(1.0 - p, q, dof))
            significant = not F <= F_lim
        else:
            F, F_lim, significant = float("nan"), float("nan"), True
        passed = bool(np.isfinite(rms) and not (significant and ratio > RMS_RATIO_LIMIT))
        text = (
            f"residuals {rms:.3g} px RMS per axis in {cam} for a {rms_floor:.3g} px noise floor (PnP of each "
            f"image): {ratio:.1f}x the floor (limit {RMS_RATIO_LIMIT:g}x), F = {F:.3g} (limit {F_lim:.3g})"
        )
        report.add(HealthCheck(f"residuals.{cam}", passed, text, "" if passed else hint_model, ratio, RMS_RATIO_LIMIT))
    sigma = result.extra.get("pixel_sigma")
    n_obs = 2 * sum(f[3] for f in floors.values())
    ss_all = sum(f[2] for f in floors.values())
    if sigma is not None:
        dof_m = max(n_obs - (6 * K + n_theta + n_global - n_offsets), 1)
        chi = ss_all / sigma**2
        lim = float(stats.chi2.ppf(1.0 - p, dof_m))
        rms = float(np.sqrt(ss_all / max(n_obs, 1)))
        passed = not (chi > lim and rms > RMS_RATIO_LIMIT * sigma)
        text = (f"residuals {rms:.3g} px RMS per axis for the given pixel_sigma {sigma:g} px: chi-square {chi:.4g} "
                f"(limit {lim:.4g}, {dof_m} degrees of freedom)")  # fmt: skip
        hint = "" if passed else "give a --pixel-sigma that matches the detector, or omit it to estimate it"
        report.add(HealthCheck("residuals.pixel_sigma", bool(passed), text, hint, rms / sigma, RMS_RATIO_LIMIT))
    report.add(convergence_check(result, floors, max_iterations))
    report.add(finite_check(result))
    report.extend(joint_range_checks(result))
    report.add(distance_check(result))
    return report


def convergence_check(
    result: ClusterCalibrationResult, floors: Mapping[str, tuple[float, int, float, int]], max_iterations: int
) -> HealthCheck:
    """``convergence`` (see :func:`cluster_health`)."""
    hint = "start from --init auto (or better values in the --cluster file); raise solver.max_iterations"
    if not (np.isfinite(result.initial_error) and np.isfinite(result.final_error)):
        return HealthCheck("convergence", False, f"the cost is not finite (initial {result.initial_error}, final "
                           f"{result.final_error})", hint)  # fmt: skip
    if result.iterations >= max_iterations:
        return HealthCheck(
            "convergence",
            False,
            f"Levenberg-Marquardt stopped on its cap of {max_iterations} iterations: not converged",
            hint,
            float(result.iterations),
            float(max_iterations),
        )
    ss_floor = sum(f[0] for f in floors.values())
    dof = sum(f[1] for f in floors.values())
    ss_model = sum(f[2] for f in floors.values())
    at_noise = ss_model <= RMS_RATIO_LIMIT**2 * ss_floor / max(dof, 1) * max(2 * sum(f[3] for f in floors.values()), 1)
    if result.iterations == 0 and not at_noise:
        return HealthCheck("convergence", False, "Levenberg-Marquardt ran 0 iterations with a cost above the noise: "
                           "the result is the initial guess", hint, 0.0, 1.0)  # fmt: skip
    return HealthCheck("convergence", True, f"{result.iterations} iterations (cap {max_iterations})")


def finite_check(result: ClusterCalibrationResult) -> HealthCheck:
    """``finite``: kinematics and the estimated parameters' 1-sigma are finite numbers."""
    m = result.model
    values = [*m.tau_s.values(), *m.dh.values(), *m.tau_d.values(), *m.T_cs.values(), result.T_st]
    bad = []
    if not all(np.all(np.isfinite(v)) for v in values):
        bad.append("kinematic parameters or target poses")
    fixed = set(result.gauge_fixed)
    nan_std = [n for n, s in result.parameter_std.items() if n not in fixed and not np.isfinite(s)]
    if nan_std:
        bad.append(f"1-sigma of {', '.join(nan_std[:5])}{' ...' if len(nan_std) > 5 else ''}")
    if bad:
        return HealthCheck("finite", False, f"not finite: {'; '.join(bad)}", "check the data and the mounts")
    return HealthCheck("finite", True, "estimates and 1-sigma values are finite")


def joint_range_checks(result: ClusterCalibrationResult) -> list[HealthCheck]:
    """``joint_angles.range.CHAIN``: the chain's estimated angles (where estimated) finite."""
    out = []
    for ch, th in result.joint_angles.items():
        if th.size == 0 or th.shape[1] == 0:
            continue
        seen = ~np.all(np.isnan(th), axis=1)
        rows = th[seen]
        finite = bool(rows.size and np.all(np.isfinite(rows)))
        span = circular_span(rows) if finite else np.full(th.shape[1], np.inf)
        worst = int(np.argmax(span))
        text = (f"chain {ch} joint {worst + 1} covers {span[worst]:.4g} rad over {int(seen.sum())} snapshots (shortest "
                "arc holding every estimate)") if finite else f"chain {ch}: non-finite joint angles"  # fmt: skip
        hint = "" if finite else "check the chain's joint count and mounts"
        out.append(HealthCheck(f"joint_angles.range.{ch}", finite, text, hint, float(span[worst]), FULL_TURN))
    return out


def distance_check(result: ClusterCalibrationResult) -> HealthCheck:
    """``geometry.distances``: every camera centre (over the used snapshots) within
    :data:`MAX_CAMERA_DISTANCE_M` of cam0's."""
    worst, where = 0.0, REFERENCE
    for cam in result.model.cameras:
        for i in range(len(result.snapshot_index)):
            ch = result.model.mounts[cam]
            if ch is not None and not np.all(np.isfinite(result.joint_angles[ch][i])):
                continue
            T = result.T_cs(cam, i)
            d = float(np.linalg.norm(T[:3, :3].T @ T[:3, 3]))
            if not d <= worst:
                worst, where = d, cam
            if ch is None:
                break
    passed = bool(worst <= MAX_CAMERA_DISTANCE_M)
    text = f"camera {where} sits {worst:.4g} m from cam0 (largest; limit {MAX_CAMERA_DISTANCE_M:g} m)"
    hint = "" if passed else "check the target size (metres) and the mounts"
    return HealthCheck("geometry.distances", passed, text, hint, worst, MAX_CAMERA_DISTANCE_M)


# ------------------------------------------------------------------------------------------- outputs


def _std(result: ClusterCalibrationResult, names: list[str]) -> FloatArray:
    return np.array([result.parameter_std.get(n, np.nan) for n in names], dtype=float)


def estimated_cluster(result: ClusterCalibrationResult, setup: ClusterSetup) -> CameraCluster:
    """The estimate as a cluster with intrinsics, rostopics and 1-sigma (``tau_s_std``, ``dh_std``,
    ``tau_d_std``; NaN where held by the gauge)."""
    est = result.cluster()
    cams = []
    for m in est.cameras:
        extra: dict[str, Any] = {"rostopic": setup.rostopics.get(m.name)}
        if m.chain is not None:
            extra["tau_d_std"] = _std(result, [f"{m.name}.tau_d.{n}" for n in TAU_NAMES])
        cams.append(dataclasses.replace(m, **extra))
    chains = []
    for ch in est.chains:
        L = ch.n_joints
        dh_names = [f"{ch.name}.dh{k + 1}.{n}" for k in range(L) for n in ("d", "a", "alpha")]
        chains.append(ChainSpec(ch.name, ch.tau_s, ch.dh, _std(result, [f"{ch.name}.tau_s.{n}" for n in TAU_NAMES]),
                                _std(result, dh_names).reshape(L, 3)))  # fmt: skip
    return CameraCluster(tuple(cams), tuple(chains))


def T_cs_std_summary(result: ClusterCalibrationResult) -> dict[str, dict[str, float]]:
    """Per camera (not cam0), median / max over the snapshots of the ``T_cs(theta_i)`` 1-sigma: rotation
    (mrad) and translation (mm), the root of the trace of each 3x3 block of the tangent covariance."""
    out: dict[str, dict[str, float]] = {}
    for cam, cov in (result.T_cs_covariances or {}).items():
        if cam == REFERENCE:
            continue
        ok = np.all(np.isfinite(cov.reshape(len(cov), -1)), axis=1)
        if not ok.any():
            continue
        c = cov[ok]
        rot = 1e3 * np.sqrt(np.maximum(np.trace(c[:, :3, :3], axis1=1, axis2=2), 0.0))
        tra = 1e3 * np.sqrt(np.maximum(np.trace(c[:, 3:, 3:], axis1=1, axis2=2), 0.0))
        out[cam] = {
            "rotation_mrad_median": float(np.median(rot)),
            "rotation_mrad_max": float(rot.max()),
            "translation_mm_median": float(np.median(tra)),
            "translation_mm_max": float(tra.max()),
        }
    return out


def joint_columns(result: ClusterCalibrationResult) -> list[str]:
    """``CHAIN.theta_l`` of each column ``theta_1..theta_J`` of ``joint_angles.csv`` (flat order)."""
    return [f"{ch}.theta_{k + 1}" for ch in result.model.chain_order for k in range(result.model.n_joints(ch))]


def joint_angles_csv_text(result: ClusterCalibrationResult, data: ClusterDataset) -> str:
    """``timestamp_ns,theta_1..theta_J`` (integer ns, rad; chains in file order), one row per used
    snapshot, ``nan`` where no camera of a chain saw the target."""
    buf = io.StringIO()
    J = len(joint_columns(result))
    buf.write(",".join(["timestamp_ns"] + [f"theta_{k + 1}" for k in range(J)]) + "\n")
    for pos, idx in enumerate(result.snapshot_index):
        row = [result.joint_angles[ch][pos] for ch in result.model.chain_order]
        values = np.concatenate(row) if row else np.zeros(0)
        buf.write(",".join([str(int(data.snapshots[int(idx)].timestamp_ns))] + [f"{x:.12g}" for x in values]) + "\n")
    return buf.getvalue()


def observability_summary(result: ClusterCalibrationResult) -> dict[str, Any]:
    """Observable / gauge-fixed / gauge-dependent parameter names, null-space dimension vs gauge count."""
    fixed = set(result.gauge_fixed)
    names = list(result.observable) or list(result.parameter_std)
    return {
        "n_parameters": len(names),
        "n_observable": sum(bool(result.observable.get(n, False)) for n in names),
        "observable": [n for n in names if result.observable.get(n, False)],
        "gauge_fixed": list(result.gauge_fixed),
        "gauge_dependent": [n for n in names if not result.observable.get(n, False) and n not in fixed],
        "null_space_dim": int(result.null_space_dim),
        "n_gauge": int(result.n_gauge),
    }


def run_statistics(
    result: ClusterCalibrationResult, data: ClusterDataset, setup: ClusterSetup, init: str, total_s: float
) -> dict[str, Any]:
    """The ``statistics`` of calibration.yaml and summary.json (units in the key names: px, mrad, mm, s)."""
    rms = result.reprojection_rms()
    counts: dict[str, dict[str, int]] = {}
    for cam in data.camera_names:
        blocks = result.residuals.get(cam, [])
        counts[cam] = {
            "snapshots_seen": int(data.observation_counts().get(cam, 0)),
            "snapshots_used": len(blocks),
            "corners_used": int(sum(len(r) for _, r in blocks)),
        }
    static_std = {}
    for cam in result.model.static_unknown:
        static_std[cam] = [None if not np.isfinite(s) else float(s)
                           for s in _std(result, [f"{cam}.T_cs.{n}" for n in POSE_NAMES])]  # fmt: skip
    skipped = [int(data.snapshots[i].timestamp_ns) for i in result.skipped_snapshots]
    cameras = data.camera_names
    return {
        "cameras": {c: "static" if setup.mounts[c] is None else f"chain {setup.mounts[c]}" for c in cameras},
        "init": init,
        "reprojection_rms_px": rms,
        "counts": counts,
        "snapshots": {
            "total": len(data.snapshots),
            "used": len(result.snapshot_index),
            "skipped": len(skipped),
            "skipped_timestamps_ns": skipped,
            "skip_rule": "a snapshot is used when its cameras span at least two rigid groups (each static camera, "
            "each chain)",
        },
        "solver": {
            "iterations": int(result.iterations),
            "initial_error": float(result.initial_error),
            "final_error": float(result.final_error),
            "variance_factor": float(result.variance_factor),
            "pixel_sigma_px": float(np.sqrt(result.variance_factor) * (result.extra.get("pixel_sigma") or 1.0)),
            "solve_time_s": float(result.solve_time_s),
            "total_time_s": float(total_s),
        },
        "T_cs_std": {
            "frame": "tangent [wx, wy, wz, vx, vy, vz] of T_cs (s -> camera, right perturbation), rad and m",
            "static": static_std,
        },
        "T_cs_std_over_snapshots": T_cs_std_summary(result),
        "observability": observability_summary(result),
        "joint_columns": joint_columns(result),
    }


def write_cluster_files(
    out: Path,
    result: ClusterCalibrationResult,
    data: ClusterDataset,
    setup: ClusterSetup,
    statistics: dict[str, Any],
    summary: dict[str, Any],
) -> list[Path]:
    """calibration.yaml, joint_angles.csv and summary.json into ``out`` (the staging folder); every text
    is serialized before the first file is written. Returns the paths."""
    cal = GimbalCalibration.from_cluster(estimated_cluster(result, setup), statistics=statistics)
    cal_text = yaml.safe_dump(cal.to_dict(), sort_keys=False)
    csv_text = joint_angles_csv_text(result, data)
    json_text = json.dumps(plain(summary), indent=2) + "\n"
    out.mkdir(parents=True, exist_ok=True)
    paths = [out / "calibration.yaml", out / "joint_angles.csv", out / "summary.json"]
    for path, text in zip(paths, (cal_text, csv_text, json_text), strict=True):
        write_text_atomic(path, text)
    return paths


def summary_table(statistics: Mapping[str, Any]) -> str:
    """Per camera: mount, snapshots used, corners, RMS (px), median T_cs 1-sigma (mrad, mm)."""
    lines = [f"{'camera':8} {'mount':14} {'snapshots':>9} {'corners':>8} {'rms px':>8} {'rot mrad':>9} {'tra mm':>8}"]
    std = statistics["T_cs_std_over_snapshots"]
    for cam, mount in statistics["cameras"].items():
        c = statistics["counts"][cam]
        s = std.get(cam, {})
        rot, tra = s.get("rotation_mrad_median", float("nan")), s.get("translation_mm_median", float("nan"))
        lines.append(f"{cam:8} {mount:14} {c['snapshots_used']:>9} {c['corners_used']:>8} "
                     f"{statistics['reprojection_rms_px'][cam]:>8.3f} {rot:>9.3f} {tra:>8.3f}")  # fmt: skip
    sn = statistics["snapshots"]
    lines.append(f"snapshots used {sn['used']} of {sn['total']}; {statistics['solver']['iterations']} iterations")
    return "\n".join(lines)


# ------------------------------------------------------------------------------------------- the run


def run_calibrate_cluster(
    inputs: ClusterInputs,
    out: Path,
    config: ClusterCalibrateConfig,
    quiet: bool = False,
    config_file: str | Path | None = None,
) -> ClusterRun:
    """Calibrate the N-camera cluster of ``inputs`` (module docstring); writes ``out`` as one output set
    (checked before any work; nothing written when the run fails or its result is unhealthy and not
    accepted: :class:`~dcc_fg.util.health.UnhealthyResultError`, exit 3)."""
    t0 = time.perf_counter()
    setup = cluster_setup(inputs)
    if config.init.method == "file" and setup.start is None:
        raise ValueError("--init file starts from the kinematic values of a --cluster file; --camchain with --mounts "
                         "has none (use --init auto)")  # fmt: skip
    cameras = sorted(setup.cameras, key=lambda c: int(c[3:]))
    outputs = OutputSet(out, "calibrate", inputs.by_option(config_file))
    with outputs:
        folder = Path(inputs.data)
        check_detection_folder(folder, cameras, setup.source)
        target = target_of(inputs, folder, cameras)
        tol_ns = int(round(config.reader.sync_tolerance_ms * 1e6))
        data = read_cluster_detections(folder, setup.cameras, target, tol_ns)
        unseen = [c for c, n in data.observation_counts().items() if n == 0]
        if unseen:
            raise ValueError(f"{folder}: camera(s) {', '.join(unseen)} of {setup.source} never see the target "
                             f"({', '.join(str(folder / c) for c in unseen)} hold no corners)")  # fmt: skip
        if config.init.method == "auto":
            with stage("automatic initialization", hint="check the mounts and joint counts; or start from --init file"):
                start = auto_initialize_cluster(data, setup.mounts, setup.joints, list(setup.joints))
        else:
            assert setup.start is not None
            start = setup.start
        result = calibrate_cluster(data, start, config.solver.options())
        result.extra["pixel_sigma"] = config.solver.pixel_sigma
        health = cluster_health(result, data, config.solver.max_iterations)
        health_block = common.judge_health(health, config.output.accept_unhealthy)
        statistics = run_statistics(result, data, setup, config.init.method, time.perf_counter() - t0)
        provenance = run_record("calibrate", inputs.paths(), config)
        summary = {**provenance, "cluster": True, **statistics, "health": health_block}
        paths = write_cluster_files(outputs.path, result, data, setup, statistics, summary)
    final = [outputs.final(p) for p in paths]
    if not quiet:
        print(summary_table(statistics))
        print("wrote " + ", ".join(str(p) for p in final))
    return ClusterRun(result, data, health, final)


# ------------------------------------------------------------------------------------------- command line


def add_cluster_flags(c: argparse.ArgumentParser) -> None:
    """``--cluster`` and ``--mounts`` on the ``calibrate`` parser (its ``--init`` takes ``file`` for them)."""
    c.add_argument("--cluster", metavar="CLUSTER.yaml", help=CLUSTER_HELP)
    c.add_argument("--mounts", metavar="camN=CHAIN:L,...", help=MOUNTS_HELP)


def wants_cluster(args: argparse.Namespace) -> bool:
    """Whether ``calibrate`` runs on an N-camera cluster (``--cluster`` or ``--mounts`` given)."""
    return getattr(args, "cluster", None) is not None or getattr(args, "mounts", None) is not None


def check_cluster_args(args: argparse.Namespace) -> None:
    """Options that do not go with an N-camera calibration, refused by name (ValueError, exit 2)."""
    if args.cluster is not None and args.camchain is not None:
        raise ValueError("--cluster and --camchain: give the cameras either as a --cluster file (intrinsics and "
                         "mounts) or as --camchain with --mounts, not both")  # fmt: skip
    if args.cluster is not None and args.mounts is not None:
        raise ValueError("--cluster and --mounts: the --cluster file gives the mounts; --mounts goes with --camchain")
    if args.mounts is not None and args.camchain is None:
        raise ValueError("--mounts needs --camchain (the intrinsics of cam0 .. camN-1)")
    given = [f for f, v in (("--gimbal", getattr(args, "gimbal", None)), ("--rerun", getattr(args, "rerun", None)),
                            ("--rerun-spawn", getattr(args, "rerun_spawn", False)),
                            ("--incremental", getattr(args, "incremental", False))) if v]  # fmt: skip
    given += [FLAG_OF.get(k, k) for k in common.option_flags(args) if k not in CLUSTER_OPTIONS]
    if given:
        raise ValueError(
            f"{', '.join(given)}: not available with an N-camera cluster (--cluster / --mounts); it takes --init "
            "auto|file, --target, --sync-tolerance, --pixel-sigma, --robust, --robust-k, --accept-unhealthy, --config"
        )


def calibrate_cluster_command(args: argparse.Namespace) -> int:
    """The ``--cluster`` / ``--mounts`` branch of ``dcc-fg calibrate``."""
    check_cluster_args(args)
    path = getattr(args, "config", None)
    config = load_yaml_config(path, ClusterCalibrateConfig, "calibrate") if path else ClusterCalibrateConfig()
    overrides = {k: v for k, v in common.option_flags(args).items() if k in CLUSTER_OPTIONS}
    config = apply_overrides(config, overrides)
    inputs = ClusterInputs(args.data, args.cluster, args.camchain, args.mounts, args.target)
    run_calibrate_cluster(inputs, Path(args.out), config, args.quiet, path)
    return 0
