"""Benchmark: statistical efficiency of the calibration over seeds of the pinned simulated scenes.

Per seed ``s`` in ``--seed0 .. --seed0 + --seeds - 1``: ``simulate_calibration(s, SceneConfig(n_joints=L))``
(the pinned L-joint mechanism of dcc_fg/sim/calibration_scene.py, 81 calibration snapshots, 0.4 px
corner noise, truth-perturbed initial guess), an encoderless bundle calibration, its errors against
the truth (T_ds per snapshot: rotation in rad, translation in m; offset-free joint angles in rad) and
the Cramer-Rao bound of the same quantities at the truth. Optionally (``--covariance``) the reported
T_ds covariances are scored by their NEES (chi-square with 6 degrees of freedom per snapshot when
consistent), and (``--two-way``) the paper's two-way formulation is solved on the same corners.

Printed: one line per seed (iterations, RMS residual per axis, errors, ratios to the bound, wall
time), then the study: RMS over seeds of each error and of its bound and their ratio, the mean
|offset-free joint error| per joint, the mean NEES (one snapshot per seed, and all snapshots) with
its 95 % interval, and the combined T_ds RMS of the bundle and two-way formulations; last, one line
of JSON. This is the full study behind tests/test_statistics.py (``--joints 2 --seeds 20
--covariance --two-way``) and the L = 1 and L = 3 tests of tests/test_calibrate.py (``--joints 1``,
``--joints 3``, 20 seeds); the tests run a fixed subset of seeds through :func:`run_seed`.

Run: ``python benchmarks/bench_statistics.py [--joints 2] [--seeds 20] [--seed0 0] [--covariance] [--two-way]``.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.stats import chi2

from dcc_fg.calibrate import CalibrationOptions, calibrate
from dcc_fg.sim.calibration_scene import SceneConfig, simulate_calibration
from dcc_fg.studies.calibration_accuracy import (
    CramerRaoBound,
    GroundTruthErrors,
    cramer_rao_bound,
    evaluate_against_truth,
    nees_T_ds,
)

PIXEL_SIGMA = 0.4  # px, the simulated corner noise
TWO_WAY_LEVER = 0.1  # m: translation error / lever -> rad in the combined T_ds score


@dataclass
class SeedRun:
    """One seed: solver report, errors and Cramer-Rao bound; NEES per snapshot and the two-way
    errors when asked for (else None)."""

    seed: int
    iterations: int
    rms_px: float  # RMS residual per image axis, px
    err: GroundTruthErrors
    crb: CramerRaoBound
    nees: NDArray[np.float64] | None
    two_way: GroundTruthErrors | None
    seconds: float


def run_seed(seed: int, n_joints: int, covariance: bool = False, two_way: bool = False) -> SeedRun:
    """Calibrate seed ``seed`` of the pinned ``n_joints`` scene and score it against the truth."""
    t0 = time.perf_counter()
    sim = simulate_calibration(seed, SceneConfig(n_joints=n_joints, n_validation=1))
    res = calibrate(sim.calibration_set, sim.initial, CalibrationOptions(compute_covariance=covariance))
    err = evaluate_against_truth(res, sim.truth, sim.joints_calibration)
    crb = cramer_rao_bound(sim.calibration_set, sim.truth, sim.joints_calibration, sim.T_st_calibration, PIXEL_SIGMA)
    nees = nees_T_ds(err.T_ds, res.T_ds_covariances) if covariance else None
    tw = None
    if two_way:
        opts = CalibrationOptions(formulation="two_way", compute_covariance=False)
        tw = evaluate_against_truth(
            calibrate(sim.calibration_set, sim.initial, opts), sim.truth, sim.joints_calibration
        )
    px = float(res.reprojection_stats()["all"]["rms_per_axis"])
    return SeedRun(seed, res.iterations, px, err, crb, nees, tw, time.perf_counter() - t0)


def _rms(x: list | NDArray[np.float64]) -> NDArray[np.float64]:
    return np.sqrt(np.mean(np.square(np.asarray(x, dtype=float)), axis=0))


def nees_interval(n_seeds: int, dof: int = 6, level: float = 0.95) -> tuple[float, float]:
    """Two-sided ``level`` interval of the mean of ``n_seeds`` independent chi-square(``dof``) values."""
    lo, hi = chi2.ppf([(1 - level) / 2, (1 + level) / 2], dof * n_seeds)
    return float(lo) / n_seeds, float(hi) / n_seeds


def summarize(runs: list[SeedRun]) -> dict[str, object]:
    """The study over ``runs``: RMS over seeds of the errors and bounds (rotation rad, translation m,
    joints rad per joint), their ratios, iterations, residuals, mean |joint error|, NEES, two-way."""
    out: dict[str, object] = {
        "seeds": [r.seed for r in runs],
        "iterations_max": max(r.iterations for r in runs),
        "rms_px": [r.rms_px for r in runs],
        "rot": float(_rms([r.err.rotation_rms for r in runs])),
        "tra": float(_rms([r.err.translation_rms for r in runs])),
        "joint": _rms([r.err.joint_rms for r in runs]).tolist(),
        "crb_rot": float(_rms([r.crb.rotation_rms for r in runs])),
        "crb_tra": float(_rms([r.crb.translation_rms for r in runs])),
        "crb_joint": _rms([r.crb.joint_rms for r in runs]).tolist(),
        "mean_abs_joint": np.mean([np.abs(r.err.joints).mean(axis=0) for r in runs], axis=0).tolist(),
        "rot_over_crb_per_seed": [r.err.rotation_rms / r.crb.rotation_rms for r in runs],
    }
    out["ratio_rot"] = out["rot"] / out["crb_rot"]  # type: ignore[operator]
    out["ratio_tra"] = out["tra"] / out["crb_tra"]  # type: ignore[operator]
    out["ratio_joint"] = (np.array(out["joint"]) / np.array(out["crb_joint"])).tolist()
    if all(r.nees is not None for r in runs):
        per_seed = [r.nees for r in runs]
        out["nees_single"] = float(np.mean([n[r.seed % n.size] for r, n in zip(runs, per_seed, strict=True)]))  # type: ignore[index,union-attr]
        out["nees_all"] = float(np.mean([n.mean() for n in per_seed]))  # type: ignore[union-attr]
        out["nees_interval"] = nees_interval(len(runs))
    if all(r.two_way is not None for r in runs):
        comb = lambda e: e.rotation_rms**2 + (e.translation_rms / TWO_WAY_LEVER) ** 2  # noqa: E731
        out["combined_bundle"] = float(np.sqrt(np.mean([comb(r.err) for r in runs])))
        out["combined_two_way"] = float(np.sqrt(np.mean([comb(r.two_way) for r in runs])))
    return out


def main(argv: list[str] | None = None) -> dict[str, object]:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--joints", type=int, default=2, help="joints of the pinned mechanism, 1-3 (default 2)")
    p.add_argument("--seeds", type=int, default=20, help="number of seeds (default 20)")
    p.add_argument("--seed0", type=int, default=0, help="first seed (default 0)")
    p.add_argument("--covariance", action="store_true", help="compute covariances and score their NEES")
    p.add_argument("--two-way", action="store_true", help="also solve the two-way formulation")
    args = p.parse_args(argv)
    t0 = time.perf_counter()
    runs = []
    for seed in range(args.seed0, args.seed0 + args.seeds):
        r = run_seed(seed, args.joints, args.covariance, args.two_way)
        runs.append(r)
        print(
            f"L={args.joints} seed {seed}: {r.iterations} it, {r.rms_px:.4f} px; rot {r.err.rotation_rms:.3e} "
            f"(x{r.err.rotation_rms / r.crb.rotation_rms:.3f} CRB), tra {r.err.translation_rms:.3e} "
            f"(x{r.err.translation_rms / r.crb.translation_rms:.3f}), joints x"
            f"{np.round(r.err.joint_rms / r.crb.joint_rms, 3)}"
            + (f", NEES {r.nees.mean():.2f}" if r.nees is not None else "")
            + f", {r.seconds:.1f} s",
            flush=True,
        )
    s = summarize(runs)
    print(
        f"L={args.joints}, {len(runs)} seeds: iterations max {s['iterations_max']}; RMS residual per axis "
        f"{min(s['rms_px']):.4f}-{max(s['rms_px']):.4f} px; RMS over seeds / CRB: T_ds rotation "  # type: ignore[type-var]
        f"{s['rot']:.3e} / {s['crb_rot']:.3e} (x{s['ratio_rot']:.3f}), translation {s['tra']:.3e} / "
        f"{s['crb_tra']:.3e} (x{s['ratio_tra']:.3f}), joints {np.round(s['joint'], 6)} / "
        f"{np.round(s['crb_joint'], 6)} (x{np.round(s['ratio_joint'], 3)}); mean |offset-free joint error| "
        f"{np.round(s['mean_abs_joint'], 6)} rad"
    )
    if "nees_all" in s:
        lo, hi = s["nees_interval"]  # type: ignore[misc]
        print(
            f"mean NEES, one snapshot per seed {s['nees_single']:.2f}, all snapshots {s['nees_all']:.2f} "
            f"(95% interval {lo:.2f}-{hi:.2f})"
        )
    if "combined_two_way" in s:
        print(
            f"combined T_ds RMS (rad, {TWO_WAY_LEVER} m lever for translation): bundle {s['combined_bundle']:.3e}, "
            f"two-way {s['combined_two_way']:.3e}"
        )
    s["seconds"] = round(time.perf_counter() - t0, 1)
    print(f"{s['seconds']} s")
    print(json.dumps(s))
    return s


if __name__ == "__main__":
    main()
