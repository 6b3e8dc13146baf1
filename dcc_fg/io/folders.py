"""Image-folder datasets: ``cam0/<timestamp_ns>.png`` (static), ``cam1/<timestamp_ns>.png``
(dynamic), optional ``joints.csv`` (``timestamp_ns,theta_1,...,theta_L``, radians).

Images are paired by timestamp (ns) with a tolerance and read lazily, one pair at a time.
Unpaired frames are reported in :attr:`ImageFolder.pairing` and logged, never silently dropped.
Also used by the bag reader: :class:`FramePair` is what both yield.
"""

from __future__ import annotations

import csv
import io
import logging
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np
from numpy.typing import NDArray

from dcc_fg.io import validate
from dcc_fg.io.pairing import DEFAULT_TOLERANCE_NS, Pairing, check_pairing, nearest_within, pair_timestamps

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".pgm", ".ppm", ".bmp", ".tif", ".tiff")
STATIC_DIR = "cam0"
DYNAMIC_DIR = "cam1"
JOINTS_FILE = "joints.csv"


@dataclass
class FramePair:
    """One synchronized image pair.

    Attributes:
        timestamp_ns: the static frame's timestamp, ns (the snapshot time).
        static: static-camera image (H, W) grey or (H, W, 3|4) BGR(A), uint8 or uint16.
        dynamic: dynamic-camera image, same conventions.
        joints: (L,) joint angles in radians nearest in time (within the tolerance), or None.
        static_source, dynamic_source: where the images came from (file path, ``bag:topic@ns``),
            for error messages.
        dynamic_timestamp_ns: the dynamic frame's own timestamp, ns.
    """

    timestamp_ns: int
    static: NDArray[np.generic]
    dynamic: NDArray[np.generic]
    joints: NDArray[np.float64] | None = None
    static_source: str = ""
    dynamic_source: str = ""
    dynamic_timestamp_ns: int = 0


def read_joints_csv(path: str | Path) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """Read ``joints.csv``: header ``timestamp_ns,theta_1,...,theta_L``, radians.

    Returns:
        (N,) timestamps in ns and (N, L) joint angles in radians.

    Raises:
        FileNotFoundError: no such file.
        ValueError: naming the file and line for: a folder, bytes that are not UTF-8, an empty
            file, a bad header, a wrong field count, a timestamp that is not a positive integer
            or does not increase, an angle that is not a finite number, or an angle beyond one
            turn (|theta| > 2*pi: the file looks like degrees, it must be radians).
    """
    path = Path(path)
    form = "header timestamp_ns,theta_1,...,theta_L, then one row per sample, radians"
    text = validate.read_text(path, "joints.csv", form)
    stamps: list[int] = []
    rows: list[list[float]] = []
    lines: list[int] = []
    reader = csv.reader(io.StringIO(text))
    try:
        header = next(reader)
        header = [h.strip().lstrip("#").strip() for h in header]
        if header[0] != "timestamp_ns" or len(header) < 2:
            raise ValueError(f"{path}: header must be 'timestamp_ns,theta_1,...,theta_L', got '{','.join(header)}'")
        n_joints = len(header) - 1
        for row in reader:
            line_no = reader.line_num
            if not row or not "".join(row).strip():
                continue
            if len(row) != n_joints + 1:
                raise ValueError(
                    f"{path}:{line_no}: expected {n_joints + 1} fields (timestamp_ns and {n_joints} angles), "
                    f"got {len(row)}"
                )
            try:
                stamp = int(row[0])
                values = [float(x) for x in row[1:]]
            except ValueError:
                raise ValueError(
                    f"{path}:{line_no}: not a number in '{','.join(row)}' (expected an integer timestamp_ns and "
                    f"{n_joints} angles in radians)"
                ) from None
            if stamp <= 0:
                raise ValueError(f"{path}:{line_no}: timestamp_ns must be a positive integer (ns), got {stamp}")
            if stamps and stamp <= stamps[-1]:
                raise ValueError(
                    f"{path}:{line_no}: timestamp_ns {stamp} does not increase (previous row: {stamps[-1]}); "
                    "rows must be in time order, one per stamp"
                )
            stamps.append(stamp)
            rows.append(values)
            lines.append(line_no)
    except csv.Error as exc:
        raise ValueError(f"{path}:{reader.line_num}: malformed CSV ({exc})") from None
    angles = np.array(rows, dtype=np.float64).reshape(-1, n_joints)
    validate.check_joint_angles(angles, str(path), lines)
    return np.array(stamps, dtype=np.int64), angles


def list_timestamped(folder: Path, suffixes: tuple[str, ...]) -> dict[int, Path]:
    """``{timestamp_ns: path}`` of the files in ``folder`` named ``<integer>.<suffix>``.

    Raises:
        ValueError: a file with an accepted suffix whose stem is not an integer, or two files
            with the same timestamp.
    """
    out: dict[int, Path] = {}
    for p in sorted(folder.iterdir()):
        if not p.is_file() or p.suffix.lower() not in suffixes:
            continue
        try:
            stamp = int(p.stem)
        except ValueError:
            raise ValueError(f"{p}: file name must be <timestamp_ns>{p.suffix}") from None
        if stamp in out:
            raise ValueError(f"{p}: timestamp {stamp} also used by {out[stamp].name}")
        out[stamp] = p
    return out


def read_image(path: str | Path) -> NDArray[np.generic]:
    """Read an image unchanged (8/16-bit, grey or BGR); ValueError naming the file if it fails."""
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError(f"{path}: image does not decode")
    return img


class FilePairReference(NamedTuple):
    """A pair of an image folder, not read: the static stamp (ns), the two image files, the joint angles
    (rad) nearest in time or None, the dynamic stamp (ns)."""

    timestamp_ns: int
    static: Path
    dynamic: Path
    joints: NDArray[np.float64] | None
    dynamic_ns: int


class ImageFolder:
    """An image-folder dataset, paired but not loaded.

    Attributes:
        root: the folder.
        pairing: the timestamp pairing; ``pairing.unpaired_static`` / ``unpaired_dynamic`` list
            the frames that have no partner.
        joints: ``(timestamps_ns, angles)`` from ``joints.csv`` or None.
    """

    def __init__(self, root: str | Path, tolerance_ns: int = DEFAULT_TOLERANCE_NS) -> None:
        """Index ``root`` and pair its frames.

        Raises:
            ValueError: missing ``cam0`` / ``cam1`` folder, no frames, or no pairs (naming the
                folders and their time ranges).
        """
        self.root = Path(root)
        dirs = [self.root / STATIC_DIR, self.root / DYNAMIC_DIR]
        for d in dirs:
            if not d.is_dir():
                raise ValueError(f"{d}: folder missing (image folder layout: cam0/<ns>.png, cam1/<ns>.png)")
        self.static_files = list_timestamped(dirs[0], IMAGE_SUFFIXES)
        self.dynamic_files = list_timestamped(dirs[1], IMAGE_SUFFIXES)
        s_ts = sorted(self.static_files)
        d_ts = sorted(self.dynamic_files)
        self.pairing: Pairing = pair_timestamps(s_ts, d_ts, tolerance_ns)
        check_pairing(self.pairing, len(s_ts), len(d_ts), str(dirs[0]), str(dirs[1]))
        self._pairs = [(s_ts[i], d_ts[j]) for i, j in self.pairing.pairs]
        self.tolerance_ns = tolerance_ns
        joints_path = self.root / JOINTS_FILE
        # exists(), not is_file(): a folder named joints.csv is refused by read_joints_csv, not ignored
        self.joints = read_joints_csv(joints_path) if joints_path.exists() else None
        self._joint_index = (
            nearest_within([s for s, _ in self._pairs], self.joints[0], tolerance_ns)
            if self.joints is not None
            else None
        )

    def __len__(self) -> int:
        return len(self._pairs)

    def references(self) -> list[FilePairReference]:
        """The pairs in time order (that of :meth:`__iter__`) as their two files, not read: for readers
        that read the images themselves (e.g. detection workers)."""
        out = []
        for n, (ts, td) in enumerate(self._pairs):
            joints = None
            if self.joints is not None and self._joint_index is not None and self._joint_index[n] >= 0:
                joints = self.joints[1][self._joint_index[n]].copy()
            out.append(FilePairReference(ts, self.static_files[ts], self.dynamic_files[td], joints, td))
        return out

    def __iter__(self) -> Iterator[FramePair]:
        """Yield the pairs in time order, reading the two images of each pair on demand."""
        for ref in self.references():
            ps, pd = ref.static, ref.dynamic
            yield FramePair(
                ref.timestamp_ns, read_image(ps), read_image(pd), ref.joints, str(ps), str(pd), ref.dynamic_ns
            )


def read_image_folder(root: str | Path, tolerance_ns: int = DEFAULT_TOLERANCE_NS) -> ImageFolder:
    """Open an image-folder dataset (see :class:`ImageFolder`)."""
    return ImageFolder(root, tolerance_ns)


def write_image_folder(root: str | Path, frames: Iterable[FramePair]) -> Path:
    """Write frames in the image-folder layout (tests, simulators); returns ``root``.

    The static image of each frame goes to ``cam0/<timestamp_ns>.png``, the dynamic one to
    ``cam1/<dynamic_timestamp_ns>.png`` (``timestamp_ns`` if that is 0), and the joints of the
    frames that have them to ``joints.csv`` at the static timestamps.
    """
    root = Path(root)
    (root / STATIC_DIR).mkdir(parents=True, exist_ok=True)
    (root / DYNAMIC_DIR).mkdir(parents=True, exist_ok=True)
    joint_rows: list[tuple[int, NDArray[np.float64]]] = []
    for fr in frames:
        td = fr.dynamic_timestamp_ns or fr.timestamp_ns
        for img, path in (
            (fr.static, root / STATIC_DIR / f"{fr.timestamp_ns}.png"),
            (fr.dynamic, root / DYNAMIC_DIR / f"{td}.png"),
        ):
            if not cv2.imwrite(str(path), img):
                raise ValueError(f"{path}: could not write image of shape {img.shape} {img.dtype}")
        if fr.joints is not None:
            joint_rows.append((fr.timestamp_ns, np.asarray(fr.joints, dtype=float)))
    if joint_rows:
        with (root / JOINTS_FILE).open("w") as f:
            f.write("timestamp_ns," + ",".join(f"theta_{k + 1}" for k in range(len(joint_rows[0][1]))) + "\n")
            for ts, q in joint_rows:
                f.write(f"{ts}," + ",".join(repr(float(x)) for x in q) + "\n")
    return root
