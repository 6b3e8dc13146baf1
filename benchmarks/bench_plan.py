"""Benchmark: does following ``dcc-fg plan`` reach a worst-case T_ds tolerance over the operating range
with fewer snapshots than uniformly random joint angles or a regular grid? (dcc_fg.planning)

Per member of the randomized mechanism family (:mod:`dcc_fg.sim.mechanism_family`, seeds ``seed0 ..
seed0 + n - 1``, L drawn by the family, its cameras and target):

* operating range (true joint angles): the spread the scene's 40-snapshot grid achieves (the joint
  angles at which both cameras see the board; :func:`dcc_fg.sim.mechanism_family.achieved_spread`);
* held-out angles: ``--heldout`` uniformly random angles in the range at which a view both cameras share
  exists; never used by a calibration;
* start: 10 snapshots at uniformly random angles (board placed by the simulator), shared by the three
  strategies; every snapshot is rendered into both images (:func:`dcc_fg.sim.render.render_view`) and
  detected (:func:`dcc_fg.detection.detect_target`), as ``dcc-fg calibrate`` would; a snapshot whose
  board is not detected in both images (at least 8 common corners) is lost but counts as taken;
* strategies, ``--step`` snapshots at a time up to ``--max-added``: ``plan`` (``plan_snapshots`` on the
  current calibration, objective worst, calibration prediction; the board held where the plan says,
  with a person's error of 2 cm and 2 deg), ``random`` (uniform angles, board placed by the simulator),
  ``grid`` (a regular grid of m^L cell centres over the range for m = 1, 2, ..., each grid a fresh set
  added to the start; board placed by the simulator);
* after each step: calibrate (encoderless bundle, from the true kinematics: the benchmark is about
  which snapshots, not about convergence) and measure the TRUE worst-case error over the held-out
  angles: at each, the joint angles are fitted to the true T_ds with the calibrated kinematics
  (weighted by the information of a snapshot there, i.e. what a noise-free validation snapshot
  gives), and the error ``Log(T_true^-1 T_est)`` is split into rotation (rad) and translation (m);
* tolerance: ``--tolerance ROT,TRANS`` for every member, or (default) ``--relative F`` (default 1) times
  the true worst errors (rotation, translation) of a reference calibration of the member: the start
  plus ``REFERENCE_ADDED`` (30) snapshots on the scene's jittered grid, i.e. "reach the worst-case
  accuracy a 40-snapshot calibration of this mechanism reaches" (an absolute tolerance means very
  different things for the family's cameras, targets and mechanisms);
* snapshots needed: the added snapshots at the first step whose true worst errors are both within the
  tolerance (``inf`` when not reached by ``--max-added``).

Printed: one line per member, then the median over members of the ratios needed(random) / needed(plan)
and needed(grid) / needed(plan) (members where the plan did not reach count as ratio 0; where neither
reached, they are left out), and the consistency of the final plan calibration's predicted covariance
with its true errors: per member the NEES of the first held-out angle under the ``calibration``
prediction (dof 6 - L: the joint-angle fit removes L directions), summed over members against
``chi2.ppf([0.025, 0.975], sum dof)``, and the median ratio true worst error / predicted worst 1-sigma.

Run: ``python benchmarks/bench_plan.py [--n 20] [--seed0 0] [--step 2] [--max-added 40] [--relative 1 |
--tolerance 1mrad,1mm] [--workers 1] [--json OUT.json]``. About 3-6 min per member on one core.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field

import gtsam
import numpy as np
from scipy.stats import chi2

from dcc_fg.calibrate import CalibrationOptions, calibrate
from dcc_fg.data import CalibrationDataset, Snapshot
from dcc_fg.detection import detect_target
from dcc_fg.model import GimbalCalibration
from dcc_fg.planning.plan import plan_snapshots
from dcc_fg.planning.predict import KinematicsInformation, ViewModel, kinematics_information, place_targets, predict
from dcc_fg.planning.range_spec import Tolerance, parse_tolerance
from dcc_fg.sim.calibration_scene import SceneConfig, grid_joint_samples, simulate_calibration, simulate_snapshots
from dcc_fg.sim.mechanism_family import FamilyMember, family_member
from dcc_fg.sim.render import BoardTexture, RenderConfig, aprilgrid_view_flip, make_texture, render_view
from dcc_fg.util.errors import EstimatorError
from factors import chain

START = 10
REFERENCE_ADDED = 30  # snapshots of the reference calibration that sets the default tolerance
MIN_COMMON = 8
STRATEGIES = ("plan", "random", "grid")
PERSON_POSITION_M = 0.02
PERSON_ANGLE_RAD = np.deg2rad(2.0)


@dataclass
class Scene:
    """One member's fixed parts: truth, range (true angles, rad), held-out angles, renderer."""

    member: FamilyMember
    truth: GimbalCalibration
    ranges: np.ndarray
    heldout: np.ndarray
    texture: BoardTexture
    render: RenderConfig
    config: SceneConfig


@dataclass
class MemberResult:
    seed: int
    joints: int
    description: str
    tolerance_mrad_mm: tuple[float, float]
    start_error_mrad_mm: tuple[float, float]
    needed: dict[str, float] = field(default_factory=dict)
    curves: dict[str, list[tuple[int, float, float]]] = field(default_factory=dict)
    nees: float = float("nan")
    nees_dof: int = 0
    true_over_predicted: float = float("nan")
    lost_snapshots: int = 0
    time_s: float = 0.0
    failure: str = ""


# ------------------------------------------------------------------ simulation


def _perturbed(T: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    xi = np.concatenate([rng.normal(scale=PERSON_ANGLE_RAD, size=3), rng.normal(scale=PERSON_POSITION_M, size=3)])
    return T @ gtsam.Pose3.Expmap(xi).matrix()


def render_snapshot(
    sc: Scene, theta: np.ndarray, T_st: np.ndarray, stamp: int, rng: np.random.Generator
) -> Snapshot | None:
    """Render both images of the board at ``T_st`` (static camera) with the gimbal at true ``theta``,
    detect; None when the board is not detected in both (fewer than MIN_COMMON common corners)."""
    cams = (sc.truth.static_camera, sc.truth.dynamic_camera)
    assert cams[0] is not None and cams[1] is not None
    target = sc.config.target
    T = T_st @ aprilgrid_view_flip(target) if target.target_type == "aprilgrid" else T_st
    T_ds = sc.truth.T_ds(theta)
    obs = []
    for cam, T_ct in zip(cams, (T, T_ds @ T), strict=True):
        obs.append(detect_target(render_view(cam, T_ct, sc.texture, sc.render, rng), target))
    if len(np.intersect1d(obs[0].ids, obs[1].ids)) < MIN_COMMON:
        return None
    return Snapshot(stamp, obs[0], obs[1], np.asarray(theta, float).copy())


def simulator_snapshots(
    sc: Scene, thetas: np.ndarray, rng: np.random.Generator, stamp0: int
) -> tuple[list[Snapshot | None], np.ndarray]:
    """Snapshots at true ``thetas`` with the simulator's board placement (joint samples without a view move
    towards the centre, as the scene does); the true angles used."""
    snaps: list[Snapshot | None] = []
    used = np.array(thetas, dtype=float).reshape(-1, sc.truth.n_joints)
    for k, th in enumerate(used):
        try:
            _, th_used, poses = simulate_snapshots(sc.truth, th[None], sc.config, rng, "bench")
        except RuntimeError:  # no board pose both cameras see at these angles: the snapshot is lost
            snaps.append(None)
            continue
        used[k] = th_used[0]
        snaps.append(render_snapshot(sc, th_used[0], poses[0], stamp0 + k, rng))
    return snaps, used


def make_scene(seed: int) -> Scene:
    member = family_member(seed, None, 40)
    sim = simulate_calibration(seed, member.scene, mechanism=(member.truth, member.ranges))
    th = sim.joints_calibration
    ranges = np.column_stack([th.min(axis=0), th.max(axis=0)])
    truth = member.truth
    assert truth.static_camera is not None and truth.dynamic_camera is not None
    view = ViewModel(
        truth.static_camera,
        truth.dynamic_camera,
        member.scene.target.points,
        float(np.mean(member.scene.distance_range)),
        member.scene.distance_range,
        member.scene.pixel_sigma,
    )
    rng = np.random.default_rng([seed, 1])
    cand = ranges[:, 0] + rng.uniform(size=(2000, truth.n_joints)) * (ranges[:, 1] - ranges[:, 0])
    ok = place_targets(view, chain.T_ds_batch(truth.kin, cand, truth.n_joints)).full
    return Scene(member, truth, ranges, cand[ok][:60], make_texture(member.scene.target), RenderConfig(), member.scene)


# ------------------------------------------------------------------ scoring


def true_errors(sc: Scene, cal: GimbalCalibration, info: KinematicsInformation, offset: np.ndarray) -> np.ndarray:
    """(H, 6) errors ``Log(T_true^-1 T_est(theta_fit))`` at the held-out angles, the joint angles fitted to
    the true T_ds with the calibrated kinematics, weighted by the information of a snapshot there."""
    L = cal.n_joints
    th = sc.heldout + offset
    T_true = chain.T_ds_batch(sc.truth.kin, sc.heldout, L)
    Lam = predict(info, th).view_info
    for _ in range(8):
        T_est, _, Jt = chain.d_T_ds_tangent_batch(cal.kin, th, L)
        r = np.array([gtsam.Pose3(a).localCoordinates(gtsam.Pose3(b)) for a, b in zip(T_true, T_est, strict=True)])
        A = np.swapaxes(Jt, 1, 2) @ Lam @ Jt
        g = np.einsum("hji,hjk,hk->hi", Jt, Lam, r)
        th = th - np.linalg.solve(A, g[..., None])[..., 0]
    T_est = chain.T_ds_batch(cal.kin, th, L)
    return np.array([gtsam.Pose3(a).localCoordinates(gtsam.Pose3(b)) for a, b in zip(T_true, T_est, strict=True)])


def worst(err: np.ndarray) -> tuple[float, float]:
    return float(np.linalg.norm(err[:, :3], axis=1).max()), float(np.linalg.norm(err[:, 3:], axis=1).max())


@dataclass
class Calibrated:
    cal: GimbalCalibration
    info: KinematicsInformation
    offset: np.ndarray  # calibration's joint angles minus true ones (gauge offsets), rad
    err: np.ndarray


def calibrate_set(sc: Scene, snaps: list[Snapshot | None], thetas_true: np.ndarray) -> Calibrated:
    keep = [i for i, s in enumerate(snaps) if s is not None]
    cams = (sc.truth.static_camera, sc.truth.dynamic_camera)
    assert cams[0] is not None and cams[1] is not None
    data = CalibrationDataset(cams[0], cams[1], sc.config.target.points, [snaps[i] for i in keep], "bench")  # type: ignore[misc]
    res = calibrate(data, sc.truth, CalibrationOptions())
    d = res.joint_angles - thetas_true[keep]
    offset = np.arctan2(np.sin(d), np.cos(d)).mean(axis=0)
    info = kinematics_information(res, data)
    return Calibrated(res.calibration, info, offset, true_errors(sc, res.calibration, info, offset))


def grid_points(ranges: np.ndarray, m: int) -> np.ndarray:
    L = ranges.shape[0]
    u = (np.arange(m) + 0.5) / m
    cells = np.stack(np.meshgrid(*[u] * L, indexing="ij"), axis=-1).reshape(-1, L)
    return ranges[:, 0] + cells * (ranges[:, 1] - ranges[:, 0])


def run_member(seed: int, args: argparse.Namespace) -> MemberResult:
    t0 = time.perf_counter()
    sc = make_scene(seed)
    L = sc.truth.n_joints
    rng = np.random.default_rng([seed, 2])
    start_th = sc.ranges[:, 0] + rng.uniform(size=(START, L)) * (sc.ranges[:, 1] - sc.ranges[:, 0])
    start, start_th = simulator_snapshots(sc, start_th, rng, 0)
    base = calibrate_set(sc, start, start_th)
    e_r, e_t = worst(base.err)
    if args.tolerance:
        tol = parse_tolerance(args.tolerance)
    else:  # the true worst error of a reference calibration: the start plus REFERENCE_ADDED jittered-grid snapshots
        ref_th = grid_joint_samples(REFERENCE_ADDED, sc.ranges, np.random.default_rng([seed, 4]))
        ref, ref_th = simulator_snapshots(sc, ref_th, np.random.default_rng([seed, 5]), 10**7)
        r_r, r_t = worst(calibrate_set(sc, start + ref, np.vstack([start_th, ref_th])).err)
        tol = Tolerance(args.relative * r_r, args.relative * r_t)
    rec = MemberResult(
        seed, L, sc.member.description["twists"], (tol.rotation * 1e3, tol.translation * 1e3), (e_r * 1e3, e_t * 1e3)
    )
    lost = sum(s is None for s in start)
    final_plan: Calibrated | None = None
    for strat in STRATEGIES:
        curve = [(0, e_r * 1e3, e_t * 1e3)]
        needed = 0.0 if (e_r <= tol.rotation and e_t <= tol.translation) else math.inf
        snaps, ths = list(start), start_th.copy()
        cur = base
        srng = np.random.default_rng([seed, 3, STRATEGIES.index(strat)])
        steps = (
            [m**L for m in range(1, 100) if m**L <= args.max_added]
            if strat == "grid" and L > 1
            else list(range(args.step, args.max_added + 1, args.step))
        )
        added = 0
        for n_total in steps:
            if needed < math.inf:
                break
            n_new = n_total - added
            if strat == "plan":
                ranges_est = sc.ranges + cur.offset[:, None]
                plan = plan_snapshots(cur.info, ranges_est, tol, n_new, "worst", "calibration")
                if not plan.snapshots:  # predicted to meet the tolerance: take the step at random angles
                    th_new = sc.ranges[:, 0] + srng.uniform(size=(n_new, L)) * np.ptp(sc.ranges, axis=1)
                    new, th_new = simulator_snapshots(sc, th_new, srng, 10**6 + added)
                else:
                    th_new = np.array([s.theta for s in plan.snapshots]) - cur.offset
                    poses = [np.array(s.target["T_st"]) for s in plan.snapshots]
                    new = [
                        render_snapshot(sc, th, _perturbed(T, srng), 10**6 + added + k, srng)
                        for k, (th, T) in enumerate(zip(th_new, poses, strict=True))
                    ]
            elif strat == "random":
                th_new = sc.ranges[:, 0] + srng.uniform(size=(n_new, L)) * np.ptp(sc.ranges, axis=1)
                new, th_new = simulator_snapshots(sc, th_new, srng, 10**6 + added)
            else:
                m = int(round(n_total ** (1.0 / L))) if L > 1 else n_total
                g = grid_points(sc.ranges, m)
                new, th_new = simulator_snapshots(sc, g, srng, 10**6)
                snaps, ths = list(start), start_th.copy()
            lost += sum(s is None for s in new)
            snaps += new
            ths = np.vstack([ths, th_new])
            added = n_total
            cur = calibrate_set(sc, snaps, ths)
            w_r, w_t = worst(cur.err)
            curve.append((added, w_r * 1e3, w_t * 1e3))
            if w_r <= tol.rotation and w_t <= tol.translation:
                needed = float(added)
        rec.needed[strat] = needed
        rec.curves[strat] = curve
        if strat == "plan":
            final_plan = cur
    assert final_plan is not None
    cov = predict(final_plan.info, sc.heldout[:1] + final_plan.offset).calibration[0]
    e = final_plan.err[0]
    rec.nees = float(e @ np.linalg.pinv(cov, rcond=1e-9, hermitian=True) @ e)
    rec.nees_dof = 6 - L
    pred = predict(final_plan.info, sc.heldout + final_plan.offset)
    p_r, p_t = pred.sigmas("calibration")
    w_r, w_t = worst(final_plan.err)
    rec.true_over_predicted = float(0.5 * (w_r / p_r.max() + w_t / p_t.max()))
    rec.lost_snapshots = lost
    rec.time_s = time.perf_counter() - t0
    return rec


def safe_member(seed: int, args: argparse.Namespace) -> MemberResult:
    try:
        return run_member(seed, args)
    except (EstimatorError, ValueError, RuntimeError, np.linalg.LinAlgError) as exc:
        return MemberResult(
            seed, 0, "", (math.nan, math.nan), (math.nan, math.nan), failure=f"{type(exc).__name__}: {exc}"
        )


# ------------------------------------------------------------------ report


def member_line(r: MemberResult) -> str:
    if r.failure:
        return f"member {r.seed:3d}: FAILED {r.failure}"
    need = "  ".join(f"{s} {r.needed[s]:>4.0f}" for s in STRATEGIES)
    return (
        f"member {r.seed:3d} L={r.joints}: start worst {r.start_error_mrad_mm[0]:.3g} mrad / "
        f"{r.start_error_mrad_mm[1]:.3g} mm, tolerance {r.tolerance_mrad_mm[0]:.3g} / {r.tolerance_mrad_mm[1]:.3g}; "
        f"snapshots needed: {need}; NEES {r.nees:.2f} (dof {r.nees_dof}); true/predicted worst "
        f"{r.true_over_predicted:.2f}; lost {r.lost_snapshots}; {r.time_s:.0f} s"
    )


def ratios(records: list[MemberResult], other: str) -> list[float]:
    out = []
    for r in records:
        p, o = r.needed["plan"], r.needed[other]
        if math.isinf(p) and math.isinf(o):
            continue
        if p == 0 and o == 0:
            out.append(1.0)
        elif math.isinf(p):
            out.append(0.0)
        else:
            out.append(o / max(p, 1e-9) if not math.isinf(o) else math.inf)
    return out


def summary(records: list[MemberResult]) -> str:
    ok = [r for r in records if not r.failure]
    lines = [f"{len(ok)} of {len(records)} members ran"]
    for other in ("random", "grid"):
        rs = ratios(ok, other)
        med = float(np.median(rs)) if rs else math.nan
        lines.append(
            f"median ratio snapshots needed {other} / plan: {med:.2f} over {len(rs)} members "
            f"(>= 2: {sum(x >= 2 for x in rs)}, < 1: {sum(x < 1 for x in rs)})"
        )
    for s in STRATEGIES:
        needs = [r.needed[s] for r in ok]
        lines.append(
            f"  {s:6s}: median needed {np.median(needs) if needs else math.nan:.0f}, reached the tolerance in "
            f"{sum(not math.isinf(x) for x in needs)} of {len(needs)}"
        )
    dof = sum(r.nees_dof for r in ok)
    if dof:
        lo, hi = chi2.ppf([0.025, 0.975], dof)
        total = sum(r.nees for r in ok)
        verdict = "inside" if lo <= total <= hi else "OUTSIDE"
        lines.append(
            f"NEES of the final plan calibration at one held-out angle per member (calibration prediction): sum "
            f"{total:.1f} over {dof} dof, 95% interval {lo:.1f}-{hi:.1f}: {verdict}"
        )
        lines.append(
            "median true worst error / predicted worst 1-sigma over the held-out angles: "
            f"{np.median([r.true_over_predicted for r in ok]):.2f}"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--n", type=int, default=20, help="members of the family (default 20)")
    p.add_argument("--seed0", type=int, default=0, help="first family seed (default 0)")
    p.add_argument("--step", type=int, default=2, help="snapshots added per step (default 2)")
    p.add_argument("--max-added", type=int, default=40, help="largest number of added snapshots (default 40)")
    p.add_argument(
        "--relative",
        type=float,
        default=1.0,
        help="tolerance = this times the true worst error of a "
        f"reference calibration (the start plus {REFERENCE_ADDED} jittered-grid snapshots; default 1)",
    )
    p.add_argument("--tolerance", help="absolute tolerance for every member (e.g. 1mrad,1mm); overrides --relative")
    p.add_argument("--workers", type=int, default=1, help="members in parallel (default 1; the machine has 2 cores)")
    p.add_argument("--json", help="write the per-member records here")
    args = p.parse_args(argv)
    seeds = list(range(args.seed0, args.seed0 + args.n))
    records: list[MemberResult] = []
    if args.workers > 1:
        with ProcessPoolExecutor(args.workers) as pool:
            for r in pool.map(safe_member, seeds, [args] * len(seeds)):
                print(member_line(r), flush=True)
                records.append(r)
    else:
        for s in seeds:
            r = safe_member(s, args)
            print(member_line(r), flush=True)
            records.append(r)
    print(summary(records))
    if args.json:
        with open(args.json, "w") as f:
            json.dump([asdict(r) for r in records], f, indent=1, default=str)
    return 0


if __name__ == "__main__":
    sys.exit(main())
