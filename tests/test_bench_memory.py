"""Smoke test of benchmarks/bench_memory.py on small bags (the 2,000-frame runs are not part of CI).

A streaming reader holds a bounded number of images, so the peak RSS of ``load_dataset`` on a
bag must not grow with the number of frames: from 20 to 80 frames a reader that kept every
image would add at least 60 pairs x 2 x 640 x 480 bytes = 36.9 MB; we allow a quarter of that.

The gimbal option (``--joints 2``, automatic initialization) runs on 30 rendered frames.  Its
T_ds bound is derived, not read off a run: the encoderless bundle estimator attains the
Cramer-Rao bound (tests/test_statistics.py), so the per-snapshot T_ds errors are ~Gaussian with
the CRB covariance of the same scenario at the run's pixel noise ``sigma``.  The renderer's 2 grey
levels of image noise and 0.6 px blur give detected corners far below the corner-level
simulator's 0.4 px, so ``sigma`` is taken as the run's per-axis RMS reprojection residual (which
underestimates the noise by the factor sqrt(1 - p / n) = 0.98 here: p = 258 parameters,
n = 30 x 2 x 70 x 2 = 8,400 residuals), and checked to lie below 0.4 px.  The squared RMS over
the snapshots of the rotation (translation) error norm is a positive combination of chi2_1
variables whose mean is the squared CRB RMS; the errors of the snapshots are correlated through
the shared kinematics, so few directions carry it.  The ratio RMS / CRB RMS exceeds 3 with
probability P(chi2_3 > 27) = 6e-6 if three directions share it equally, and P(chi2_1 > 9) = 0.27%
in the worst case of a single direction.  Hence: rotation and translation RMS <= 3 x their CRB RMS
(a calibration that lost its way, e.g. a wrong automatic initialization, is off by orders of
magnitude).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import load_benchmark

from dcc_fg.sim.calibration_scene import simulate_calibration
from dcc_fg.sim.write_dataset import default_target, load_ground_truth, scene_config
from dcc_fg.studies.calibration_accuracy import cramer_rao_bound

pytestmark = pytest.mark.slow  # renders bags and runs dcc-fg calibrate in a child process (~45 s)


def test_bench_memory_runs_and_streams(tmp_path: Path) -> None:
    bench = load_benchmark("bench_memory")
    small = bench.run(frames_n=20, fmt="ros2", workdir=tmp_path / "small", verbose=False)
    assert small["load"]["snapshots"] == 20
    cal = small["calibrate"]
    assert cal["returncode"] == 0 and cal["snapshots"] == 20
    # 20 noise-free rendered pairs, 54 corners each: T_ds to well under a mrad / mm
    assert cal["T_ds_rot_err_mrad"] < 1.0 and cal["T_ds_trans_err_mm"] < 1.0

    big_dir = tmp_path / "big"
    inputs = bench.write_inputs(big_dir, 80, "ros2", "sqlite3")
    big = bench.measure("load", big_dir, inputs["bag"])
    assert big["snapshots"] == 80
    pair_bytes = 2 * bench.SIZE[0] * bench.SIZE[1]
    growth = big["peak_rss_bytes"] - small["load"]["peak_rss_bytes"]
    assert growth < 0.25 * 60 * pair_bytes, f"peak RSS grew by {growth / 2**20:.1f} MiB from 20 to 80 frames"


def test_bench_memory_gimbal_auto_init(tmp_path: Path) -> None:
    bench = load_benchmark("bench_memory")
    n, seed = 30, 0
    res = bench.run(frames_n=n, fmt="ros2", workdir=tmp_path / "gimbal", verbose=False, joints=2, seed=seed)
    assert res["joints"] == 2 and res["frames"] == n and res["bag_bytes"] > 2 * n * bench.SIZE[0] * bench.SIZE[1]
    command = res["calibrate_command"]
    assert "--joints 2" in command and "--gimbal" not in command  # automatic initialization, no gimbal.yaml
    for mode in ("baseline", "load", "calibrate"):
        assert res[mode]["peak_rss_bytes"] > 0 and res[mode]["wall_s"] > 0
    assert res["load"]["snapshots"] == n
    cal = res["calibrate"]
    assert cal["returncode"] == 0 and cal["snapshots"] == n  # both cameras see the whole board in every pair
    err = cal["T_ds_error"]
    for part in ("rotation_rad", "translation_m"):
        assert set(err[part]) == {"rms", "median", "max"}
        assert 0.0 < err[part]["median"] <= err[part]["max"]
    sigma = cal["pixel_rms_per_axis"]
    assert 0.005 < sigma < 0.4  # sub-pixel detection on the blurred, noisy renderings

    # the same scenario at corner level (write_calibration_dataset renders this simulation)
    sim = simulate_calibration(seed, scene_config(default_target("checkerboard"), n, 2))
    gt = load_ground_truth(res["ground_truth"])
    np.testing.assert_allclose(gt.theta, sim.joints_calibration, atol=1e-12)
    crb = cramer_rao_bound(sim.calibration_set, sim.truth, sim.joints_calibration, sim.T_st_calibration, sigma)
    assert err["rotation_rad"]["rms"] <= 3.0 * crb.rotation_rms, (err, crb.rotation_rms)
    assert err["translation_m"]["rms"] <= 3.0 * crb.translation_rms, (err, crb.translation_rms)
