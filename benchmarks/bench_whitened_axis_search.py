"""Benchmark: how often the L = 3 axis search reaches the truth's basin of the whitened pose-level cost.

For random L = 3 family members (``dcc_fg.sim.mechanism_family``, simulated with Gaussian corners, no
rendering), the whitened pose-level cost ``0.5 sum_i |W_i Log(T_ds_i^-1 T_ds(kin, theta_i))|^2`` (W from
the images' noise floor) is refit from:

* the truth (kinematics and joint angles): the reference basin;
* the equal-weight axis search's candidates (``auto_init.three_joint_candidates``, 1 mrad / 1 mm);
* the whitened axis search's starts (``auto_init.whitened_axis_starts``).

A search "reaches" the truth basin when its best refit is at most ``HOP_DISTINCT`` (0.05, i.e. 0.1
chi-square) above the truth's refit, or below it. Printed: one line per member, then the success
counts of both searches and their median time, the whitened one as a ratio of the equal-weight one
(same process). Neither count includes the basin hopping (``whitened_hops``) run after both.

Run: ``python benchmarks/bench_whitened_axis_search.py [--seeds 0-49] [--snapshots 25]``.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from dcc_fg.auto_init import HOP_DISTINCT, pnp_T_ds, three_joint_candidates, whitened_axis_starts
from dcc_fg.init import PoseLevelProblem, levenberg_marquardt
from dcc_fg.noise_floor import noise_floor
from dcc_fg.sim.mechanism_family import family_member, simulate_member
from factors import chain


def whitened_cost(kin: np.ndarray, th: np.ndarray, T: np.ndarray, W: np.ndarray, free: np.ndarray) -> float:
    """Whitened pose-level refit (300 LM iterations) from ``(kin, th)``: 0.5 chi-square."""
    p = PoseLevelProblem(kin, 3, T, th, free, [2], True, 1e-3, 1e-3, W)
    _, r = levenberg_marquardt(p, 300, 1e-10)
    r = r[: 6 * p.K]
    return 0.5 * float(r @ r)


def seeds_of(text: str) -> list[int]:
    """``"0-49"`` or ``"3,7,11"``."""
    if "-" in text:
        a, b = text.split("-")
        return list(range(int(a), int(b) + 1))
    return [int(x) for x in text.split(",")]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--seeds", default="0-29", help="family seeds, e.g. 0-29 or 3,7,11 (default 0-29)")
    p.add_argument("--snapshots", type=int, default=25, help="snapshots per member (default 25)")
    args = p.parse_args(argv)
    free = np.ones(chain.n_kin(3), dtype=bool)
    free[[2, 5, 18, 19, 20]] = False
    ok_plain, ok_white, t_plain, t_white = [], [], [], []
    for seed in seeds_of(args.seeds):
        sim = simulate_member(family_member(seed, 3, args.snapshots))
        data = sim.calibration_set
        floor = noise_floor(data)
        T = floor.T_dt @ np.linalg.inv(floor.T_st)
        W = floor.T_ds_whitening()
        truth = whitened_cost(sim.truth.kin, sim.joints_calibration, T, W, free)
        t0 = time.process_time()
        plain = three_joint_candidates(pnp_T_ds(data), free)
        t1 = time.process_time()
        white = whitened_axis_starts(T, W)
        t2 = time.process_time()
        best_plain = min(whitened_cost(k, th, T, W, free) for k, th, _ in plain)
        best_white = min(whitened_cost(k, th, T, W, free) for k, th in white)
        ok_plain.append(best_plain <= truth + HOP_DISTINCT)
        ok_white.append(best_white <= truth + HOP_DISTINCT)
        t_plain.append(t1 - t0)
        t_white.append(t2 - t1)
        print(
            f"seed {seed:3d}: truth basin {truth:9.3f} | equal-weight search {best_plain:9.3f} "
            f"({'reached' if ok_plain[-1] else 'missed '}) | whitened search {best_white:9.3f} "
            f"({'reached' if ok_white[-1] else 'missed '})",
            flush=True,
        )
    n = len(ok_plain)
    either = sum(a or b for a, b in zip(ok_plain, ok_white, strict=True))
    print(f"\ntruth basin reached: equal-weight axis search {sum(ok_plain)}/{n}, "
          f"whitened axis search {sum(ok_white)}/{n}, either {either}/{n}")  # fmt: skip
    ratio = statistics.median(t_white) / max(statistics.median(t_plain), 1e-9)
    print(f"median CPU: equal-weight {statistics.median(t_plain):.2f} s, whitened {statistics.median(t_white):.2f} s "
          f"({ratio:.2f}x)")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
