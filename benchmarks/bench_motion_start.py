"""Benchmark: the VIO started in motion against the same flight started from standstill (issue 16, item 4).

The 60 s rendered flight of ``bench_vio.py`` (two 30 m x 15 m loops at up to ~6 m/s, the gimbal moving;
``--keep`` reuses it) is run twice with ``dcc`` through :func:`dcc_fg.vio.pipeline.run_vio_bag`:

1. from the start of the bag: the body hovers for 1 s, the rest test passes, standstill start;
2. from ``--start`` s into the bag (default 10 s, moving at speed): the rest test fails and the start comes
   from the visual-inertial alignment (:mod:`dcc_fg.vio.backend.motion_init`).

Printed: the start each run chose; the normalized translation RMSE of each run over its own span and the
ratio run 2 / run 1 (issue target <= 1.5), and run 1 over run 2's span; convergence of run 2 at
``--converge`` s after its start (default 2 s): the tilt error (angle between the estimated and true body
z axes in W; both worlds have gravity along -z, so no alignment is needed), the speed error and the joint
error (targets: 1 deg, 0.1 m/s, 1e-2 rad). Exits 1 when a target is missed.

Usage: ``python benchmarks/bench_motion_start.py [--start 10] [--converge 2] [--seed 0] [--keep DIR]``
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_vio import _flight  # noqa: E402
from bench_vio_cluster import flight_config  # noqa: E402

from dcc_fg.sim.flight_bag import FlightBag, load_flight_calibration  # noqa: E402
from dcc_fg.vio.backend import VioOptions, VioResult  # noqa: E402
from dcc_fg.vio.evaluate import GroundTruth, evaluate_trajectory, joint_rmse, load_ground_truth  # noqa: E402
from dcc_fg.vio.pipeline import PipelineOptions, run_vio_bag  # noqa: E402

NS = 1_000_000_000


def run(fb: FlightBag, start_s: float) -> VioResult:
    cal, imu = load_flight_calibration(fb.calibration)
    focal = float(cal.static_camera.intrinsics[0])  # type: ignore[union-attr]
    opts = VioOptions(mode="dcc", sigma=1.0 / focal, keyframe_every=3)
    res, _ = run_vio_bag(fb.bag, cal, imu, opts, pipeline=PipelineOptions(start_s=start_s))
    return res


def _nearest(gt_t: np.ndarray, t: int) -> int:
    return int(np.clip(np.searchsorted(gt_t, t), 0, gt_t.size - 1))


def convergence(res: VioResult, gt: GroundTruth, after_s: float) -> dict[str, float]:
    """Tilt (deg), speed (m/s) and joint (rad) errors of the first keyframe ``after_s`` past the start."""
    k = int(np.searchsorted(res.timestamps_ns, res.timestamps_ns[0] + int(after_s * NS)))
    t = int(res.timestamps_ns[k])
    i = _nearest(gt.t_ns, t)
    z_est = res.T_WI[k][:3, :3].T @ np.array([0.0, 0.0, 1.0])
    z_true = gt.T_WI[i][:3, :3].T @ np.array([0.0, 0.0, 1.0])
    tilt = float(np.degrees(np.arccos(np.clip(z_est @ z_true, -1.0, 1.0))))
    j0, j1 = max(i - 5, 0), min(i + 5, gt.t_ns.size - 1)
    v_true = (gt.T_WI[j1][:3, 3] - gt.T_WI[j0][:3, 3]) / ((gt.t_ns[j1] - gt.t_ns[j0]) / NS)
    speed = float(abs(np.linalg.norm(res.v_W[k]) - np.linalg.norm(v_true)))
    joint = float("nan")
    if gt.joints is not None and gt.joint_t_ns is not None:
        jj = _nearest(gt.joint_t_ns, t)
        joint = float(np.max(np.abs(res.theta[k] - gt.joints[jj])))
    return {"t_after_start_s": (t - int(res.timestamps_ns[0])) / NS, "tilt_deg": tilt, "speed_mps": speed,
            "joint_rad": joint}  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--start", type=float, default=10.0, help="start of the motion run, s into the bag (default 10)")
    p.add_argument("--converge", type=float, default=2.0, help="convergence checked this long after it (s)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--keep", help="folder of the rendered flight (reused when it matches; default: temporary)")
    a = p.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(a.keep or tmp)
        fb = _flight(root / "moving", flight_config(60.0), a.seed, moving=True)
        gt = load_ground_truth(fb.bag)
        still, moving = run(fb, 0.0), run(fb, a.start)
        out: dict[str, Any] = {}
        for name, res in (("standstill", still), ("motion", moving)):
            ev = evaluate_trajectory(res.timestamps_ns, res.T_WI, gt, "se3")
            out[name] = ev["normalized_translation_rmse_percent"]
            print(
                f"{name:10s} start ({res.stats['start']['how']}): {res.timestamps_ns.size} keyframes, norm. transl. "
                f"RMSE {ev['normalized_translation_rmse_percent']:.4f} % over {ev['distance_m']:.0f} m, joint RMSE "
                + ", ".join(f"{x:.2e}" for x in joint_rmse(res.timestamps_ns, res.theta, gt))
                + " rad"
            )
        same = still.timestamps_ns >= moving.timestamps_ns[0]
        ev_same = evaluate_trajectory(still.timestamps_ns[same], still.T_WI[same], gt, "se3")
        ratio = out["motion"] / out["standstill"]
        print(f"motion start detail: {moving.stats['start']['detail']}")
        print(
            f"RMSE ratio motion / standstill (whole runs): {ratio:.2f} (target <= 1.5); standstill run over the "
            f"motion run's span: {ev_same['normalized_translation_rmse_percent']:.4f} %"
        )
        c = convergence(moving, gt, a.converge)
        print(
            f"{c['t_after_start_s']:.2f} s after the motion start: tilt error {c['tilt_deg']:.2f} deg, speed error "
            f"{c['speed_mps']:.3f} m/s, joint error {c['joint_rad']:.2e} rad (targets 1 deg, 0.1 m/s, 1e-2 rad)"
        )
        ok = moving.stats["start"]["how"] == "motion" and ratio <= 1.5
        ok = ok and c["tilt_deg"] <= 1.0 and c["speed_mps"] <= 0.1 and c["joint_rad"] <= 1e-2
        print("PASS" if ok else "FAIL")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
