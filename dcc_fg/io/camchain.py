"""Kalibr camchain YAML: read/write ``pinhole`` cameras with ``radtan`` or ``equidistant`` distortion.

Kalibr's ``intrinsics`` are ``[fx, fy, cx, cy]`` (pixels), ``resolution`` is ``[width, height]``.
Fields we do not interpret (``T_cn_cnm1``, ``cam_overlaps``, ``timeshift_cam_imu``...) are kept
verbatim in :class:`CamchainEntry.extra` so a camchain round-trips unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from factors.camera import CameraModel

REQUIRED = ("camera_model", "intrinsics", "distortion_model", "distortion_coeffs", "resolution")


@dataclass
class CamchainEntry:
    """One ``camN`` entry: the camera model, its ROS topic and the fields we pass through."""

    camera: CameraModel
    rostopic: str | None = None
    extra: dict[str, Any] = field(default_factory=dict)


def camera_from_dict(d: dict[str, Any], source: str) -> CameraModel:
    """Parse a Kalibr camera entry; errors name ``source`` and the field at fault."""
    if not isinstance(d, dict):
        raise ValueError(f"{source}: expected a mapping with {', '.join(REQUIRED)}")
    for key in REQUIRED:
        if key not in d:
            raise ValueError(f"{source}: missing field '{key}'")
    try:
        intr = tuple(float(x) for x in d["intrinsics"])
        dist = tuple(float(x) for x in d["distortion_coeffs"])
        res = tuple(int(x) for x in d["resolution"])
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{source}: intrinsics/distortion_coeffs/resolution must be numeric lists ({exc})") from None
    if len(res) != 2:
        raise ValueError(f"{source}: 'resolution' must be [width, height]")
    try:
        return CameraModel(
            intrinsics=intr,  # type: ignore[arg-type]
            distortion_model=str(d["distortion_model"]),
            distortion_coeffs=dist,
            resolution=res,  # type: ignore[arg-type]
            camera_model=str(d["camera_model"]),
        )
    except ValueError as exc:
        raise ValueError(f"{source}: {exc}") from None


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
    """Read a Kalibr camchain YAML; returns ``{'cam0': entry, 'cam1': entry, ...}``."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: camchain file not found")
    with path.open() as f:
        d = yaml.safe_load(f)
    if not isinstance(d, dict) or not any(k.startswith("cam") for k in d):
        raise ValueError(f"{path}: not a Kalibr camchain (no 'cam0', 'cam1', ... entries)")
    out: dict[str, CamchainEntry] = {}
    for name in sorted(k for k in d if k.startswith("cam")):
        entry = d[name]
        cam = camera_from_dict(entry, f"{path}: {name}")
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
