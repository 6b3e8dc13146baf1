"""``dcc-fg demo``: the paper's simulation study (section V-A) end to end.

Simulates the pinned 2-DOF gimbal scene (:mod:`dcc_fg.sim.calibration_scene`), runs encoderless
calibration with the maximum-likelihood (bundle) and the paper's two-way formulation, validates
on an independent set, compares against ground truth and the Cramer-Rao bound, prints a table
beside the paper's Tables I-III and writes ``calibration.yaml``, ``joint_angles.csv`` and
``summary.json``.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from dcc_fg.calibrate import CalibrationOptions, CalibrationResult, calibrate
from dcc_fg.calibration_health import calibration_health
from dcc_fg.io.output_set import OutputSet
from dcc_fg.io.outputs import write_joint_angles_csv, write_json
from dcc_fg.model import GimbalCalibration
from dcc_fg.plots.output import write_calibration_outputs
from dcc_fg.report import demo_table, parameter_table
from dcc_fg.sim.calibration_scene import SceneConfig, SimulatedCalibration, simulate_calibration
from dcc_fg.studies.calibration_accuracy import CramerRaoBound, cramer_rao_bound, evaluate_against_truth
from dcc_fg.viz.rerun_log import RerunOptions, record_calibration

FloatArray = NDArray[np.float64]

log = logging.getLogger("dcc_fg.demo")

# the paper's Tables I-III (simulation)
PAPER = {
    "reprojection_mean_px": {"calibration": 0.3858, "validation": 0.3854},
    "reprojection_std_px": {"calibration": 0.0183, "validation": 0.0172},
    "joint_mean_rad": {"calibration": [5.89e-3, 2.38e-3], "validation": [5.83e-3, 2.52e-3]},
    "joint_std_rad": {"calibration": [0.80e-3, 0.71e-3], "validation": [0.75e-3, 0.67e-3]},
    "translation_param_mean_m": 1.73e-3,
    "translation_param_std_m": 7.93e-4,
    "rotation_param_mean_rad": 1.21e-3,
    "rotation_param_std_rad": 1.83e-3,
}


def ground_truth_errors(result: CalibrationResult, truth: GimbalCalibration, thetas: FloatArray) -> dict[str, Any]:
    """Gauge-invariant errors of ``result`` against the simulator's truth (``thetas``: true joint angles, rad)."""
    return evaluate_against_truth(result, truth, thetas).as_dict()


@dataclass(frozen=True)
class DemoRuns:
    """The demo's simulated scene, its three calibrations and the Cramer-Rao bound of the calibration set."""

    config: SceneConfig
    sim: SimulatedCalibration
    bundle: CalibrationResult  # maximum-likelihood (bundle) encoderless calibration
    two_way: CalibrationResult  # the paper's two-way formulation on the same data
    validation: CalibrationResult  # the validation set with the bundle calibration held
    crb: CramerRaoBound


def run_demo_calibrations(seed: int, n_joints: int) -> DemoRuns:
    """Simulate the scene, calibrate (bundle, two-way), validate and compute the Cramer-Rao bound."""
    cfg = SceneConfig(n_joints=n_joints)
    sim = simulate_calibration(seed, cfg)
    opts = CalibrationOptions(mode="encoderless", formulation="bundle")
    res = calibrate(sim.calibration_set, sim.initial, opts)
    res_two_way = calibrate(sim.calibration_set, sim.initial, replace(opts, formulation="two_way"))
    val = calibrate(sim.validation_set, res.calibration, replace(opts, mode="validate"))
    crb = cramer_rao_bound(
        sim.calibration_set, sim.truth, sim.joints_calibration, sim.T_st_calibration, cfg.pixel_sigma
    )
    return DemoRuns(cfg, sim, res, res_two_way, val, crb)


def demo_summary(runs: DemoRuns, seed: int) -> dict[str, Any]:
    """The summary dictionary of ``summary.json`` (``total_time_s`` still 0; the caller sets it)."""
    cfg, sim, res = runs.config, runs.sim, runs.bundle
    return {
        "scenario": {
            "seed": seed,
            "joints": cfg.n_joints,
            "calibration_snapshots": cfg.n_calibration,
            "validation_snapshots": cfg.n_validation,
            "pixel_noise_px": cfg.pixel_sigma,
            "target": cfg.target.to_kalibr(),
        },
        "calibration": res.calibration.statistics,
        "validation": runs.validation.calibration.statistics,
        "ground_truth_errors": {
            "bundle": {
                "calibration": ground_truth_errors(res, sim.truth, sim.joints_calibration),
                "validation": ground_truth_errors(runs.validation, sim.truth, sim.joints_validation),
            },
            "two_way": {"calibration": ground_truth_errors(runs.two_way, sim.truth, sim.joints_calibration)},
        },
        "two_way_statistics": runs.two_way.calibration.statistics,
        "cramer_rao_bound": {
            "T_ds_rotation_rms_rad": runs.crb.rotation_rms,
            "T_ds_translation_rms_m": runs.crb.translation_rms,
            "joint_offset_free_rms_rad": runs.crb.joint_rms.tolist(),
        },
        "paper": PAPER,
        "observable_parameters": [
            n for n, o in zip(res.calibration.names, res.calibration.observable, strict=True) if o
        ],
        "total_time_s": 0.0,
    }


def write_demo_figures(out_dir: Path, runs: DemoRuns, summary: dict[str, Any], report: bool) -> list[Path]:
    """Save the bundle calibration's figures (with the ground truth); with ``report`` also ``report.pdf``."""
    sim = runs.sim
    summary_text = (
        demo_table(summary) + "\n\n" + parameter_table(runs.bundle.calibration, sim.truth) if report else None
    )
    return write_calibration_outputs(
        out_dir,
        runs.bundle,
        summary_text,
        truth=sim.truth,
        thetas_true=sim.joints_calibration,
        target_points=sim.calibration_set.target_points,
        data=sim.calibration_set,
    )


def print_demo_summary(out_dir: Path, summary: dict[str, Any], figure_paths: list[Path]) -> None:
    """Print the demo table, the written files and the run times."""
    print(demo_table(summary))
    print(f"\nwrote {out_dir / 'calibration.yaml'}, {out_dir / 'joint_angles.csv'}, {out_dir / 'summary.json'}")
    if figure_paths:
        print("wrote " + ", ".join(str(p) for p in figure_paths))
    print(f"total time {summary['total_time_s']:.1f} s (+ {summary['figures_time_s']:.1f} s for the figures)")


def run_demo(
    out_dir: Path,
    seed: int = 0,
    n_joints: int = 2,
    verbose: bool = True,
    figures: bool = True,
    report: bool = False,
    provenance: dict[str, Any] | None = None,
    rerun: RerunOptions | None = None,
) -> dict[str, Any]:
    """Run the demo; returns the summary dictionary (also written to ``out_dir/summary.json``).

    ``rerun``: also record the bundle calibration for Rerun (:func:`~dcc_fg.viz.rerun_log.record_calibration`:
    corners and the chain per snapshot; the simulation has no images).

    ``figures`` saves the calibration figures (with the ground truth) as ``out_dir/calibration_*.png``;
    ``report`` also writes ``out_dir/report.pdf`` (the demo table, then the figures); ``provenance``
    (version, command line, options) is written first in ``summary.json``. ``summary.json`` also
    records the health checks of the bundle calibration (``health``; a failure is logged as a
    warning: the simulated study should always be healthy). The files are written as one output set
    (:class:`~dcc_fg.io.output_set.OutputSet`, command ``demo``): ``out_dir`` is checked before the
    work and nothing is written when the run fails or is interrupted.
    """
    outputs = OutputSet(out_dir, "demo")
    t0 = time.perf_counter()
    with outputs:
        runs = run_demo_calibrations(seed, n_joints)
        summary = {**(provenance or {}), **demo_summary(runs, seed)}
        health = calibration_health(result=runs.bundle, data=runs.sim.calibration_set)
        summary["health"] = health.to_dict()
        for check in health.failures:
            log.warning("demo calibration failed a health check: %s: %s", check.name, check.message)
        stage = outputs.path
        runs.bundle.calibration.save(stage / "calibration.yaml")
        write_joint_angles_csv(stage / "joint_angles.csv", runs.bundle.timestamps_ns, runs.bundle.joint_angles)
        summary["total_time_s"] = time.perf_counter() - t0  # simulation, calibrations, evaluation (figures: below)
        if rerun is not None:
            t_rec = time.perf_counter()
            record_calibration(rerun, runs.bundle, runs.sim.calibration_set, None)
            summary["rerun_time_s"] = time.perf_counter() - t_rec
        t_fig = time.perf_counter()
        staged = write_demo_figures(stage, runs, summary, report) if figures or report else []
        figure_paths = [outputs.final(p) for p in staged]
        summary["figures_time_s"] = time.perf_counter() - t_fig
        write_json(stage / "summary.json", summary)
    if verbose:
        print_demo_summary(out_dir, summary, figure_paths)
    return summary
