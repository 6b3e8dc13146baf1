"""Joint angles of the further gimbal chains of a ``dcc`` run (a cluster with two or more gimbals).

The primary chain's joint angles are ``t(k)`` (:mod:`.keys`); every further chain with joints that
carries a camera of the run (:func:`dcc_fg.data.cameras.run_chains`, ``slot`` 1, 2, ...) has a state of
its own per keyframe, ``u(64 k + slot)`` (Vector L_slot, rad), handled the same way as ``t(k)``: a prior
where a window starts (first keyframe, a new segment, a restart), a random walk between keyframes
(``theta_random_walk`` rad/sqrt(s)), and as starting value at each keyframe the fit of the chain's first
camera's observations of known landmarks with the body pose held (:func:`~.joints.fit_joint_angles_to_landmarks`).
The cameras on a further chain project onto their auxiliary poses ``e(k)`` tied to ``u(k)``
(:mod:`.cameras`). Angles in rad, times in ns.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import gtsam
import numpy as np

from dcc_fg.data.cameras import RunCamera
from dcc_fg.data.vio import TrackFrame
from dcc_fg.model import GimbalCalibration
from dcc_fg.vio.backend.joints import fit_joint_angles_to_landmarks
from dcc_fg.vio.backend.keys import MAX_CAMERAS, chain_theta_key
from dcc_fg.vio.backend.landmarks import LandmarkMap
from dcc_fg.vio.backend.options import FloatArray, VioOptions
from dcc_fg.vio.joint_init import fit_joint_angles
from factors.calibration import RobustLoss
from factors.vio import joint_random_walk_factor


@dataclass(frozen=True)
class FurtherChain:
    """One further chain of the run: its name, slot, joint count and the camera that measures it
    (the first of the run's cameras on it)."""

    name: str
    slot: int
    n_joints: int
    camera: RunCamera


def further_chains(cameras: Sequence[RunCamera]) -> list[FurtherChain]:
    """The further chains (slot >= 1) the run's cameras sit on, in slot order."""
    out: dict[int, FurtherChain] = {}
    for c in cameras:
        if c.on_gimbal and c.slot >= 1 and c.slot not in out:
            if c.slot >= MAX_CAMERAS:
                raise ValueError(f"at most {MAX_CAMERAS - 1} further chains")
            assert c.chain is not None
            out[c.slot] = FurtherChain(c.chain, c.slot, c.n_joints, c)
    return [out[s] for s in sorted(out)]


class ChainStates:
    """The further chains' joint-angle states of one run (module docstring).

    ``theta`` slot -> the newest keyframe's angles; ``history`` keyframe -> slot -> its latest estimate.
    """

    def __init__(self, cameras: Sequence[RunCamera], options: VioOptions, T_sI: FloatArray) -> None:
        self.chains = further_chains(cameras)
        self.opt = options
        self.T_sI = T_sI
        self.robust = RobustLoss("huber", options.robust_k)
        self.theta: dict[int, FloatArray] = {}
        self.history: dict[int, dict[int, FloatArray]] = {}

    def __bool__(self) -> bool:
        return bool(self.chains)

    def theta_at(self, k: int, slot: int, values: gtsam.Values | None = None) -> FloatArray:
        """Angles of chain ``slot`` at keyframe ``k``: from ``values``, the history, or the newest."""
        key = chain_theta_key(k, slot)
        if values is not None and values.exists(key):
            return np.asarray(values.atVector(key), float)
        return self.history.get(k, {}).get(slot, self.theta[slot])

    # ------------------------------------------------------------------ start values
    def fit_pairs(self, frame: TrackFrame, guess: FloatArray | None = None) -> dict[int, FloatArray]:
        """Each chain's angles from the frame's cam0 <-> chain-camera pairs (epipolar fit,
        :func:`~dcc_fg.vio.joint_init.fit_joint_angles`; grid start without ``guess``); chains with too
        few agreeing pairs keep ``guess`` / their newest estimate / zeros."""
        out = {}
        for ch in self.chains:
            fallback = self.theta.get(ch.slot, np.zeros(ch.n_joints)) if guess is None else guess
            xy = next((e for e in frame.extra if e.camera == ch.camera.index), None)
            need = max(8, 2 * ch.n_joints + 2)
            if xy is None:
                out[ch.slot] = np.asarray(fallback, float)
                continue
            _, i_s, i_c = np.intersect1d(frame.static_ids, xy.ids, return_indices=True)
            if i_s.size < need:
                out[ch.slot] = np.asarray(fallback, float)
                continue
            assert ch.camera.kin is not None
            cal = GimbalCalibration(ch.camera.kin, ch.n_joints, dynamic_camera=ch.camera.model)
            start = self.theta.get(ch.slot) if guess is None else guess
            fit = fit_joint_angles(cal, frame.static_xy[i_s], xy.xy[i_c], start)
            ok = fit.inliers >= max(need, fit.pairs // 2)
            out[ch.slot] = np.asarray(fit.theta if ok else fallback, float)
        return out

    def _fit_landmarks(self, ch: FurtherChain, frame: TrackFrame, T_WI: FloatArray, theta0: FloatArray,
                       prior_sigma: float, landmarks: LandmarkMap) -> FloatArray:  # fmt: skip
        """Chain ``ch``'s angles fitted to its camera's observations of known landmarks in ``frame`` (body
        pose ``T_WI`` held; prior ``theta0`` with ``prior_sigma`` rad); ``theta0`` without them."""
        xy = next((e for e in frame.extra if e.camera == ch.camera.index), None)
        if xy is None:
            return theta0
        idx = [i for i, tid in enumerate(xy.ids) if int(tid) in landmarks.active]
        p_W = np.array([landmarks.position[landmarks.active[int(xy.ids[i])]] for i in idx]).reshape(-1, 3)
        assert ch.camera.kin is not None
        return fit_joint_angles_to_landmarks(
            T_WI, p_W, xy.xy[idx], theta0, prior_sigma, ch.camera.kin, self.T_sI, self.opt.sigma, self.robust
        )

    # ------------------------------------------------------------------ graph
    def anchor(
        self,
        k: int,
        t_ns: int,
        sigma: float,
        graph: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        stamps: dict[int, int],
        theta: dict[int, FloatArray] | None = None,
    ) -> None:
        """A window starts at keyframe ``k``: each chain's value (``theta``, else its newest estimate) with
        a prior of ``sigma`` rad."""
        for ch in self.chains:
            th = np.asarray((theta or {}).get(ch.slot, self.theta.get(ch.slot, np.zeros(ch.n_joints))), float)
            key = chain_theta_key(k, ch.slot)
            graph.add(gtsam.PriorFactorVector(key, th, gtsam.noiseModel.Isotropic.Sigma(ch.n_joints, sigma)))
            values.insert(key, th)
            stamps[key] = t_ns
            self.theta[ch.slot] = th.copy()
            self.history.setdefault(k, {})[ch.slot] = th.copy()

    def add(
        self,
        k_prev: int,
        k: int,
        dt_s: float,
        frame: TrackFrame,
        T_WI: FloatArray,
        landmarks: LandmarkMap,
        t_ns: int,
        graph: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        stamps: dict[int, int],
    ) -> None:
        """Keyframe ``k``: each chain's value, fitted to its camera's observations of known landmarks from
        the newest estimate (body pose ``T_WI`` held), and the random walk from ``k_prev`` (``dt_s`` s)."""
        walk = max(self.opt.theta_random_walk * np.sqrt(max(dt_s, 0.0)), 1e-6)
        for ch in self.chains:
            th0 = self._fit_landmarks(ch, frame, T_WI, self.theta[ch.slot], walk, landmarks)
            key = chain_theta_key(k, ch.slot)
            values.insert(key, th0)
            stamps[key] = t_ns
            graph.add(joint_random_walk_factor(chain_theta_key(k_prev, ch.slot), key, ch.n_joints, walk))
            self.history.setdefault(k, {})[ch.slot] = th0.copy()

    def refresh(self, estimate: gtsam.Values, kf_times: dict[int, int], k: int) -> None:
        """Every window keyframe's angles from the smoother's estimate; the newest from keyframe ``k``."""
        for kk in kf_times:
            for ch in self.chains:
                key = chain_theta_key(kk, ch.slot)
                if estimate.exists(key):
                    self.history.setdefault(kk, {})[ch.slot] = np.asarray(estimate.atVector(key), float)
        for ch in self.chains:
            if estimate.exists(chain_theta_key(k, ch.slot)):
                self.theta[ch.slot] = np.asarray(estimate.atVector(chain_theta_key(k, ch.slot)), float)

    def result(self, keyframes: Sequence[int]) -> dict[str, FloatArray]:
        """Chain name -> (N, L) angles of ``keyframes`` (NaN where a keyframe has none)."""
        out = {}
        for ch in self.chains:
            rows = [self.history.get(kk, {}).get(ch.slot, np.full(ch.n_joints, np.nan)) for kk in keyframes]
            out[ch.name] = np.array(rows, float).reshape(len(rows), ch.n_joints)
        return out
