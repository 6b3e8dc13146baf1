"""Benchmark: ``dcc-fg calibrate --incremental`` (dcc_fg.incremental) against the batch calibration.

A simulated 200-snapshot encoderless calibration (the paper's 2-DOF scene, :mod:`dcc_fg.sim.calibration_scene`,
0.4 px corner noise, snapshots in the scene's order) is fed one snapshot at a time to
:class:`~dcc_fg.incremental.IncrementalCalibration`; every update solves and predicts the worst-case
T_ds 1-sigma over the range and the next suggested snapshot. Printed: the time per update (median,
95th percentile, max; warm updates and global solves apart, and the warm updates of the last 50
snapshots), its ratio to the batch calibration of the same 200 snapshots (the global strategy with
covariances, what ``dcc-fg calibrate --joints 2`` runs), the time of ``finish()``, and the load
average (2 shared cores: other jobs inflate the times). Asserted: the final result equals the batch
one (data cost to 1e-6 relative, every ``T_ds(theta_i)`` within its 1-sigma).

With ``--background`` the global solves run in a background process (what ``dcc-fg calibrate --incremental``
does) and the snapshots arrive every ``--interval`` s (default 0.5 s: a person taking snapshots by hand
takes one every few seconds; a snapshot that arrives while an update still runs waits for it): the
update times then include adopting a finished background solve and adding the snapshots that arrived
during it. Also printed: how long after the ``start_snapshots``-th snapshot the first solution arrived.

Usage: ``python benchmarks/bench_incremental.py [--snapshots 200] [--seed 0] [--backend isam2|lm]
[--background [--interval 0.5]]``
"""

from __future__ import annotations

import argparse
import os
import time
from dataclasses import replace

import gtsam
import numpy as np

from dcc_fg.calibrate import CalibrationOptions
from dcc_fg.data import with_joints
from dcc_fg.global_fit import calibrate_global, data_cost
from dcc_fg.incremental import BACKENDS, DEFAULT_GLOBAL_UNTIL, IncrementalCalibration, IncrementalOptions
from dcc_fg.sim.calibration_scene import SceneConfig, simulate_calibration

BUDGET_S = 1.0  # the limit per update


def stats(times: list[float]) -> str:
    if not times:
        return "none"
    t = np.asarray(times)
    return (
        f"median {np.median(t):.3f} s, p95 {np.percentile(t, 95):.3f} s, max {t.max():.3f} s "
        f"({len(t)} updates, {int((t > BUDGET_S).sum())} over {BUDGET_S:g} s)"
    )


def main(argv: list[str] | None = None) -> dict[str, float]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--snapshots", type=int, default=200)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--backend", choices=list(BACKENDS), default="isam2")
    ap.add_argument("--global-until", type=int, default=DEFAULT_GLOBAL_UNTIL)
    ap.add_argument("--predict-every", type=int, default=1)
    ap.add_argument("--background", action="store_true", help="global solves in a background process")
    ap.add_argument("--interval", type=float, default=0.5, help="--background: seconds between snapshots")
    args = ap.parse_args(argv)
    sim = simulate_calibration(args.seed, SceneConfig(n_calibration=args.snapshots, n_validation=1))
    data = sim.calibration_set
    data = with_joints(data, None)  # encoderless, no guesses
    load0 = os.getloadavg()

    opt = IncrementalOptions(
        backend=args.backend,
        global_until=args.global_until,
        predict_every=args.predict_every,
        background=args.background,
    )
    inc = IncrementalCalibration(replace(data, snapshots=[]), 2, opt)
    t0 = time.perf_counter()
    arrivals: list[float] = []
    first_solution = float("nan")
    for s in data.snapshots:
        arrivals.append(time.perf_counter())
        inc.add(s)
        if inc.solving and not np.isfinite(first_solution):
            first_solution = time.perf_counter() - arrivals[inc.start_snapshots - 1]
        if args.background:  # the next snapshot arrives `interval` s after this one (or when this update ends)
            time.sleep(max(0.0, arrivals[-1] + args.interval - time.perf_counter()))
    t_feed = time.perf_counter() - t0
    t0 = time.perf_counter()
    final = inc.finish()
    t_finish = time.perf_counter() - t0

    t0 = time.perf_counter()
    batch = calibrate_global(data, 2, CalibrationOptions())
    t_batch = time.perf_counter() - t0
    load1 = os.getloadavg()

    ups = [u for u in inc.updates if u.strategy != "collect"]
    warm = [u.update_time_s for u in ups if u.strategy == "warm"]
    glob = [(u.n_snapshots, u.reason.split(";")[0], u.update_time_s) for u in ups if u.strategy == "global"]
    late = [u.update_time_s for u in ups if u.strategy == "warm" and u.n_snapshots > len(data.snapshots) - 50]
    all_times = [u.update_time_s for u in ups]
    last = inc.updates[-1]
    mode = f"global solves in the background, a snapshot every {args.interval:g} s" if args.background else (
        "global solves inside the updates")  # fmt: skip
    print(f"{len(data.snapshots)} snapshots, L = 2, backend {args.backend}, prediction every {args.predict_every}, "
          f"{mode}; load average {load0[0]:.2f} before, {load1[0]:.2f} after (2 cores)")  # fmt: skip
    print(f"first solution {first_solution:.2f} s after the {inc.start_snapshots}th snapshot arrived")
    print(f"collecting:   {sum(u.strategy == 'collect' for u in inc.updates)} snapshots before the first solve")
    print(f"all updates:  {stats(all_times)}")
    print(f"warm updates: {stats(warm)}")
    print(f"  last 50:    {stats(late)}")
    print("global solves: " + ", ".join(f"at {k} ({r}) {t:.2f} s" for k, r, t in glob))
    print(f"whole feed {t_feed:.1f} s; finish() {t_finish:.2f} s; batch calibration {t_batch:.2f} s")
    print(f"ratio median update / batch: {np.median(all_times) / t_batch:.3f}; "
          f"p95 update / batch: {np.percentile(all_times, 95) / t_batch:.3f}")  # fmt: skip
    print(f"last update: {last.line()}")

    c_inc, c_batch = data_cost(final), data_cost(batch)
    assert batch.T_ds_covariances is not None
    worst = 0.0
    for i in range(len(data.snapshots)):
        e = np.asarray(gtsam.Pose3(batch.T_ds(i)).localCoordinates(gtsam.Pose3(final.T_ds(i))))
        worst = max(worst, float(np.max(np.abs(e) / np.sqrt(np.diag(batch.T_ds_covariances[i])))))
    print(f"final data cost {c_inc:.6f} vs batch {c_batch:.6f} (relative {abs(c_inc - c_batch) / c_batch:.2e}); "
          f"largest T_ds difference {worst:.2e} of its 1-sigma")  # fmt: skip
    assert abs(c_inc - c_batch) <= 1e-6 * c_batch, (c_inc, c_batch)
    assert worst <= 1.0, worst
    print("same final result as the batch calibration: OK")
    print(f"warm updates under {BUDGET_S:g} s: {'OK' if warm and max(warm) < BUDGET_S else 'NOT MET'}")
    print(f"every update under {BUDGET_S:g} s: {'OK' if all_times and max(all_times) < BUDGET_S else 'NOT MET'}")
    return {
        "median_s": float(np.median(all_times)),
        "p95_s": float(np.percentile(all_times, 95)),
        "max_warm_s": float(max(warm)) if warm else float("nan"),
        "max_s": float(max(all_times)),
        "first_solution_s": first_solution,
        "batch_s": t_batch,
    }


if __name__ == "__main__":
    main()
