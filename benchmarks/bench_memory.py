"""Benchmark: peak memory of reading, detecting and calibrating a large calibration bag.

What is measured
----------------
1. A calibration bag of ``--frames`` image pairs (default 2,000) is written with
   :func:`dcc_fg.io.bags.write_ros2_bag` / :func:`write_ros1_bag` from a generator (one pair in
   memory at a time), 640x480 ``mono8`` images, uncompressed: the bag on disk is about
   ``frames * 2 * 307 kB`` (1.2 GB for 2,000 frames).  Two scenes (``--joints``):

   * ``--joints 0`` (default): a zero-joint cluster (L = 0), two undistorted pinhole cameras
     0.1 m apart, a 9x6 chessboard (0.025 m squares) at random board poses (0.45-0.9 m, tilts up
     to 30 degrees, fully visible in both), rendered by one perspective warp of a pre-rendered
     board texture plus a 3x3 blur; an L = 0 gimbal.yaml is given.  The weakest case.
   * ``--joints L`` (L = 1, 2, 3; measured: 2): a gimbal cluster, rendered by the project's
     simulator, i.e. :func:`dcc_fg.sim.write_dataset.write_calibration_dataset` (the
     ``dcc-fg simulate calibration`` machinery) with ``--frames`` snapshots: the pinned
     mechanism of :mod:`dcc_fg.sim.calibration_scene` (``true_kinematics(L)``, cameras
     ``default_cameras()`` with radial-tangential distortion, joint angles on a jittered grid over
     ``joint_ranges(L)``, the board 0.6-1.2 m away and fully visible in both cameras), a 10x7
     chessboard of 0.06 m squares rendered through the distorted cameras
     (:func:`dcc_fg.sim.render.render_view`: 2x2 supersampling, 0.6 px blur, 2 grey levels of
     noise), plus ``ground_truth.yaml``.  No gimbal.yaml is used: the calibration starts from
     automatic initialization (``--joints L``).  Rendering costs ~36 ms per image (2.5 minutes
     for 2,000 pairs).
2. Each workload runs in a fresh Python process and reports its peak resident set size
   ``peak_rss_bytes``, read as soon as the workload returns: ``VmHWM`` of ``/proc/self/status``,
   the high-water mark of the process's own address space.  ``ru_maxrss_bytes``
   (``resource.getrusage(RUSAGE_SELF).ru_maxrss``) is reported too, but on Linux it carries over
   the peak RSS of the process that spawned the child (``parent_peak_rss_bytes``; the rendering
   parent of ``--joints L`` peaks near 400 MB), so it is only the workload's own peak when that is
   larger (as in the ``--joints 0`` runs):

   * ``baseline``: the imports only (numpy, OpenCV, GTSAM, rosbags, dcc_fg): the fixed cost;
   * ``load``: :func:`dcc_fg.sources.dataset.load_dataset` on the bag: the streaming reader
     (:class:`~dcc_fg.io.bags.BagImagePairs`) and chessboard detection of every image;
   * ``calibrate``: the whole ``dcc-fg calibrate BAG --camchain C --target T --out OUT`` command
     with ``--gimbal gimbal.yaml`` (L = 0) or ``--joints L`` (automatic initialization): reading,
     detection, initialization, the calibration graph over all snapshots with covariances, and
     the output files.

   ``time_s`` is the workload's time inside its process, ``wall_s`` the whole child process
   (interpreter start and imports included).
3. The calibration is compared with the rendering's ground truth on the gauge-invariant
   per-snapshot ``T_ds(theta_i)`` (docs/architecture.md): the rotation angle (rad) and the norm of the
   translation part (m) of ``Log(T_ds_true^-1 T_ds_est)`` (:func:`dcc_fg.studies.calibration_accuracy.T_ds_errors`)
   for every snapshot the calibration used (``T_ds_error``: RMS, median and max over snapshots).
   For L = 0, T_ds is one transform (also reported in mrad / mm as before).  ``pixel_rms_per_axis``
   is the calibration's per-axis RMS reprojection residual (the detection noise, px).

Printed ratios: peak RSS / bag size on disk, and (peak - baseline) / bag size (the part that
grows with the data).  Reading every image into memory instead would need at least the bag size.
The target in the issue is a peak below 1 GB for 2,000 frames.  The last line of output is JSON.

Measured (2,000 pairs, ROS2 sqlite3, seed 0, 2 cores shared with other jobs, so times are noisy;
MiB = 2^20 bytes; the bag is 1.231e9 bytes = 1,174 MiB in both scenes):

=========================  ==============  ==============  ================================
workload                   ``--joints 0``  ``--joints 2``  notes (``--joints 2``)
=========================  ==============  ==============  ================================
baseline (imports)         129 MiB         129 MiB
load (read + detect)       151 MiB, 11 s   152 MiB, 16 s   2,000 / 2,000 pairs detected
calibrate (whole command)  282 MiB, 25 s   357 MiB, 69 s   auto init, then calibrate()
                                                           (graph, LM, covariances)
=========================  ==============  ==============  ================================

(``--joints 2`` calibrate: before the gauge prior was limited to 100 reference snapshots and the
auto-init axis search was blocked, 716 MiB and 538 s; the 357 MiB / 69 s row is ``/usr/bin/time -v``
of the printed command over the same bag.)

``--joints 2`` T_ds errors per snapshot (0.024 px/axis RMS reprojection residual): rotation RMS
4.1e-5 rad (median 2.9e-5, max 1.7e-4), translation RMS 9.4e-6 m (median 7.2e-6, max 2.9e-5);
``--joints 0``: 4.1e-6 rad, 2.5e-6 m.  Both peaks are below the issue's 1 GB.  Whole
``--joints 2`` run before those changes (render 149 s, three workloads): 11 min 51 s.

Run: ``python benchmarks/bench_memory.py [--frames 2000] [--joints 0|1|2|3] [--seed 0]
[--format ros2|ros1] [--storage sqlite3|mcap] [--workdir DIR] [--keep] [--skip-calibrate]``.
"""

from __future__ import annotations

import argparse
import json
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml
from scipy.spatial.transform import Rotation

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from dcc_fg.io.bag_writer import write_ros1_bag, write_ros2_bag  # noqa: E402
from dcc_fg.io.folders import FramePair  # noqa: E402
from dcc_fg.targets import TargetGeometry  # noqa: E402
from factors import chain  # noqa: E402
from factors.camera import CameraModel  # noqa: E402

SIZE = (640, 480)
CAMERA = CameraModel((500.0, 500.0, 319.5, 239.5), "radtan", (0.0, 0.0, 0.0, 0.0), SIZE)
TARGET = TargetGeometry.checkerboard(9, 6, 0.025)
#: static camera s -> dynamic camera d: 0.1 m baseline along x, a few degrees of rotation
TAU_DS = np.array([0.02, -0.05, 0.01, -0.1, 0.002, 0.001])
PX_PER_M = 1200.0  # board texture resolution (30 px per 0.025 m square)
PERIOD_NS = 50_000_000
T0_NS = 1_700_000_000_000_000_000


def board_texture() -> tuple[np.ndarray, np.ndarray]:
    """8-bit texture of the board with a one-square white margin, and the 3x3 map texture pixel
    -> target metres.  Square (i, j), i in -1..cols-1, j in -1..rows-1, spans [i s, (i+1) s] x
    [j s, (j+1) s] and is black iff i + j is even (the square diagonally before corner 0 is black,
    the orientation :func:`dcc_fg.detection.detect_checkerboard` resolves)."""
    s = TARGET.col_spacing
    n_x, n_y = TARGET.cols + 1, TARGET.rows + 1  # squares
    margin = s
    w = int(round((n_x * s + 2 * margin) * PX_PER_M))
    h = int(round((n_y * s + 2 * margin) * PX_PER_M))
    # pixel centre (a, b) <-> metres (a + 0.5) / PX_PER_M - margin - s
    x = (np.arange(w) + 0.5) / PX_PER_M - margin - s
    y = (np.arange(h) + 0.5) / PX_PER_M - margin - s
    i = np.floor(x / s).astype(int)
    j = np.floor(y / s).astype(int)
    inside_x = (i >= -1) & (i < TARGET.cols)
    inside_y = (j >= -1) & (j < TARGET.rows)
    black = ((i[None, :] + j[:, None]) % 2 == 0) & inside_x[None, :] & inside_y[:, None]
    tex = np.where(black, 20, 235).astype(np.uint8)
    A = np.array([[1 / PX_PER_M, 0, 0.5 / PX_PER_M - margin - s], [0, 1 / PX_PER_M, 0.5 / PX_PER_M - margin - s]])
    return tex, np.vstack([A, [0, 0, 1]])


def random_pose(rng: np.random.Generator) -> np.ndarray:
    """T_st: board pose in the static camera with the board centre 0.45-0.9 m ahead."""
    c = TARGET.points.mean(axis=0)
    tilt = rng.normal(size=2)
    axis = np.r_[tilt / np.linalg.norm(tilt), 0.0] * np.deg2rad(rng.uniform(0, 30))
    R = cv2.Rodrigues(axis)[0] @ cv2.Rodrigues(np.array([0, 0, rng.uniform(-0.4, 0.4)]))[0]
    z = rng.uniform(0.45, 0.9)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.array([rng.uniform(-0.15, 0.1) * z, rng.uniform(-0.12, 0.12) * z, z]) - R @ c
    return T


def render(tex: np.ndarray, tex_to_m: np.ndarray, T_ct: np.ndarray) -> np.ndarray:
    """Image of the board at pose T_ct (undistorted pinhole: one homography), grey surround."""
    H = CAMERA.K @ np.c_[T_ct[:3, 0], T_ct[:3, 1], T_ct[:3, 3]] @ tex_to_m
    img = cv2.warpPerspective(tex, H, SIZE, flags=cv2.INTER_LINEAR, borderValue=128)
    return cv2.GaussianBlur(img, (3, 3), 0)


def frames(n: int, seed: int = 0) -> Iterator[FramePair]:
    """``n`` rendered image pairs (generator: one pair in memory at a time)."""
    rng = np.random.default_rng(seed)
    tex, tex_to_m = board_texture()
    T_ds = chain.se3_from_tau(TAU_DS)
    P = TARGET.points
    k = 0
    while k < n:
        T_st = random_pose(rng)
        T_dt = T_ds @ T_st
        ok = True
        for T in (T_st, T_dt):
            p_c = P @ T[:3, :3].T + T[:3, 3]
            uv, _ = CAMERA.project(p_c, jacobian=False)
            ok &= bool(CAMERA.in_front(p_c).all() and CAMERA.in_image(uv, margin=30).all())
        if not ok:
            continue
        t = T0_NS + k * PERIOD_NS
        yield FramePair(t, render(tex, tex_to_m, T_st), render(tex, tex_to_m, T_dt))
        k += 1


def write_inputs(workdir: Path, n: int, fmt: str, storage: str, joints: int = 0, seed: int = 0) -> dict[str, Any]:
    """Write the bag, camchain.yaml and target.yaml into ``workdir``; for ``joints = 0`` also an
    L = 0 gimbal.yaml, for ``joints >= 1`` the rendered gimbal scene and its ``ground_truth.yaml``
    (the simulator's perturbed gimbal.yaml is written too but not used)."""
    workdir.mkdir(parents=True, exist_ok=True)
    if joints > 0:
        from dcc_fg.sim.write_dataset import CalibrationSimSpec, write_calibration_dataset

        t = time.perf_counter()
        spec = CalibrationSimSpec("checkerboard", fmt, seed, n, joints, storage=storage)  # type: ignore[arg-type]
        r = write_calibration_dataset(workdir, spec)
        write_s = time.perf_counter() - t
        bag = r.data
        files = [bag] if bag.is_file() else [p for p in bag.rglob("*") if p.is_file()]
        return {
            "bag": str(bag),
            "bag_bytes": int(sum(p.stat().st_size for p in files)),
            "write_s": write_s,
            "render_write_s": r.render_time_s,
            "ground_truth": str(r.ground_truth),
        }
    entry = {
        "camera_model": "pinhole",
        "intrinsics": list(CAMERA.intrinsics),
        "distortion_model": "radtan",
        "distortion_coeffs": list(CAMERA.distortion_coeffs),
        "resolution": list(SIZE),
    }
    camchain = {"cam0": dict(entry, rostopic="/cam0/image_raw"), "cam1": dict(entry, rostopic="/cam1/image_raw")}
    (workdir / "camchain.yaml").write_text(yaml.safe_dump(camchain))
    (workdir / "target.yaml").write_text(yaml.safe_dump(TARGET.to_kalibr()))
    (workdir / "gimbal.yaml").write_text(
        yaml.safe_dump({"joints": 0, "tau_s": [0.0] * 6, "tau_d": [0.0] * 6, "dh": []})
    )
    t = time.perf_counter()
    if fmt == "ros1":
        bag = write_ros1_bag(workdir / "calib.bag", frames(n, seed))
    else:
        bag = write_ros2_bag(workdir / "calib_ros2", frames(n, seed), storage=storage)  # type: ignore[arg-type]
    files = [bag] if bag.is_file() else [p for p in bag.rglob("*") if p.is_file()]
    return {"bag": str(bag), "bag_bytes": int(sum(p.stat().st_size for p in files)), "write_s": time.perf_counter() - t}


# ------------------------------------------------------------------ child workloads


def calibrate_argv(workdir: Path, bag: str, joints: int) -> list[str]:
    """The ``dcc-fg calibrate`` arguments of the calibrate workload (``--gimbal`` for L = 0,
    automatic initialization with ``--joints L`` otherwise)."""
    args = ["calibrate", bag, "--camchain", str(workdir / "camchain.yaml"), "--target", str(workdir / "target.yaml")]
    if joints > 0:
        args += ["--joints", str(joints)]
    else:
        args += ["--gimbal", str(workdir / "gimbal.yaml")]
    return args + ["--out", str(workdir / "out")]


def _child(mode: str, workdir: Path, bag: str, joints: int = 0) -> dict[str, Any]:
    """Run one workload in this process; returns its peak RSS (read before anything else is done)."""
    import gtsam  # noqa: F401  (the baseline holds every heavy import the workloads use)
    import rosbags.highlevel  # noqa: F401

    import dcc_fg.calibrate  # noqa: F401
    from dcc_fg.cli import main
    from dcc_fg.sources.dataset import load_dataset

    out: dict[str, Any] = {"mode": mode}
    t = time.perf_counter()
    if mode == "load":
        data = load_dataset(bag, workdir / "camchain.yaml", workdir / "target.yaml", progress=False)
        out["snapshots"] = len(data.snapshots)
    elif mode == "calibrate":
        out["returncode"] = main(calibrate_argv(workdir, bag, joints))
    out["time_s"] = time.perf_counter() - t
    out["peak_rss_bytes"] = peak_rss_bytes()
    out["ru_maxrss_bytes"] = int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024  # Linux: kB
    return out


def _status_kb(field: str) -> int | None:
    """A ``kB`` field of ``/proc/self/status`` (Linux), or None where there is none."""
    try:
        text = Path("/proc/self/status").read_text()
    except OSError:
        return None
    for line in text.splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    return None


def peak_rss_bytes() -> int:
    """Peak resident set size of this process's own address space, bytes.

    ``VmHWM`` of ``/proc/self/status``: the high-water mark of the memory map created at exec.
    ``ru_maxrss`` is not used for this because Linux carries it over from the process that was
    replaced at exec: a child started by :mod:`subprocess` reports at least the parent's RSS at
    the time of the spawn (a parent holding 1 GiB makes an idle child report 1 GiB).  Where
    ``/proc`` is missing, ``ru_maxrss`` is returned (kB on Linux).
    """
    hwm = _status_kb("VmHWM")
    if hwm is None:
        return int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024
    return hwm * 1024


def measure(mode: str, workdir: Path, bag: str, joints: int = 0) -> dict[str, Any]:
    """Run ``_child(mode)`` in a fresh interpreter and parse its JSON line (adds ``wall_s``)."""
    cmd = [sys.executable, str(Path(__file__).resolve()), "--child", mode, "--workdir", str(workdir), "--bag", bag]
    cmd += ["--joints", str(joints)]
    parent_peak = _status_kb("VmHWM")
    t = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - t
    if proc.returncode != 0:
        raise RuntimeError(f"{mode} child failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    res = json.loads(proc.stdout.strip().splitlines()[-1])
    res["wall_s"] = wall
    if parent_peak is not None:
        res["parent_peak_rss_bytes"] = parent_peak * 1024  # what the child's ru_maxrss inherits
    return res


def _stats(x: np.ndarray) -> dict[str, float]:
    return {"rms": float(np.sqrt(np.mean(x**2))), "median": float(np.median(x)), "max": float(np.max(x))}


def evaluate(workdir: Path, joints: int) -> dict[str, Any]:
    """Compare ``workdir/out`` (calibration.yaml, joint_angles.csv, summary.json) with the truth.

    Returns ``snapshots`` (used by the calibration), ``pixel_rms_per_axis`` (px), ``iterations``
    and ``T_ds_error``: per-snapshot rotation angle (rad) and translation norm (m) of
    ``Log(T_ds_true^-1 T_ds_est)``, each as RMS / median / max over the snapshots.
    """
    from dcc_fg.io.outputs import read_joint_angles_csv
    from dcc_fg.model import load_calibration
    from dcc_fg.studies.calibration_accuracy import T_ds_errors

    out_dir = workdir / "out"
    cal = load_calibration(out_dir / "calibration.yaml")
    summary = json.loads((out_dir / "summary.json").read_text())
    res: dict[str, Any] = {
        "snapshots": int(cal.statistics.get("snapshots", 0)),
        "pixel_rms_per_axis": float(summary["reprojection_error_px"]["all"]["rms_per_axis"]),
        "iterations": int(summary.get("iterations", -1)),
    }
    if joints > 0:
        from dcc_fg.sim.write_dataset import load_ground_truth

        stamps, thetas = read_joint_angles_csv(out_dir / "joint_angles.csv")
        gt = load_ground_truth(workdir / "ground_truth.yaml")
        err = T_ds_errors(gt.kinematics, gt.theta_at(stamps), cal, thetas)
        res["truth_snapshots"] = len(gt.timestamps_ns)
    else:
        truth = chain.se3_from_tau(TAU_DS)
        e = np.linalg.inv(truth) @ cal.T_ds(np.zeros(0))
        res["T_ds_rot_err_mrad"] = float(Rotation.from_matrix(e[:3, :3]).magnitude() * 1e3)
        res["T_ds_trans_err_mm"] = float(np.linalg.norm(e[:3, 3]) * 1e3)
        import gtsam

        err = np.array([gtsam.Pose3(truth).localCoordinates(gtsam.Pose3(cal.T_ds(np.zeros(0))))])
    res["T_ds_error"] = {
        "rotation_rad": _stats(np.linalg.norm(err[:, :3], axis=1)),
        "translation_m": _stats(np.linalg.norm(err[:, 3:], axis=1)),
    }
    return res


def run(
    frames_n: int = 2000,
    fmt: str = "ros2",
    storage: str = "sqlite3",
    workdir: Path | None = None,
    keep: bool = False,
    calibrate: bool = True,
    verbose: bool = True,
    joints: int = 0,
    seed: int = 0,
) -> dict[str, Any]:
    """Write the bag, measure the workloads, return the numbers."""
    tmp = workdir is None
    wd = Path(tempfile.mkdtemp(prefix="dcc_fg_bench_memory_")) if workdir is None else Path(workdir)
    try:
        res: dict[str, Any] = {
            "frames": frames_n,
            "joints": joints,
            "seed": seed,
            "format": fmt,
            "storage": storage if fmt == "ros2" else "ros1",
        }
        if verbose:
            print(f"writing {frames_n} image pairs (L = {joints}) ...", flush=True)
        res.update(write_inputs(wd, frames_n, fmt, storage, joints, seed))
        frame_bytes = SIZE[0] * SIZE[1]
        res["image_bytes_total"] = 2 * frames_n * frame_bytes
        if calibrate:
            res["calibrate_command"] = " ".join(["dcc-fg"] + calibrate_argv(wd, res["bag"], joints))
        modes = ["baseline", "load"] + (["calibrate"] if calibrate else [])
        for mode in modes:
            if verbose:
                print(f"running {mode} ...", flush=True)
            res[mode] = measure(mode, wd, res["bag"], joints)
        base = res["baseline"]["peak_rss_bytes"]
        for mode in modes[1:]:
            peak = res[mode]["peak_rss_bytes"]
            res[mode]["peak_over_bag"] = peak / res["bag_bytes"]
            res[mode]["growth_bytes"] = peak - base
            res[mode]["growth_over_bag"] = (peak - base) / res["bag_bytes"]
        if calibrate and res["calibrate"]["returncode"] == 0:
            res["calibrate"].update(evaluate(wd, joints))
        if verbose:
            _print(res, modes)
        return res
    finally:
        if tmp and not keep:
            shutil.rmtree(wd, ignore_errors=True)


def _print(res: dict[str, Any], modes: list[str]) -> None:
    """Human-readable lines, then the JSON line."""
    mb = 1.0 / 2**20
    print(
        f"bag: {res['bag']} ({res['format']}, L = {res['joints']}), {res['frames']} image pairs, "
        f"{res['bag_bytes'] * mb:.1f} MiB on disk, written in {res['write_s']:.1f} s"
    )
    print(f"baseline (imports only): peak RSS {res['baseline']['peak_rss_bytes'] * mb:.1f} MiB")
    for mode in modes[1:]:
        r = res[mode]
        print(
            f"{mode:>9}: peak RSS {r['peak_rss_bytes'] * mb:.1f} MiB in {r['time_s']:.1f} s "
            f"({r['wall_s']:.1f} s wall); "
            f"peak / bag = {r['peak_over_bag']:.3f}; (peak - baseline) / bag = {r['growth_over_bag']:.4f}; "
            f"{r.get('snapshots', 0)} snapshots"
        )
        if "T_ds_error" in r:
            rot, tr = r["T_ds_error"]["rotation_rad"], r["T_ds_error"]["translation_m"]
            print(
                f"           T_ds error per snapshot: rotation RMS {rot['rms']:.3e} rad (median {rot['median']:.3e}, "
                f"max {rot['max']:.3e}), translation RMS {tr['rms']:.3e} m (median {tr['median']:.3e}, "
                f"max {tr['max']:.3e}); reprojection {r['pixel_rms_per_axis']:.3f} px/axis RMS"
            )
    if "calibrate_command" in res:
        print(f"command: {res['calibrate_command']}")
    print(json.dumps(res))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--frames", type=int, default=2000, help="image pairs in the bag (default 2000)")
    p.add_argument(
        "--joints",
        type=int,
        default=0,
        choices=[0, 1, 2, 3],
        help="0: rigid stereo pair with a given gimbal.yaml (default); L >= 1: the simulator's L-joint gimbal, "
        "calibrated with automatic initialization",
    )
    p.add_argument("--seed", type=int, default=0, help="random seed of the scene and image noise (default 0)")
    p.add_argument("--format", choices=["ros2", "ros1"], default="ros2", help="bag format (default ros2)")
    p.add_argument("--storage", choices=["sqlite3", "mcap"], default="sqlite3", help="ROS2 storage plugin")
    p.add_argument("--workdir", help="folder for the bag and outputs (default: a temporary folder, deleted)")
    p.add_argument("--keep", action="store_true", help="keep the temporary folder")
    p.add_argument("--skip-calibrate", action="store_true", help="measure reading + detection only")
    p.add_argument("--child", choices=["baseline", "load", "calibrate"], help=argparse.SUPPRESS)
    p.add_argument("--bag", help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    if a.child:
        print(json.dumps(_child(a.child, Path(a.workdir), a.bag, a.joints)))
        return 0
    wd = Path(a.workdir) if a.workdir else None
    run(a.frames, a.format, a.storage, wd, a.keep, not a.skip_calibrate, joints=a.joints, seed=a.seed)
    return 0


if __name__ == "__main__":
    sys.exit(main())
