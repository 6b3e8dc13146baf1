"""Benchmark: the projected solve (dcc_fg.projection) against more Levenberg-Marquardt iterations, on
nearly intersecting yaw-roll-pitch gimbals.

Each seed's scene (:func:`dcc_fg.sim.calibration_scene.yaw_roll_pitch_gimbal`, axes that miss each
other by up to ``--offset`` m, 20 snapshots, 0.3 px) is calibrated from the true kinematics, in the
same process, three ways:

* ``calibrate`` with the defaults (the joint solve, then the polish with the weakened prior), the
  baseline;
* the same with ``project_held=True`` (the projected solve at the end);
* the same with ``max_iterations`` raised ``--lm-factor`` times (more of the joint solve instead).

It prints, per seed, each run's data cost (:func:`dcc_fg.calibrate.data_cost`), its decrease below the
baseline in chi-square units (``2 dC / variance factor``) and its CPU time as a ratio to the baseline.
Usage: ``python benchmarks/bench_projection.py [--seeds 0,1,2,3] [--offset 0.005] [--lm-factor 4]``
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

from dcc_fg.calibrate import CalibrationOptions, CalibrationResult, calibrate, data_cost
from dcc_fg.data import with_joints
from dcc_fg.sim.calibration_scene import yaw_roll_pitch_gimbal


def timed(run) -> tuple[float, CalibrationResult]:  # noqa: ANN001
    t0 = time.process_time()
    res = run()
    return time.process_time() - t0, res


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0,1,2,3", help="comma-separated scene seeds (default 0,1,2,3)")
    ap.add_argument("--offset", type=float, default=0.005, help="largest link offset, m (default 0.005)")
    ap.add_argument("--lm-factor", type=int, default=4, help="iteration cap multiple of the LM run (default 4)")
    args = ap.parse_args(argv)
    seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
    base_opt = CalibrationOptions()
    print(f"{'seed':>4} {'held':>4} {'baseline cost':>14} {'projected: -chi2':>17} {'cpu x':>6} "
          f"{'LM x' + str(args.lm_factor) + ': -chi2':>14} {'cpu x':>6}")  # fmt: skip
    gains, ratios = [], []
    for seed in seeds:
        sim = yaw_roll_pitch_gimbal(seed, 20, args.offset)
        data = with_joints(sim.calibration_set, sim.joints_calibration)
        t_base, base = timed(lambda: calibrate(data, sim.truth, base_opt))  # noqa: B023
        t_proj, proj = timed(lambda: calibrate(data, sim.truth, replace(base_opt, project_held=True)))  # noqa: B023
        more = replace(base_opt, max_iterations=base_opt.max_iterations * args.lm_factor)
        t_lm, lm = timed(lambda: calibrate(data, sim.truth, more))  # noqa: B023
        vf = max(float(base.variance_factor), 1e-12)
        d_proj = 2.0 * (data_cost(base) - data_cost(proj)) / vf
        d_lm = 2.0 * (data_cost(base) - data_cost(lm)) / vf
        held = len(base.extra.get("held_by_prior", []))
        print(f"{seed:>4} {held:>4} {data_cost(base):>14.6f} {d_proj:>17.3f} {t_proj / t_base:>6.2f} "
              f"{d_lm:>14.3f} {t_lm / t_base:>6.2f}")  # fmt: skip
        gains.append((d_proj, d_lm))
        ratios.append((t_proj / t_base, t_lm / t_base))
    n_better = sum(p >= m - 1e-9 for p, m in gains)
    print(f"\nprojected solve at or below the longer LM run on {n_better}/{len(gains)} seeds; "
          f"mean CPU ratio to the baseline: projected {sum(r[0] for r in ratios) / len(ratios):.2f}x, "
          f"LM x{args.lm_factor} {sum(r[1] for r in ratios) / len(ratios):.2f}x")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
