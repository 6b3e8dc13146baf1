"""Benchmark: N-camera VIO on rendered cluster flights, against the two-camera run of the same flight.

For each cluster preset of :func:`dcc_fg.sim.cluster_flight.flight_cluster` (``stereo+gimbal``: a static
stereo pair cam0 + cam1 and the gimbal camera cam2; ``gimbal-pair``: cam0 static, cam1 and cam2 on the
same gimbal; ``two-gimbals``: cam1 and cam2 on two gimbals moving on their own) one flight of
``--duration`` seconds is rendered into a ROS2 bag (``dcc-fg simulate flight --cluster``; not timed).
The bag is then run through :func:`dcc_fg.vio.pipeline.run_vio_bag` in ``dcc``
mode, as ``dcc-fg vio`` runs it (front end in a child process), twice in this process:

* with every camera of the cluster;
* with cam0 and the gimbal camera only (``cameras=()``): the one-static-camera run of the same flight,
  the same images of those two cameras.

Printed per run: wall time, real-time factor (processing time / data duration), normalized translation
RMSE (SE(3) alignment to the bag's ground truth) and joint RMSE (each chain's); per preset the ratios all-cameras /
two-cameras of RMSE, joint RMSE and wall time. ``--repeat`` alternates the two runs and reports the
median wall-time ratio (machines here are noisy: the ratios hold, absolute times do not).

Usage: ``python benchmarks/bench_vio_cluster.py [--duration 20] [--seed 0] [--presets stereo+gimbal,gimbal-pair]
[--repeat 1] [--keep DIR]``
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

from dcc_fg.sim.cluster_flight import FLIGHT_PRESETS
from dcc_fg.sim.flight_bag import load_flight_calibration, write_flight
from dcc_fg.sim.trajectory import FlightConfig
from dcc_fg.vio.backend import VioOptions
from dcc_fg.vio.evaluate import evaluate_trajectory, joint_rmse, load_ground_truth
from dcc_fg.vio.pipeline import BagTopics, PipelineOptions, run_vio_bag


def flight_config(duration: float) -> FlightConfig:
    """The paper's two loops when there is time to fly them (>= 40 s), else one short loop."""
    return FlightConfig(duration=duration) if duration >= 40.0 else FlightConfig.short(duration)


def render(folder: Path, preset: str, cfg: FlightConfig, seed: int) -> tuple[Path, Path]:
    """Render the cluster flight into ``folder`` (reused when ``--keep`` left one with the same settings);
    the bag and its calibration.yaml."""
    marker = folder / "bench_settings.json"
    settings = json.dumps({"duration": cfg.duration, "loops": cfg.loops, "seed": seed, "cluster": preset})
    if not (marker.is_file() and marker.read_text() == settings):
        write_flight(folder, "ros2", cfg, seed=seed, cluster=preset, force=True)
        marker.write_text(settings)
    return folder / "flight", folder / "calibration.yaml"


def run(bag: Path, calibration: Path, cameras: tuple[str, ...] | None, worker: str = "process") -> dict[str, Any]:
    """One dcc run over the bag with the further cameras ``cameras`` (None: all), timed and scored.
    ``worker``: the front end in its own process (``process``, what ``dcc-fg vio`` does on 2 cores; the
    back end's joint angles reach it when they arrive, so results vary a little with the machine's
    load) or ``inline`` (in this process, in step with the back end: the same result every run)."""
    cal, imu = load_flight_calibration(calibration)
    cluster = cal.cluster()
    primary = cluster.primary_gimbal_camera
    focal = float(cal.static_camera.intrinsics[0])  # type: ignore[union-attr]
    opts = VioOptions(mode="dcc", sigma=1.0 / focal, keyframe_every=3)
    topics = BagTopics(dynamic=cluster.camera(primary).rostopic or f"/{primary}/image_raw")
    t0 = time.perf_counter()
    res, info = run_vio_bag(bag, cal, imu, opts, topics, PipelineOptions(worker=worker, cameras=cameras))
    wall = time.perf_counter() - t0
    gt = load_ground_truth(bag)
    ev = evaluate_trajectory(res.timestamps_ns, res.T_WI, gt, "se3")
    return {
        "cameras": info["cameras"]["used"],
        "wall_s": wall,
        "data_s": res.stats["data_duration_s"],
        "real_time_factor": wall / res.stats["data_duration_s"],
        "normalized_translation_rmse_percent": ev["normalized_translation_rmse_percent"],
        "joint_rmse_rad": joint_rmse(res.timestamps_ns, res.theta, gt),
        "chain_joint_rmse_rad": {
            n: joint_rmse(res.timestamps_ns, th, gt.chain(n)) for n, th in res.chain_theta.items()
        },
        "failed_updates": res.stats["failed_updates"],
        "extra_obs": res.stats["extra_obs"],
        "landmarks": res.stats["landmarks"],
    }


def line(r: dict[str, Any]) -> str:
    j = ", ".join(f"{x:.2e}" for x in r["joint_rmse_rad"])
    for name, rmse in r["chain_joint_rmse_rad"].items():
        j += f"; {name} " + ", ".join(f"{x:.2e}" for x in rmse)
    return (
        f"  {'+'.join(r['cameras']):16s} {r['wall_s']:6.1f} s for {r['data_s']:.1f} s  RTF {r['real_time_factor']:.3f}"
        f"  norm. transl. RMSE {r['normalized_translation_rmse_percent']:.4f} %  joint RMSE {j} rad"
        f"  landmarks {r['landmarks']}  failed updates {r['failed_updates']}"
    )


def main(argv: list[str] | None = None) -> dict[str, Any]:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--duration", type=float, default=20.0, help="flight duration, s (default 20)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--presets", default=",".join(FLIGHT_PRESETS), help="comma-separated cluster presets")
    p.add_argument("--repeat", type=int, default=1, help="alternate the two runs this many times (wall-time ratio)")
    p.add_argument("--keep", help="write the flights into this folder (default: a temporary one)")
    p.add_argument(
        "--worker",
        choices=("process", "inline"),
        default="process",
        help="front end in its own process (default; timing-dependent results) or inline (deterministic)",
    )
    a = p.parse_args(argv)
    out: dict[str, Any] = {}
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(a.keep or tmp)
        cfg = flight_config(a.duration)
        for preset in a.presets.split(","):
            t0 = time.perf_counter()
            bag, calibration = render(root / preset.replace("+", "_"), preset, cfg, a.seed)
            print(f"{preset}: rendered {a.duration:.0f} s in {time.perf_counter() - t0:.1f} s (not timed below)")
            ratios, runs = [], {}
            for _ in range(max(1, a.repeat)):
                runs["all"] = run(bag, calibration, None, a.worker)
                runs["two"] = run(bag, calibration, (), a.worker)
                ratios.append(runs["all"]["wall_s"] / runs["two"]["wall_s"])
            for r in runs.values():
                print(line(r))
            all_, two = runs["all"], runs["two"]
            res = {
                "all_cameras": all_,
                "two_cameras": two,
                "rmse_ratio": all_["normalized_translation_rmse_percent"] / two["normalized_translation_rmse_percent"],
                "joint_rmse_ratio": [x / y for x, y in zip(all_["joint_rmse_rad"], two["joint_rmse_rad"], strict=True)],
                "wall_time_ratio_median": statistics.median(ratios),
            }
            out[preset] = res
            print(
                f"  all cameras / cam0 + gimbal camera: translation RMSE {res['rmse_ratio']:.2f}, joint RMSE "
                + ", ".join(f"{x:.2f}" for x in res["joint_rmse_ratio"])
                + f", wall time {res['wall_time_ratio_median']:.2f} (median of {len(ratios)})"
            )
    return out


if __name__ == "__main__":
    main()
