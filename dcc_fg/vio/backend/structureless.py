"""Structureless landmarks: one GTSAM smart projection factor per landmark instead of a Point3 variable.

With ``VioOptions(landmarks="smart")`` a landmark's observations are not reprojection factors on a
landmark variable ``l(n)``: they form one ``SmartProjectionRigFactorPinholePoseCal3_S2`` on the camera
poses that saw it. The factor triangulates the point from the current poses at every linearization and
eliminates it (Schur complement) inside C++, so the window holds only the keyframe states: the iSAM2
update no longer re-eliminates hundreds of 3-D landmark variables at every keyframe.

Every observation must sit on a camera-pose variable with an identity mount: the static camera's
exposure-time pose ``s(k)`` (time offsets estimated) and the gimbal camera's pose ``c(k)``
(``gimbal_factor='camera_pose'``); :meth:`VioOptions.__post_init__` refuses other settings.
Observations are undistorted normalized coordinates (unit focal length), noise ``sigma`` in the same
units, isotropic (a smart factor cannot carry a robust loss: outliers are held off by the gate of
:meth:`~.smoother.VioSmoother._observe` and the front end's outlier stages).

Bookkeeping. A factor is rebuilt with every new observation of its landmark: the old one is removed
from the smoother (``factorsToRemove``) and the new one added. When the oldest keyframe of a factor
leaves the window the fixed-lag smoother marginalizes the factor with it (its information goes into
the marginal on the remaining keyframes); the landmark then starts a fresh factor from its next
observation on, so no observation is counted twice. Landmark positions (W, m) for the gate, the
joint-angle fit and the outputs come from the factors' triangulation at the window's estimate.
"""

from __future__ import annotations

import gtsam
import numpy as np

from dcc_fg.vio.backend.options import FloatArray

#: Rank tolerance of the factors' triangulation: points worse conditioned than this are degenerate and
#: give a zero factor (with gtsam's default 1, nearly degenerate points made indefinite Hessians that
#: stopped iSAM2's Cholesky with an indeterminant-system error on the 60 s benchmark flight).
RANK_TOLERANCE = 1e-3


class StructurelessLandmarks:
    """Smart-factor bookkeeping of the window's landmarks (module docstring); landmark index ->
    observations ``(pose key, xy)`` since its current factor started, the factor and its slot."""

    def __init__(self, sigma: float, max_depth: float, outlier_sigmas: float | None = None) -> None:
        self.noise = gtsam.noiseModel.Isotropic.Sigma(2, sigma)
        self.params = gtsam.SmartProjectionParams()
        self.params.setLinearizationMode(gtsam.LinearizationMode.HESSIAN)
        self.params.setDegeneracyMode(gtsam.DegeneracyMode.ZERO_ON_DEGENERACY)
        self.params.setRankTolerance(RANK_TOLERANCE)
        self.params.setLandmarkDistanceThreshold(max_depth)
        if outlier_sigmas is not None:
            self.params.setDynamicOutlierRejectionThreshold(outlier_sigmas * sigma)
        self.rig = gtsam.CameraSetPinholePoseCal3_S2()
        self.rig.push_back(gtsam.PinholePoseCal3_S2(gtsam.Pose3(), gtsam.Cal3_S2(1.0, 1.0, 0.0, 0.0, 0.0)))
        self.keys: dict[int, list[int]] = {}
        self.xy: dict[int, list[FloatArray]] = {}
        self.factor: dict[int, gtsam.SmartProjectionRigFactorPinholePoseCal3_S2] = {}
        self.slot: dict[int, int] = {}
        self.touched: set[int] = set()
        self._pending: list[int] = []
        self._first_new = 0

    def clear(self) -> None:
        """Forget every landmark (a restarted window holds none of their factors)."""
        self.keys.clear()
        self.xy.clear()
        self.factor.clear()
        self.slot.clear()
        self.touched.clear()
        self._pending = []

    def add(self, lm: int, pose_key: int, z: FloatArray) -> None:
        """Observation ``z`` (normalized xy) of landmark ``lm`` from the camera pose ``pose_key``."""
        self.keys.setdefault(lm, []).append(int(pose_key))
        self.xy.setdefault(lm, []).append(np.asarray(z, float).reshape(2))
        self.touched.add(lm)

    def stage(self, graph: gtsam.NonlinearFactorGraph) -> list[int]:
        """Append the rebuilt factors of the landmarks observed since the last update to ``graph``; returns
        the smoother slots of the factors they replace (``factorsToRemove``)."""
        remove = []
        self._first_new = int(graph.size())
        self._pending = []
        for lm in sorted(self.touched):
            if lm in self.slot:
                remove.append(self.slot.pop(lm))
            self.factor.pop(lm, None)
            keys = self.keys.get(lm, [])
            if len(keys) < 2:
                continue
            f = gtsam.SmartProjectionRigFactorPinholePoseCal3_S2(self.noise, self.rig, self.params)
            f.add(self.xy[lm], keys, [0] * len(keys))
            graph.add(f)
            self.factor[lm] = f
            self._pending.append(lm)
        self.touched.clear()
        return remove

    def adopt(self, new_factor_slots: list[int]) -> None:
        """After a successful update: the smoother slots of the factors :meth:`stage` added
        (``ISAM2Result.getNewFactorsIndices()`` of that update)."""
        for i, lm in enumerate(self._pending):
            self.slot[lm] = int(new_factor_slots[self._first_new + i])
        self._pending = []

    def discard(self) -> None:
        """A failed update: the staged factors never entered the smoother."""
        for lm in self._pending:
            self.factor.pop(lm, None)
        self._pending = []

    def prune(self, estimate: gtsam.Values) -> None:
        """Landmarks whose oldest observed pose left the window: the smoother marginalized their factor;
        they start afresh (observations before now are in the marginal already)."""
        for lm in list(self.keys):
            keys = self.keys[lm]
            if keys and not estimate.exists(keys[0]):
                self.forget(lm)

    def forget(self, lm: int) -> None:
        """A landmark left the map: its factor (if any) stays in the smoother until it is marginalized."""
        self.keys.pop(lm, None)
        self.xy.pop(lm, None)
        self.factor.pop(lm, None)
        self.slot.pop(lm, None)
        self.touched.discard(lm)

    def positions(self, estimate: gtsam.Values) -> dict[int, FloatArray]:
        """Triangulated positions (W, m) at ``estimate`` of the landmarks with a factor in the window."""
        out = {}
        for lm, f in self.factor.items():
            result = f.point(estimate)
            if result.valid():
                out[lm] = np.asarray(result.get(), float).reshape(3)
        return out
