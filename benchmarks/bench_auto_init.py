"""Benchmark: automatic initialization (no gimbal.yaml) over random 2-joint mechanisms.

The study of the automatic-initialization issue: ``--n`` random 2-DOF mechanisms
(:func:`dcc_fg.sim.calibration_scene.random_mechanism` drawn one after the other from
``numpy.random.default_rng(--seed0)``; geometry ``g`` is simulated with seed ``100 + g``, 25
calibration snapshots, 0.4 px corner noise). Each is calibrated twice on the same corners:

* from the automatic initialization (the ``dcc-fg calibrate --joints 2`` path: every automatic
  start solved at the corner level, the lowest cost kept, :func:`dcc_fg.global_fit.calibrate_global`), and
* from the truth-perturbed initial guess (the "hand-measured" start).

Success: the automatic start reaches the same optimum, i.e. the RMS over snapshots of the T_ds
rotation error (rad) and of the translation error (m) are each within 1.5x of the reference run's.
A draw that calibrate() refuses (``ValueError``) counts as a failure; directions the data leave
undetermined are held by weak priors (:mod:`dcc_fg.degeneracy`) instead of refused since issue 14.

The issue asked for at least 48 of the 50 default geometries; tests/test_auto_init.py runs a fixed
subset (``SUBSET`` there) of the same protocol with :func:`run_geometry`.

``--pinned-joints L``: the same comparison on seeds ``--seed0 .. --seed0 + --n - 1`` of the pinned
L-joint scene (81 snapshots; :func:`run_pinned`, which also asks the automatic start to end at the
reference cost or below); tests/test_auto_init.py runs a few of these seeds.

Run: ``python benchmarks/bench_auto_init.py [--n 50] [--seed0 2024] [--only 0 3 7] [--pinned-joints L]``.
Prints one line per geometry (or seed), the failures, the success count and, last, one line of JSON.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass

import numpy as np

from dcc_fg.calibrate import CalibrationOptions, CalibrationResult, calibrate
from dcc_fg.data import CalibrationDataset, with_joints
from dcc_fg.global_fit import calibrate_global, data_cost
from dcc_fg.model import GimbalCalibration
from dcc_fg.sim.calibration_scene import SceneConfig, SimulatedCalibration, random_mechanism, simulate_calibration
from dcc_fg.studies.calibration_accuracy import evaluate_against_truth

FAST = CalibrationOptions(compute_covariance=False)
RATIO_LIMIT = 1.5  # automatic-start RMS T_ds error / reference-start RMS T_ds error
DEFAULT_SEED0 = 2024
N_SNAPSHOTS = 25


@dataclass(frozen=True)
class GeometryOutcome:
    """One random geometry: success, the RMS ratios (auto / reference) and the costs, or the error."""

    index: int
    ok: bool
    ratio_rotation: float = float("nan")
    ratio_translation: float = float("nan")
    cost_auto: float = float("nan")
    cost_reference: float = float("nan")
    error: str = ""
    seconds: float = 0.0

    def line(self) -> str:
        if self.error:
            return f"{self.index}: error {self.error} ({self.seconds:.1f} s)"
        return (
            f"{self.index}: {self.ok} rot x{self.ratio_rotation:.3f} tr x{self.ratio_translation:.3f} "
            f"cost {self.cost_auto:.2f}/{self.cost_reference:.2f} ({self.seconds:.1f} s)"
        )


def calibrate_auto(data: CalibrationDataset, n_joints: int) -> CalibrationResult:
    """The ``--init auto`` path: every automatic start solved at the corner level, the lowest cost kept
    (:func:`dcc_fg.global_fit.calibrate_global`)."""
    return calibrate_global(with_joints(data, None), n_joints, FAST)


def accuracy_ratios(sim: SimulatedCalibration, auto: CalibrationResult, ref: CalibrationResult) -> tuple[float, float]:
    """RMS T_ds rotation (rad) and translation (m) errors of ``auto`` over those of ``ref``."""
    ea = evaluate_against_truth(auto, sim.truth, sim.joints_calibration)
    er = evaluate_against_truth(ref, sim.truth, sim.joints_calibration)
    return ea.rotation_rms / er.rotation_rms, ea.translation_rms / er.translation_rms


def mechanisms(n: int, seed0: int = DEFAULT_SEED0) -> list[tuple[GimbalCalibration, np.ndarray]]:
    """The first ``n`` random 2-joint mechanisms of the study (drawn in sequence from one generator)."""
    rng = np.random.default_rng(seed0)
    return [random_mechanism(rng, 2) for _ in range(n)]


def run_geometry(index: int, mechanism: tuple[GimbalCalibration, np.ndarray]) -> GeometryOutcome:
    """Calibrate geometry ``index`` from the automatic and the reference start and compare."""
    t0 = time.perf_counter()
    sim = simulate_calibration(100 + index, SceneConfig(n_calibration=N_SNAPSHOTS, n_validation=1), mechanism=mechanism)
    try:
        auto = calibrate_auto(sim.calibration_set, 2)
        ref = calibrate(sim.calibration_set, sim.initial, FAST)
    except ValueError as exc:  # a degenerate draw refused as unobservable
        return GeometryOutcome(index, False, error=str(exc), seconds=time.perf_counter() - t0)
    r_rot, r_tr = accuracy_ratios(sim, auto, ref)
    ok = bool(r_rot <= RATIO_LIMIT and r_tr <= RATIO_LIMIT)
    return GeometryOutcome(index, ok, r_rot, r_tr, auto.final_error, ref.final_error, seconds=time.perf_counter() - t0)


def run_pinned(seed: int, n_joints: int) -> GeometryOutcome:
    """Seed ``seed`` of the pinned ``n_joints`` scene (81 snapshots): success also needs the automatic
    start to end at the reference optimum or a lower one (cost within a relative 1e-6)."""
    t0 = time.perf_counter()
    sim = simulate_calibration(seed, SceneConfig(n_joints=n_joints, n_validation=1))
    try:
        auto = calibrate_auto(sim.calibration_set, n_joints)
        ref = calibrate(sim.calibration_set, sim.initial, FAST)
    except ValueError as exc:
        return GeometryOutcome(seed, False, error=str(exc), seconds=time.perf_counter() - t0)
    r_rot, r_tr = accuracy_ratios(sim, auto, ref)
    c_auto, c_ref = data_cost(auto), data_cost(ref)
    ok = bool(r_rot <= RATIO_LIMIT and r_tr <= RATIO_LIMIT and c_auto <= c_ref * (1 + 1e-6))
    return GeometryOutcome(seed, ok, r_rot, r_tr, c_auto, c_ref, seconds=time.perf_counter() - t0)


def main(argv: list[str] | None = None) -> dict[str, object]:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n", type=int, default=50, help="random geometries (default 50, the issue's study)")
    p.add_argument("--seed0", type=int, default=DEFAULT_SEED0, help="seed of the mechanism generator (default 2024)")
    p.add_argument("--only", type=int, nargs="*", help="run only these geometry indices (< --n)")
    p.add_argument(
        "--pinned-joints",
        type=int,
        choices=(1, 2, 3),
        help="instead: the pinned L-joint scene (81 snapshots) over seeds --seed0 .. --seed0 + --n - 1",
    )
    args = p.parse_args(argv)
    pinned = args.pinned_joints
    mechs = [] if pinned else mechanisms(args.n, args.seed0)
    indices = list(range(args.n)) if not args.only else sorted(set(args.only))
    t0 = time.perf_counter()
    outcomes = []
    for g in indices:
        out = run_pinned(args.seed0 + g, pinned) if pinned else run_geometry(g, mechs[g])
        outcomes.append(out)
        print(out.line(), flush=True)
    n_ok = sum(o.ok for o in outcomes)
    failures = [o for o in outcomes if not o.ok]
    print("failures:" + ("" if failures else " none"))
    for o in failures:
        print("  " + o.line())
    wall = time.perf_counter() - t0
    what = f"pinned L={pinned}, seeds from {args.seed0}" if pinned else f"random 2-joint, seed0 {args.seed0}"
    print(f"{n_ok}/{len(outcomes)} converged ({what}), {wall:.1f} s")
    summary: dict[str, object] = {
        "pinned_joints": pinned,
        "seed0": args.seed0,
        "n": len(outcomes),
        "converged": n_ok,
        "failed": [o.index for o in failures],
        "seconds": round(wall, 1),
    }
    print(json.dumps(summary))
    return summary


if __name__ == "__main__":
    main()
