"""Detection folders in yac's layout, for users with their own corner detector -> observations, snapshots.

The file format (``cam0/<timestamp_ns>.csv``, ``cam1/<timestamp_ns>.csv``, optional ``joints.csv``)
is parsed by :mod:`dcc_fg.io.detections`; here the rows become :class:`~dcc_fg.data.Observation`
objects checked against the AprilGrid geometry (point id = 4 * tag_id + corner_idx, Kalibr order,
see :mod:`dcc_fg.targets`) and the two cameras' frames become :class:`~dcc_fg.data.Snapshot` objects.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from dcc_fg.data import Observation, Snapshot
from dcc_fg.io.detections import read_detection_table, write_detection_table
from dcc_fg.io.folders import DYNAMIC_DIR, JOINTS_FILE, STATIC_DIR, list_timestamped, read_joints_csv
from dcc_fg.io.pairing import DEFAULT_TOLERANCE_NS, Pairing, check_pairing, nearest_within, pair_timestamps
from dcc_fg.targets import TargetGeometry

log = logging.getLogger(__name__)

#: Tolerance (metres) when comparing p_x, p_y, p_z with the target geometry (yac writes 6 decimals).
POINT_TOLERANCE_M = 2e-6


def _check_grid(path: Path, file_target: TargetGeometry, target: TargetGeometry) -> None:
    """ValueError naming ``path`` if the file's AprilGrid differs from the expected ``target``."""
    if (target.target_type, target.cols, target.rows) != ("aprilgrid", file_target.cols, file_target.rows) or (
        not np.isclose(target.tag_size, file_target.tag_size, atol=1e-6)
        or not np.isclose(target.tag_spacing, file_target.tag_spacing, atol=1e-6)
    ):
        raise ValueError(
            f"{path}: target in the file (aprilgrid {file_target.cols}x{file_target.rows} tags, size "
            f"{file_target.tag_size}, spacing {file_target.tag_spacing}) differs from the expected {target}"
        )


def read_detection_csv(
    path: str | Path, target: TargetGeometry | None = None
) -> tuple[int | None, Observation, TargetGeometry | None]:
    """Read one yac detection file.

    Args:
        path: the CSV file.
        target: expected target; if None it is inferred from the file's first row.

    Returns:
        (timestamp_ns from the ``ts`` column or None if the file has no rows, the observation,
        the target geometry of the rows or ``target`` / None if the file has no rows).

    Raises:
        ValueError: naming the file (and line) for a wrong header, unparsable numbers, rows with
            different target parameters or timestamps, a corner index outside 0..3, a tag id
            outside the grid, or target-frame points (p_x, p_y, p_z) that disagree with
            :attr:`TargetGeometry.points`.
    """
    path = Path(path)
    table = read_detection_table(path)
    if table.grid is None:
        return None, Observation(np.zeros(0, dtype=np.int64), np.zeros((0, 2))), target
    rows, cols, size, spacing = table.grid
    file_target = TargetGeometry.aprilgrid(cols, rows, size, spacing)
    if target is None:
        target = file_target
    else:
        _check_grid(path, file_target, target)
    tag_id, corner = table.tag_id, table.corner_idx
    n_tags = target.cols * target.rows
    if ((tag_id < 0) | (tag_id >= n_tags)).any():
        bad = int(tag_id[(tag_id < 0) | (tag_id >= n_tags)][0])
        raise ValueError(f"{path}: tag_id {bad} outside the {target.cols}x{target.rows} grid")
    ids = 4 * tag_id + corner
    if np.unique(ids).size != ids.size:
        raise ValueError(f"{path}: a corner (tag_id, corner_idx) appears twice")
    err = np.abs(target.points[ids] - table.points).max(axis=1)
    if (err > POINT_TOLERANCE_M).any():
        k = int(np.argmax(err))
        raise ValueError(
            f"{path}:{k + 2}: p_x,p_y,p_z = {table.points[k].tolist()} for tag {tag_id[k]} corner {corner[k]} "
            f"disagree with the target geometry {target.points[ids[k]].tolist()} (off by {err[k]:.3g} m)"
        )
    order = np.argsort(ids)
    return table.timestamp_ns, Observation(ids[order], table.pixels[order]), target


def read_detection_folder(
    root: str | Path,
    target: TargetGeometry | None = None,
    tolerance_ns: int = DEFAULT_TOLERANCE_NS,
) -> tuple[list[Snapshot], TargetGeometry, Pairing]:
    """Read a yac detection folder into snapshots.

    Args:
        root: folder with ``cam0/``, ``cam1/`` and optionally ``joints.csv``.
        target: expected target; None infers it from the CSV headers (every file must agree).
        tolerance_ns: pairing tolerance between cam0 and cam1 timestamps (file names), ns.

    Returns:
        (snapshots at the cam0 timestamps in time order, with joints nearest in time within the
        tolerance if ``joints.csv`` exists; the target geometry; the pairing, whose unpaired lists
        report frames without a partner).  Snapshots may have empty observations.

    Raises:
        ValueError: naming the folder or file at fault (see :func:`read_detection_csv`), when
            the target cannot be inferred (every file empty), or when no timestamps pair.
    """
    root = Path(root)
    dirs = (root / STATIC_DIR, root / DYNAMIC_DIR)
    for d in dirs:
        if not d.is_dir():
            raise ValueError(f"{d}: folder missing (detection folder layout: cam0/<ns>.csv, cam1/<ns>.csv)")
    files = [list_timestamped(d, (".csv",)) for d in dirs]
    obs: list[dict[int, Observation]] = [{}, {}]
    for cam in (0, 1):
        for stamp, path in files[cam].items():
            ts, ob, t = read_detection_csv(path, target)
            if ts is not None and ts != stamp:
                raise ValueError(f"{path}: column ts = {ts} differs from the file name timestamp {stamp}")
            target = t if t is not None else target
            obs[cam][stamp] = ob
    if target is None:
        raise ValueError(f"{root}: every detection file is empty; cannot infer the target")
    s_ts, d_ts = sorted(obs[0]), sorted(obs[1])
    pairing = pair_timestamps(s_ts, d_ts, tolerance_ns)
    check_pairing(pairing, len(s_ts), len(d_ts), str(dirs[0]), str(dirs[1]))
    joints: tuple[NDArray[np.int64], NDArray[np.float64]] | None = None
    if (root / JOINTS_FILE).exists():
        joints = read_joints_csv(root / JOINTS_FILE)
    stamps = [s_ts[i] for i, _ in pairing.pairs]
    jidx = nearest_within(stamps, joints[0], tolerance_ns) if joints is not None else None
    snapshots = []
    for n, (i, j) in enumerate(pairing.pairs):
        q = joints[1][jidx[n]].copy() if joints is not None and jidx is not None and jidx[n] >= 0 else None
        snapshots.append(Snapshot(s_ts[i], obs[0][s_ts[i]], obs[1][d_ts[j]], q))
    return snapshots, target, pairing


def write_detection_csv(path: str | Path, timestamp_ns: int, obs: Observation, target: TargetGeometry) -> None:
    """Write one observation of an AprilGrid in yac's CSV layout (tests, simulators)."""
    if target.target_type != "aprilgrid":
        raise ValueError("yac detection files describe AprilGrids only")
    grid = (target.rows, target.cols, target.tag_size, target.tag_spacing)
    write_detection_table(path, timestamp_ns, grid, obs.ids, obs.pixels, target.points[obs.ids])
