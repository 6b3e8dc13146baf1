"""Benchmark: the cost of ``dcc-fg plan`` (:func:`dcc_fg.planning.plan.plan_snapshots`, K snapshots, objective
worst, calibration prediction) with its target-pose choice against the facing pose alone, per L.

For members of the randomized mechanism family (default seeds 8, 4, 0: L = 1, 2, 3) the start of
``bench_plan.py`` is rendered and calibrated (10 random snapshots), then the plan is timed twice with
the candidate target poses of :func:`dcc_fg.planning.predict.candidate_poses` and twice with their
tilts switched off (facing pose at the same distances), alternating in one process; printed: the best
time of each and their ratio.

Run: ``python benchmarks/bench_plan_cost.py [--seeds 8,4,0] [--k 5]``.
"""

from __future__ import annotations

import argparse
import sys
import time

import bench_plan as bp
import numpy as np

from dcc_fg.planning import predict
from dcc_fg.planning.plan import plan_snapshots
from dcc_fg.planning.range_spec import Tolerance


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seeds", default="8,4,0", help="family seeds (default 8,4,0: L = 1, 2, 3)")
    p.add_argument("--k", type=int, default=5, help="snapshots per plan (default 5)")
    args = p.parse_args(argv)
    tilts = predict.POSE_TILTS_DEG
    for seed in (int(x) for x in args.seeds.split(",")):
        sc = bp.make_scene(seed)
        L = sc.truth.n_joints
        rng = np.random.default_rng([seed, 2])
        start_th = sc.ranges[:, 0] + rng.uniform(size=(bp.START, L)) * np.ptp(sc.ranges, axis=1)
        start, start_th = bp.simulator_snapshots(sc, start_th, rng, 0)
        base = bp.calibrate_set(sc, start, start_th)
        times: dict[str, list[float]] = {"poses": [], "facing": []}
        for label in ("poses", "facing", "poses", "facing"):
            predict.POSE_TILTS_DEG = tilts if label == "poses" else ()
            t0 = time.perf_counter()
            plan_snapshots(base.info, sc.ranges + base.offset[:, None], Tolerance(1e-6, 1e-6), args.k)
            times[label].append(time.perf_counter() - t0)
        predict.POSE_TILTS_DEG = tilts
        a, b = min(times["poses"]), min(times["facing"])
        print(
            f"member {seed} L={L}: K={args.k} plan {a:.3f} s with the target poses, {b:.3f} s facing pose only "
            f"(ratio {a / b:.1f})",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
