"""Benchmark: real-time factor of the VIO back end on a simulated flight (tracks level, no images).

A flight of ``--duration`` seconds (default 60 s, the paper's two-loop pattern of ~180 m) is observed
by the static and the gimbal camera (0.5 px noise, ~0.5 landmarks per square metre of ground and
walls); the smoother runs in ``dcc`` (gimbal moving, joint angles estimated), ``scc`` (gimbal locked,
angles known: the baseline) and ``mono``. Printed per mode: processing time, real-time factor
(processing time / data duration; < 0.5 means at least 2x faster than real time), normalized
translation RMSE (%) and joint RMSE; then the ratio of dcc's processing time to scc's (the cost of
estimating the joint angles), measured in the same process. ``--eq14`` adds a dcc run with one
Python eq. 14 factor per gimbal observation instead of the camera-pose constraint (slower).

Run: ``python benchmarks/bench_vio_backend.py [--duration 60] [--seed 0] [--eq14]``.
The front end (feature tracking on images) is not included here.
"""

from __future__ import annotations

import argparse
from typing import Any

from dcc_fg.studies.vio_study import StudyConfig, run_mode


def run(duration: float = 60.0, seed: int = 0, eq14: bool = False, verbose: bool = True) -> dict[str, Any]:
    cfg = StudyConfig(duration=duration, pattern="paper", seed=seed)
    runs: list[tuple[str, str, dict[str, Any]]] = [("dcc", "dcc", {}), ("scc", "scc", {}), ("mono", "mono", {})]
    if eq14:
        runs.append(("dcc-eq14", "dcc", {"gimbal_factor": "eq14"}))
    out: dict[str, Any] = {}
    for name, mode, opts in runs:
        ev = run_mode(mode, cfg, opts)
        out[name] = {k: v for k, v in ev.items() if k not in ("result", "truth")}
        if verbose:
            joints = ev["joint_rmse_rad"]
            jtxt = "" if joints is None else "  joint RMSE " + ", ".join(f"{j:.2e}" for j in joints) + " rad"
            print(
                f"{name:9s} time {ev['processing_time_s']:6.1f} s  RTF {ev['real_time_factor']:.3f}  "
                f"norm. transl. RMSE {ev['normalized_translation_rmse_percent']:.4f} %  "
                f"APE {ev['ape_rmse_m']:.4f} m over {ev['distance_m']:.0f} m{jtxt}"
            )
    out["dcc_over_scc_time"] = out["dcc"]["processing_time_s"] / out["scc"]["processing_time_s"]
    if verbose:
        print(f"dcc / scc processing time: {out['dcc_over_scc_time']:.2f}")
        if eq14:
            r = out["dcc-eq14"]["processing_time_s"] / out["dcc"]["processing_time_s"]
            print(f"eq. 14 per-observation factors / camera-pose constraint: {r:.2f}x the time")
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--duration", type=float, default=60.0)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--eq14", action="store_true", help="also time the per-observation eq. 14 factor")
    a = p.parse_args()
    run(a.duration, a.seed, a.eq14)


if __name__ == "__main__":
    main()
