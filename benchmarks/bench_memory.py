"""Benchmark: peak memory of reading, detecting and calibrating a large calibration bag.

What is measured
----------------
1. A calibration bag of ``--frames`` image pairs (default 2,000) is written with
   :func:`dcc_fg.io.bags.write_ros2_bag` / :func:`write_ros1_bag` from a generator (one pair in
   memory at a time): 640x480 ``mono8`` images of a 9x6 chessboard (0.025 m squares) rendered for
   two undistorted pinhole cameras 0.1 m apart (a zero-joint cluster, L = 0) at random board
   poses (0.45-0.9 m, tilts up to 30 degrees, fully visible in both), by one perspective warp of a
   pre-rendered board texture plus a 3x3 blur.  Uncompressed images: the bag on disk is about
   ``frames * 2 * 307 kB`` (1.2 GB for 2,000 frames).
2. Each workload runs in a fresh Python process (so its peak resident set size is its own) and
   reports ``resource.getrusage(RUSAGE_SELF).ru_maxrss``:

   * ``baseline``: the imports only (numpy, OpenCV, GTSAM, rosbags, dcc_fg): the fixed cost;
   * ``load``: :func:`dcc_fg.io.dataset.load_dataset` on the bag: the streaming reader
     (:class:`~dcc_fg.io.bags.BagImagePairs`) and chessboard detection of every image;
   * ``calibrate``: the whole ``dcc-fg calibrate BAG --camchain --target --gimbal --out`` command
     (L = 0 gimbal.yaml): reading, detection, the calibration graph over all snapshots with
     covariances, and the output files.  Its T_ds is compared with the rendering's ground truth.

Printed ratios: peak RSS / bag size on disk, and (peak - baseline) / bag size (the part that
grows with the data).  Reading every image into memory instead would need at least the bag size.
The target in the issue is a peak below 1 GB for 2,000 frames.  The last line of output is JSON.

Run: ``python benchmarks/bench_memory.py [--frames 2000] [--format ros2|ros1] [--storage sqlite3|mcap]
[--workdir DIR] [--keep] [--skip-calibrate]``.
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

from dcc_fg.io.bags import write_ros1_bag, write_ros2_bag  # noqa: E402
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


def write_inputs(workdir: Path, n: int, fmt: str, storage: str) -> dict[str, Any]:
    """Write the bag, camchain.yaml, target.yaml and an L = 0 gimbal.yaml into ``workdir``."""
    workdir.mkdir(parents=True, exist_ok=True)
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
        bag = write_ros1_bag(workdir / "calib.bag", frames(n))
    else:
        bag = write_ros2_bag(workdir / "calib_ros2", frames(n), storage=storage)  # type: ignore[arg-type]
    files = [bag] if bag.is_file() else [p for p in bag.rglob("*") if p.is_file()]
    return {"bag": str(bag), "bag_bytes": int(sum(p.stat().st_size for p in files)), "write_s": time.perf_counter() - t}


# ------------------------------------------------------------------ child workloads


def _child(mode: str, workdir: Path, bag: str) -> dict[str, Any]:
    """Run one workload in this process; returns its peak RSS and results."""
    import gtsam  # noqa: F401  (the baseline holds every heavy import the workloads use)
    import rosbags.highlevel  # noqa: F401

    import dcc_fg.calibrate  # noqa: F401
    from dcc_fg.cli import main
    from dcc_fg.io.dataset import load_dataset
    from dcc_fg.model import load_calibration

    out: dict[str, Any] = {"mode": mode}
    t = time.perf_counter()
    if mode == "load":
        data = load_dataset(bag, workdir / "camchain.yaml", workdir / "target.yaml", progress=False)
        out["snapshots"] = len(data.snapshots)
    elif mode == "calibrate":
        args = [
            "calibrate",
            bag,
            "--camchain",
            str(workdir / "camchain.yaml"),
            "--target",
            str(workdir / "target.yaml"),
        ]
        args += ["--gimbal", str(workdir / "gimbal.yaml"), "--out", str(workdir / "out")]
        rc = main(args)
        out["returncode"] = rc
        if rc == 0:
            cal = load_calibration(workdir / "out" / "calibration.yaml")
            err = np.linalg.inv(chain.se3_from_tau(TAU_DS)) @ cal.T_ds(np.zeros(0))
            out["T_ds_rot_err_mrad"] = float(Rotation.from_matrix(err[:3, :3]).magnitude() * 1e3)
            out["T_ds_trans_err_mm"] = float(np.linalg.norm(err[:3, 3]) * 1e3)
            out["snapshots"] = int(cal.statistics.get("snapshots", 0))
    out["time_s"] = time.perf_counter() - t
    out["peak_rss_bytes"] = int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024  # Linux: kB
    return out


def measure(mode: str, workdir: Path, bag: str) -> dict[str, Any]:
    """Run ``_child(mode)`` in a fresh interpreter and parse its JSON line."""
    cmd = [sys.executable, str(Path(__file__).resolve()), "--child", mode, "--workdir", str(workdir), "--bag", bag]
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        raise RuntimeError(f"{mode} child failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def run(
    frames_n: int = 2000,
    fmt: str = "ros2",
    storage: str = "sqlite3",
    workdir: Path | None = None,
    keep: bool = False,
    calibrate: bool = True,
    verbose: bool = True,
) -> dict[str, Any]:
    """Write the bag, measure the workloads, return the numbers."""
    tmp = workdir is None
    wd = Path(tempfile.mkdtemp(prefix="dcc_fg_bench_memory_")) if workdir is None else Path(workdir)
    try:
        res: dict[str, Any] = {"frames": frames_n, "format": fmt, "storage": storage if fmt == "ros2" else "ros1"}
        res.update(write_inputs(wd, frames_n, fmt, storage))
        frame_bytes = SIZE[0] * SIZE[1]
        res["image_bytes_total"] = 2 * frames_n * frame_bytes
        modes = ["baseline", "load"] + (["calibrate"] if calibrate else [])
        for mode in modes:
            res[mode] = measure(mode, wd, res["bag"])
        base = res["baseline"]["peak_rss_bytes"]
        for mode in modes[1:]:
            peak = res[mode]["peak_rss_bytes"]
            res[mode]["peak_over_bag"] = peak / res["bag_bytes"]
            res[mode]["growth_bytes"] = peak - base
            res[mode]["growth_over_bag"] = (peak - base) / res["bag_bytes"]
        if verbose:
            mb = 1.0 / 2**20
            print(f"bag: {res['bag']} ({fmt}), {frames_n} image pairs, {res['bag_bytes'] * mb:.1f} MiB on disk, ")
            print(f"     written in {res['write_s']:.1f} s")
            print(f"baseline (imports only): peak RSS {base * mb:.1f} MiB")
            for mode in modes[1:]:
                r = res[mode]
                line = (
                    f"{mode:>9}: peak RSS {r['peak_rss_bytes'] * mb:.1f} MiB in {r['time_s']:.1f} s; "
                    f"peak / bag = {r['peak_over_bag']:.3f}; (peak - baseline) / bag = {r['growth_over_bag']:.4f}; "
                    f"{r.get('snapshots', 0)} snapshots"
                )
                if "T_ds_rot_err_mrad" in r:
                    line += f"; T_ds error {r['T_ds_rot_err_mrad']:.3f} mrad, {r['T_ds_trans_err_mm']:.3f} mm"
                print(line)
            print(json.dumps(res))
        return res
    finally:
        if tmp and not keep:
            shutil.rmtree(wd, ignore_errors=True)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--frames", type=int, default=2000, help="image pairs in the bag (default 2000)")
    p.add_argument("--format", choices=["ros2", "ros1"], default="ros2", help="bag format (default ros2)")
    p.add_argument("--storage", choices=["sqlite3", "mcap"], default="sqlite3", help="ROS2 storage plugin")
    p.add_argument("--workdir", help="folder for the bag and outputs (default: a temporary folder, deleted)")
    p.add_argument("--keep", action="store_true", help="keep the temporary folder")
    p.add_argument("--skip-calibrate", action="store_true", help="measure reading + detection only")
    p.add_argument("--child", choices=["baseline", "load", "calibrate"], help=argparse.SUPPRESS)
    p.add_argument("--bag", help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    if a.child:
        print(json.dumps(_child(a.child, Path(a.workdir), a.bag)))
        return 0
    wd = Path(a.workdir) if a.workdir else None
    run(a.frames, a.format, a.storage, wd, a.keep, not a.skip_calibrate)
    return 0


if __name__ == "__main__":
    sys.exit(main())
