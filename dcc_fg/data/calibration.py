"""Public measurement containers shared by the simulators, the readers and the estimators.

A real data set (bag, image folder, detection folder) and a simulated one produce the same
:class:`CalibrationDataset`, so every estimator runs unchanged on both.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from factors.camera import CameraModel

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass
class Observation:
    """Target corners seen by one camera in one image.

    Attributes:
        ids: (N,) target point ids (index into :attr:`TargetGeometry.points`).
        pixels: (N, 2) measured pixel coordinates (u, v), distorted image.
    """

    ids: IntArray
    pixels: FloatArray

    def __post_init__(self) -> None:
        self.ids = np.asarray(self.ids, dtype=np.int64).reshape(-1)
        self.pixels = np.asarray(self.pixels, dtype=float).reshape(-1, 2)
        if self.ids.shape[0] != self.pixels.shape[0]:
            raise ValueError(f"{self.ids.shape[0]} ids but {self.pixels.shape[0]} pixels")

    def __len__(self) -> int:
        return int(self.ids.shape[0])


@dataclass
class Snapshot:
    """One synchronized image pair of the target.

    Attributes:
        timestamp_ns: capture time, nanoseconds.
        static: corners in the static camera s.
        dynamic: corners in the dynamic (gimbal) camera d.
        joints: optional (L,) joint angles in radians: encoder readings (``encoders`` mode)
            or initial guesses (``encoderless`` mode).
    """

    timestamp_ns: int
    static: Observation
    dynamic: Observation
    joints: FloatArray | None = None


@dataclass
class CalibrationDataset:
    """Everything a calibration needs besides the initial kinematics.

    Attributes:
        static_camera: intrinsics of camera s.
        dynamic_camera: intrinsics of camera d.
        target_points: (M, 3) target corner positions in the target frame t, metres.
        snapshots: the image pairs.
        source: where the data came from (file name, ``simulation``), used in error messages.
    """

    static_camera: CameraModel
    dynamic_camera: CameraModel
    target_points: FloatArray
    snapshots: list[Snapshot] = field(default_factory=list)
    source: str = "<memory>"


def with_joints(data: CalibrationDataset, thetas: FloatArray | None) -> CalibrationDataset:
    """``data`` with ``thetas[i]`` (rad, one row of L joint angles per snapshot) as snapshot i's joint
    guess; ``thetas=None`` removes every guess (the encoderless case)."""
    if thetas is None:
        return replace(data, snapshots=[replace(s, joints=None) for s in data.snapshots])
    return replace(data, snapshots=[replace(s, joints=t) for s, t in zip(data.snapshots, thetas, strict=True)])


def common_corners(data: CalibrationDataset) -> CalibrationDataset:
    """The same dataset with each snapshot reduced to the target points both cameras see.

    This is the measurement set a stereo calibration such as ``cv2.stereoCalibrate`` uses (it
    needs one object-point list per image pair); the bundle formulation can also use the corners
    only one camera sees, which constrain the target pose of that snapshot.
    """
    snaps = []
    for s in data.snapshots:
        ids, i_s, i_d = np.intersect1d(s.static.ids, s.dynamic.ids, return_indices=True)
        static, dynamic = Observation(ids, s.static.pixels[i_s]), Observation(ids, s.dynamic.pixels[i_d])
        snaps.append(Snapshot(s.timestamp_ns, static, dynamic, s.joints))
    return CalibrationDataset(data.static_camera, data.dynamic_camera, data.target_points, snaps, data.source)
