"""Benchmark: calibration of a whole camera cluster in one graph (issue item "cluster calibration").

Two studies on simulated clusters (:mod:`dcc_fg.sim.cluster_scene`, 60 snapshots, 0.4 px noise):

* **CRB study** (``--seeds``, default 20 per preset): the pinned ``stereo+gimbal`` and ``gimbal-pair``
  clusters, seeds 0..n-1 (noise, board poses, joint samples), calibrated from the perturbed
  ("hand-measured") start with the pixel sigma given; per camera (all but cam0) the RMS over seeds and
  snapshots of the rotation and translation errors of ``T_cs(theta_i)`` divided by the Cramer-Rao
  bound's RMS (:mod:`dcc_fg.studies.cluster_accuracy`). Target: every ratio <= 1.2.
* **automatic-initialization study** (``--geometries``, default 10 per preset): random geometries
  (``random_geometry=True``: random base rotation, DH links, joint ranges, jittered cameras), seeds
  1000 + g, 40 snapshots, the snapshot joint guesses removed; :func:`dcc_fg.cluster_init.
  auto_initialize_cluster` then :func:`dcc_fg.cluster_calibration.calibrate_cluster`. Success: the data
  cost is no more than 1 above that of the same calibration started at the truth, and every camera's
  RMS rotation and translation error of ``T_cs(theta_i)`` is within 1.5x of that reference run's.
  Target: at least 9 of 10 per preset.

Run: ``python benchmarks/bench_cluster_calibration.py [--seeds 20] [--geometries 10] [--presets ...]``.
Prints one line per run, a summary per preset and one line of JSON last.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass, replace

import numpy as np

from dcc_fg.cluster_calibration import ClusterOptions, calibrate_cluster
from dcc_fg.cluster_data import ClusterDataset, ClusterSnapshot
from dcc_fg.cluster_init import auto_initialize_cluster
from dcc_fg.sim.cluster_scene import ClusterSceneConfig, SimulatedCluster, simulate_cluster
from dcc_fg.studies.cluster_accuracy import CameraAccuracy, cluster_accuracy

CRB_PRESETS = ("stereo+gimbal", "gimbal-pair")
CRB_SNAPSHOTS = 60
AUTO_SNAPSHOTS = 40
AUTO_SEED0 = 1000
CRB_RATIO_TARGET = 1.2
AUTO_RATIO = 1.5
AUTO_COST_MARGIN = 1.0


@dataclass
class CrbSummary:
    """Per camera: (rotation ratio, translation ratio) of the RMS error to the RMS bound."""

    preset: str
    seeds: int
    ratios: dict[str, tuple[float, float]]
    errors: dict[str, tuple[float, float]]
    bounds: dict[str, tuple[float, float]]


def crb_run(preset: str, seed: int, n_snapshots: int = CRB_SNAPSHOTS) -> dict[str, CameraAccuracy]:
    """One seed of the CRB study: camera -> errors and bound."""
    sim = simulate_cluster(preset, seed, ClusterSceneConfig(n_snapshots=n_snapshots))
    res = calibrate_cluster(sim.data, sim.initial, ClusterOptions(pixel_sigma=sim.config.pixel_sigma,
                                                                  compute_covariance=False))  # fmt: skip
    return cluster_accuracy(sim, res)


def crb_study(preset: str, seeds: list[int], n_snapshots: int = CRB_SNAPSHOTS, verbose: bool = True) -> CrbSummary:
    """The CRB study of ``preset`` over ``seeds``."""
    per_cam: dict[str, list[CameraAccuracy]] = {}
    for seed in seeds:
        t0 = time.perf_counter()
        acc = crb_run(preset, seed, n_snapshots)
        for c, a in acc.items():
            per_cam.setdefault(c, []).append(a)
        if verbose:
            parts = []
            for c, a in acc.items():
                (er, et), (br, bt) = a.rms(a.errors), a.bound_rms(a.bound)
                parts.append(f"{c} rot {er * 1e3:.3f}/{br * 1e3:.3f} mrad trans {et * 1e3:.3f}/{bt * 1e3:.3f} mm")
            print(f"  {preset} seed {seed:2d} ({time.perf_counter() - t0:.1f} s): error/bound " + "; ".join(parts))
    ratios, errors, bounds = {}, {}, {}
    for c, accs in per_cam.items():
        e = np.concatenate([a.errors for a in accs])
        P = np.concatenate([a.bound for a in accs])
        errors[c], bounds[c] = CameraAccuracy.rms(e), CameraAccuracy.bound_rms(P)
        ratios[c] = (errors[c][0] / bounds[c][0], errors[c][1] / bounds[c][1])
    return CrbSummary(preset, len(seeds), ratios, errors, bounds)


def strip_joints(data: ClusterDataset) -> ClusterDataset:
    """The data without the snapshot joint-angle guesses (a fully automatic calibration)."""
    snaps = [ClusterSnapshot(s.timestamp_ns, s.observations, None) for s in data.snapshots]
    return ClusterDataset(data.cameras, data.target_points, snaps, data.source)


def auto_run(preset: str, geometry: int, n_snapshots: int = AUTO_SNAPSHOTS) -> dict[str, object]:
    """One random geometry of the automatic-initialization study."""
    cfg = ClusterSceneConfig(n_snapshots=n_snapshots, random_geometry=True)
    sim: SimulatedCluster = simulate_cluster(preset, AUTO_SEED0 + geometry, cfg)
    data = strip_joints(sim.data)
    opts = ClusterOptions(pixel_sigma=cfg.pixel_sigma, compute_covariance=False)
    truth_data = ClusterDataset(data.cameras, data.target_points,
                                [replace(s, joints={ch: sim.joints[ch][i] for ch in sim.truth.chain_names})
                                 for i, s in enumerate(data.snapshots)], data.source)  # fmt: skip
    ref = calibrate_cluster(truth_data, sim.truth, replace(opts, pose_level_init=False))
    mounts = {c.name: c.chain for c in sim.truth.cameras}
    joints = {c.name: c.n_joints for c in sim.truth.chains}
    t0 = time.perf_counter()
    try:
        init = auto_initialize_cluster(data, mounts, joints)
        res = calibrate_cluster(data, init, opts)
    except (ValueError, RuntimeError) as exc:
        return {"preset": preset, "geometry": geometry, "ok": False, "error": str(exc)}
    elapsed = time.perf_counter() - t0
    acc, acc_ref = cluster_accuracy(sim, res), cluster_accuracy(sim, ref)
    ok = res.final_error <= ref.final_error + AUTO_COST_MARGIN
    worst = 0.0
    for c in acc:
        e, r = CameraAccuracy.rms(acc[c].errors), CameraAccuracy.rms(acc_ref[c].errors)
        worst = max(worst, e[0] / r[0], e[1] / r[1])
    ok = bool(ok and worst <= AUTO_RATIO)
    return {
        "preset": preset,
        "geometry": geometry,
        "ok": ok,
        "cost": float(res.final_error),
        "reference_cost": float(ref.final_error),
        "worst_error_ratio": float(worst),
        "time_s": float(elapsed),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=20, help="seeds per preset of the CRB study (0: skip)")
    ap.add_argument("--geometries", type=int, default=10, help="random geometries per preset of the auto-init study")
    ap.add_argument("--presets", nargs="*", default=list(CRB_PRESETS))
    ap.add_argument("--snapshots", type=int, default=CRB_SNAPSHOTS)
    args = ap.parse_args()
    out: dict[str, object] = {"crb": {}, "auto_init": {}}
    for preset in args.presets:
        if args.seeds:
            s = crb_study(preset, list(range(args.seeds)), args.snapshots)
            for c, (rr, rt) in s.ratios.items():
                flag = "ok" if max(rr, rt) <= CRB_RATIO_TARGET else "ABOVE 1.2"
                print(
                    f"{preset} {c}: RMS error / CRB over {s.seeds} seeds: rotation {rr:.3f} "
                    f"({s.errors[c][0] * 1e3:.4f} / {s.bounds[c][0] * 1e3:.4f} mrad), translation {rt:.3f} "
                    f"({s.errors[c][1] * 1e3:.4f} / {s.bounds[c][1] * 1e3:.4f} mm) {flag}"
                )
            out["crb"][preset] = {c: {"rotation": r[0], "translation": r[1]} for c, r in s.ratios.items()}  # type: ignore[index]
        if args.geometries:
            runs = []
            for g in range(args.geometries):
                r = auto_run(preset, g)
                runs.append(r)
                print(f"  auto-init {preset} geometry {g}: {r}")
            n_ok = sum(bool(r["ok"]) for r in runs)
            print(f"{preset}: automatic initialization converged on {n_ok} of {len(runs)} random geometries")
            out["auto_init"][preset] = {"converged": n_ok, "of": len(runs)}  # type: ignore[index]
    print(json.dumps(out))


if __name__ == "__main__":
    main()
