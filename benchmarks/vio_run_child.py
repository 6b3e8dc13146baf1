"""One ``dcc`` or ``scc`` run of a rendered flight, printed as one JSON line: the child process of
``bench_vio_revision.py``. It imports whichever ``dcc_fg`` comes first on ``PYTHONPATH``, so it uses only
the API that checkouts from before issue 18 (5eea12d) share with today's: the flight's calibration, the
bag through :func:`~dcc_fg.vio.pipeline.run_vio_bag` with the front end in its own process, and the
evaluation against the bag's ground truth (translation RMSE in % of the distance, joint RMSE in rad).

Usage: ``python benchmarks/vio_run_child.py FLIGHT_DIR dcc|scc``
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import yaml

import dcc_fg
from dcc_fg.sim.flight_bag import load_flight_calibration
from dcc_fg.vio.backend import VioOptions
from dcc_fg.vio.evaluate import evaluate_trajectory, joint_rmse, load_ground_truth
from dcc_fg.vio.pipeline import PipelineOptions, run_vio_bag


def main(argv: list[str]) -> int:
    folder, mode = Path(argv[0]), argv[1]
    calibration = folder / "calibration.yaml"
    cal, imu = load_flight_calibration(calibration)
    fixed = None
    if mode == "scc":
        fixed = tuple(yaml.safe_load(calibration.read_text())["flight"]["joints_locked"])
    focal = float(cal.static_camera.intrinsics[0])  # type: ignore[union-attr]
    opts = VioOptions(mode=mode, sigma=1.0 / focal, keyframe_every=3, theta_fixed=fixed)
    t0 = time.perf_counter()
    c0 = time.process_time()
    res, _ = run_vio_bag(folder / "flight", cal, imu, opts, pipeline=PipelineOptions(worker="process"))
    wall = time.perf_counter() - t0
    cpu = time.process_time() - c0
    gt = load_ground_truth(folder / "flight")
    ev = evaluate_trajectory(res.timestamps_ns, res.T_WI, gt, "se3")
    out = {
        "code": str(Path(dcc_fg.__file__).resolve().parent.parent),
        "mode": mode,
        "wall_s": wall,
        "cpu_s": cpu,
        "real_time_factor": wall / res.stats["data_duration_s"],
        "normalized_translation_rmse_percent": ev["normalized_translation_rmse_percent"],
        "joint_rmse_rad": joint_rmse(res.timestamps_ns, res.theta, gt) if mode == "dcc" else None,
    }
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
