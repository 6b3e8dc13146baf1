"""Calibrate as you record: warm-started re-solves as snapshots arrive (``dcc-fg calibrate --incremental``).

Frames and symbols as in docs/architecture.md: ``T_ab`` maps points from frame b into frame a, ``s``
static camera, ``d`` gimbal camera, ``t`` target; ``T_ds(theta)`` static -> gimbal camera; angles in
rad, lengths in m, pixels in px.

:class:`IncrementalCalibration` keeps the snapshots, the calibration graph of
:mod:`dcc_fg.calibration_graph` (bundle formulation, encoderless mode) and its current estimate.
:meth:`IncrementalCalibration.add` takes one snapshot and returns an :class:`Update`:

1. **Collect.** Until ``start_snapshots`` snapshots exist (at least
   :func:`dcc_fg.calibrate.minimum_snapshots`), nothing is solved; the update says how many more
   are needed.
2. **Global solve** (:func:`dcc_fg.global_fit.calibrate_global`: the automatic initialization and
   every start, plus ``initial`` when given) at the first solve, again whenever the number of
   snapshots has doubled since the last global solve while there are at most ``global_until`` of
   them (a bad early local minimum is escaped while the problem is small), and whenever the RMS
   pixel residual after a warm update exceeds ``jump_ratio`` times its value at the last global
   solve even after a polish (up to ``POLISH_ITERATIONS`` Levenberg-Marquardt iterations on the whole
   graph: early on, one new snapshot can move the kinematics further than one warm step goes); a
   wrong basin shows as a jump in the cost per observation. These interim solves do not log the
   global strategy's ambiguity warning. The graph is then rebuilt
   at the global solution, with the gauge of that solution (held kinematic entries, the mean prior
   on ``theta_L`` over its reference snapshots) and its held directions
   (:func:`dcc_fg.calibrate.hold_degenerate_directions`) kept for the warm updates that follow.
3. **Warm update.** The new snapshot's target pose starts at its PnP pose in the static camera and
   its joint angles at the inverse kinematics of its PnP ``T_ds`` on the current kinematics
   (:func:`dcc_fg.init.joint_angles_from_T_ds`, seeded with the previous snapshot's angles, on their
   branch); its bundle factor is added to the graph and the estimate is updated: backend ``isam2``
   (default) one ``gtsam.ISAM2`` update (Gauss-Newton; only the factors of variables that moved by
   more than ``ISAM2_RELINEARIZE_THRESHOLD`` are relinearized, about 0.1 s at 200 snapshots),
   backend ``lm`` ``warm_iterations`` Levenberg-Marquardt iterations on the whole graph from the
   current estimate. The gauge prior stays on the reference snapshots of the last global solve
   (a gauge choice: it changes neither the cost nor ``T_ds``).

**Background solves** (``background``, what ``dcc-fg calibrate --incremental`` uses): a global solve
(first, doubled or after a residual jump) runs in a separate process (one worker of a ``forkserver``
pool) on the snapshots collected so far, while the updates go on: before the first solution the
snapshots are collected, after it they are warm updates. A finished background solve is adopted at the
next :meth:`IncrementalCalibration.add` or :meth:`IncrementalCalibration.poll`: the graph is rebuilt at
its solution and the snapshots that arrived meanwhile are added by warm updates (at most
``catch_up`` of them, besides the new one, per update; the rest wait for the next). A re-solve replaces
the current estimate only when its cost over the same snapshots is not higher. So no update waits for
a global solve; the first solution arrives a global solve's time after the ``start_snapshots``-th
snapshot. Without ``background`` (the API's default, deterministic) the global solves run inside
:meth:`IncrementalCalibration.add`.

Time per update at 200 snapshots: ``benchmarks/bench_incremental.py`` (the prediction, ~0.2 s, is most
of a warm update; ``predict_every`` > 1 skips it in between).

After a solve, every ``predict_every`` snapshots, the update carries the predicted ``T_ds`` 1-sigma
over the operating range (:func:`dcc_fg.planning.predict.kinematics_information`, its worst and mean
in the planner's ``calibration`` mode: the calibration's share of a new snapshot's ``T_ds`` error),
the next suggested snapshot (:func:`dcc_fg.planning.plan.plan_snapshots` with K = 1) and whether the
tolerance is reached. The RMS residual of a warm update is derived from the solver's cost
(``sigma * sqrt(2 E / n)``, ``E`` GTSAM's error including the weak priors, ``n`` the number of pixel
coordinates), so it needs no extra pass over the data.

:meth:`IncrementalCalibration.finish` returns the full :class:`~dcc_fg.calibrate.CalibrationResult`
of all snapshots: :func:`dcc_fg.calibrate.calibrate` started from the current kinematics and joint
angles, converged to the solver's tolerances, with covariances. It reaches the minimum of the batch
calibration (same cost; ``T_ds(theta_i)`` equal within their 1-sigma; the gauge-fixed entries, and
so the kinematic vector itself, may differ from the batch's: they are a choice of gauge).
"""

from __future__ import annotations

import logging
import multiprocessing
import time
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass, field, replace
from typing import Any

import gtsam
import numpy as np
from gtsam.symbol_shorthand import J, X
from numpy.typing import NDArray

from dcc_fg.calibrate import (
    CalibrationOptions,
    CalibrationResult,
    calibrate,
    check_dataset,
    hold_degenerate_directions,
    minimum_snapshots,
)
from dcc_fg.calibration_graph import (
    KIN_KEY,
    CalibrationProblem,
    build_graph,
    gauge_fixed_joint_offsets,
    lm_params,
    snapshot_measurements,
)
from dcc_fg.data import CalibrationDataset, Snapshot, with_joints
from dcc_fg.global_fit import calibrate_global
from dcc_fg.init import joint_angles_from_T_ds, pnp_pose
from dcc_fg.model import GimbalCalibration
from dcc_fg.model_selection import EXACT
from dcc_fg.planning.plan import PlannedSnapshot, plan_snapshots
from dcc_fg.planning.predict import accuracy_over_range, kinematics_information
from dcc_fg.planning.range_spec import Tolerance, default_range
from dcc_fg.util.errors import EstimatorError, stage
from factors import chain
from factors.calibration import RobustLoss, SnapshotMeasurements, bundle_factor

FloatArray = NDArray[np.float64]

#: Fewest snapshots before the first (global) solve, beyond the count the unknowns need: the automatic
#: initialization fits axes to the PnP rotations and needs some spread of the joint angles.
DEFAULT_START_SNAPSHOTS = 8
DEFAULT_WARM_ITERATIONS = 2  # Levenberg-Marquardt iterations per warm update (backend "lm")
BACKENDS = ("isam2", "lm")
#: iSAM2 relinearizes a variable whose update exceeds this (each tangent entry, rad or m): the kinematics
#: move by less than this per snapshot once dozens are in, so most updates linearize the new factor only.
ISAM2_RELINEARIZE_THRESHOLD = 1e-3
DEFAULT_GLOBAL_UNTIL = 40  # global re-solves at doubled snapshot counts only up to this many snapshots
DEFAULT_JUMP_RATIO = 1.5  # RMS residual growth (vs. the last global solve) that triggers a polish / global re-solve
POLISH_ITERATIONS = 30  # Levenberg-Marquardt iterations of the polish after a residual jump
PLAN_MODE = "calibration"  # the planner's prediction mode used for the tolerance (dcc_fg.planning.plan)
DEFAULT_CATCH_UP = 3  # background mode: waiting snapshots added per update besides the new one


@dataclass(frozen=True)
class IncrementalOptions:
    """Options of :class:`IncrementalCalibration` (module docstring).

    Attributes:
        solver: calibration options (mode must be ``encoderless``, formulation ``bundle``); the warm
            updates skip the covariances, :meth:`IncrementalCalibration.finish` computes them when
            ``solver.compute_covariance``.
        backend: how a warm update solves: ``isam2`` (default: ``gtsam.ISAM2``, Gauss-Newton on the
            factors whose variables moved by more than ``ISAM2_RELINEARIZE_THRESHOLD``, the rest keep
            their linearization) or ``lm`` (Levenberg-Marquardt on the whole graph, ``warm_iterations``).
        start_snapshots: snapshots collected before the first solve (raised to the minimum the
            unknowns need).
        warm_iterations: Levenberg-Marquardt iterations per warm update (>= 1).
        global_until: global re-solves at doubled snapshot counts up to this many snapshots (0: only the first).
        jump_ratio: a warm update whose RMS residual exceeds this multiple of the last global solve's
            triggers a global re-solve (> 1; ``inf`` disables it).
        predict_every: compute the predicted accuracy and the next suggestion every this many
            snapshots (1: after every update; the last prediction is repeated in between).
        ranges: (L, 2) operating range of the joint angles, rad; None: the data's range plus a margin
            (:func:`dcc_fg.planning.range_spec.default_range`, re-evaluated at every prediction).
        tolerance: largest acceptable worst-case 1-sigma of ``T_ds`` over the range (rad, m).
        background: run the global solves in a separate process while the updates go on (module
            docstring); False: inside :meth:`IncrementalCalibration.add` (deterministic).
        catch_up: background mode: snapshots that arrived during a background solve added per update
            besides the new one (>= 1).
    """

    solver: CalibrationOptions = field(default_factory=CalibrationOptions)
    backend: str = "isam2"
    start_snapshots: int = DEFAULT_START_SNAPSHOTS
    warm_iterations: int = DEFAULT_WARM_ITERATIONS
    global_until: int = DEFAULT_GLOBAL_UNTIL
    jump_ratio: float = DEFAULT_JUMP_RATIO
    predict_every: int = 1
    ranges: FloatArray | None = None
    tolerance: Tolerance = field(default_factory=lambda: Tolerance(1e-3, 1e-3))
    background: bool = False
    catch_up: int = DEFAULT_CATCH_UP

    def __post_init__(self) -> None:
        if self.solver.mode != "encoderless":
            raise ValueError(f"incremental calibration is encoderless only (got mode {self.solver.mode!r})")
        if self.backend not in BACKENDS:
            raise ValueError(f"backend must be one of {', '.join(BACKENDS)}, got {self.backend!r}")
        if self.solver.formulation != "bundle":
            raise ValueError(f"incremental calibration uses the bundle formulation (got {self.solver.formulation!r})")
        for name in ("start_snapshots", "warm_iterations", "predict_every", "catch_up"):
            value = getattr(self, name)
            if not (isinstance(value, int | np.integer) and value >= 1):
                raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
        if not (isinstance(self.global_until, int | np.integer) and self.global_until >= 0):
            raise ValueError(f"global_until must be an integer >= 0, got {self.global_until!r}")
        if not (self.jump_ratio > 1.0):
            raise ValueError(f"jump_ratio must be > 1, got {self.jump_ratio!r}")
        if not (self.tolerance.rotation > 0 and self.tolerance.translation > 0):
            raise ValueError(f"tolerance must be positive, got {self.tolerance.describe()}")


@dataclass
class Update:
    """What one :meth:`IncrementalCalibration.add` did.

    Attributes:
        n_snapshots: snapshots so far.
        needed: snapshots still needed before the first solve (0 once solving).
        strategy: ``collect`` (nothing solved yet), ``global`` (global strategy; in background mode: a
            background solve was adopted at this update), ``warm`` (warm update).
        reason: why a global solve ran (``first``, ``doubled``, ``residual jump``), what a background
            solve did, how many snapshots wait to be added, or an error text.
        update_time_s: wall time of the whole update (solve and prediction), s.
        solve_time_s: of which the solve, s.
        iterations: Levenberg-Marquardt iterations of the solve.
        rms_px: RMS pixel residual per axis (NaN before the first solve).
        worst_rotation / worst_translation / mean_rotation / mean_translation: predicted 1-sigma of
            ``T_ds`` over the range (rad, m; planner's ``calibration`` mode); NaN when not available.
        predicted: whether the prediction was computed at this update (else repeated from an earlier one).
        suggestion: the next snapshot to take (joint angles rad, target placement), or None.
        tolerance_reached: the predicted worst 1-sigma is within the tolerance.
    """

    n_snapshots: int
    needed: int = 0
    strategy: str = "collect"
    reason: str = ""
    update_time_s: float = 0.0
    solve_time_s: float = 0.0
    iterations: int = 0
    rms_px: float = float("nan")
    worst_rotation: float = float("nan")
    worst_translation: float = float("nan")
    mean_rotation: float = float("nan")
    mean_translation: float = float("nan")
    predicted: bool = False
    suggestion: PlannedSnapshot | None = None
    tolerance_reached: bool = False

    def line(self) -> str:
        """One line for a person recording by hand (angles in deg, mrad, mm, px)."""
        head = f"[{self.n_snapshots:4d}]"
        if self.strategy == "collect":
            if not self.needed:  # background mode: enough snapshots, the first solve is running
                return f"{head} collecting: {self.reason}"
            text = f"{head} collecting: {self.needed} more snapshot(s) before the first solve"
            return text + (f" ({self.reason})" if self.reason else "")
        solve = self.strategy + (f" ({self.reason})" if self.reason else "")
        text = f"{head} {solve}: {self.update_time_s:.2f} s, RMS {self.rms_px:.3f} px"
        if np.isfinite(self.worst_rotation):
            text += (
                f"; worst 1-sigma {self.worst_rotation * 1e3:.3g} mrad / {self.worst_translation * 1e3:.3g} mm, "
                f"mean {self.mean_rotation * 1e3:.3g} mrad / {self.mean_translation * 1e3:.3g} mm"
            )
        else:
            text += "; accuracy prediction unavailable"
        if self.tolerance_reached:
            return text + "; DONE: tolerance reached, you can stop"
        if self.suggestion is not None:
            angles = ", ".join(f"{np.degrees(x):.1f}" for x in self.suggestion.theta)
            dist = self.suggestion.target.get("distance_m", float("nan"))
            text += f"; next: joints ({angles}) deg, target {dist:.2f} m from the static camera"
        return text

    def to_dict(self) -> dict[str, Any]:
        """Plain numbers for a summary (angles deg, mrad, mm)."""
        out: dict[str, Any] = {
            "snapshots": self.n_snapshots,
            "strategy": self.strategy,
            "reason": self.reason,
            "update_time_s": self.update_time_s,
            "solve_time_s": self.solve_time_s,
            "iterations": self.iterations,
            "rms_px": self.rms_px,
            "worst_rotation_mrad": self.worst_rotation * 1e3,
            "worst_translation_mm": self.worst_translation * 1e3,
            "tolerance_reached": self.tolerance_reached,
        }
        if self.suggestion is not None:
            out["next_joint_angles_deg"] = [float(np.degrees(x)) for x in self.suggestion.theta]
        return out


@dataclass(frozen=True)
class GlobalSolution:
    """What a global solve hands back (picklable, from a background process too).

    Attributes:
        n_snapshots: the first ``n_snapshots`` snapshots were solved.
        kin: kinematic vector of the solution; ``gauge_fixed`` its gauge-held entries.
        T_st: (K, 4, 4) target -> static camera; ``T_dt`` (K, 4, 4) the PnP target -> gimbal camera poses.
        joint_angles: (K, L) rad.
        iterations: Levenberg-Marquardt iterations; ``solve_time_s`` wall time of the solve, s.
        nominal: the nominal geometry of the kept model (``exactly-intersecting`` when the model selection
            of :mod:`dcc_fg.model_selection` kept it, else the options' ``nominal``); the warm updates and
            the final solve use it.
    """

    n_snapshots: int
    kin: FloatArray
    gauge_fixed: NDArray[np.bool_]
    T_st: FloatArray
    T_dt: FloatArray
    joint_angles: FloatArray
    iterations: int
    solve_time_s: float
    nominal: str | None = None


def solve_global(
    data: CalibrationDataset, n_joints: int, options: CalibrationOptions, initial: GimbalCalibration | None
) -> GlobalSolution:
    """The global strategy (:func:`dcc_fg.global_fit.calibrate_global`) on ``data``, without its interim
    ambiguity warning (no news for the person recording). EstimatorError / ValueError when it fails."""
    t0 = time.perf_counter()
    logger = logging.getLogger("dcc_fg.global_fit")
    level = logger.level
    logger.setLevel(logging.ERROR)
    try:
        res = calibrate_global(data, n_joints, options, initial=initial)
    finally:
        logger.setLevel(level)
    return GlobalSolution(
        n_snapshots=len(data.snapshots),
        kin=res.calibration.kin.copy(),
        gauge_fixed=np.asarray(res.calibration.gauge_fixed, bool).copy(),
        T_st=np.asarray(res.T_st, float).copy(),
        T_dt=np.asarray(res.extra["pnp_T_dt"], float).copy(),
        joint_angles=res.joint_angles.copy(),
        iterations=int(res.iterations),
        solve_time_s=time.perf_counter() - t0,
        nominal=EXACT if (res.extra.get("model_selection") or {}).get("model") == EXACT else options.nominal,
    )


@dataclass
class _Pending:
    """A global solve running in the background: its future, why, and the snapshots it was given."""

    future: Future[GlobalSolution]
    reason: str
    snapshots: list[Snapshot]


@dataclass
class _Prediction:
    worst_rotation: float = float("nan")
    worst_translation: float = float("nan")
    mean_rotation: float = float("nan")
    mean_translation: float = float("nan")
    suggestion: PlannedSnapshot | None = None
    reached: bool = False


@dataclass(frozen=True)
class _GraphState:
    """The solver's graph state, saved while a background solution is tried and restored if it is not
    kept: problem, graph, values, iSAM2, held-direction count, pixel-coordinate count, global RMS."""

    problem: CalibrationProblem | None
    graph: gtsam.NonlinearFactorGraph | None
    values: gtsam.Values | None
    isam: gtsam.ISAM2 | None
    n_held: int
    n_obs: int
    global_rms: float


class IncrementalCalibration:
    """Encoderless calibration that grows one snapshot at a time (module docstring).

    Args:
        data: cameras, target and source of the recording; its snapshots (may be none) are the first ones.
        n_joints: L (>= 1).
        options: see :class:`IncrementalOptions`.
        initial: hand-measured kinematics, one more start of every global solve; None: automatic starts only.
    """

    def __init__(
        self,
        data: CalibrationDataset,
        n_joints: int,
        options: IncrementalOptions | None = None,
        initial: GimbalCalibration | None = None,
    ) -> None:
        if n_joints < 1:
            raise ValueError(f"incremental calibration needs a gimbal of L >= 1 joints, got {n_joints}")
        if initial is not None and initial.n_joints != n_joints:
            raise ValueError(f"the initial kinematics have {initial.n_joints} joints, not {n_joints}")
        self.options = options or IncrementalOptions()
        self.n_joints = n_joints
        self.initial = initial
        self._template = replace(data, snapshots=[])
        self.snapshots: list[Snapshot] = []
        self.updates: list[Update] = []
        self.start_snapshots = max(self.options.start_snapshots, minimum_snapshots(n_joints, "encoderless"))
        self._problem: CalibrationProblem | None = None
        self._graph: gtsam.NonlinearFactorGraph | None = None
        self._values: gtsam.Values | None = None
        self._isam: gtsam.ISAM2 | None = None
        self._n_held = 0
        self._nominal: str | None = self.options.solver.nominal  # of the last global solve's kept model
        self._n_obs = 0  # pixel coordinates (2 per corner) in the graph
        self._last_global = 0
        self._global_rms = float("nan")
        self._prediction = _Prediction()
        self._since_prediction = 0
        self._pool: ProcessPoolExecutor | None = None
        self._pending: _Pending | None = None
        for s in data.snapshots:
            self.add(s)

    # ---------------------------------------------------------------- state

    @property
    def data(self) -> CalibrationDataset:
        """The snapshots so far as a dataset."""
        return self._data_upto(len(self.snapshots))

    def _data_upto(self, n: int) -> CalibrationDataset:
        """The first ``n`` snapshots as a dataset."""
        return replace(self._template, snapshots=self.snapshots[:n])

    def _waiting(self) -> list[Snapshot]:
        """Snapshots kept but not yet in the graph (background mode: they arrived during a background
        solve); all of them before the first solution."""
        n = self._problem.n_snapshots if self._problem is not None else 0
        return self.snapshots[n:]

    @property
    def solving(self) -> bool:
        """Whether a solution exists (enough snapshots were collected and the first solve succeeded)."""
        return self._problem is not None

    def current(self) -> tuple[GimbalCalibration, FloatArray, FloatArray]:
        """The current kinematics (no covariances), joint angles (K, L) rad and target poses ``T_st`` (K, 4, 4)."""
        problem, values = self._require()
        kin = problem.layout.expand(values.atVector(KIN_KEY))
        K = problem.n_snapshots
        thetas = np.array([values.atVector(J(i)) for i in range(K)]).reshape(K, self.n_joints)
        T_st = np.array([values.atPose3(X(i)).matrix() for i in range(K)])
        cal = GimbalCalibration(
            kin,
            self.n_joints,
            self._template.static_camera,
            self._template.dynamic_camera,
            gauge_fixed=problem.fixed.copy(),
        )
        return cal, thetas, T_st

    def _require(self) -> tuple[CalibrationProblem, gtsam.Values]:
        if self._problem is None or self._values is None:
            need = self.start_snapshots - len(self.snapshots)
            raise ValueError(
                f"{self._template.source}: no solution yet ({len(self.snapshots)} snapshots; "
                f"the first solve needs {max(need, 1)} more)"
            )
        return self._problem, self._values

    # ---------------------------------------------------------------- adding snapshots

    def add(self, snapshot: Snapshot) -> Update:
        """Add one snapshot, re-solve and predict (module docstring). ValueError for a snapshot the
        calibration cannot use (too few corners, bad pixels or ids, PnP or inverse kinematics failing
        on it); such a snapshot is not kept. A failing global re-solve keeps the warm estimate."""
        t0 = time.perf_counter()
        check_dataset(replace(self._template, snapshots=[snapshot]), self.n_joints, "validate")
        adopted = self._adopt(wait=False)
        start = None
        if self._problem is not None and not self._waiting():
            try:
                start = self._warm_start(snapshot)
            except EstimatorError as exc:
                raise ValueError(f"snapshot t={snapshot.timestamp_ns} ns: {exc}") from exc
        self.snapshots.append(snapshot)
        K = len(self.snapshots)
        if K < self.start_snapshots:
            return self._record(Update(K, needed=self.start_snapshots - K), t0)
        reason = ""
        if self._problem is None:
            reason = "first"
        elif K >= 2 * self._last_global and K <= self.options.global_until:
            reason = "doubled"
        if self.options.background:
            return self._record(self._background_update(reason, adopted, start), t0)
        solved = self._solve_global(reason) if reason else None
        if solved is not None:
            update = solved
        else:
            assert start is not None
            update = self._warm(snapshot, start)
            if reason:  # the global re-solve failed
                update.reason = f"global solve failed, {reason}"
            elif update.rms_px > self.options.jump_ratio * self._global_rms:
                update = self._polish(update)
                if update.rms_px > self.options.jump_ratio * self._global_rms:
                    update = self._solve_global("residual jump") or update
        return self._record(self._with_prediction(update), t0)

    def poll(self) -> Update | None:
        """Background mode, without a new snapshot: adopt a finished background solve and add waiting
        snapshots (as :meth:`add` does first); the update, or None when there was nothing to do."""
        if not self.options.background:
            return None
        t0 = time.perf_counter()
        adopted = self._adopt(wait=False)
        if not adopted and not (self._problem is not None and self._waiting()):
            return None
        return self._record(self._background_update("", adopted, None), t0)

    def wait(self) -> Update | None:
        """Background mode: wait for a running background solve and adopt it (:meth:`poll` after it)."""
        if self._pending is None:
            return None
        self._pending.future.exception()  # blocks until done; its outcome is read by poll
        return self.poll()

    def close(self) -> None:
        """Stop the background process (a running solve is abandoned)."""
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool = None
        self._pending = None

    def __enter__(self) -> IncrementalCalibration:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _with_prediction(self, update: Update) -> Update:
        """The update with the predicted accuracy and the next suggestion (every ``predict_every``)."""
        if self._problem is not None:
            self._since_prediction += 1
            if self._since_prediction >= self.options.predict_every or update.strategy == "global":
                self._prediction = self._predict()
                self._since_prediction = 0
                update.predicted = True
            p = self._prediction
            update.worst_rotation, update.worst_translation = p.worst_rotation, p.worst_translation
            update.mean_rotation, update.mean_translation = p.mean_rotation, p.mean_translation
            update.suggestion, update.tolerance_reached = p.suggestion, p.reached
        return update

    # ---------------------------------------------------------------- background solves

    def _background_update(
        self, reason: str, adopted: str, start: tuple[SnapshotMeasurements, FloatArray, FloatArray, FloatArray] | None
    ) -> Update:
        """Background mode (module docstring): start a global solve when one is due and none runs, add
        the waiting snapshots (up to ``catch_up`` + 1, the newest last; ``start`` is the newest's warm
        start when it is the only one waiting), polish and submit a re-solve after a residual jump."""
        K = len(self.snapshots)
        if reason and self._pending is None:
            self._submit(reason)
        if self._problem is None:
            why = adopted or "the first solve is running in the background"
            return Update(K, needed=0, reason=why)
        update = self._catch_up(self.options.catch_up + 1, start)
        if update.rms_px > self.options.jump_ratio * self._global_rms and not self._waiting():
            update = self._polish(update)
            if update.rms_px > self.options.jump_ratio * self._global_rms and self._pending is None:
                self._submit("residual jump")
                update.reason += ", global re-solve started in the background"
        if adopted:
            update.strategy = "global"
            update.reason = adopted + (f"; {update.reason}" if update.reason else "")
        return self._with_prediction(update)

    def _submit(self, reason: str) -> None:
        """Start the global strategy on every snapshot so far in the background process."""
        if self._pool is None:
            ctx = multiprocessing.get_context("forkserver")
            self._pool = ProcessPoolExecutor(max_workers=1, mp_context=ctx)
        data = self.data
        future = self._pool.submit(solve_global, data, self.n_joints, self._solve_opts(), self.initial)
        self._pending = _Pending(future, reason, data.snapshots)
        self._last_global = len(data.snapshots)

    def _adopt(self, wait: bool) -> str:
        """Adopt a finished background solve (``wait``: wait for a running one): rebuild the graph at
        its solution and add the snapshots that arrived meanwhile (all of them), keeping the current
        estimate instead when its cost over the same snapshots is lower. Returns what happened ("" when
        nothing was finished)."""
        pending = self._pending
        if pending is None or not (wait or pending.future.done()):
            return ""
        self._pending = None
        try:
            sol = pending.future.result()
        except (EstimatorError, ValueError) as exc:
            return f"background {pending.reason} solve failed: {exc}"
        n = sol.n_snapshots
        if any(a is not b for a, b in zip(self.snapshots[:n], pending.snapshots, strict=False)):
            return f"background {pending.reason} solve discarded: its snapshots were dropped meanwhile"
        done = f"{pending.reason} solve on {n} snapshots, {sol.solve_time_s:.1f} s in the background"
        if self._problem is None:
            self._rebuild(sol)
            return done
        saved = self._save_state()
        assert self._graph is not None and self._values is not None
        current_error = self._graph.error(self._values)
        n_current = self._problem.n_snapshots
        self._rebuild(sol)
        try:
            self._catch_up(max(n_current - n, 0), None, drop=False)
            assert self._graph is not None and self._values is not None
            if self._graph.error(self._values) <= current_error:
                return done
            why = "lower cost"
        except EstimatorError as exc:
            why = f"a later snapshot does not fit the new solution: {exc}"
        self._restore_state(saved)
        return f"{done}: kept the current estimate ({why})"

    def _save_state(self) -> _GraphState:
        return _GraphState(
            self._problem, self._graph, self._values, self._isam, self._n_held, self._n_obs, self._global_rms
        )

    def _restore_state(self, s: _GraphState) -> None:
        self._problem, self._graph, self._values, self._isam = s.problem, s.graph, s.values, s.isam
        self._n_held, self._n_obs, self._global_rms = s.n_held, s.n_obs, s.global_rms

    def _catch_up(
        self,
        limit: int,
        start: tuple[SnapshotMeasurements, FloatArray, FloatArray, FloatArray] | None,
        drop: bool = True,
    ) -> Update:
        """Add up to ``limit`` waiting snapshots by warm updates, in order; ``start``: the warm start of
        the newest snapshot when it is the only one waiting. A waiting snapshot whose warm start fails
        is dropped (said in the update's reason and logged), or with ``drop`` False the EstimatorError
        is raised."""
        t0 = time.perf_counter()
        self._require()
        update: Update | None = None
        dropped: list[str] = []
        iterations = 0
        for snap in self._waiting()[:limit]:
            try:
                begin = start if start is not None and snap is self.snapshots[-1] else self._warm_start(snap)
            except EstimatorError as exc:
                if not drop:
                    raise
                self.snapshots.remove(snap)
                dropped.append(f"dropped snapshot t={snap.timestamp_ns} ns ({exc})")
                logging.getLogger(__name__).warning("%s", dropped[-1])
                continue
            update = self._warm(snap, begin)
            iterations += update.iterations
        if update is None:
            assert self._graph is not None and self._values is not None
            update = Update(len(self.snapshots), 0, "warm", "", 0.0, 0.0, 0, self._rms(self._graph.error(self._values)))
        update.n_snapshots = len(self.snapshots)
        update.iterations = iterations
        update.solve_time_s = time.perf_counter() - t0
        notes = dropped + ([f"{len(self._waiting())} snapshot(s) waiting"] if self._waiting() else [])
        update.reason = "; ".join(notes)
        return update

    def _record(self, update: Update, t0: float) -> Update:
        update.update_time_s = time.perf_counter() - t0
        self.updates.append(update)
        return update

    def _solve_opts(self) -> CalibrationOptions:
        return replace(self.options.solver, compute_covariance=False)

    def _solve_global(self, reason: str) -> Update | None:
        """The global strategy on all snapshots so far, here; on success the graph is rebuilt at its
        solution. On failure: before the first solve a ``collect`` update (try again with the next
        snapshot), after it None (the caller keeps the warm estimate)."""
        K = len(self.snapshots)
        try:
            sol = solve_global(self.data, self.n_joints, self._solve_opts(), self.initial)
        except (EstimatorError, ValueError) as exc:
            if self._problem is None:  # keep collecting; try again with the next snapshot
                return Update(K, needed=1, reason=f"first solve failed: {exc}")
            return None
        self._rebuild(sol)
        self._last_global = K
        return Update(K, 0, "global", reason, 0.0, sol.solve_time_s, sol.iterations, self._global_rms)

    def _rebuild(self, sol: GlobalSolution) -> None:
        """The persistent graph and values at a global solution of the first ``sol.n_snapshots``
        snapshots (its gauge and held directions); the RMS residual there is the new reference for a jump."""
        data, L, opt = self._data_upto(sol.n_snapshots), self.n_joints, self.options.solver
        sigma = opt.pixel_sigma if opt.pixel_sigma is not None else 1.0
        problem = CalibrationProblem(
            data=data,
            n_joints=L,
            mode="encoderless",
            formulation="bundle",
            sigma=sigma,
            robust=RobustLoss(opt.robust, opt.robust_k / sigma) if opt.robust else None,
            meas=[snapshot_measurements(data, s) for s in data.snapshots],
            T_st0=sol.T_st.copy(),
            T_dt0=sol.T_dt.copy(),
            thetas_given=sol.joint_angles.copy(),
            thetas0=sol.joint_angles.copy(),
            kin_start=sol.kin.copy(),
            fixed=sol.gauge_fixed.copy(),
            offsets=gauge_fixed_joint_offsets(L, "encoderless"),
        )
        self._nominal = sol.nominal
        held = hold_degenerate_directions(problem, sol.nominal)
        graph, values = build_graph(problem)
        for factor in held.factors(KIN_KEY):
            graph.add(factor)
        self._problem, self._graph, self._values = problem, graph, values
        self._n_held = held.count
        self._n_obs = 2 * sum(len(m.z_static) + len(m.z_dynamic) for m in problem.meas)
        self._start_isam()
        self._global_rms = self._rms(graph.error(values))

    def _start_isam(self) -> None:
        """A fresh iSAM2 on the whole graph at the current values (backend ``isam2``)."""
        self._isam = None
        if self.options.backend == "isam2":
            params = gtsam.ISAM2Params()
            params.setRelinearizeThreshold(ISAM2_RELINEARIZE_THRESHOLD)
            params.relinearizeSkip = 1
            self._isam = gtsam.ISAM2(params)
            self._isam.update(self._graph, self._values)

    def _polish(self, update: Update) -> Update:
        """Levenberg-Marquardt on the whole graph from the warm update's values (``POLISH_ITERATIONS``)."""
        assert self._graph is not None and self._values is not None
        t0 = time.perf_counter()
        optimizer = gtsam.LevenbergMarquardtOptimizer(self._graph, self._values, lm_params(POLISH_ITERATIONS))
        self._values = gtsam.Values(optimizer.optimize())
        self._start_isam()
        update.reason = "polished"
        update.rms_px = self._rms(optimizer.error())
        update.iterations += int(optimizer.iterations())
        update.solve_time_s += time.perf_counter() - t0
        return update

    def _warm_start(self, snapshot: Snapshot) -> tuple[SnapshotMeasurements, FloatArray, FloatArray, FloatArray]:
        """The new snapshot's measurements, PnP poses ``T_st0``, ``T_dt0`` (4x4) and joint angles (L,) rad:
        the inverse kinematics of its PnP ``T_ds`` on the current kinematics, on the previous snapshot's
        branch. Nothing is changed (EstimatorError from PnP or the inverse kinematics)."""
        cal, thetas, _ = self.current()
        data = self._template
        m = snapshot_measurements(data, snapshot)
        with stage("PnP of the new snapshot"):
            T_st0 = pnp_pose(data.static_camera, m.p_t_static, m.z_static)
            T_dt0 = pnp_pose(data.dynamic_camera, m.p_t_dynamic, m.z_dynamic)
        with stage("joint angles of the new snapshot (inverse kinematics)"):
            theta0 = joint_angles_from_T_ds(cal, T_dt0 @ chain.inv_se3(T_st0), thetas[-1])
        theta0 = thetas[-1] + np.angle(np.exp(1j * (theta0 - thetas[-1])))  # the branch of the previous angles
        return m, T_st0, T_dt0, theta0

    def _warm(
        self, snapshot: Snapshot, start: tuple[SnapshotMeasurements, FloatArray, FloatArray, FloatArray]
    ) -> Update:
        """Add the snapshot's factor (initial values ``start`` of :meth:`_warm_start`) and update the
        estimate: one iSAM2 update, or a few Levenberg-Marquardt iterations from the current estimate."""
        problem, values = self._require()
        assert self._graph is not None
        t0 = time.perf_counter()
        m, T_st0, T_dt0, theta0 = start
        i = problem.n_snapshots
        problem.meas.append(m)
        problem.T_st0 = np.concatenate([problem.T_st0, T_st0[None]])
        problem.T_dt0 = np.concatenate([problem.T_dt0, T_dt0[None]])
        problem.thetas_given = np.concatenate([problem.thetas_given, theta0[None]])
        problem.thetas0 = np.concatenate([problem.thetas0, theta0[None]])
        problem.data = self._data_upto(i + 1)
        factor = bundle_factor(
            problem.layout, m, problem.cams, problem.sigma, X(i), KIN_KEY, J(i), None, problem.robust
        )
        self._graph.add(factor)
        self._n_obs += 2 * (len(m.z_static) + len(m.z_dynamic))
        K = len(self.snapshots)
        if self._isam is not None:
            new_factors, new_values = gtsam.NonlinearFactorGraph(), gtsam.Values()
            new_factors.add(factor)
            new_values.insert(J(i), theta0)
            new_values.insert(X(i), gtsam.Pose3(T_st0))
            self._isam.update(new_factors, new_values)
            self._values = self._isam.calculateEstimate()
            rms = self._rms(self._graph.error(self._values))
            return Update(K, 0, "warm", "", 0.0, time.perf_counter() - t0, 1, rms)
        values.insert(J(i), theta0)
        values.insert(X(i), gtsam.Pose3(T_st0))
        optimizer = gtsam.LevenbergMarquardtOptimizer(self._graph, values, lm_params(self.options.warm_iterations))
        self._values = gtsam.Values(optimizer.optimize())
        rms = self._rms(optimizer.error())
        return Update(K, 0, "warm", "", 0.0, time.perf_counter() - t0, int(optimizer.iterations()), rms)

    def _rms(self, error: float) -> float:
        """RMS pixel residual per axis from GTSAM's error (0.5 * whitened sum of squares), px."""
        assert self._problem is not None
        return float(self._problem.sigma * np.sqrt(2.0 * max(error, 0.0) / max(self._n_obs, 1)))

    # ---------------------------------------------------------------- prediction

    def _light_result(self) -> CalibrationResult:
        """A :class:`CalibrationResult` of the current estimate for the predictions (no residuals, no
        covariances; the variance factor from the solver's cost, as :func:`dcc_fg.calibrate.variance_factor_of`)."""
        problem, values = self._require()
        cal, thetas, T_st = self.current()
        K, L, opt = problem.n_snapshots, self.n_joints, self.options.solver
        n_unknowns = int((~problem.fixed).sum()) + K * L + 6 * K - len(problem.offsets) - self._n_held
        dof = max(self._n_obs - n_unknowns, 1)
        assert self._graph is not None
        vf = 1.0 if opt.pixel_sigma is not None else 2.0 * self._graph.error(values) / dof
        empty: list[FloatArray] = []
        res = CalibrationResult(
            calibration=cal,
            joint_angles=thetas,
            joint_angle_std=np.full_like(thetas, np.nan),
            T_st=T_st,
            timestamps_ns=np.array([s.timestamp_ns for s in self.snapshots[:K]], dtype=np.int64),
            residuals_static=empty,
            residuals_dynamic=empty,
            null_space_dim=0,
            n_gauge_fixed=problem.n_gauge,
            iterations=0,
            initial_error=float("nan"),
            final_error=float("nan"),
            solve_time_s=0.0,
            variance_factor=float(vf),
            options=self._solve_opts(),
        )
        res.extra["solver"] = {"sigma": float(problem.sigma)}
        return res

    def _predict(self) -> _Prediction:
        """Predicted accuracy over the range and the next suggestion; NaN / None where the linear
        algebra or the view placement fails (the calibration itself is fine)."""
        out = _Prediction()
        try:
            res = self._light_result()
            info = kinematics_information(res, self._data_upto(res.joint_angles.shape[0]))
            ranges = self.options.ranges if self.options.ranges is not None else default_range(res.joint_angles)
            acc = accuracy_over_range(info, ranges)
            s = acc.stats(PLAN_MODE)
            if s.get("points", 0):
                out.worst_rotation = s["worst_rotation_mrad"] * 1e-3
                out.worst_translation = s["worst_translation_mm"] * 1e-3
                out.mean_rotation = s["mean_rotation_mrad"] * 1e-3
                out.mean_translation = s["mean_translation_mm"] * 1e-3
            plan = plan_snapshots(info, acc.ranges, self.options.tolerance, 1, "worst", PLAN_MODE)
        except (np.linalg.LinAlgError, ValueError):
            return out
        out.reached = plan.reached
        out.suggestion = plan.snapshots[0] if plan.snapshots else None
        return out

    # ---------------------------------------------------------------- the result

    def finish(self) -> CalibrationResult:
        """The calibration of all snapshots: :func:`dcc_fg.calibrate.calibrate` from the current
        estimate (kinematics and joint angles), converged, with covariances when
        ``options.solver.compute_covariance``; ``extra["incremental"]`` lists the updates.
        ValueError when no solve has happened yet. Background mode: waits for a running background
        solve, adds every waiting snapshot (a first solve that failed in the background is tried once
        more here) and stops the background process."""
        if self.options.background:
            try:
                self._adopt(wait=True)
                if self._problem is None and len(self.snapshots) >= self.start_snapshots:
                    self._solve_global("first")
                if self._problem is not None:
                    self._catch_up(len(self._waiting()), None)
            finally:
                self.close()
        cal, thetas, _ = self.current()
        data = self.data
        res = calibrate(with_joints(data, thetas), cal, replace(self.options.solver, nominal=self._nominal))
        if self._nominal == EXACT and self.options.solver.nominal != EXACT:
            res.extra["model_selection"] = {"model": EXACT, "reason": "kept by the last global solve"}
            res.calibration.statistics["model_selection"] = res.extra["model_selection"]
        res.extra["incremental"] = {
            "updates": [u.to_dict() for u in self.updates],
            "global_solves": sum(1 for u in self.updates if u.strategy == "global"),
        }
        res.calibration.statistics["incremental"] = {
            "snapshots": len(self.snapshots),
            "global_solves": res.extra["incremental"]["global_solves"],
            "median_update_time_s": float(np.median([u.update_time_s for u in self.updates])),
            "max_update_time_s": float(max(u.update_time_s for u in self.updates)),
        }
        return res
