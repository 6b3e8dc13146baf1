"""Starting the VIO without a standstill: rest detection and visual-inertial alignment in motion.

:class:`StartSelector` takes the first frames of a run and decides how to start:

* **standstill** (today's start): the IMU looks at rest over the first ``standstill_window`` seconds
  (mean specific force within 0.5 m/s^2 of gravity, samples within ``REST_ACC_SPREAD`` of it, gyro below
  ``REST_GYRO``) *and* the static camera's tracks do not move (median displacement between the first
  frame and the last one of the window below ``REST_FLOW`` in normalized units). A body moving at
  constant velocity passes the IMU test and fails the visual one.
* **motion**: a linear visual-inertial alignment over the first ``motion_init_window`` seconds
  (:func:`align_in_motion`), retried as frames arrive, up to ``motion_init_max_window``.

Alignment (closed form, as in Martinelli's linear visual-inertial structure from motion): in the first
keyframe's body frame b0, the IMU preintegration from t0 gives each frame's rotation ``R_j`` (b_j -> b0)
and the specific-force position increment ``dP_j`` (biases taken as zero), so the body position is
``p_j = v0 t_j + g t_j^2 / 2 + dP_j`` with unknown velocity ``v0`` and gravity ``g`` (both in b0). A
static-camera track f at point ``p_f`` (b0) seen in frame j with normalized coordinates ``(x, y)``
satisfies ``[u]_x R_cj^T (p_f - p_j - R_j c_I) = 0`` with ``u = (x, y, 1)``, ``R_cj = R_j R_Is`` and
``c_I`` the camera centre in the body frame (from ``T_sI``): linear in ``(v0, g, p_f)``. The metric
scale comes from the IMU. The least-squares solution is accepted when the problem is well conditioned,
``|g|`` is within ``GRAVITY_TOLERANCE`` of the configured gravity, and the points reproject within
``MAX_RESIDUAL_SIGMAS`` of the pixel noise; gravity is then refined on its sphere (tangent-space
Gauss-Newton). The start state: W with gravity along -z and the yaw of b0 (the gauge), position 0,
velocity ``R_Wb0 v0``, biases 0; its roll and pitch are good to about ``acc bias / g`` rad.
Times ns, lengths m, angles rad; ``T_sI`` maps IMU points into the static camera frame s.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import gtsam
import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix

from dcc_fg.data.vio import ImuConfig, ImuSamples, TrackFrame
from dcc_fg.vio.backend.imu import standstill_state, up_to_z_rotation
from dcc_fg.vio.backend.options import NS, FloatArray, InitialState, VioOptions
from dcc_fg.vio.backend.window import AnchorSigmas
from factors.chain import skew

log = logging.getLogger(__name__)

#: Rest test: largest deviation (m/s^2) of a sample's specific force from the window's mean (vibration of
#: a vehicle at rest, e.g. EuRoC's MAV on the ground: 2.9).
REST_ACC_SPREAD = 3.0
#: Rest test: largest mean gyro rate (rad/s; EuRoC's MAV on the ground: 0.08).
REST_GYRO = 0.1
#: Rest test: largest median track displacement over the window (normalized units, ~2 px at f = 460).
REST_FLOW = 2.0 / 460.0
#: Alignment: accepted relative error of the unconstrained gravity magnitude.
GRAVITY_TOLERANCE = 0.15
#: Alignment: accepted RMS reprojection error in pixel-noise sigmas.
MAX_RESIDUAL_SIGMAS = 4.0
#: Alignment: largest accepted 1-sigma of the gravity direction (rad) and of the velocity (m/s), from the
#: linear least squares' covariance (the fit's residual as its noise).
MAX_GRAVITY_SIGMA = float(np.radians(1.5))
MAX_VELOCITY_SIGMA = 0.2
#: Alignment: tracks used (the longest) and the fewest frames a track must span.
MAX_TRACKS = 80
MIN_TRACK_FRAMES = 4


@dataclass(frozen=True)
class Alignment:
    """Result of :func:`align_in_motion`: the start state and what it rests on."""

    state: InitialState
    gravity_b0: FloatArray
    v0_b0: FloatArray
    tracks: int
    frames: int
    residual_sigmas: float
    gravity_sigma: float
    velocity_sigma: float


def _tangent_basis(d: FloatArray) -> FloatArray:
    """(3, 2) orthonormal basis of the plane orthogonal to unit vector ``d``."""
    a = np.array([1.0, 0.0, 0.0]) if abs(d[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    b1 = np.cross(d, a)
    b1 /= np.linalg.norm(b1)
    return np.c_[b1, np.cross(d, b1)]


def preintegrate_frames(
    imu: ImuSamples, stamps_ns: list[int]
) -> tuple[list[FloatArray], list[FloatArray], list[FloatArray]]:
    """From the first stamp to each stamp, with zero biases: the body rotation ``R_j`` (b_j -> b0), the
    specific-force position increment ``dP_j`` (m, b0; gravity not included) and its derivative by the
    accelerometer bias ``d dP_j / d b_a`` (3x3, s^2; the rotations' dependence on the gyro bias is
    neglected). Midpoint samples clipped to each interval, as :func:`~.imu.integrate_imu`."""
    t = imu.t_ns
    Rk, v, p = np.eye(3), np.zeros(3), np.zeros(3)
    Jv, Jp = np.zeros((3, 3)), np.zeros((3, 3))
    R_out, P_out, J_out = [np.eye(3)], [np.zeros(3)], [np.zeros((3, 3))]
    for a_ns, b_ns in zip(stamps_ns[:-1], stamps_ns[1:], strict=True):
        i0 = max(int(np.searchsorted(t, a_ns, side="right")) - 1, 0)
        i1 = min(int(np.searchsorted(t, b_ns, side="left")), len(t) - 1)
        for i in range(i0, i1):
            lo, hi = max(int(t[i]), a_ns), min(int(t[i + 1]), b_ns)
            if hi <= lo:
                continue
            h = (hi - lo) / NS
            acc = 0.5 * (imu.acc[i] + imu.acc[i + 1])
            gyro = 0.5 * (imu.gyro[i] + imu.gyro[i + 1])
            Ra = Rk @ acc
            p = p + v * h + 0.5 * Ra * h * h
            Jp = Jp + Jv * h - 0.5 * Rk * h * h
            v = v + Ra * h
            Jv = Jv - Rk * h
            Rk = Rk @ gtsam.Rot3.Expmap(gyro * h).matrix()
        R_out.append(Rk.copy())
        P_out.append(p.copy())
        J_out.append(Jp.copy())
    return R_out, P_out, J_out


def _select_tracks(frames: list[TrackFrame]) -> dict[int, list[tuple[int, FloatArray]]]:
    """The longest static tracks (id -> [(frame index, normalized xy)]) spanning >= MIN_TRACK_FRAMES frames."""
    tracks: dict[int, list[tuple[int, FloatArray]]] = {}
    for j, f in enumerate(frames):
        for tid, xy in zip(f.static_ids.tolist(), f.static_xy, strict=True):
            tracks.setdefault(int(tid), []).append((j, np.asarray(xy, float)))
    good = {tid: obs for tid, obs in tracks.items() if len(obs) >= MIN_TRACK_FRAMES}
    best = sorted(good, key=lambda tid: -len(good[tid]))[:MAX_TRACKS]
    return {tid: good[tid] for tid in best}


def align_in_motion(
    frames: list[TrackFrame], imu: ImuSamples, cfg: ImuConfig, sigma: float
) -> tuple[Alignment | None, str]:
    """Visual-inertial alignment over ``frames`` (module docstring): the state at ``frames[0]`` and a
    reason, or None and why it was not accepted. ``sigma``: pixel noise in normalized units."""
    if len(frames) < MIN_TRACK_FRAMES:
        return None, f"{len(frames)} frames"
    t0 = frames[0].timestamp_ns
    R, dP, J_ba = preintegrate_frames(imu, [f.timestamp_ns for f in frames])
    dt = [(f.timestamp_ns - t0) / NS for f in frames]
    tracks = _select_tracks(frames)
    F = len(tracks)
    if F < 10:
        return None, f"only {F} static tracks span {MIN_TRACK_FRAMES} frames"
    T_sI = np.asarray(cfg.T_sI, float)
    R_Is = T_sI[:3, :3].T
    c_I = -R_Is @ T_sI[:3, 3]  # static camera centre in the body frame
    rows: list[tuple[int, int, FloatArray, FloatArray]] = []  # (track column, frame, M, rhs)
    for col, obs in enumerate(tracks.values()):
        for j, xy in obs:
            M = skew(np.array([xy[0], xy[1], 1.0])) @ (R[j] @ R_Is).T
            rows.append((col, j, M, M @ (dP[j] + R[j] @ c_I)))
    n = 6 + 3 * F
    A = np.zeros((3 * len(rows), n))
    y = np.zeros(3 * len(rows))
    for r, (col, j, M, rhs) in enumerate(rows):
        A[3 * r : 3 * r + 3, 0:3] = -dt[j] * M
        A[3 * r : 3 * r + 3, 3:6] = -0.5 * dt[j] ** 2 * M
        A[3 * r : 3 * r + 3, 6 + 3 * col : 9 + 3 * col] = M
        y[3 * r : 3 * r + 3] = rhs
    scale = np.linalg.norm(A, axis=0)
    scale[scale == 0] = 1.0
    x, *_, sv = np.linalg.lstsq(A / scale, y, rcond=None)
    if sv[-1] < 1e-9 * sv[0]:
        return None, "the motion does not determine velocity and gravity (ill-conditioned alignment)"
    x = x / scale
    g = x[3:6]
    if abs(np.linalg.norm(g) - cfg.gravity) > GRAVITY_TOLERANCE * cfg.gravity:
        return None, f"|g| = {np.linalg.norm(g):.2f} m/s^2 from the alignment, not {cfg.gravity:g}"
    # refine gravity on its sphere: g = |g0| (d + B w), re-normalized after each step
    d = g / np.linalg.norm(g)
    for _ in range(4):
        B = _tangent_basis(d)
        Ag = A[:, 3:6] * cfg.gravity
        A2 = np.c_[A[:, :3], Ag @ B, A[:, 6:]]
        y2 = y - Ag @ d
        s2 = np.linalg.norm(A2, axis=0)
        s2[s2 == 0] = 1.0
        zs, *_ = np.linalg.lstsq(A2 / s2, y2, rcond=None)
        z = zs / s2
        d = d + B @ z[3:5]
        d /= np.linalg.norm(d)
        x = np.r_[z[:3], cfg.gravity * d, z[5:]]
    # nonlinear refinement on the reprojection error, the accelerometer bias included (weak prior)
    obs_col = np.array([col for col, _, _, _ in rows])
    obs_j = np.array([j for _, j, _, _ in rows])
    obs_xy = np.array([xy for obs in tracks.values() for _, xy in obs])
    R_c = np.array([(R[j] @ R_Is).T for j in obs_j])  # b0 -> camera j
    t_j = np.asarray(dt)[obs_j]
    dP_o = np.array([dP[j] + R[j] @ c_I for j in obs_j])
    J_o = np.array([J_ba[j] for j in obs_j])
    d0 = x[3:6] / np.linalg.norm(x[3:6])
    B0 = _tangent_basis(d0)
    bias_sigma = 0.1  # m/s^2: a weak prior that keeps the bias from trading freely with gravity

    def unpack(z: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        d = d0 + B0 @ z[3:5]
        return z[:3], cfg.gravity * d / np.linalg.norm(d), z[5:8], z[8:].reshape(F, 3)

    def residuals(z: FloatArray) -> FloatArray:
        v0_, g_, ba_, P_ = unpack(z)
        c = v0_ * t_j[:, None] + 0.5 * g_ * (t_j**2)[:, None] + dP_o + J_o @ ba_
        p_c = np.einsum("nij,nj->ni", R_c, P_[obs_col] - c)
        z_c = np.where(np.abs(p_c[:, 2]) < 1e-6, 1e-6, p_c[:, 2])
        r = (p_c[:, :2] / z_c[:, None] - obs_xy) / sigma
        return np.r_[r.ravel(), ba_ / bias_sigma]

    n_obs = len(rows)
    sparsity = lil_matrix((2 * n_obs + 3, 8 + 3 * F), dtype=int)
    for r_i in range(n_obs):
        sparsity[2 * r_i : 2 * r_i + 2, :8] = 1
        sparsity[2 * r_i : 2 * r_i + 2, 8 + 3 * obs_col[r_i] : 11 + 3 * obs_col[r_i]] = 1
    sparsity[2 * n_obs :, 5:8] = 1
    z0 = np.r_[x[:3], 0.0, 0.0, np.zeros(3), x[6:]]
    sol = least_squares(residuals, z0, jac_sparsity=sparsity, method="trf", x_scale="jac", max_nfev=50)
    v0, g, b_a, _ = unpack(sol.x)
    r_img = sol.fun[: 2 * n_obs]
    rms = float(np.sqrt(np.mean(r_img**2) * 2))  # |error| RMS in sigmas, as before
    # 1-sigma of gravity direction (rad) and velocity (m/s): Gauss-Newton covariance at the solution
    Jd = sol.jac.toarray() if hasattr(sol.jac, "toarray") else np.asarray(sol.jac)
    cov = np.linalg.pinv(Jd.T @ Jd)
    gravity_sigma = float(np.sqrt(np.linalg.eigvalsh(cov[3:5, 3:5]).max()))
    velocity_sigma = float(np.sqrt(np.linalg.eigvalsh(cov[:3, :3]).max()))
    if not np.isfinite(rms) or rms > MAX_RESIDUAL_SIGMAS:
        return None, f"the aligned tracks reproject at {rms:.1f} pixel sigmas (> {MAX_RESIDUAL_SIGMAS:g})"
    R_Wb0 = up_to_z_rotation(-g)  # W with gravity along -z, the yaw of b0
    T = np.eye(4)
    T[:3, :3] = R_Wb0
    state = InitialState(t0, T, R_Wb0 @ v0, np.asarray(b_a, float), np.zeros(3), np.zeros(0))
    if gravity_sigma > MAX_GRAVITY_SIGMA or velocity_sigma > MAX_VELOCITY_SIGMA:
        return None, (
            f"the motion determines gravity to {np.degrees(gravity_sigma):.2f} deg and the velocity to "
            f"{velocity_sigma:.3f} m/s (1-sigma; accepted: {np.degrees(MAX_GRAVITY_SIGMA):.2f} deg, "
            f"{MAX_VELOCITY_SIGMA:g} m/s)"
        )
    return Alignment(state, g, v0, F, len(frames), rms, gravity_sigma, velocity_sigma), "aligned"


def at_rest(frames: list[TrackFrame], imu: ImuSamples, cfg: ImuConfig, window_s: float) -> tuple[bool, str]:
    """The rest test of the module docstring over the first ``window_s`` seconds from ``frames[0]``; (at
    rest, why). Without enough static tracks the IMU alone decides (as the standstill start always did)."""
    t0 = frames[0].timestamp_ns
    t1 = t0 + int(window_s * NS)
    sel = (imu.t_ns >= t0) & (imu.t_ns <= t1)
    if sel.sum() < 5:
        return False, "too few IMU samples"
    f = imu.acc[sel].mean(axis=0)
    spread = float(np.linalg.norm(imu.acc[sel] - f, axis=1).max())
    gyro = float(np.linalg.norm(imu.gyro[sel].mean(axis=0)))
    if abs(np.linalg.norm(f) - cfg.gravity) > 0.5 or spread > REST_ACC_SPREAD or gyro > REST_GYRO:
        return False, f"IMU: |mean acc| {np.linalg.norm(f):.2f} m/s^2, spread {spread:.2f}, gyro {gyro:.3f} rad/s"
    inside = [fr for fr in frames if fr.timestamp_ns <= t1]
    first, last = inside[0], inside[-1]
    _, i0, i1 = np.intersect1d(first.static_ids, last.static_ids, return_indices=True)
    if i0.size < 8:
        return True, f"IMU at rest ({i0.size} static tracks span the window: no visual check)"
    flow = float(np.median(np.linalg.norm(last.static_xy[i1] - first.static_xy[i0], axis=1)))
    if flow > REST_FLOW:
        return False, f"static tracks move {flow * 460:.1f} px (at f = 460) while the IMU looks at rest"
    return True, "IMU and static tracks at rest"


def start_sigmas(selector: StartSelector, options: VioOptions) -> AnchorSigmas | None:
    """Anchor priors for the start ``selector`` chose: None (the first keyframe's) for a standstill."""
    a = selector.alignment
    if selector.how != "motion" or a is None:
        return None
    return AnchorSigmas.motion_start(options, a.gravity_sigma, a.velocity_sigma)


class StartSelector:
    """Collects the first frames of a run and returns the start state (module docstring): ``push`` each
    frame until it returns a state at ``frames[0]``'s time; ``how`` says which start was chosen, ``sigmas``
    the anchor sigmas the state deserves (None: the first keyframe's usual priors)."""

    def __init__(self, imu: ImuSamples, cfg: ImuConfig, options: VioOptions) -> None:
        self.imu, self.cfg, self.opt = imu, cfg, options
        self.frames: list[TrackFrame] = []
        self.how = ""
        self.detail = ""
        self.rest_checked = False
        self.alignment: Alignment | None = None
        self._last_try = -1

    def push(self, frame: TrackFrame) -> InitialState | None:
        self.frames.append(frame)
        o = self.opt
        t0 = self.frames[0].timestamp_ns
        span = (frame.timestamp_ns - t0) / NS
        if not self.rest_checked and span >= o.standstill_window:
            self.rest_checked = True
            rest, why = at_rest(self.frames, self.imu, self.cfg, o.standstill_window)
            if rest and o.initialization != "motion":
                self.how, self.detail = "standstill", why
                return standstill_state(self.imu, t0, o.standstill_window, self.cfg.gravity, 0)
            self.detail = why
        if not self.rest_checked or span < o.motion_init_window:
            return None
        if len(self.frames) - self._last_try < 3 and span < o.motion_init_max_window:
            return None
        self._last_try = len(self.frames)
        alignment, why = align_in_motion(self.frames, self.imu, self.cfg, o.sigma)
        if alignment is not None:
            self.alignment = alignment
            self.how = "motion"
            self.detail = (
                f"{self.detail}; aligned {alignment.tracks} tracks over {alignment.frames} frames "
                f"({span:.2f} s), |v0| {np.linalg.norm(alignment.v0_b0):.2f} m/s, residual "
                f"{alignment.residual_sigmas:.2f} sigma"
            )
            return alignment.state
        if span >= o.motion_init_max_window:
            raise ValueError(
                f"could not start the VIO: not at rest ({self.detail}) and the visual-inertial alignment over the "
                f"first {span:.1f} s failed ({why}); start the recording with the body still for "
                f"{o.standstill_window:g} s, or give an initial state, or raise smoother.motion_init_max_window"
            )
        return None
