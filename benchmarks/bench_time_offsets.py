"""Study: VIO time offsets over a randomized family of unsynchronized rigs (tracks level, no rendering).

One simulated 16 m x 8 m loop (``--duration`` s) is observed by ``--n`` random rigs of
:func:`dcc_fg.studies.time_offset_study.timing_family` (each camera 15-30 Hz, a random phase, offsets
up to +-0.4 frame periods / 25 ms, stamp jitter 0-0.5 ms), plus the issue's rig (20 / 30 Hz,
``t_s`` = 5 ms, ``t_d`` = 15 ms, no jitter) and the synchronized zero-offset reference; each through
the dcc smoother with the offsets estimated from 0 (``--workers`` processes).

Per member: both offset errors within 1 ms (the issue's criterion), per-joint RMSE <= 1e-2 rad,
normalized translation RMSE / the synchronized reference. Over the family: success rate, and the
offsets' NEES (mean of ``error^2 / sigma^2`` over all estimates; 1 when the reported 1-sigma is
honest) with its 95 % interval (chi-square with as many degrees of freedom as estimates). Exits 1 if
fewer than 95 % of the members succeed or the NEES lies outside the interval.

``--cost N`` measures instead what estimating the offsets costs when they are truly 0: N flights (IMU
noise, landmarks and feature noise from the seed), synchronized, each run with the offsets estimated
and held at 0; the ratio of the normalized translation RMSE (``--freeze S``: the estimate is held
once its 1-sigma is below S seconds, ``VioOptions.time_offset_freeze_sigma``).

Usage: ``python benchmarks/bench_time_offsets.py [--n 20] [--seed0 0] [--duration 14] [--workers 2] [--json F]``
``[--cost N [--freeze S]]``
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
from scipy.stats import chi2

from dcc_fg.sim.timing import CameraTiming
from dcc_fg.studies.time_offset_study import ISSUE_TIMING, make_flight, run_timing, timing_family

MAX_OFFSET_ERROR_S = 1e-3
MAX_JOINT_RMSE_RAD = 1e-2
MIN_SUCCESS = 0.95


def member(job: tuple[str, CameraTiming, float]) -> dict[str, Any]:
    """One rig through the smoother (in a worker process)."""
    name, timing, duration = job
    t0 = time.perf_counter()
    r = run_timing(make_flight(duration), timing)
    r["name"] = name
    r["seconds"] = time.perf_counter() - t0
    errors = [abs(r["static_error_s"]), abs(r["dynamic_error_s"])]
    r["offsets_ok"] = max(errors) <= MAX_OFFSET_ERROR_S
    r["joints_ok"] = max(r["joint_rmse_rad"]) <= MAX_JOINT_RMSE_RAD
    return r


def cost_member(job: tuple[int, bool, float, float | None]) -> dict[str, Any]:
    """One synchronized zero-offset flight (seed), offsets estimated or held (in a worker process)."""
    seed, estimate, duration, freeze = job
    r = run_timing(make_flight(duration, seed=seed), CameraTiming(), estimate, seed=seed + 1,
                   options={"time_offset_freeze_sigma": freeze})  # fmt: skip
    return {"seed": seed, "estimate": estimate, **r}


def accuracy_cost(a: argparse.Namespace) -> int:
    """``--cost``: translation RMSE with the offsets estimated / held at their true value 0."""
    jobs = [(s, e, a.duration, a.freeze) for s in range(a.seed0, a.seed0 + a.cost) for e in (True, False)]
    with ProcessPoolExecutor(max_workers=a.workers) as pool:
        out = list(pool.map(cost_member, jobs))
    est = {r["seed"]: r for r in out if r["estimate"]}
    held = {r["seed"]: r for r in out if not r["estimate"]}
    key = "normalized_translation_rmse_percent"
    ratios = []
    for s in est:
        ratios.append(est[s][key] / held[s][key])
        err = f"{1e3 * est[s]['static_error_s']:+.3f} {1e3 * est[s]['dynamic_error_s']:+.3f} ms"
        print(f"seed {s}: RMSE {est[s][key]:.4f} % estimated, {held[s][key]:.4f} % held (ratio {ratios[-1]:.2f}); "
              f"offset errors {err}")  # fmt: skip
    pooled = float(
        np.sqrt(np.mean([r[key] ** 2 for r in est.values()]) / np.mean([r[key] ** 2 for r in held.values()]))
    )
    print(f"\n{len(est)} flights, freeze sigma {a.freeze}: RMSE estimated / held: median {np.median(ratios):.2f}, "
          f"pooled {pooled:.2f}")  # fmt: skip
    if a.json:
        Path(a.json).write_text(json.dumps({"runs": out, "ratios": ratios, "pooled": pooled}, indent=1, default=float))
    return 0


def line(r: dict[str, Any], reference: float) -> str:
    tm = r["timing"]
    rates = f"{tm['rates_hz']['static']:.0f}/{tm['rates_hz']['dynamic']:.0f} Hz"
    off = tm["time_offsets_s"]
    return (
        f"{r['name']:10s} {rates:9s} offsets {1e3 * off['static']:+6.2f} {1e3 * off['dynamic']:+6.2f} ms "
        f"jitter {1e3 * tm['stamp_jitter_s']:.2f} ms | errors {1e3 * r['static_error_s']:+.3f} "
        f"{1e3 * r['dynamic_error_s']:+.3f} ms "
        f"(1-sigma {1e3 * r['static_sigma_s']:.3f} {1e3 * r['dynamic_sigma_s']:.3f})"
        f" | joint RMSE {max(r['joint_rmse_rad']):.2e} | RMSE {r['normalized_translation_rmse_percent']:.4f} % "
        f"({r['normalized_translation_rmse_percent'] / reference:.2f}x sync) | {r['seconds']:.0f} s"
    )


def summary(records: list[dict[str, Any]]) -> dict[str, Any]:
    """Success rate and offset NEES over the family members (not the reference runs)."""
    family = [r for r in records if r["name"].startswith("family")]
    z2 = [
        (r[f"{c}_error_s"] / r[f"{c}_sigma_s"]) ** 2 for r in family for c in ("static", "dynamic") if r[f"{c}_sigma_s"]
    ]
    dof = len(z2)
    ok = [r["offsets_ok"] and r["joints_ok"] for r in family]
    return {
        "members": len(family),
        "success": int(sum(ok)),
        "success_rate": float(np.mean(ok)) if ok else float("nan"),
        "offset_error_rms_ms": float(
            1e3 * np.sqrt(np.mean([r[f"{c}_error_s"] ** 2 for r in family for c in ("static", "dynamic")]))
        ),
        "nees": float(np.mean(z2)) if z2 else float("nan"),
        "nees_interval": [float(chi2.ppf(0.025, dof) / dof), float(chi2.ppf(0.975, dof) / dof)] if dof else None,
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n", type=int, default=20, help="family members (default 20)")
    p.add_argument("--seed0", type=int, default=0)
    p.add_argument("--duration", type=float, default=14.0, help="flight duration, s (default 14)")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--json", help="write the records and the summary to this file")
    p.add_argument("--cost", type=int, default=0, help="instead: the accuracy cost of estimating on N flights")
    p.add_argument("--freeze", type=float, default=None, help="with --cost: time_offset_freeze_sigma, s")
    a = p.parse_args(argv)
    if a.cost:
        return accuracy_cost(a)
    jobs = [("sync", CameraTiming(), a.duration), ("issue", ISSUE_TIMING, a.duration)]
    jobs += [(f"family {s}", timing_family(s), a.duration) for s in range(a.seed0, a.seed0 + a.n)]
    t0 = time.perf_counter()
    with ProcessPoolExecutor(max_workers=a.workers) as pool:
        records = list(pool.map(member, jobs))
    reference = records[0]["normalized_translation_rmse_percent"]
    for r in records:
        print(line(r, reference))
    s = summary(records)
    lo, hi = s["nees_interval"] or (float("nan"), float("nan"))
    nees_ok = lo <= s["nees"] <= hi
    success_ok = s["success_rate"] >= MIN_SUCCESS
    print(
        f"\n{len(records)} runs in {time.perf_counter() - t0:.0f} s wall with {a.workers} workers\n"
        f"family: {s['success']}/{s['members']} members with both offsets within 1 ms and joint RMSE <= 1e-2 rad "
        f"({'PASS' if success_ok else 'FAIL'}, >= {MIN_SUCCESS:.0%} required); offset error RMS "
        f"{s['offset_error_rms_ms']:.3f} ms; NEES {s['nees']:.2f} (95 % interval {lo:.2f}-{hi:.2f}: "
        f"{'PASS' if nees_ok else 'FAIL'})"
    )
    if a.json:
        Path(a.json).write_text(json.dumps({"records": records, "summary": s}, indent=1, default=float))
    return 0 if success_ok and nees_ok else 1


if __name__ == "__main__":
    sys.exit(main())
