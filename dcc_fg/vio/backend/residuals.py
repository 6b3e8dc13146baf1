"""Reprojection residuals per camera, for the health of an N-camera run.

Every keyframe, up to ``per_keyframe`` of each camera's new observation factors are kept and, after the
window's update, evaluated at its estimate: the norm of the unwhitened residual (normalized image
coordinates) times the camera's focal length, in pixels. Observations the smoother's gate rejected count
with their predicted error. The median over all of them is a robust noise level per camera (for 2D
Gaussian noise of sigma px per axis the norm's median is 1.18 sigma, whatever the outliers). All cameras
go through the same front end, so their levels should agree; a camera whose level is several times
cam0's does not fit the others (a wrong ``T_cs`` / ``tau_d``, wrong intrinsics, a camera not triggered
with cam0): :func:`dcc_fg.vio.health.vio_health` fails such a run.

A camera whose tracks almost never become observations is as suspect (with a wrong extrinsic its stereo
tracks fail triangulation, so it may have no residual at all): per camera, the fraction of its tracks
(frames x features) that became observations of landmarks, :meth:`CameraResiduals.used_fractions`.
"""

from __future__ import annotations

import gtsam
import numpy as np

from dcc_fg.vio.backend.options import FloatArray


class CameraResiduals:
    """Residual norms (px) per camera (run index) of the observations added at each keyframe."""

    def __init__(self, focal_px: dict[int, float], per_keyframe: int = 40) -> None:
        self.focal = focal_px
        self.per_keyframe = per_keyframe
        self.pending: dict[int, list[gtsam.NonlinearFactor]] = {}
        self.norms: dict[int, list[float]] = {cam: [] for cam in focal_px}
        self.offered: dict[int, int] = {cam: 0 for cam in focal_px}  # tracks of keyframes (features x frames)
        self.used: dict[int, int] = {cam: 0 for cam in focal_px}  # observations made of them

    def offer(self, cam: int, n: int) -> None:
        """Camera ``cam`` had ``n`` tracks in a keyframe."""
        if cam in self.offered:
            self.offered[cam] += int(n)

    def add(self, cam: int, factor: gtsam.NonlinearFactor) -> None:
        """Keep ``factor`` (camera ``cam``) for evaluation after the update, up to ``per_keyframe``."""
        if cam not in self.focal:
            return
        self.used[cam] += 1
        kept = self.pending.setdefault(cam, [])
        if len(kept) < self.per_keyframe:
            kept.append(factor)

    def add_gated(self, cam: int, error: float) -> None:
        """An observation of camera ``cam`` the gate rejected, with its predicted error (normalized units;
        inf behind the camera)."""
        if cam in self.focal:
            self.norms[cam].append(float(error) * self.focal[cam])

    def evaluate(self, values: gtsam.Values, points: dict[int, FloatArray] | None = None) -> None:
        """The kept factors' residual norms (px) at ``values`` (the estimate after the update); ``points``:
        landmark key -> position (W, m) of landmarks that are not variables (structureless)."""
        if points:
            values = gtsam.Values(values)
            for f in (f for factors in self.pending.values() for f in factors):
                for key in f.keys():
                    if key in points and not values.exists(key):
                        values.insert(key, points[key])
        for cam, factors in self.pending.items():
            for f in factors:
                if all(values.exists(key) for key in f.keys()):
                    r: FloatArray = np.asarray(f.unwhitenedError(values), float)
                    self.norms[cam].append(float(np.linalg.norm(r[:2])) * self.focal[cam])
        self.pending.clear()

    def discard(self) -> None:
        """Forget the kept factors (a failed update)."""
        self.pending.clear()

    def used_fractions(self) -> dict[int, float | None]:
        """Per camera, observations made / tracks offered (None without tracks)."""
        return {cam: self.used[cam] / n if n else None for cam, n in self.offered.items()}

    def medians(self) -> dict[int, float | None]:
        """Median residual norm (px) per camera (None without observations)."""
        return {cam: float(np.median(v)) if v else None for cam, v in self.norms.items()}
