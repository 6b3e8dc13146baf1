"""Kalibr camchain YAML: read/write ``pinhole`` cameras with ``radtan`` or ``equidistant`` distortion.

Kalibr's ``intrinsics`` are ``[fx, fy, cx, cy]`` (pixels; Kalibr names them fu, fv, pu, pv),
``resolution`` is ``[width, height]``.  Every field is checked when the file is loaded (finite
numbers, positive focal lengths and resolution, known distortion model with the right number of
coefficients, rigid ``T_cn_cnm1`` / ``T_cam_imu``); errors name the file, the entry and the field.
Fields we do not interpret (``T_cn_cnm1``, ``cam_overlaps``, ``timeshift_cam_imu``...) are kept
verbatim in :class:`CamchainEntry.extra` so a camchain round-trips unchanged;
:func:`camchain_transforms` chains the ``T_cn_cnm1`` into each camera's pose relative to cam0.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import NDArray

from dcc_fg.io import validate
from factors.camera import CameraModel

log = logging.getLogger(__name__)

REQUIRED = ("camera_model", "intrinsics", "distortion_model", "distortion_coeffs", "resolution")


@dataclass
class CamchainEntry:
    """One ``camN`` entry: the camera model, its ROS topic and the fields we pass through."""

    camera: CameraModel
    rostopic: str | None = None
    extra: dict[str, Any] = field(default_factory=dict)


#: Names of the four Kalibr intrinsics, for messages.
INTRINSIC_NAMES = ("fu", "fv", "pu", "pv")

#: Distortion coefficient counts per model (Kalibr's: radtan k1 k2 p1 p2, equidistant k1..k4).
DISTORTION_COUNTS = {"radtan": (4,), "equidistant": (4,), "none": (0, 4)}

#: Fields holding a 4x4 rigid transform (checked when present, kept verbatim).
TRANSFORM_FIELDS = ("T_cn_cnm1", "T_cam_imu")


def camera_from_dict(d: dict[str, Any], source: str, name: str = "") -> CameraModel:
    """Parse a Kalibr camera entry, checking every field; errors name ``source``, the entry and the field.

    Args:
        d: the entry (``camera_model``, ``intrinsics``, ``distortion_model``, ``distortion_coeffs``,
            ``resolution``, optional ``rostopic``, ``T_cn_cnm1``, ``T_cam_imu``, ``timeshift_cam_imu``).
        source: the file, for messages.
        name: the entry's name (``cam0``), for messages (``<source>: cam0.intrinsics[0] (fu) ...``).

    Raises:
        ValueError: a missing field; a camera or distortion model other than pinhole / radtan,
            equidistant, none; intrinsics that are not 4 finite numbers with positive focal
            lengths (pixels); a resolution that is not 2 positive integers; distortion
            coefficients that are not finite or of the wrong count; a transform that is not
            rigid (see :func:`dcc_fg.io.validate.rigid_transform`).
    """
    prefix = f"{name}." if name else ""
    entry = name or "camera entry"
    if not isinstance(d, dict):
        raise ValueError(f"{source}: {entry} must be a mapping with {', '.join(REQUIRED)}, got {d!r}")
    for key in REQUIRED:
        if key not in d:
            raise ValueError(f"{source}: {prefix}{key}: missing field (a Kalibr camera has {', '.join(REQUIRED)})")
    where = f"{source}: {prefix}"
    if d["camera_model"] != "pinhole":
        raise ValueError(f"{where}camera_model must be 'pinhole', got {d['camera_model']!r}")
    res = validate.numbers(
        d["resolution"], f"{where}resolution", 2, ("width", "height"), form="[width, height]", integer=True,
        positive=True, unit="pixels",
    )  # fmt: skip
    fu, fv, pu, pv = validate.numbers(
        d["intrinsics"], f"{where}intrinsics", 4, INTRINSIC_NAMES, form="[fu, fv, pu, pv]"
    )
    for k, f in enumerate((fu, fv)):
        if f <= 0:
            raise ValueError(
                f"{where}intrinsics[{k}] ({INTRINSIC_NAMES[k]}) must be a positive number of pixels, got {f:g}"
            )
    width, height = int(res[0]), int(res[1])
    if not (0.0 <= pu <= width and 0.0 <= pv <= height):
        log.warning(
            "%sintrinsics: principal point (%g, %g) px lies outside the %dx%d image; check the camchain",
            where, pu, pv, width, height,
        )  # fmt: skip
    model = d["distortion_model"]
    if model not in DISTORTION_COUNTS:
        raise ValueError(f"{where}distortion_model must be one of {', '.join(DISTORTION_COUNTS)}, got {model!r}")
    counts = DISTORTION_COUNTS[model]
    coeffs = validate.numbers(d["distortion_coeffs"], f"{where}distortion_coeffs")
    if len(coeffs) not in counts:
        raise ValueError(
            f"{where}distortion_coeffs must have {' or '.join(map(str, counts))} entries for {model} distortion, "
            f"got {len(coeffs)}"
        )
    if "rostopic" in d and not isinstance(d["rostopic"], str):
        raise ValueError(f"{where}rostopic must be a topic name (text), got {d['rostopic']!r}")
    for key in TRANSFORM_FIELDS:
        if key in d:
            validate.rigid_transform(d[key], f"{where}{key}")
    if "timeshift_cam_imu" in d:
        validate.number(d["timeshift_cam_imu"], f"{where}timeshift_cam_imu", unit="seconds")
    return CameraModel(
        intrinsics=(fu, fv, pu, pv),
        distortion_model=str(model),
        distortion_coeffs=tuple(coeffs),
        resolution=(width, height),
        camera_model="pinhole",
    )


def camera_to_dict(cam: CameraModel, rostopic: str | None = None) -> dict[str, Any]:
    """Kalibr camera entry for ``cam``."""
    out: dict[str, Any] = {
        "camera_model": cam.camera_model,
        "intrinsics": [float(x) for x in cam.intrinsics],
        "distortion_model": cam.distortion_model,
        "distortion_coeffs": [float(x) for x in cam.distortion_coeffs],
        "resolution": [int(x) for x in cam.resolution],
    }
    if rostopic is not None:
        out["rostopic"] = rostopic
    return out


def load_camchain(path: str | Path) -> dict[str, CamchainEntry]:
    """Read a Kalibr camchain YAML; returns ``{'cam0': entry, 'cam1': entry, ...}``.

    Every entry is checked (see :func:`camera_from_dict`); errors name the file, the entry and the field.
    """
    path = Path(path)
    d = validate.load_yaml(path, "Kalibr camchain", "cam0:, cam1:, ... entries")
    if not any(str(k).startswith("cam") for k in d):
        raise ValueError(f"{path}: not a Kalibr camchain (no 'cam0', 'cam1', ... entries)")
    out: dict[str, CamchainEntry] = {}
    for name in sorted(str(k) for k in d if str(k).startswith("cam")):
        entry = d[name]
        cam = camera_from_dict(entry, str(path), name)
        extra = {k: v for k, v in entry.items() if k not in REQUIRED and k != "rostopic"}
        out[name] = CamchainEntry(cam, entry.get("rostopic"), extra)
    return out


def camchain_to_yaml(entries: dict[str, CamchainEntry]) -> str:
    """Serialize camchain entries (inverse of :func:`load_camchain`)."""
    d: dict[str, Any] = {}
    for name, e in entries.items():
        item = camera_to_dict(e.camera, e.rostopic)
        item.update(e.extra)
        d[name] = item
    return yaml.safe_dump(d, sort_keys=False)


def camchain_transforms(
    entries: Mapping[str, CamchainEntry], source: str, cameras: Sequence[str] | None = None
) -> dict[str, NDArray[np.float64]]:
    """``T_cn_c0`` (4x4: maps points of cam0 into camN, metres) of each camera, by chaining Kalibr's
    ``T_cn_cnm1`` (camN-1 -> camN): ``T_cn_c0 = T_cn_cnm1 @ T_cnm1_c0``, ``T_c0_c0 = I``.

    Args:
        entries: the camchain (:func:`load_camchain`), cameras ``cam0 .. camN-1``.
        source: the camchain file, for messages.
        cameras: the cameras wanted (default: all); only the ``T_cn_cnm1`` on their paths from cam0 are needed.

    Raises:
        ValueError: naming ``source``: no ``cam0``, a gap in the names, or a ``T_cn_cnm1`` missing on
            the path of a wanted camera (or not a rigid 4x4).
    """
    numbers = {}
    for name in entries:
        if not (name.startswith("cam") and name[3:].isdigit()):
            raise ValueError(f"{source}: camera entries must be named cam0, cam1, ... (Kalibr's names), got {name!r}")
        numbers[name] = int(name[3:])
    if sorted(numbers.values()) != list(range(len(numbers))):
        raise ValueError(
            f"{source}: cameras must be cam0 .. cam{len(numbers) - 1} without gaps, got {', '.join(entries)}"
        )
    wanted = list(entries) if cameras is None else list(cameras)
    last = max((numbers[c] for c in wanted if c in numbers), default=0)
    out: dict[str, NDArray[np.float64]] = {"cam0": np.eye(4)}
    T = np.eye(4)
    for n in range(1, last + 1):
        entry = entries[f"cam{n}"]
        raw = entry.extra.get("T_cn_cnm1")
        if raw is None:
            raise ValueError(
                f"{source}: cam{n}.T_cn_cnm1: missing field (needed to place "
                f"{', '.join(c for c in wanted if numbers.get(c, -1) >= n)} relative to cam0)"
            )
        T = validate.rigid_transform(raw, f"{source}: cam{n}.T_cn_cnm1") @ T
        out[f"cam{n}"] = T
    return {c: out[c] for c in wanted if c in out}
