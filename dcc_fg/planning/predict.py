"""Predicted accuracy of ``T_ds(theta)`` over an operating range of joint angles, from a calibration.

Frames and symbols (docs/architecture.md): ``T_ab`` maps points from frame b into frame a; ``s`` static
camera, ``d`` gimbal camera, ``t`` target; ``T_ds(theta) = T_de(tau_d) inv(A_1 .. A_L) T_bs(tau_s)``;
``kin = [tau_s, tau_d, d_1, a_1, alpha_1, ...]`` (rad, m). Uncertainties of ``T_ds`` are 6x6 covariances
of gtsam's right-perturbation tangent ``T_ds Exp(xi)``, ``xi = [omega (rad), v (m)]``; a *1-sigma*
is the root of the trace of the rotation (translation) block: the RMS rotation-error angle (rad) and
the RMS translation-error length (m) (the sum of the three axes, not the largest one).

The information of the kinematics (:func:`kinematics_information`). The calibration's information
matrix over the free kinematic entries (the gauge-fixed parameterization of :mod:`dcc_fg.calibrate`,
``calibration.gauge_fixed``), the joint angles and the target poses, with the per-snapshot variables
eliminated (Schur complement: the target pose, then the joint angles, by projection onto the
orthogonal complement of their Jacobians) and the gauge's mean prior on ``theta_L`` taken as a hard
constraint (a rank-one term ``u u^T / s``, see the function). Corner noise: the calibration's
measured sigma (its whitening sigma times the root of the a-posteriori variance factor). Its
pseudo-inverse (Jacobi-scaled, relative eigenvalue cut ``PINV_REL_TOL``) is the covariance ``C`` of
the free kinematic entries, the same one ``dcc-fg calibrate`` reports (``kin_std``) when no direction
is held by a prior and no robust loss down-weights corners.

Two predictions at joint angles ``theta*`` where no snapshot may have been taken (:func:`predict`):

* ``kinematics`` (VIO use: theta known in the calibration's convention, e.g. from a smoother that
  estimates it): ``P = J_k C J_k^T`` with ``J_k = d T_ds / d kin`` at ``theta*``.
* ``snapshot`` (the default): the accuracy of ``T_ds`` at a snapshot taken at ``theta*`` and
  evaluated with the calibration held fixed, the joint angles estimated from that snapshot's
  images (what ``dcc-fg validate`` does, and what any user of the calibration gets at a new pose):
  a hypothetical target pose both cameras see (:func:`place_targets`), its corners' information
  on ``xi`` after eliminating the target pose (``Lambda``, :func:`view_information`), then
  ``Sigma = M P M^T + J_t A^-1 J_t^T`` with ``J_t = d T_ds / d theta``, ``A = J_t^T Lambda J_t``,
  ``M = I - J_t A^-1 J_t^T Lambda`` (the joint-angle fit absorbs the part of the kinematic error
  along ``J_t``; the second term is the snapshot's own noise). Where no target pose shows at least
  ``MIN_CORNERS`` corners in both images this prediction is NaN ("no shared view").
* ``calibration``: the calibration's share of the ``snapshot`` prediction, ``M P M^T`` (what more
  calibration snapshots can reduce; the snapshot's own noise ``J_t A^-1 J_t^T`` is the floor that
  remains with perfect kinematics). Gauge-invariant, unlike ``kinematics``, which also carries the
  uncertainty of the joint-angle zero the calibration chose.

These are first-order (linearized at the estimate) predictions under Gaussian corner noise.
"""

from __future__ import annotations

import io
import json
import logging
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from dcc_fg.calibrate import CalibrationResult, image_sigma_of
from dcc_fg.calibration_graph import gauge_reference_snapshots, snapshot_measurements
from dcc_fg.data import CalibrationDataset
from dcc_fg.io.camchain import camera_from_dict, camera_to_dict
from dcc_fg.planning.range_spec import Tolerance, default_range, format_range
from factors import chain
from factors.calibration import KinLayout, bundle_residuals, two_way_residuals
from factors.camera import CameraModel

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

PINV_REL_TOL = 1e-12  # scaled eigenvalues below this are exact gauge / degenerate directions
MIN_CORNERS = 8  # corners each camera must see for a snapshot to count (the reader's default)
MARGIN_PX = 10.0  # corners this far inside the image (as the simulator places the board)
GRID_PER_AXIS = 15  # accuracy grid: points per joint ...
GRID_CAP = 2000  # ... capped at this many points in all (12^3 for L = 3)
DISTANCE_STEPS = 7  # target distances tried per view
POSE_TILTS_DEG = (30.0,)  # the planner's target poses: extra tilts of the facing board's normal ...
POSE_TILT_DIRECTIONS = 6  # ... towards this many directions in the board plane
MAX_OBLIQUE_DEG = 50.0  # largest angle between the board normal and a camera's ray to the board centre
INFORMATION_FILE = "kinematics_information.npz"
MODES = ("snapshot", "calibration", "kinematics")

log = logging.getLogger(__name__)


# ------------------------------------------------------------------ the view of a hypothetical snapshot


@dataclass(frozen=True)
class ViewModel:
    """How a hypothetical snapshot is taken.

    Attributes:
        static_camera / dynamic_camera: intrinsics.
        target_points: (M, 3) corners in the target frame t, metres.
        distance: preferred distance of the board centre from the static camera, m (the data's median).
        distance_range: (near, far) distances tried when the preferred one does not fit both images, m.
        pixel_sigma: corner noise, px (1-sigma per axis).
    """

    static_camera: CameraModel
    dynamic_camera: CameraModel
    target_points: FloatArray
    distance: float
    distance_range: tuple[float, float]
    pixel_sigma: float

    @property
    def cams(self) -> tuple[CameraModel, CameraModel]:
        return (self.static_camera, self.dynamic_camera)


@dataclass
class Placement:
    """Target poses for G views: ``T_st`` (G, 4, 4); per corner whether each camera sees it (G, M);
    ``ok`` (G,) when both cameras see at least ``MIN_CORNERS``; ``full`` (G,) when both see every corner;
    ``distance`` (G,) of the board centre from the static camera (m) and that ``centre`` (G, 3) in s (m)."""

    T_st: FloatArray
    seen_s: BoolArray
    seen_d: BoolArray
    ok: BoolArray
    full: BoolArray
    distance: FloatArray
    centre: FloatArray

    def take(self, idx: NDArray[np.int64]) -> Placement:
        """The placements ``idx`` (an index array) as a new Placement."""
        return Placement(
            self.T_st[idx], self.seen_s[idx], self.seen_d[idx], self.ok[idx], self.full[idx],
            self.distance[idx], self.centre[idx],
        )  # fmt: skip

    @staticmethod
    def concat(parts: list[Placement]) -> Placement:
        """The placements of ``parts`` (at least one) one after the other."""
        return Placement(
            *(
                np.concatenate([getattr(p, f) for p in parts])
                for f in ("T_st", "seen_s", "seen_d", "ok", "full", "distance", "centre")
            )
        )

    def describe(self, g: int) -> dict[str, Any]:
        """Where to hold the target for view g: distance (m), centre in s (x right, y down, z forward; m),
        tilt of the board normal from the static optical axis (deg), the direction its face points
        (``f = -n``, towards the cameras) as turns from facing the static camera squarely: right (+x,
        ``face_right_deg = atan2(f_x, -f_z)``) and up (-y, ``face_up_deg = atan2(-f_y, -f_z)``), ``T_st`` (4x4)."""
        n = self.T_st[g, :3, 2]
        return {
            "distance_m": float(self.distance[g]),
            "centre_in_static_camera_m": [float(x) for x in self.centre[g]],
            "tilt_deg": float(np.degrees(np.arccos(np.clip(abs(n[2]), 0.0, 1.0)))),
            "face_right_deg": float(np.degrees(np.arctan2(-n[0], n[2]))),
            "face_up_deg": float(np.degrees(np.arctan2(n[1], n[2]))),
            "T_st": [[float(x) for x in row] for row in self.T_st[g]],
            "all_corners_in_both_images": bool(self.full[g]),
        }


def _visible(cam: CameraModel, p: FloatArray) -> BoolArray:
    """(G, M) points in the camera frame (G, M, 3) in front and inside the image with ``MARGIN_PX``."""
    G, M = p.shape[:2]
    flat = p.reshape(-1, 3)
    uv, _ = cam.project(flat, jacobian=False)
    return (cam.in_front(flat) & cam.in_image(uv, MARGIN_PX)).reshape(G, M)


def _facing_pose(c_d: FloatArray, axis_d: FloatArray, z: float, centre_t: FloatArray) -> tuple[FloatArray, FloatArray]:
    """(G, 4, 4) ``T_st`` of the facing placement at distance ``z`` (m) and its aim point (G, 3) in s:
    board centre half way between the static optical axis at z and the dynamic one (centre ``c_d``,
    axis ``axis_d`` in s) at depth z, normal from the midpoint of the two camera centres to the aim."""
    aim = 0.5 * (np.array([0.0, 0.0, z]) + c_d + z * axis_d)
    n = aim - 0.5 * c_d
    return _board_pose(n / np.linalg.norm(n, axis=1, keepdims=True), aim, centre_t), aim


def _board_pose(n: FloatArray, aim: FloatArray, centre_t: FloatArray) -> FloatArray:
    """(G, 4, 4) ``T_st`` with board normal (target z axis, pointing away from the cameras) ``n`` (G, 3),
    its x axis as close to the static camera's x axis as that allows (no roll), centre at ``aim``."""
    x = np.array([1.0, 0.0, 0.0]) - n[:, :1] * n
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    y = np.cross(n, x)
    T = np.tile(np.eye(4), (len(n), 1, 1))
    T[:, :3, 0], T[:, :3, 1], T[:, :3, 2] = x, y, n
    T[:, :3, 3] = aim - np.einsum("gij,j->gi", T[:, :3, :3], centre_t)
    return T


def _camera_geometry(T_ds: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """``R_ds``, ``t_ds``, the dynamic camera centre in s and its optical axis in s, per ``T_ds``."""
    R_ds, t_ds = T_ds[:, :3, :3], T_ds[:, :3, 3]
    return R_ds, t_ds, -np.einsum("gji,gj->gi", R_ds, t_ds), R_ds[:, 2, :]


def _seen(view: ViewModel, T_st: FloatArray, T_ds: FloatArray) -> tuple[BoolArray, BoolArray]:
    """(G, M) corners of the board at ``T_st`` inside each image (static, dynamic), ``MARGIN_PX`` in."""
    pts = view.target_points
    p_s = pts @ np.swapaxes(T_st[:, :3, :3], 1, 2) + T_st[:, None, :3, 3]
    p_d = p_s @ np.swapaxes(T_ds[:, :3, :3], 1, 2) + T_ds[:, None, :3, 3]
    return _visible(view.static_camera, p_s), _visible(view.dynamic_camera, p_d)


def placement_at(view: ViewModel, T_st: FloatArray, T_ds: FloatArray) -> Placement:
    """The :class:`Placement` of given target poses ``T_st`` (G, 4, 4) for ``T_ds`` (G, 4, 4): which
    corners each camera sees, the board centre in s and its distance from the static camera."""
    T_st = np.asarray(T_st, dtype=float).reshape(-1, 4, 4)
    T_ds = np.asarray(T_ds, dtype=float).reshape(-1, 4, 4)
    vs, vd = _seen(view, T_st, T_ds)
    score = np.minimum(vs.sum(axis=1), vd.sum(axis=1))
    centre = np.einsum("gij,j->gi", T_st[:, :3, :3], view.target_points.mean(axis=0)) + T_st[:, :3, 3]
    M = len(view.target_points)
    return Placement(T_st, vs, vd, score >= MIN_CORNERS, score == M, np.linalg.norm(centre, axis=1), centre)


def place_targets(view: ViewModel, T_ds: FloatArray) -> Placement:
    """A target pose per ``T_ds`` (G, 4, 4) that both cameras see, as the simulator aims the board:
    its centre half way between the two optical axes at distance z, its normal pointing from the
    midpoint of the two camera centres to the board centre (facing both cameras), its x axis as close
    to the static camera's x axis as that allows (no roll). z is the view's preferred distance, else
    the first of ``DISTANCE_STEPS`` distances over ``distance_range`` at which every corner is
    ``MARGIN_PX`` inside both images, else the one that shows the most corners to the camera seeing
    fewer."""
    T_ds = np.asarray(T_ds, dtype=float).reshape(-1, 4, 4)
    G = T_ds.shape[0]
    pts = view.target_points
    centre_t = pts.mean(axis=0)
    _, _, c_d, axis_d = _camera_geometry(T_ds)
    near, far = view.distance_range
    dists = [view.distance] + [
        float(z) for z in np.linspace(near, far, DISTANCE_STEPS) if abs(z - view.distance) > 1e-9
    ]
    best_T = np.zeros((G, 4, 4))
    best_score = np.full(G, -1)
    best_s = np.zeros((G, len(pts)), dtype=bool)
    best_d = np.zeros((G, len(pts)), dtype=bool)
    best_c = np.zeros((G, 3))
    done = np.zeros(G, dtype=bool)
    for z in dists:
        T, aim = _facing_pose(c_d, axis_d, z, centre_t)
        vs, vd = _seen(view, T, T_ds)
        score = np.minimum(vs.sum(axis=1), vd.sum(axis=1))
        better = (~done) & (score > best_score)
        best_T[better], best_s[better], best_d[better] = T[better], vs[better], vd[better]
        best_score[better], best_c[better] = score[better], aim[better]
        done |= score == len(pts)
        if done.all():
            break
    ok = best_score >= MIN_CORNERS
    return Placement(best_T, best_s, best_d, ok, best_score == len(pts), np.linalg.norm(best_c, axis=1), best_c)


def _tilted(n: FloatArray, T_face: FloatArray, tilt: float, direction: float) -> FloatArray:
    """Normals ``n`` (G, 3) turned by ``tilt`` rad about the in-plane axis at angle ``direction`` (rad)
    from the facing board's x axis (``T_face`` (G, 4, 4))."""
    u = np.cos(direction) * T_face[:, :3, 0] + np.sin(direction) * T_face[:, :3, 1]
    # Rodrigues for a unit axis u perpendicular to n: n cos + (u x n) sin
    return np.cos(tilt) * n + np.sin(tilt) * np.cross(u, n)


def candidate_poses(view: ViewModel, T_ds: FloatArray) -> tuple[Placement, NDArray[np.int64]]:
    """Target poses a planner may propose for each ``T_ds`` (G, 4, 4): at the view's nearest (the data's
    10th percentile) and preferred (median) distance, the facing pose of :func:`place_targets` and that
    pose's normal tilted by each of ``POSE_TILTS_DEG`` towards ``POSE_TILT_DIRECTIONS`` directions in
    the board plane (no roll; the centre stays). (With the farthest distance and a 15 deg tilt as well,
    the planner took the nearest distance at 30 deg in all 36 picks of six random family members: the
    information grows with the tilt and as the board comes closer.) Kept: every corner ``MARGIN_PX``
    inside both images (a checkerboard detector needs the whole board) and the board seen by each
    camera at most ``MAX_OBLIQUE_DEG`` from its normal (centre ray against normal). Returns the kept
    poses as one :class:`Placement` (P poses; ``ok`` and ``full`` all true) and (P,) the index into
    ``T_ds`` of each."""
    T_ds = np.asarray(T_ds, dtype=float).reshape(-1, 4, 4)
    G = T_ds.shape[0]
    centre_t = view.target_points.mean(axis=0)
    _, _, c_d, axis_d = _camera_geometry(T_ds)
    cos_max = np.cos(np.radians(MAX_OBLIQUE_DEG))
    dists = sorted({float(view.distance_range[0]), float(view.distance)})
    turns = [(0.0, 0.0)] + [
        (np.radians(t), 2.0 * np.pi * k / POSE_TILT_DIRECTIONS)
        for t in POSE_TILTS_DEG
        for k in range(POSE_TILT_DIRECTIONS)
    ]
    parts, owner = [], []
    for z in dists:
        T_face, aim = _facing_pose(c_d, axis_d, z, centre_t)
        ray_s = aim / np.linalg.norm(aim, axis=1, keepdims=True)
        ray_d = aim - c_d
        ray_d /= np.linalg.norm(ray_d, axis=1, keepdims=True)
        for tilt, direction in turns:
            n = _tilted(T_face[:, :3, 2], T_face, tilt, direction)
            pl = placement_at(view, _board_pose(n, aim, centre_t), T_ds)
            good = pl.full & (np.einsum("gi,gi->g", n, ray_s) >= cos_max) & (np.einsum("gi,gi->g", n, ray_d) >= cos_max)
            idx = np.flatnonzero(good)
            parts.append(pl.take(idx))
            owner.append(idx)
    assert G == 0 or int(np.concatenate(owner, dtype=np.int64).max(initial=-1)) < G
    return Placement.concat(parts), np.concatenate(owner).astype(np.int64)


def _gram(J: FloatArray, K: FloatArray) -> FloatArray:
    """sum over corners and pixel axes of ``J^T K`` for (G, M, 2, n) blocks: (G, n, m)."""
    G = J.shape[0]
    Jf, Kf = J.reshape(G, -1, J.shape[-1]), K.reshape(G, -1, K.shape[-1])
    return np.swapaxes(Jf, 1, 2) @ Kf


def view_information(view: ViewModel, T_ds: FloatArray, placement: Placement) -> FloatArray:
    """(G, 6, 6) information of a snapshot's corners on ``xi`` (``T_ds`` tangent ``[omega, v]``,
    1/rad^2, 1/m^2) with its target pose eliminated (Schur complement), for the corners each camera
    sees (``placement.seen_s`` / ``seen_d``), corner noise ``view.pixel_sigma`` px per axis.

    Model: ``u_s = pi_s(T_st p_t)``, ``u_d = pi_d(T_ds T_st p_t)``; right perturbations
    ``T_ds Exp(xi)`` and ``T_st Exp(eta)``: ``d p_s / d eta = R_st [-[p_t]x, I]``,
    ``d p_d / d xi = R_ds [-[p_s]x, I]``, ``d p_d / d eta = R_ds d p_s / d eta``.
    """
    T_ds = np.asarray(T_ds, dtype=float).reshape(-1, 4, 4)
    T_st = placement.T_st
    G = T_ds.shape[0]
    pts = view.target_points
    M = len(pts)
    R_st, R_ds = T_st[:, :3, :3], T_ds[:, :3, :3]
    p_t = np.broadcast_to(pts, (G, M, 3))
    p_s = pts @ np.swapaxes(R_st, 1, 2) + T_st[:, None, :3, 3]
    p_d = p_s @ np.swapaxes(R_ds, 1, 2) + T_ds[:, None, :3, 3]
    _, Js = view.static_camera.project(p_s.reshape(-1, 3))
    _, Jd = view.dynamic_camera.project(p_d.reshape(-1, 3))
    assert Js is not None and Jd is not None
    # Row vectors a (1x3) times [-[p]x, I] are [p x a, a] (a [p]x = (a x p)^T), so every block is a
    # cross product and a 3x3 product, no per-corner 2x6 matrix product.
    Js_R = (Js.reshape(G, M * 2, 3) @ R_st).reshape(G, M, 2, 3)
    Jd_R = (Jd.reshape(G, M * 2, 3) @ R_ds).reshape(G, M, 2, 3)
    Jd_RR = (Jd_R.reshape(G, M * 2, 3) @ R_st).reshape(G, M, 2, 3)
    w_s = placement.seen_s[..., None, None] / view.pixel_sigma
    w_d = placement.seen_d[..., None, None] / view.pixel_sigma
    pt4, ps4 = p_t[:, :, None, :], p_s[:, :, None, :]
    J_eta_s = np.concatenate([np.cross(pt4, Js_R), Js_R], axis=3) * w_s
    J_xi = np.concatenate([np.cross(ps4, Jd_R), Jd_R], axis=3) * w_d
    J_eta_d = np.concatenate([np.cross(pt4, Jd_RR), Jd_RR], axis=3) * w_d
    H_xx = _gram(J_xi, J_xi)
    H_xe = _gram(J_xi, J_eta_d)
    H_ee = _gram(J_eta_s, J_eta_s) + _gram(J_eta_d, J_eta_d)
    # a view seen by one camera only: a tiny regularization; seen by neither (no corner in view at
    # that pose): H_xe = 0 as well, so any positive value gives the view no information, not an error
    tr = np.trace(H_ee, axis1=1, axis2=2)
    H_ee += np.eye(6) * np.where(tr > 0, 1e-12 * tr, 1.0)[:, None, None]
    Lam = H_xx - H_xe @ np.linalg.solve(H_ee, np.swapaxes(H_xe, 1, 2))
    return 0.5 * (Lam + np.swapaxes(Lam, 1, 2))


# ------------------------------------------------------------------ the kinematics' information


def scaled_pinv(S: FloatArray, rel_tol: float = PINV_REL_TOL) -> FloatArray:
    """Pseudo-inverse of a PSD matrix after Jacobi scaling (metres and radians alike); scaled
    eigenvalues below ``rel_tol`` times the largest are dropped (exact gauge / degenerate directions)."""
    d = np.sqrt(np.maximum(np.diag(S), 1e-300))
    w, V = np.linalg.eigh(S / np.outer(d, d))
    keep = w > rel_tol * max(float(w.max()), 1e-300)
    return ((V[:, keep] / w[keep]) @ V[:, keep].T) / np.outer(d, d)


@dataclass
class KinematicsInformation:
    """What the predictions and the planner need from a calibration (saved as ``INFORMATION_FILE``).

    Attributes:
        kin: (12 + 3L,) estimated kinematics (rad, m).
        n_joints: L.
        free: (12 + 3L,) mask of the estimated entries (the rest is the gauge, held).
        information: (n_free, n_free) information of the free entries (1/rad^2, 1/(rad m), 1/m^2),
            per-snapshot variables eliminated (module docstring).
        view: how a hypothetical snapshot is taken (cameras, target, distances, measured corner sigma).
        joint_angles: (K, L) the calibration's estimated joint angles, rad.
    """

    kin: FloatArray
    n_joints: int
    free: BoolArray
    information: FloatArray
    view: ViewModel
    joint_angles: FloatArray

    @cached_property
    def covariance(self) -> FloatArray:
        """(n_free, n_free) covariance of the free kinematic entries (:func:`scaled_pinv`)."""
        return scaled_pinv(self.information)

    @property
    def kin_std(self) -> FloatArray:
        """(12 + 3L,) 1-sigma of each kinematic entry (NaN where held)."""
        out = np.full(len(self.kin), np.nan)
        out[self.free] = np.sqrt(np.maximum(np.diag(self.covariance), 0.0))
        return out

    def save(self, path: str | Path) -> Path:
        """Write an ``.npz`` (arrays, and the cameras / target as JSON text)."""
        path = Path(path)
        meta = {
            "format": "dcc-fg kinematics information 1",
            "cam0": camera_to_dict(self.view.static_camera),
            "cam1": camera_to_dict(self.view.dynamic_camera),
            "distance_m": self.view.distance,
            "distance_range_m": list(self.view.distance_range),
            "pixel_sigma_px": self.view.pixel_sigma,
            "n_joints": self.n_joints,
        }
        buf = io.BytesIO()
        np.savez(
            buf,
            kin=self.kin,
            free=self.free,
            information=self.information,
            joint_angles=self.joint_angles,
            target_points=self.view.target_points,
            meta=np.array(json.dumps(meta)),
        )
        tmp = path.with_name(f".{path.name}.tmp")
        tmp.write_bytes(buf.getvalue())
        tmp.replace(path)
        return path

    @staticmethod
    def load(path: str | Path) -> KinematicsInformation:
        """Read what :meth:`save` wrote; ValueError naming the file when it is not such a file."""
        path = Path(path)
        try:
            with np.load(path, allow_pickle=False) as z:
                arrays = {k: z[k] for k in z.files}
        except (OSError, ValueError) as exc:
            raise ValueError(f"{path}: not a kinematics information file ({exc})") from exc
        need = {"kin", "free", "information", "joint_angles", "target_points", "meta"}
        if not need <= set(arrays):
            raise ValueError(f"{path}: not a kinematics information file (missing {sorted(need - set(arrays))})")
        meta = json.loads(str(arrays["meta"]))
        L = int(meta["n_joints"])
        view = ViewModel(
            camera_from_dict(meta["cam0"], str(path), "cam0"),
            camera_from_dict(meta["cam1"], str(path), "cam1"),
            np.asarray(arrays["target_points"], float),
            float(meta["distance_m"]),
            (float(meta["distance_range_m"][0]), float(meta["distance_range_m"][1])),
            float(meta["pixel_sigma_px"]),
        )
        info = KinematicsInformation(
            np.asarray(arrays["kin"], float),
            L,
            np.asarray(arrays["free"], bool),
            np.asarray(arrays["information"], float),
            view,
            np.asarray(arrays["joint_angles"], float).reshape(-1, L),
        )
        if info.kin.shape != (chain.n_kin(L),) or info.information.shape != (int(info.free.sum()),) * 2:
            raise ValueError(f"{path}: inconsistent array shapes for L = {L}")
        return info


def measured_pixel_sigma(result: CalibrationResult) -> float:
    """Corner noise of the calibration, px: the whitening sigma times the root of the variance factor."""
    sigma = result.options.pixel_sigma
    if sigma is None:
        sigma = float(result.extra.get("solver", {}).get("sigma", 1.0))
    return float(sigma * np.sqrt(max(result.variance_factor, 1e-300)))


def _project_out(J: FloatArray, X: FloatArray) -> FloatArray:
    """``J - Q Q^T J`` with Q an orthonormal basis of the columns of X (Schur complement that stays PSD)."""
    if X.shape[1] == 0:
        return J
    Q = np.linalg.qr(X)[0]
    return J - Q @ (Q.T @ J)


def kinematics_information(result: CalibrationResult, data: CalibrationDataset) -> KinematicsInformation:
    """The information of the free kinematic entries of an ``encoderless`` or ``encoders``
    calibration (module docstring), at its solution, with the measured corner sigma.

    Per snapshot (bundle: Jacobians of :func:`factors.calibration.bundle_residuals` over the free
    entries, theta_i and the target pose; two-way: over the free entries and theta_i) the target pose
    and then the joint angles are projected out. The gauge's mean prior on theta_L over the reference
    snapshots (hard constraint ``a^T theta = c``) adds ``u u^T / s`` with ``u = sum_i B_i D_i^-1 a_i``,
    ``s = sum_i a_i^T D_i^-1 a_i`` (``B_i``, ``D_i`` the kin-theta and theta-theta blocks after the pose
    elimination): the limit of the Schur complement of ``D + c a a^T`` for ``c -> inf``.

    Raises ValueError for a validation (no free kinematics) or L = 0.
    """
    cal = result.calibration
    L, mode = cal.n_joints, result.options.mode
    if mode == "validate" or cal.gauge_fixed is None or L == 0:
        raise ValueError("accuracy predictions need an encoderless or encoders calibration of L >= 1 joints")
    free = ~np.asarray(cal.gauge_fixed, bool)
    kin = cal.kin
    layout = KinLayout(kin, free, L)
    kin_free = kin[free]
    cams = (data.static_camera, data.dynamic_camera)
    sigma = measured_pixel_sigma(result)
    # each image whitened as the calibration did, [static, dynamic] (a given pixel sigma: variance factor 1)
    image_sigma = image_sigma_of(result) * np.sqrt(max(result.variance_factor, 1e-300))
    nf = int(free.sum())
    estimate_theta = mode == "encoderless"
    K = len(data.snapshots)
    ref = set(int(i) for i in gauge_reference_snapshots(K)) if estimate_theta else set()
    S = np.zeros((nf, nf))
    u = np.zeros(nf)
    s_sum = 0.0
    for i, snap in enumerate(data.snapshots):
        meas = snapshot_measurements(data, snap)
        theta = result.joint_angles[i]
        if result.options.formulation == "bundle":
            blocks = bundle_residuals(layout, kin_free, theta, result.T_st[i], meas, cams, True)
            block_sigma = image_sigma[i]  # blocks: static, dynamic image
            Jp = np.concatenate([b[1][2].reshape(-1, 6) for b in blocks])
        else:
            T_st0 = result.extra.get("pnp_T_st")
            T_dt0 = result.extra.get("pnp_T_dt")
            if T_st0 is None or T_dt0 is None:
                raise ValueError("a two-way calibration result without its PnP poses (extra pnp_T_st / pnp_T_dt)")
            P_s = meas.p_t_dynamic @ T_st0[i][:3, :3].T + T_st0[i][:3, 3]
            P_d = meas.p_t_static @ T_dt0[i][:3, :3].T + T_dt0[i][:3, 3]
            blocks = two_way_residuals(layout, kin_free, theta, P_s, meas.z_dynamic, P_d, meas.z_static, cams, True)
            block_sigma = image_sigma[i, ::-1]  # blocks: dynamic, static image
            Jp = np.zeros((sum(b[0].size for b in blocks), 0))
        row_sigma = np.concatenate([np.full(b[0].size, s) for b, s in zip(blocks, block_sigma, strict=True)])[:, None]
        Jk = np.concatenate([b[1][0].reshape(-1, nf) for b in blocks]) / row_sigma
        Jt = np.concatenate([b[1][1].reshape(-1, L) for b in blocks]) / row_sigma
        Jp = Jp / row_sigma
        Jk = _project_out(Jk, Jp)
        if not estimate_theta:
            S += Jk.T @ Jk
            continue
        Jt = _project_out(Jt, Jp)
        S += _project_out(Jk, Jt).T @ _project_out(Jk, Jt)
        if i in ref:
            D = Jt.T @ Jt
            a = np.zeros(L)
            a[L - 1] = 1.0
            Da = np.linalg.lstsq(D, a, rcond=None)[0]
            u += (Jk.T @ Jt) @ Da
            s_sum += float(a @ Da)
    if estimate_theta and s_sum > 0:
        S += np.outer(u, u) / s_sum
    S = 0.5 * (S + S.T)
    return KinematicsInformation(kin.copy(), L, free, S, view_model(result, data, sigma), result.joint_angles.copy())


def view_model(result: CalibrationResult, data: CalibrationDataset, pixel_sigma: float) -> ViewModel:
    """The hypothetical snapshots look like the data's: board distance the median (range: 10th-90th
    percentile) of the estimated board centres' distances from the static camera."""
    centre_t = data.target_points.mean(axis=0)
    d = np.linalg.norm(np.einsum("kij,j->ki", result.T_st[:, :3, :3], centre_t) + result.T_st[:, :3, 3], axis=1)
    lo, mid, hi = (float(x) for x in np.percentile(d, [10, 50, 90]))
    return ViewModel(data.static_camera, data.dynamic_camera, data.target_points.copy(), mid, (lo, hi), pixel_sigma)


# ------------------------------------------------------------------ predictions


@dataclass
class Prediction:
    """Predicted ``T_ds`` covariances at G joint-angle vectors.

    Attributes:
        thetas: (G, L) joint angles, rad.
        kinematics: (G, 6, 6) kinematics-alone covariance ``P`` (theta known).
        snapshot: (G, 6, 6) covariance at a snapshot taken there (NaN where no shared view).
        calibration: (G, 6, 6) the calibration's share of ``snapshot`` (NaN where no shared view).
        placement: the hypothetical target poses.
        view_info: (G, 6, 6) each view's information on ``xi``.
        J_kin / J_theta: (G, 6, n_free) / (G, 6, L) Jacobians of ``T_ds`` (tangent) at ``thetas``.
    """

    thetas: FloatArray
    kinematics: FloatArray
    snapshot: FloatArray
    calibration: FloatArray
    placement: Placement
    view_info: FloatArray
    J_kin: FloatArray
    J_theta: FloatArray

    def covariance(self, mode: str) -> FloatArray:
        if mode not in MODES:
            raise ValueError(f"prediction mode must be one of {', '.join(MODES)}, got {mode!r}")
        return {"snapshot": self.snapshot, "calibration": self.calibration, "kinematics": self.kinematics}[mode]

    def sigmas(self, mode: str) -> tuple[FloatArray, FloatArray]:
        """(rotation rad, translation m) 1-sigma per point: roots of the traces of the 3x3 blocks."""
        C = self.covariance(mode)
        rot = np.sqrt(np.maximum(np.trace(C[:, :3, :3], axis1=1, axis2=2), 0.0))
        tra = np.sqrt(np.maximum(np.trace(C[:, 3:, 3:], axis1=1, axis2=2), 0.0))
        return rot, tra


def snapshot_operators(J_theta: FloatArray, view_info: FloatArray) -> tuple[FloatArray, FloatArray]:
    """``M = I - J_t A^-1 J_t^T Lambda`` and the snapshot's own noise ``N = J_t A^-1 J_t^T`` (G, 6, 6),
    ``A = J_t^T Lambda J_t`` (module docstring)."""
    A = np.swapaxes(J_theta, 1, 2) @ view_info @ J_theta
    Ainv = np.linalg.pinv(A)
    N = J_theta @ Ainv @ np.swapaxes(J_theta, 1, 2)
    M = np.eye(6) - N @ view_info
    return M, 0.5 * (N + np.swapaxes(N, 1, 2))


def predict(info: KinematicsInformation, thetas: FloatArray, covariance: FloatArray | None = None) -> Prediction:
    """Predicted ``T_ds`` covariances at joint angles ``thetas`` (G, L) rad, both modes (module
    docstring). ``covariance``: of the free kinematic entries (default ``info.covariance``)."""
    thetas = np.asarray(thetas, dtype=float).reshape(-1, info.n_joints)
    C = info.covariance if covariance is None else covariance
    T, Jk_full, Jt = chain.d_T_ds_tangent_batch(info.kin, thetas, info.n_joints)
    Jk = Jk_full[:, :, info.free]
    P = Jk @ C @ np.swapaxes(Jk, 1, 2)
    placement = place_targets(info.view, T)
    Lam = view_information(info.view, T, placement)
    M, N = snapshot_operators(Jt, Lam)
    share = M @ P @ np.swapaxes(M, 1, 2)
    snap = share + N
    snap[~placement.ok] = np.nan
    share[~placement.ok] = np.nan
    return Prediction(thetas, P, snap, share, placement, Lam, Jk, Jt)


def range_grid(
    ranges: FloatArray, per_axis: int = GRID_PER_AXIS, cap: int = GRID_CAP
) -> tuple[FloatArray, list[FloatArray]]:
    """Regular grid over the range (L, 2) rad, limits included: ``per_axis`` points per joint, fewer when
    ``per_axis^L`` exceeds ``cap``. Returns the (G, L) points (the last joint varies fastest) and the axes."""
    ranges = np.asarray(ranges, dtype=float).reshape(-1, 2)
    L = ranges.shape[0]
    n = max(2, min(per_axis, int(np.floor(cap ** (1.0 / L) + 1e-9))))
    axes = [np.linspace(lo, hi, n) for lo, hi in ranges]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, L)
    return pts, axes


@dataclass
class RangeAccuracy:
    """Predicted accuracy over a grid of the operating range: the prediction, the grid axes and the range (L, 2) rad."""

    ranges: FloatArray
    axes: list[FloatArray]
    prediction: Prediction
    range_source: str

    def stats(self, mode: str) -> dict[str, Any]:
        """Worst and mean 1-sigma over the grid points that have a value (mrad, mm) and where the worst is."""
        rot, tra = self.prediction.sigmas(mode)
        have = np.isfinite(rot) & np.isfinite(tra)
        if not have.any():
            return {"points": 0}
        th = self.prediction.thetas
        i_r = int(np.flatnonzero(have)[np.argmax(rot[have])])
        i_t = int(np.flatnonzero(have)[np.argmax(tra[have])])
        return {
            "points": int(have.sum()),
            "worst_rotation_mrad": float(rot[i_r] * 1e3),
            "worst_rotation_at_deg": [float(x) for x in np.degrees(th[i_r])],
            "worst_translation_mm": float(tra[i_t] * 1e3),
            "worst_translation_at_deg": [float(x) for x in np.degrees(th[i_t])],
            "mean_rotation_mrad": float(rot[have].mean() * 1e3),
            "mean_translation_mm": float(tra[have].mean() * 1e3),
        }

    def summary(self) -> dict[str, Any]:
        """The ``accuracy_over_range`` block of ``summary.json``."""
        return {
            "range_deg": [[float(x) for x in np.degrees(r)] for r in self.ranges],
            "range_source": self.range_source,
            "grid_points": int(len(self.prediction.thetas)),
            "sigma": "root of the trace of the rotation / translation block of the T_ds tangent covariance",
            "snapshot": {
                "what": "T_ds at a snapshot taken there, joint angles estimated from its images, calibration held",
                "no_shared_view_points": int((~self.prediction.placement.ok).sum()),
                **self.stats("snapshot"),
            },
            "calibration": {
                "what": "the calibration's share of the snapshot prediction (without the snapshot's own noise)",
                **self.stats("calibration"),
            },
            "kinematics": {"what": "T_ds from the kinematics alone, joint angles known", **self.stats("kinematics")},
        }

    def meets(self, tolerance: Tolerance, mode: str = "snapshot") -> bool:
        """Worst 1-sigma over the range within the tolerance (both rotation and translation)."""
        s = self.stats(mode)
        return bool(
            s.get("points", 0) > 0
            and s["worst_rotation_mrad"] <= tolerance.rotation * 1e3
            and s["worst_translation_mm"] <= tolerance.translation * 1e3
        )


def accuracy_over_range(
    info: KinematicsInformation, ranges: FloatArray | None = None, per_axis: int = GRID_PER_AXIS, cap: int = GRID_CAP
) -> RangeAccuracy:
    """Predictions on :func:`range_grid` of ``ranges`` (default: :func:`~dcc_fg.planning.range_spec.default_range`
    of the calibration's joint angles)."""
    source = "given"
    if ranges is None:
        ranges, source = default_range(info.joint_angles), "data range plus margin"
    ranges = np.asarray(ranges, float).reshape(info.n_joints, 2)
    pts, axes = range_grid(ranges, per_axis, cap)
    return RangeAccuracy(ranges, axes, predict(info, pts), source)


def accuracy_table(acc: RangeAccuracy, max_rows: int = 12) -> str:
    """Text table for the report: worst and mean 1-sigma of both modes, then the worst grid points."""
    lines = [
        f"Predicted T_ds accuracy over the operating range {format_range(acc.ranges)} deg ({acc.range_source}; "
        f"{len(acc.prediction.thetas)} grid points; 1-sigma = root of the trace of the rotation / translation block)",
    ]
    labels = (
        ("snapshot", "snapshot there (theta from its images)"),
        ("calibration", "  of which the calibration's share"),
        ("kinematics", "kinematics alone (theta known)"),
    )
    for mode, label in labels:
        s = acc.stats(mode)
        if not s.get("points"):
            lines.append(f"  {label:42s}: no grid point with a shared view")
            continue
        lines.append(
            f"  {label:42s}: worst {s['worst_rotation_mrad']:.3g} mrad / {s['worst_translation_mm']:.3g} mm, "
            f"mean {s['mean_rotation_mrad']:.3g} mrad / {s['mean_translation_mm']:.3g} mm"
        )
    no_view = int((~acc.prediction.placement.ok).sum())
    if no_view:
        lines.append(f"  {no_view} grid point(s) without a view both cameras share (snapshot prediction undefined)")
    rot, tra = acc.prediction.sigmas("snapshot")
    krot, ktra = acc.prediction.sigmas("kinematics")
    order = np.argsort(-np.nan_to_num(krot / max(np.nanmax(krot), 1e-300) + ktra / max(np.nanmax(ktra), 1e-300)))
    header = "  " + "  ".join(f"theta_{j + 1} deg".rjust(12) for j in range(acc.prediction.thetas.shape[1]))
    header += "  snap mrad    snap mm   kin mrad     kin mm"
    lines.append("  worst grid points (kinematics alone):")
    lines.append(header)
    for g in order[:max_rows]:
        ang = "  ".join(f"{np.degrees(x):12.2f}" for x in acc.prediction.thetas[g])
        lines.append(f"  {ang}  {rot[g] * 1e3:9.3g}  {tra[g] * 1e3:9.3g}  {krot[g] * 1e3:9.3g}  {ktra[g] * 1e3:9.3g}")
    return "\n".join(lines)


def range_accuracy(
    result: CalibrationResult, data: CalibrationDataset, ranges: FloatArray | None = None
) -> tuple[KinematicsInformation, RangeAccuracy] | None:
    """For ``dcc-fg calibrate``: the kinematics information and the accuracy over ``ranges`` (default: the
    data's range plus a margin); None for a validation, L = 0, or a calibration without covariances."""
    cal = result.calibration
    if result.options.mode == "validate" or cal.n_joints == 0 or cal.gauge_fixed is None:
        return None
    if not result.options.compute_covariance:
        return None
    try:
        info = kinematics_information(result, data)
        return info, accuracy_over_range(info, ranges)
    except np.linalg.LinAlgError as exc:  # the calibration itself is fine: report, do not fail it
        log.warning("predicted accuracy over the range unavailable: %s", exc)
        return None
