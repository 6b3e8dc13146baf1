"""Measurements of an N-camera cluster: per snapshot, whichever cameras see the target.

A :class:`ClusterSnapshot` is one instant (the target and every gimbal held still) with the corners of
each camera that sees the target (camera name ``cam0 .. camN-1`` -> :class:`~dcc_fg.data.Observation`)
and, optionally, joint-angle guesses per chain (chain name -> (L,) rad). A :class:`ClusterDataset` adds
the cameras' intrinsics and the target's points (M, 3) in the target frame t (metres).

The two-camera :class:`~dcc_fg.data.CalibrationDataset` is the special case cam0 (static camera s) +
cam1 (dynamic camera d): :meth:`ClusterDataset.from_pair` converts one into the other, and
:meth:`ClusterDataset.pair` extracts the snapshots two cameras share as a two-camera data set (the
automatic initialization of :mod:`dcc_fg.cluster_init` runs the two-camera code on such pairs).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from dcc_fg.data import CalibrationDataset, Observation, Snapshot
from dcc_fg.io.detections import read_detection_table
from dcc_fg.io.folders import list_timestamped
from dcc_fg.targets import TargetGeometry
from factors.camera import CameraModel

FloatArray = NDArray[np.float64]
#: Frames of different cameras this close in time (ns) form one snapshot (:func:`read_cluster_detections`).
DEFAULT_GROUP_TOLERANCE_NS = 5_000_000


@dataclass
class ClusterSnapshot:
    """One instant of an N-camera cluster.

    Attributes:
        timestamp_ns: capture time, nanoseconds.
        observations: camera name -> corners it sees; cameras that do not see the target are absent.
        joints: optional chain name -> (L,) joint-angle guesses (rad); None or a missing chain: unknown.
    """

    timestamp_ns: int
    observations: dict[str, Observation]
    joints: dict[str, FloatArray] | None = None

    @property
    def cameras(self) -> list[str]:
        """The cameras that see the target, in camera order."""
        return sorted(self.observations, key=lambda c: int(c[3:]))


@dataclass
class ClusterDataset:
    """Everything an N-camera calibration needs besides the initial kinematics.

    Attributes:
        cameras: camera name (``cam0 .. camN-1``) -> intrinsics.
        target_points: (M, 3) target corner positions in the target frame t, metres.
        snapshots: the instants.
        source: where the data came from, for error messages.
    """

    cameras: dict[str, CameraModel]
    target_points: FloatArray
    snapshots: list[ClusterSnapshot] = field(default_factory=list)
    source: str = "<memory>"

    @property
    def camera_names(self) -> list[str]:
        return sorted(self.cameras, key=lambda c: int(c[3:]))

    def observation_counts(self) -> dict[str, int]:
        """Camera -> number of snapshots in which it sees the target."""
        return {c: sum(c in s.observations for s in self.snapshots) for c in self.camera_names}

    def co_observations(self, a: str, b: str) -> list[int]:
        """Indices of the snapshots in which both cameras ``a`` and ``b`` see the target."""
        return [i for i, s in enumerate(self.snapshots) if a in s.observations and b in s.observations]

    def pair(self, static: str, dynamic: str, chain: str | None = None) -> tuple[CalibrationDataset, list[int]]:
        """The snapshots both cameras see as a two-camera data set (``static`` as camera s, ``dynamic``
        as camera d; snapshot ``joints`` = the guesses of ``chain`` when given), and their indices here."""
        idx = self.co_observations(static, dynamic)
        snaps = []
        for i in idx:
            s = self.snapshots[i]
            joints = None
            if chain is not None and s.joints is not None and chain in s.joints:
                joints = np.asarray(s.joints[chain], dtype=float)
            snaps.append(Snapshot(s.timestamp_ns, s.observations[static], s.observations[dynamic], joints))
        data = CalibrationDataset(
            self.cameras[static],
            self.cameras[dynamic],
            self.target_points,
            snaps,
            f"{self.source} ({static}, {dynamic})",
        )
        return data, idx

    @staticmethod
    def from_pair(
        data: CalibrationDataset, names: tuple[str, str] = ("cam0", "cam1"), chain: str | None = None
    ) -> ClusterDataset:
        """A two-camera data set as a cluster data set: its static camera is ``names[0]``, its dynamic
        camera ``names[1]``; snapshot ``joints`` become the guesses of ``chain`` (when given)."""
        snaps = []
        for s in data.snapshots:
            joints = None
            if chain is not None and s.joints is not None:
                joints = {chain: np.asarray(s.joints, dtype=float)}
            snaps.append(ClusterSnapshot(s.timestamp_ns, {names[0]: s.static, names[1]: s.dynamic}, joints))
        cams = {names[0]: data.static_camera, names[1]: data.dynamic_camera}
        return ClusterDataset(cams, np.asarray(data.target_points, dtype=float), snaps, data.source)

    def subset(self, keep: Mapping[int, list[str]]) -> ClusterDataset:
        """A copy with snapshot i reduced to the cameras ``keep[i]`` (snapshots not in ``keep`` dropped)."""
        snaps = []
        for i, cams in sorted(keep.items()):
            s = self.snapshots[i]
            snaps.append(ClusterSnapshot(s.timestamp_ns, {c: s.observations[c] for c in cams}, s.joints))
        return ClusterDataset(dict(self.cameras), self.target_points, snaps, self.source)


# ------------------------------------------------------------------ detection folders


def read_cluster_detections(
    folder: str | Path,
    cameras: Mapping[str, CameraModel],
    target: TargetGeometry,
    tolerance_ns: int = DEFAULT_GROUP_TOLERANCE_NS,
) -> ClusterDataset:
    """A detection folder of N cameras in yac's layout: ``cam0/<ns>.csv`` ... ``camN-1/<ns>.csv`` (one
    file per frame with the corners it sees, :mod:`dcc_fg.io.detections`; a camera's folder may be
    missing or a frame absent where the camera does not see the target).

    Frames of different cameras whose stamps lie within ``tolerance_ns`` of each other (chained, sorted
    by time) form one snapshot, stamped with the earliest. Point ids are ``4 * tag_id + corner_idx``
    on the AprilGrid ``target``; files with no rows are skipped.

    Raises:
        ValueError: naming the file: another target than ``target``, ids outside it, a camera with two
            frames in one snapshot, no camera folder at all.
    """
    root = Path(folder)
    if target.target_type != "aprilgrid":
        raise ValueError(f"{root}: yac detection files hold AprilGrid corners; the target is a {target.target_type}")
    n_pts = target.points.shape[0]
    frames: list[tuple[int, str, Observation]] = []
    found = False
    for cam in sorted(cameras, key=lambda c: int(c[3:])):
        sub = root / cam
        if not sub.is_dir():
            continue
        found = True
        for stamp, path in sorted(list_timestamped(sub, (".csv",)).items()):
            table = read_detection_table(path)
            if table.timestamp_ns is None:
                continue
            rows, cols, size, spacing = table.grid or (0, 0, 0.0, 0.0)
            if (rows, cols) != (target.rows, target.cols) or not (
                np.isclose(size, target.tag_size, atol=1e-6) and np.isclose(spacing, target.tag_spacing, atol=1e-6)
            ):
                raise ValueError(
                    f"{path}: AprilGrid {cols}x{rows} tags of {size} m (spacing {spacing}) is not {target}"
                )
            ids = 4 * table.tag_id + table.corner_idx
            if ids.min() < 0 or ids.max() >= n_pts:
                raise ValueError(f"{path}: corner ids outside the target's 0..{n_pts - 1}")
            frames.append((stamp, cam, Observation(ids, table.pixels)))
    if not found:
        raise ValueError(f"{root}: no camera folder ({', '.join(sorted(cameras))}) found")
    frames.sort(key=lambda f: (f[0], int(f[1][3:])))
    snaps: list[ClusterSnapshot] = []
    last = None
    for stamp, cam, obs in frames:
        if last is None or stamp - last > tolerance_ns:
            snaps.append(ClusterSnapshot(stamp, {}))
        if cam in snaps[-1].observations:
            raise ValueError(
                f"{root}: camera {cam} has two frames within {tolerance_ns} ns of snapshot {snaps[-1].timestamp_ns}"
            )
        snaps[-1].observations[cam] = obs
        last = stamp
    return ClusterDataset(dict(cameras), target.points, snaps, str(root))
