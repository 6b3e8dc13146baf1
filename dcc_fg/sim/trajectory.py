"""Ground truth of a simulated VIO flight: body trajectory, IMU, gimbal joints, world and tracks.

Pure numpy (no images). The rendered simulator (``dcc_fg.sim`` flight renderer) draws its images
from the same :class:`FlightTruth` and :class:`World`, so the tracks-level simulator here and the
image pipeline share one truth.

Frames and units (docs/architecture.md): ``W`` world (z up, gravity along -z), ``I`` IMU/body
(x forward, y left, z up), ``s`` static camera, ``d`` gimbal camera (x right, y down, z optical
axis). ``T_ab`` maps points from b into a. Times in int64 nanoseconds, metres, radians.

API
---
* :class:`FlightConfig` -- the pattern: ``loops`` rounded-rectangle loops of ``size`` (m) at
  ``altitude`` (m), flown in ``duration`` (s) after ``hover`` seconds of standstill; the default is
  the paper's pattern (two loops of a 30 m x 15 m rounded rectangle, ~180 m, 90 s);
  :meth:`FlightConfig.short` is a one-loop (16 m x 8 m, ~48 m) flight of a given duration for tests.
* :class:`BodyTrajectory` -- ``evaluate(t_s) -> BodyState`` with analytic position, velocity,
  acceleration (world), rotation R_WI and body angular rate, so synthesized IMU is exact before noise.
* :class:`JointMotion` -- gimbal joint angles ``theta(t)`` (L,) and rates: a mid position, slow
  sinusoids and slews of +-``slew_amplitude`` with a cosine velocity profile whose peak rate
  (sinusoid included) is at most ``max_rate`` (default 60 deg/s); independent of the body.
* :class:`World` -- a box room: textured ground plane z = 0 over ``[x_min, x_max] x [y_min, y_max]``
  and four vertical walls (inner faces) up to ``wall_height``; :meth:`World.planes` lists each
  surface as (origin, u axis, v axis, extent_u, extent_v) for the renderer;
  :meth:`World.sample_points` draws landmarks uniformly on them. The room is convex and the
  trajectory stays inside it, so nothing occludes a landmark from a camera inside the room.
* :func:`chain_motion_variant` -- the motion of a further gimbal chain (slot k >= 1) of a cluster:
  the primary motion with its own sinusoids and slews.
* :func:`simulate_flight(config, imu, joints, seed, extra_joints=...) -> FlightTruth` -- truth at the
  IMU rate (``t_ns``, ``T_WI`` (N,4,4), ``v_W``, ``acc_bias``, ``gyro_bias``, ``theta`` (N,L), and
  ``extra_theta`` {chain: (N,L)} of further chains moving on their own), the noisy
  IMU (:class:`~dcc_fg.data.vio.ImuSamples`: white noise + bias random walk from
  :class:`~dcc_fg.data.vio.ImuConfig`, ADIS16448 defaults) and camera frame times
  ``frame_t_ns`` (``camera_rate`` Hz, on IMU sample times).
* :func:`default_static_mount` -- ``T_sI`` of the static camera (forward, tilted down).
* :func:`simulate_tracks(truth, world, calibration, T_sI, ...) -> list[TrackFrame]` -- projects
  world landmarks into the static and gimbal cameras (``p_d = T_ds(theta) T_sI T_IW p_W``), keeps
  those in front, within range and inside the image, adds pixel noise and returns undistorted
  normalized coordinates. A landmark keeps one id while it stays visible in either camera (a
  new id when it reappears after leaving both views), so ids are shared between the cameras.
* :func:`simulate_camera_tracks` -- the same with further cameras of an N-camera cluster
  (:class:`~dcc_fg.data.cameras.RunCamera`, observations in ``TrackFrame.extra``); with none it is
  :func:`simulate_tracks` bit for bit. A camera on a further chain follows that chain's angles.
* :func:`truth_at` / :func:`chain_theta_at` -- the truth (body pose, primary / further chains' joint
  angles) at any time within the flight, e.g. a camera's exposure times.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from dcc_fg.data.cameras import RunCamera
from dcc_fg.data.vio import CameraTracks, ImuConfig, ImuSamples, TrackFrame
from dcc_fg.model import GimbalCalibration
from dcc_fg.sim.calibration_scene import true_kinematics
from factors import chain
from factors.camera import CameraModel

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
DEG = np.pi / 180.0
NS = 1_000_000_000


# --------------------------------------------------------------------------- body trajectory
@dataclass(frozen=True)
class FlightConfig:
    """Flight pattern. ``size`` = (length along x, width along y) of the loop (m)."""

    duration: float = 90.0
    loops: int = 2
    size: tuple[float, float] = (30.0, 15.0)
    altitude: float = 3.0
    hover: float = 1.0
    ramp: float = 3.0
    corner_sharpness: float = 3.0
    vertical_amplitude: float = 0.4
    roll_amplitude: float = 4.0 * DEG
    pitch_amplitude: float = 4.0 * DEG
    yaw_wiggle: float = 6.0 * DEG
    camera_rate: float = 20.0

    @staticmethod
    def short(duration: float = 30.0) -> FlightConfig:
        """One smaller loop (16 m x 8 m, ~48 m) in ``duration`` seconds."""
        return FlightConfig(duration=duration, loops=1, size=(16.0, 8.0), altitude=2.5)

    def __post_init__(self) -> None:
        if self.duration <= self.hover + self.ramp:
            raise ValueError(f"duration {self.duration} s must exceed hover + ramp = {self.hover + self.ramp} s")
        if self.loops < 1:
            raise ValueError("loops must be >= 1")


@dataclass(frozen=True)
class BodyState:
    """Body state at times t (N,): p_W (N,3), v_W, a_W (m/s^2, world), R_WI (N,3,3), omega_I (rad/s, body)."""

    p_W: FloatArray
    v_W: FloatArray
    a_W: FloatArray
    R_WI: FloatArray
    omega_I: FloatArray

    def T_WI(self) -> FloatArray:
        T = np.zeros((self.p_W.shape[0], 4, 4))
        T[:, :3, :3] = self.R_WI
        T[:, :3, 3] = self.p_W
        T[:, 3, 3] = 1.0
        return T


def rotation_zyx(roll: FloatArray, pitch: FloatArray, yaw: FloatArray) -> FloatArray:
    """R = Rz(yaw) Ry(pitch) Rx(roll) (intrinsic z-y-x Euler angles, rad), vectorised: shape ``roll.shape + (3, 3)``."""
    angles = np.stack(np.broadcast_arrays(yaw, pitch, roll), axis=-1)
    R = Rotation.from_euler("ZYX", angles.reshape(-1, 3)).as_matrix()
    return R.reshape(angles.shape[:-1] + (3, 3))


class BodyTrajectory:
    """Smooth rounded-rectangle loops, analytic to second order.

    The horizontal path is ``x = A g(cos phi)``, ``y = B g(sin phi)`` with
    ``g(u) = tanh(k u) / tanh(k)`` (a rectangle with rounded corners, sharper for larger k),
    shifted so the flight starts at (0, 0, altitude) heading +x. Altitude, roll, pitch and a yaw
    wiggle around the path heading are sinusoids of the path parameter phi, so every quantity is
    a function of phi(t) alone; phi is constant during the hover, then its rate ramps up with a
    smoothstep and stays constant. Hence ``p(t) = P(phi)``, ``v = P' phidot``,
    ``a = P'' phidot^2 + P' phiddot``.
    """

    def __init__(self, config: FlightConfig) -> None:
        self.cfg = config
        self.A = config.size[0] / 2.0
        self.B = config.size[1] / 2.0
        self.k = config.corner_sharpness
        self.phi0 = -np.pi / 2.0
        moving = config.duration - config.hover - config.ramp / 2.0
        self.omega = 2.0 * np.pi * config.loops / moving
        self.offset = np.array([0.0, self.B, 0.0])  # P(phi0) = (0, -B): shift to the origin

    # phi(t) and its derivatives
    def _phi(self, t: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        c = self.cfg
        tau = np.clip((t - c.hover) / c.ramp, 0.0, 1.0)
        in_ramp = (t > c.hover) & (t < c.hover + c.ramp)
        after = t >= c.hover + c.ramp
        phi_ramp = self.omega * c.ramp * (tau**3 - 0.5 * tau**4)
        phi = np.where(after, self.omega * (c.ramp / 2.0 + (t - c.hover - c.ramp)), phi_ramp)
        phid = self.omega * (3 * tau**2 - 2 * tau**3)
        phidd = np.where(in_ramp, self.omega * 6 * tau * (1 - tau) / c.ramp, 0.0)
        return self.phi0 + phi, phid, phidd

    def _g(self, u: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        k = self.k
        th = np.tanh(k * u)
        sech2 = 1.0 - th**2
        n = np.tanh(k)
        return th / n, k * sech2 / n, -2.0 * k * k * sech2 * th / n

    def _path(self, phi: FloatArray) -> tuple[FloatArray, ...]:
        """P, P', P'' (N,3) and roll, pitch, yaw with their phi-derivatives."""
        cfg = self.cfg
        c, s = np.cos(phi), np.sin(phi)
        gc, gc1, gc2 = self._g(c)
        gs, gs1, gs2 = self._g(s)
        x, x1, x2 = self.A * gc, -self.A * gc1 * s, self.A * (gc2 * s * s - gc1 * c)
        y, y1, y2 = self.B * gs, self.B * gs1 * c, self.B * (gs2 * c * c - gs1 * s)
        u = phi - self.phi0
        m_z, m_r, m_p, m_y = 3.0, 5.0, 4.0, 7.0
        az = cfg.vertical_amplitude
        z, z1, z2 = cfg.altitude + az * np.sin(m_z * u), az * m_z * np.cos(m_z * u), -az * m_z**2 * np.sin(m_z * u)
        P = np.stack([x, y, z], axis=-1) + self.offset
        P1 = np.stack([x1, y1, z1], axis=-1)
        P2 = np.stack([x2, y2, z2], axis=-1)
        heading = np.unwrap(np.arctan2(y1, x1)) if phi.size > 1 else np.arctan2(y1, x1)
        heading1 = (x1 * y2 - y1 * x2) / (x1**2 + y1**2)
        roll = cfg.roll_amplitude * np.sin(m_r * u)
        roll1 = cfg.roll_amplitude * m_r * np.cos(m_r * u)
        pitch = cfg.pitch_amplitude * np.sin(m_p * u + 0.7)
        pitch1 = cfg.pitch_amplitude * m_p * np.cos(m_p * u + 0.7)
        yaw = heading + cfg.yaw_wiggle * np.sin(m_y * u)
        yaw1 = heading1 + cfg.yaw_wiggle * m_y * np.cos(m_y * u)
        return P, P1, P2, roll, roll1, pitch, pitch1, yaw, yaw1

    def evaluate(self, t_s: FloatArray | float) -> BodyState:
        """Analytic state at times ``t_s`` (seconds from the start of the flight)."""
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        phi, phid, phidd = self._phi(t)
        P, P1, P2, r, r1, p, p1, y, y1 = self._path(phi)
        v = P1 * phid[:, None]
        a = P2 * (phid**2)[:, None] + P1 * phidd[:, None]
        rd, pd, yd = r1 * phid, p1 * phid, y1 * phid
        # body rate of R = Rz(yaw) Ry(pitch) Rx(roll)
        omega = np.stack(
            [
                rd - np.sin(p) * yd,
                np.cos(r) * pd + np.sin(r) * np.cos(p) * yd,
                -np.sin(r) * pd + np.cos(r) * np.cos(p) * yd,
            ],
            axis=-1,
        )
        return BodyState(p_W=P, v_W=v, a_W=a, R_WI=rotation_zyx(r, p, y), omega_I=omega)

    def length(self, n: int = 20000) -> float:
        """Distance travelled over the whole flight (m)."""
        t = np.linspace(0.0, self.cfg.duration, n)
        p = self.evaluate(t).p_W
        return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())


# --------------------------------------------------------------------------- gimbal joints
@dataclass(frozen=True)
class JointMotion:
    """Joint angles theta(t) (L,) = mid + sinusoid + slew offsets, independent of the body.

    Slews move the offset through ``slew_sequence`` (multiples of ``slew_amplitude``), one slew
    every ``slew_period`` seconds (joint l starts ``l * slew_period / (2 L)`` later). The slew
    velocity profile is a raised cosine; its duration is chosen so that the peak rate plus the
    sinusoid's peak rate equals ``max_rate``. Joint l's sinusoid has the phase ``0.5 l + sin_phase``
    (rad) at t = 0.
    """

    mid: tuple[float, ...] = (90.0 * DEG, 0.0)
    sin_amplitude: float = 6.0 * DEG
    sin_frequency: tuple[float, ...] = (0.13, 0.17)
    slew_amplitude: float = 30.0 * DEG
    max_rate: float = 60.0 * DEG
    slew_period: float = 8.0
    first_slew: float = 4.0
    slew_sequence: tuple[float, ...] = (1.0, -1.0, 0.0)
    sin_phase: float = 0.0

    @property
    def n_joints(self) -> int:
        return len(self.mid)

    def _slews(self, joint: int, duration: float) -> list[tuple[float, float, float]]:
        """(t_start, t_duration, delta) of each slew of ``joint`` before ``duration``."""
        sin_rate = self.sin_amplitude * 2.0 * np.pi * max(self.sin_frequency)
        rate = self.max_rate - sin_rate
        if rate <= 0:
            raise ValueError("max_rate must exceed the sinusoid's peak rate")
        out = []
        t = self.first_slew + joint * self.slew_period / (2.0 * self.n_joints)
        level, k = 0.0, 0
        while t < duration:
            target = self.slew_sequence[k % len(self.slew_sequence)] * self.slew_amplitude
            delta = target - level
            T = np.pi * abs(delta) / (2.0 * rate) if delta else 0.0
            if delta:
                out.append((t, T, delta))
            level, k = target, k + 1
            t += self.slew_period
        return out

    def evaluate(self, t_s: FloatArray | float, duration: float = 1e9) -> tuple[FloatArray, FloatArray]:
        """theta (N, L) and theta_dot (N, L) at times ``t_s`` (s)."""
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        L = self.n_joints
        th = np.zeros((t.size, L))
        thd = np.zeros((t.size, L))
        for j in range(L):
            f = self.sin_frequency[j % len(self.sin_frequency)]
            w = 2 * np.pi * f
            phase = 0.5 * j + self.sin_phase
            th[:, j] = self.mid[j] + self.sin_amplitude * np.sin(w * t + phase)
            thd[:, j] = self.sin_amplitude * w * np.cos(w * t + phase)
            for t0, T, delta in self._slews(j, min(duration, float(t.max(initial=0.0)) + 1.0)):
                u = np.clip((t - t0) / T, 0.0, 1.0)
                th[:, j] += delta * 0.5 * (1.0 - np.cos(np.pi * u))
                inside = (t > t0) & (t < t0 + T)
                thd[:, j] += np.where(inside, delta * 0.5 * np.pi / T * np.sin(np.pi * u), 0.0)
        return th, thd

    def slew_windows(self, duration: float) -> list[tuple[int, float, float]]:
        """(joint, t_start, t_end) of every slew before ``duration`` seconds."""
        return [(j, t0, t0 + T) for j in range(self.n_joints) for t0, T, _ in self._slews(j, duration)]


def chain_motion_variant(joints: JointMotion, k: int) -> JointMotion:
    """The joint motion of the ``k``-th further chain (``k`` >= 1, its slot) of a flight whose primary
    chain moves with ``joints``: the same mid position, amplitudes and rate limit (a locked gimbal's
    variant is locked too), but its own sinusoids (frequencies swapped between the joints and lowered
    by a factor 1 + 0.15 k, phase shifted by 1.9 k rad) and its own slews (the slew sequence mirrored
    for odd ``k``, the first slew ``(0.5 + 0.1 (k - 1)) slew_period`` later: for ``k`` = 1 and the
    default timing, in the pauses between the primary's slews), so every chain moves on its own while
    staying in the primary's range.
    """
    if k < 1:
        raise ValueError(f"further chains are numbered from 1, got {k}")
    slews = tuple(0.0 - x for x in joints.slew_sequence) if k % 2 else joints.slew_sequence
    return replace(
        joints,
        sin_frequency=tuple(f / (1.0 + 0.15 * k) for f in reversed(joints.sin_frequency)),
        sin_phase=joints.sin_phase + 1.9 * k,
        first_slew=joints.first_slew + joints.slew_period * (0.5 + 0.1 * (k - 1)),
        slew_sequence=slews,
    )


def locked_gimbal(mid: tuple[float, ...] | None = None) -> JointMotion:
    """A gimbal held at ``mid`` (rad; default :class:`JointMotion`'s mid position) for ``scc`` flights."""
    return JointMotion(mid=mid if mid is not None else JointMotion().mid, sin_amplitude=0.0, slew_amplitude=0.0)


# --------------------------------------------------------------------------- world
@dataclass(frozen=True)
class World:
    """A box room: ground plane z = 0 and four inward-facing walls (z in [0, wall_height])."""

    x_range: tuple[float, float]
    y_range: tuple[float, float]
    wall_height: float = 8.0

    @staticmethod
    def around(config: FlightConfig, margin: float = 6.0) -> World:
        """The room enclosing the flight pattern with ``margin`` metres of clearance."""
        A, B = config.size[0] / 2.0, config.size[1] / 2.0
        return World((-A - margin, A + margin), (-margin, 2 * B + margin))

    def planes(self) -> list[tuple[str, FloatArray, FloatArray, FloatArray, float, float]]:
        """(name, origin, unit u, unit v, extent_u, extent_v): points origin + a u + b v, a in
        [0, extent_u], b in [0, extent_v]; u x v is the inward (visible side) normal."""
        x0, x1 = self.x_range
        y0, y1 = self.y_range
        h = self.wall_height
        ez = np.array([0.0, 0.0, 1.0])
        return [
            ("ground", np.array([x0, y0, 0.0]), np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), x1 - x0, y1 - y0),
            ("wall_south", np.array([x0, y0, 0.0]), ez, np.array([1.0, 0, 0]), h, x1 - x0),
            ("wall_east", np.array([x1, y0, 0.0]), ez, np.array([0, 1.0, 0]), h, y1 - y0),
            ("wall_north", np.array([x1, y1, 0.0]), ez, np.array([-1.0, 0, 0]), h, x1 - x0),
            ("wall_west", np.array([x0, y1, 0.0]), ez, np.array([0, -1.0, 0]), h, y1 - y0),
        ]

    def sample_points(self, density: float, rng: np.random.Generator) -> FloatArray:
        """Landmarks (N, 3) uniform on every surface, ``density`` points per square metre."""
        pts = []
        for _, o, u, v, eu, ev in self.planes():
            n = rng.poisson(density * eu * ev)
            ab = rng.uniform(size=(n, 2)) * [eu, ev]
            pts.append(o + ab[:, :1] * u + ab[:, 1:] * v)
        return np.vstack(pts)


# --------------------------------------------------------------------------- flight truth + IMU
@dataclass(frozen=True)
class FlightTruth:
    """Ground truth of a flight at the IMU rate, the noisy IMU and the camera frame times.

    ``t_ns`` (N,) int64 from 0; ``T_WI`` (N,4,4); ``v_W`` (N,3) m/s; ``acc_bias`` / ``gyro_bias``
    (N,3) m/s^2, rad/s; ``theta`` (N,L) rad; ``imu`` the noisy measurements at ``t_ns``;
    ``frame_t_ns`` camera frame times (a subset of ``t_ns``); ``distance`` metres flown;
    ``joints`` the primary chain's motion (``theta``). A flight with further gimbal chains moving on
    their own (an N-camera cluster, slots 1, 2, ... of :func:`dcc_fg.data.cameras.run_chains`) also
    holds, per chain name, their joint angles ``extra_theta[chain]`` (N, L_chain) rad at ``t_ns`` and
    their motions ``extra_joints[chain]``; both are empty for a flight with one gimbal.
    """

    t_ns: IntArray
    T_WI: FloatArray
    v_W: FloatArray
    acc_bias: FloatArray
    gyro_bias: FloatArray
    theta: FloatArray
    imu: ImuSamples
    frame_t_ns: IntArray
    config: FlightConfig
    joints: JointMotion
    distance: float
    gravity_W: FloatArray = field(default_factory=lambda: np.array([0.0, 0.0, -9.81]))
    extra_theta: dict[str, FloatArray] = field(default_factory=dict)
    extra_joints: dict[str, JointMotion] = field(default_factory=dict)

    def chain_theta(self, name: str) -> FloatArray:
        """Joint angles (N, L) rad at ``t_ns`` of the further chain ``name``; ValueError if the flight
        does not move it."""
        if name not in self.extra_theta:
            moved = ", ".join(self.extra_theta) or "none"
            raise ValueError(f"the flight does not move chain {name!r} (further chains moved: {moved})")
        return self.extra_theta[name]

    def index_of(self, t_ns: IntArray | int) -> IntArray:
        """Indices of IMU-rate truth samples at the given times (must be sample times)."""
        idx = np.searchsorted(self.t_ns, np.atleast_1d(t_ns))
        if np.any(idx >= self.t_ns.size) or np.any(self.t_ns[np.minimum(idx, self.t_ns.size - 1)] != t_ns):
            raise ValueError("times are not IMU sample times of this flight")
        return idx


def simulate_flight(
    config: FlightConfig | None = None,
    imu: ImuConfig | None = None,
    joints: JointMotion | None = None,
    seed: int = 0,
    initial_acc_bias: FloatArray | None = None,
    initial_gyro_bias: FloatArray | None = None,
    noise: bool = True,
    extra_joints: Mapping[str, JointMotion] | None = None,
) -> FlightTruth:
    """Sample the trajectory at the IMU rate and synthesize the IMU.

    ``joints`` moves the primary chain (``theta``); ``extra_joints`` (chain name -> motion) the
    further chains of a cluster, each on its own (``extra_theta``; e.g. :func:`chain_motion_variant`).
    They draw nothing from the generator: every other field is the same with or without them.

    ``acc = R_WI^T (a_W - g_W) + b_a + n_a``, ``gyro = omega_I + b_g + n_g`` with discrete white
    noise of standard deviation ``density / sqrt(dt)`` and biases following a random walk of
    ``random_walk * sqrt(dt)`` per sample. ``noise=False`` gives exact measurements (constant biases).
    """
    config = config or FlightConfig()
    imu = imu or ImuConfig()
    joints = joints or JointMotion()
    rng = np.random.default_rng(seed)
    dt = 1.0 / imu.rate_hz
    n = int(np.floor(config.duration * imu.rate_hz)) + 1
    t_ns = np.round(np.arange(n) * dt * NS).astype(np.int64)
    t = t_ns / NS
    traj = BodyTrajectory(config)
    st = traj.evaluate(t)
    g_W = np.array([0.0, 0.0, -imu.gravity])
    b_a0 = np.array([0.05, -0.08, 0.06]) if initial_acc_bias is None else np.asarray(initial_acc_bias, float)
    b_g0 = np.array([0.002, -0.003, 0.0015]) if initial_gyro_bias is None else np.asarray(initial_gyro_bias, float)
    if noise:
        b_a = b_a0 + np.cumsum(rng.normal(size=(n, 3)) * imu.accelerometer_random_walk * np.sqrt(dt), axis=0)
        b_g = b_g0 + np.cumsum(rng.normal(size=(n, 3)) * imu.gyroscope_random_walk * np.sqrt(dt), axis=0)
        n_a = rng.normal(size=(n, 3)) * imu.accelerometer_noise_density / np.sqrt(dt)
        n_g = rng.normal(size=(n, 3)) * imu.gyroscope_noise_density / np.sqrt(dt)
    else:
        b_a, b_g = np.tile(b_a0, (n, 1)), np.tile(b_g0, (n, 1))
        n_a = n_g = np.zeros((n, 3))
    f_I = np.einsum("nji,nj->ni", st.R_WI, st.a_W - g_W)
    samples = ImuSamples(t_ns=t_ns, acc=f_I + b_a + n_a, gyro=st.omega_I + b_g + n_g)
    theta, _ = joints.evaluate(t, config.duration)
    step = int(round(imu.rate_hz / config.camera_rate))
    frame_t_ns = t_ns[::step]
    motions = dict(extra_joints or {})
    extra_theta = {name: m.evaluate(t, config.duration)[0] for name, m in motions.items()}
    return FlightTruth(
        t_ns=t_ns,
        T_WI=st.T_WI(),
        v_W=st.v_W,
        acc_bias=b_a,
        gyro_bias=b_g,
        theta=theta,
        imu=samples,
        frame_t_ns=frame_t_ns,
        config=config,
        joints=joints,
        distance=traj.length(),
        gravity_W=g_W,
        extra_theta=extra_theta,
        extra_joints=motions,
    )


# --------------------------------------------------------------------------- cameras and tracks
def default_static_mount(
    tilt_down: float = 20.0 * DEG, t_Is: tuple[float, float, float] = (0.10, 0.0, 0.05)
) -> FloatArray:
    """``T_sI`` of a forward-looking static camera tilted down by ``tilt_down`` (rad).

    Camera axes in the body: z (optical) = forward tilted down, x = -y_body (right), y = z x x.
    """
    b = tilt_down
    R_Is = np.column_stack([[0.0, -1.0, 0.0], [-np.sin(b), 0.0, -np.cos(b)], [np.cos(b), 0.0, -np.sin(b)]])
    T_Is = np.eye(4)
    T_Is[:3, :3] = R_Is
    T_Is[:3, 3] = t_Is
    return chain.inv_se3(T_Is)


def flight_calibration() -> GimbalCalibration:
    """The 2-joint gimbal of the calibration simulator (joint 1 roll centred at 90 deg, joint 2 pitch)."""
    return true_kinematics(2)


def visible_points(
    camera: CameraModel, p_c: FloatArray, max_range: float, margin: float
) -> tuple[NDArray[np.bool_], FloatArray]:
    """Which points ``p_c`` (N, 3, camera frame, m) the camera sees: in front (> 0.3 m), closer than
    ``max_range`` m, inside the image by ``margin`` px, within a sane angle; and their pixels."""
    front = p_c[:, 2] > 0.3
    in_range = np.linalg.norm(p_c, axis=1) < max_range
    uv, _ = camera.project(p_c, jacobian=False)
    ok = front & in_range & camera.in_image(uv, margin)
    # strong distortion folds far off-axis points back into the image: require a sane angle
    xy = p_c[:, :2] / np.maximum(p_c[:, 2:3], 1e-9)
    ok &= np.abs(xy).max(axis=1) < 1.5
    return ok, uv


class TrackIds:
    """Track id of every landmark (-1 when unseen): kept while either camera sees the landmark in
    consecutive frames, a new id when it is seen again after a frame without it."""

    def __init__(self, n_landmarks: int) -> None:
        self.ids = np.full(n_landmarks, -1, dtype=np.int64)
        self.next_id = 0

    def update(self, seen: NDArray[np.bool_]) -> IntArray:
        """Ids after a frame in which the landmarks ``seen`` (N,) were seen."""
        self.ids[~seen] = -1
        new = seen & (self.ids < 0)
        self.ids[new] = self.next_id + np.arange(int(new.sum()))
        self.next_id += int(new.sum())
        return self.ids


def noisy_normalized(
    p_c: FloatArray, vis: NDArray[np.bool_], camera: CameraModel, pixel_sigma: float, rng: np.random.Generator
) -> FloatArray:
    """Normalized coordinates (n, 2) of the visible points ``p_c[vis]`` (camera frame) with N(0,
    ``pixel_sigma``) pixel noise converted by the camera's focal lengths."""
    xy = p_c[vis, :2] / p_c[vis, 2:3]
    fx, fy = camera.intrinsics[0], camera.intrinsics[1]
    return xy + rng.normal(size=xy.shape) * pixel_sigma / np.array([fx, fy])


def simulate_tracks(
    truth: FlightTruth,
    landmarks_W: FloatArray,
    calibration: GimbalCalibration,
    T_sI: FloatArray,
    pixel_sigma: float = 0.5,
    seed: int = 1,
    max_range: float = 40.0,
    margin_px: float = 5.0,
    dynamic: bool = True,
    theta: FloatArray | None = None,
) -> list[TrackFrame]:
    """Noisy normalized observations of ``landmarks_W`` at every camera frame of ``truth``.

    ``theta`` (F, L) overrides the joint angles at the frames (e.g. a locked gimbal); by default
    the truth's joint angles are used. Noise: N(0, pixel_sigma) per pixel axis, converted to
    normalized coordinates with the camera's focal lengths (distortion is not re-applied, as a
    front end that undistorts would report). ``dynamic=False`` omits the gimbal camera.
    """
    return simulate_camera_tracks(
        truth, landmarks_W, calibration, T_sI, (), pixel_sigma, seed, max_range, margin_px, dynamic, theta
    )


def simulate_camera_tracks(
    truth: FlightTruth,
    landmarks_W: FloatArray,
    calibration: GimbalCalibration,
    T_sI: FloatArray,
    extra: Sequence[RunCamera],
    pixel_sigma: float = 0.5,
    seed: int = 1,
    max_range: float = 40.0,
    margin_px: float = 5.0,
    dynamic: bool = True,
    theta: FloatArray | None = None,
) -> list[TrackFrame]:
    """:func:`simulate_tracks` with the further cameras ``extra`` of an N-camera run (run index >= 2).

    Camera c sees ``p_c = T_cs T_sI T_IW p_W`` with ``T_cs = c.T_cs_at(theta)``: constant for a rigid
    camera; for a camera on the primary chain (``slot`` 0) at the primary joint angles of the frame
    (``theta`` if given, else the truth's); for a camera on a further chain (``slot`` >= 1) at that
    chain's true angles ``truth.extra_theta[c.chain]`` (ValueError if the flight does not move it,
    whatever ``theta``). Its observations
    go into ``TrackFrame.extra`` (one :class:`~dcc_fg.data.vio.CameraTracks` per camera, in the order
    of ``extra``). A landmark keeps its id while any camera sees it in consecutive frames. The static
    and gimbal cameras draw their noise as :func:`simulate_tracks` does (generator ``seed``), the
    further cameras from a generator of their own (``[seed, 17]``): the static and gimbal
    coordinates are :func:`simulate_tracks`' bit for bit (only the ids differ where a further camera
    sees other landmarks), and with ``extra = ()`` the whole output is. ValueError when two cameras of
    ``extra`` have the same run index.
    """
    indices = [c.index for c in extra]
    if len(set(indices)) != len(indices):
        raise ValueError(f"run indices of the further cameras must be distinct, got {indices}")
    cam_s, cam_d = calibration.static_camera, calibration.dynamic_camera
    if cam_s is None or (dynamic and cam_d is None):
        raise ValueError("calibration must carry the static (and dynamic) camera intrinsics")
    rng = np.random.default_rng(seed)
    rng_extra = np.random.default_rng([seed, 17]) if extra else rng
    idx = truth.index_of(truth.frame_t_ns)
    thetas = truth.theta[idx] if theta is None else np.asarray(theta, float).reshape(idx.size, -1)
    chain_thetas = [
        truth.chain_theta(cam.chain)[idx] if cam.on_gimbal and cam.slot >= 1 and cam.chain is not None else None
        for cam in extra
    ]
    P_h = np.hstack([landmarks_W, np.ones((landmarks_W.shape[0], 1))])
    tracks = TrackIds(landmarks_W.shape[0])
    frames = []
    for f, i in enumerate(idx):
        T_sW = T_sI @ chain.inv_se3(truth.T_WI[i])
        p_s = P_h @ T_sW[:3].T
        vis_s, _ = visible_points(cam_s, p_s, max_range, margin_px)
        vis_d = np.zeros_like(vis_s)
        p_d = np.zeros_like(p_s)
        if dynamic:
            T_dW = calibration.T_ds(thetas[f]) @ T_sW
            p_d = P_h @ T_dW[:3].T
            vis_d, _ = visible_points(cam_d, p_d, max_range, margin_px)
        seen = vis_s | vis_d
        p_extra, vis_extra = [], []
        for cam, th_c in zip(extra, chain_thetas, strict=True):
            p_c = P_h @ (cam.T_cs_at(thetas[f] if th_c is None else th_c[f]) @ T_sW)[:3].T
            vis_c, _ = visible_points(cam.model, p_c, max_range, margin_px)
            p_extra.append(p_c)
            vis_extra.append(vis_c)
            seen |= vis_c
        track_id = tracks.update(seen)
        s_ids, s_xy = track_id[vis_s].copy(), noisy_normalized(p_s, vis_s, cam_s, pixel_sigma, rng)
        if dynamic:
            d_ids, d_xy = track_id[vis_d].copy(), noisy_normalized(p_d, vis_d, cam_d, pixel_sigma, rng)
        else:
            d_ids, d_xy = np.zeros(0, dtype=np.int64), np.zeros((0, 2))
        more = tuple(
            CameraTracks(
                cam.index,
                track_id[vis_c].copy(),
                noisy_normalized(p_c, vis_c, cam.model, pixel_sigma, rng_extra),
            )
            for cam, p_c, vis_c in zip(extra, p_extra, vis_extra, strict=True)
        )
        frames.append(TrackFrame(int(truth.frame_t_ns[f]), s_ids, s_xy, d_ids, d_xy, extra=more))
    return frames


def truth_at(truth: FlightTruth, t_ns: IntArray) -> tuple[FloatArray, FloatArray]:
    """Body pose ``T_WI`` (N, 4, 4) and joint angles ``theta`` (N, L, rad) at times ``t_ns`` (N,) ns
    from the start of the flight, e.g. a camera's true exposure times.

    At IMU sample times these are the stored truth samples (bit-identical to ``truth.T_WI`` and
    ``truth.theta``); between them the analytic trajectory (:class:`BodyTrajectory`) and joint
    motion (:class:`JointMotion`) the samples were made from. Times must lie within the flight.
    """
    t_ns = np.atleast_1d(np.asarray(t_ns, dtype=np.int64))
    if t_ns.size and (t_ns.min() < truth.t_ns[0] or t_ns.max() > truth.t_ns[-1]):
        raise ValueError("times outside the flight")
    idx = np.minimum(np.searchsorted(truth.t_ns, t_ns), truth.t_ns.size - 1)
    on = truth.t_ns[idx] == t_ns
    T_WI = np.empty((t_ns.size, 4, 4))
    theta = np.empty((t_ns.size, truth.theta.shape[1]))
    T_WI[on], theta[on] = truth.T_WI[idx[on]], truth.theta[idx[on]]
    off = ~on
    if np.any(off):
        t = t_ns[off] / NS
        T_WI[off] = BodyTrajectory(truth.config).evaluate(t).T_WI()
        theta[off] = truth.joints.evaluate(t, truth.config.duration)[0]
    return T_WI, theta


def chain_theta_at(truth: FlightTruth, t_ns: IntArray) -> dict[str, FloatArray]:
    """Joint angles (N, L) rad of every further chain of ``truth`` (``extra_theta``) at times ``t_ns``
    (N,) ns from the start of the flight, like :func:`truth_at` for the primary chain: the stored
    samples at IMU sample times (bit-identical), the chain's analytic motion between them. An empty
    dict for a flight with one gimbal."""
    t_ns = np.atleast_1d(np.asarray(t_ns, dtype=np.int64))
    if t_ns.size and (t_ns.min() < truth.t_ns[0] or t_ns.max() > truth.t_ns[-1]):
        raise ValueError("times outside the flight")
    idx = np.minimum(np.searchsorted(truth.t_ns, t_ns), truth.t_ns.size - 1)
    on = truth.t_ns[idx] == t_ns
    off = ~on
    out = {}
    for name, samples in truth.extra_theta.items():
        theta = np.empty((t_ns.size, samples.shape[1]))
        theta[on] = samples[idx[on]]
        if np.any(off):
            theta[off] = truth.extra_joints[name].evaluate(t_ns[off] / NS, truth.config.duration)[0]
        out[name] = theta
    return out
