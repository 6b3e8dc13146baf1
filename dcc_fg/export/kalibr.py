"""The cluster frozen at given joint angles, as a Kalibr camchain (and camchain-imucam) YAML.

Tools that only know static rigs (Kalibr, OpenVINS, ORB-SLAM3 via Kalibr files...) can use the
cluster at one set of joint angles ``theta`` (rad). Kalibr's conventions (its wiki, "yaml formats"):

* ``cam0`` is the static camera s, ``cam1`` the gimbal camera d; ``intrinsics`` ``[fu, fv, pu, pv]``
  (pixels), ``distortion_model`` / ``distortion_coeffs``, ``resolution`` ``[width, height]``,
  ``rostopic``, ``cam_overlaps``;
* ``cam1.T_cn_cnm1`` maps points of camera n-1 into camera n: ``T_cn_cnm1 = T_ds(theta)``;
* camchain-imucam form (only where the calibration has an ``imu:`` section): ``camN.T_cam_imu`` maps IMU
  points into camera N: ``cam0.T_cam_imu = T_sI``, ``cam1.T_cam_imu = T_ds(theta) T_sI``; and
  ``camN.timeshift_cam_imu`` (s), ``t_imu = t_cam + timeshift``, from the calibration's
  ``imu.time_offsets: [t_s, t_d]`` (same convention), 0 where absent.

Matrices are written as plain YAML floats (shortest round-trip text), so
:func:`dcc_fg.io.camchain.load_camchain` reads back exactly the numbers of ``T_ds(theta)``.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from dcc_fg.data.vio import ImuConfig
from dcc_fg.io.camchain import CamchainEntry, camchain_to_yaml
from dcc_fg.model import GimbalCalibration

FloatArray = NDArray[np.float64]

#: Default image topics of cam0 (static) and cam1 (gimbal), as ``dcc-fg simulate`` writes them.
DEFAULT_TOPICS = ("/cam0/image_raw", "/cam1/image_raw")

_UNIT = re.compile(r"^(?P<number>.*?)\s*(?P<unit>deg|rad)$")


def parse_joint_angles(text: str, n_joints: int, source: str) -> FloatArray:
    """``--joints`` text -> (L,) joint angles in rad.

    ``THETA_1,...,THETA_L`` in radians, or in degrees with ``deg`` after the last number
    (``90,5deg``: every value in degrees; ``rad`` is accepted too). An empty text is the only valid
    value for L = 0.

    Raises:
        ValueError: naming ``--joints`` and ``source`` (the calibration): not numbers, a unit on a
            value other than the last, the wrong count, non-finite values, or radians beyond one turn.
    """
    parts = [p.strip() for p in text.split(",")] if text.strip() else []
    unit = "rad"
    if parts:
        m = _UNIT.match(parts[-1])
        if m:
            unit, parts[-1] = m["unit"], m["number"]
    values = []
    for k, p in enumerate(parts):
        try:
            values.append(float(p))
        except ValueError:
            raise ValueError(
                f"--joints {text!r}: theta_{k + 1} = {p!r} is not a number (write THETA_1,...,THETA_L in rad, or "
                "in degrees with 'deg' after the last number, e.g. 90,5deg)"
            ) from None
    if len(values) != n_joints:
        raise ValueError(
            f"--joints {text!r}: {len(values)} joint angle(s) given, but {source} has {n_joints} joint(s) "
            f"(theta_1..theta_{n_joints})"
        )
    for k, v in enumerate(values):
        if not math.isfinite(v):
            raise ValueError(f"--joints {text!r}: theta_{k + 1} must be finite, got {v}")
        if unit == "rad" and abs(v) > 2.0 * math.pi:
            raise ValueError(
                f"--joints {text!r}: theta_{k + 1} = {v:g} rad is beyond one turn; for degrees put 'deg' after the "
                "last number (e.g. --joints 90,5deg)"
            )
    th = np.array(values, dtype=float)
    return np.deg2rad(th) if unit == "deg" else th


def _matrix(T: FloatArray) -> list[list[float]]:
    return [[float(x) for x in row] for row in np.asarray(T, dtype=float)]


def _cameras(cal: GimbalCalibration, source: str) -> tuple[CamchainEntry, CamchainEntry]:
    """Kalibr entries of the static and the gimbal camera; ValueError naming ``source`` and the missing entry."""
    static, dynamic = cal.static_camera, cal.dynamic_camera
    if static is None or dynamic is None:
        missing = [n for n, c in (("cam0", static), ("cam1", dynamic)) if c is None]
        roles = {"cam0": "the static camera's", "cam1": "the gimbal (dynamic) camera's"}
        whose = " and ".join(roles[m] for m in missing)
        raise ValueError(
            f"{source}: no {' and no '.join(repr(m) for m in missing)} entry ({whose} intrinsics); a Kalibr "
            "camchain needs both cameras' intrinsics (dcc-fg calibrate writes them into calibration.yaml)"
        )
    return CamchainEntry(static), CamchainEntry(dynamic)


def frozen_camchain(
    cal: GimbalCalibration,
    theta: FloatArray,
    source: str,
    topics: tuple[str, str] = DEFAULT_TOPICS,
    imu: ImuConfig | None = None,
) -> dict[str, CamchainEntry]:
    """``{'cam0': static, 'cam1': gimbal}`` Kalibr entries with ``cam1.T_cn_cnm1 = T_ds(theta)``
    (module docstring); with ``imu`` the camchain-imucam form (``T_cam_imu``, ``timeshift_cam_imu``).

    Args:
        cal: the calibration, with both cameras' intrinsics (``cam0`` / ``cam1``).
        theta: (L,) joint angles, rad.
        source: the calibration file, for messages.
        topics: image topics of cam0 and cam1.
        imu: the calibration's ``imu:`` section (``T_sI``: IMU -> static camera; ``time_offsets``).

    Raises:
        ValueError: naming ``source``: a camera without intrinsics, or the wrong number of joint angles.
    """
    cam0, cam1 = _cameras(cal, source)
    T_ds = cal.T_ds(np.asarray(theta, dtype=float))
    cam0.rostopic, cam1.rostopic = topics
    cam0.extra = {"cam_overlaps": [1]}
    cam1.extra = {"cam_overlaps": [0], "T_cn_cnm1": _matrix(T_ds)}
    if imu is not None:
        t_s, t_d = imu.time_offsets if imu.time_offsets is not None else (0.0, 0.0)
        T_sI = np.asarray(imu.T_sI, dtype=float)
        cam0.extra.update({"T_cam_imu": _matrix(T_sI), "timeshift_cam_imu": float(t_s)})
        cam1.extra.update({"T_cam_imu": _matrix(T_ds @ T_sI), "timeshift_cam_imu": float(t_d)})
    return {"cam0": cam0, "cam1": cam1}


def camchain_text(entries: dict[str, CamchainEntry], header: list[str]) -> str:
    """The YAML text of ``entries`` after a ``#`` comment header."""
    return "".join(f"# {line}\n" for line in header) + camchain_to_yaml(entries)


def imucam_path(out: Path) -> Path:
    """Where the camchain-imucam form goes beside ``out``: ``camchain*.yaml`` -> ``camchain-imucam*.yaml``
    (Kalibr's names), any other ``NAME.EXT`` -> ``NAME-imucam.EXT``."""
    stem, suffix = out.stem, out.suffix or ".yaml"
    if stem.startswith("camchain"):
        return out.with_name(f"camchain-imucam{stem[len('camchain') :]}{suffix}")
    return out.with_name(f"{stem}-imucam{suffix}")
