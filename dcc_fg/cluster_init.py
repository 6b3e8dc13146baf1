"""Automatic initialization of an N-camera cluster (no hand-measured values, no joint readings).

Frames: ``s`` = cam0; ``T_cs`` maps points of s into camera c; ``T_ct`` (PnP) the target in camera c.

1. Static extrinsics: ``T_cs`` of each static camera from the per-snapshot PnP poses of co-observing
   cameras, ``mean(T_ct inv(T_s't) T_s's)`` over the snapshots it shares with a static camera s' whose
   ``T_s's`` is already known (cam0 first, breadth-first through the static cameras; chordal mean
   rotation, mean translation: :func:`dcc_fg.init.mean_pose`).
2. Each chain: the two-camera global calibration (:func:`dcc_fg.global_fit.calibrate_global`: the
   automatic starts of :mod:`dcc_fg.auto_init`, each solved at the corner level, the lowest cost kept)
   on the pair (reference static camera r, primary camera p on the chain), r = the static camera
   sharing the most snapshots with the chain's cameras (cam0 on ties), p = the chain camera seen most
   with r. Its ``tau_s`` (r -> base) becomes ``T_bs = T_br T_rs``; its ``tau_d`` is p's.
3. The chain's other cameras c: ``T_ce = mean(T_ct inv(T_pt)) T_pe`` over the snapshots c shares with p
   (both on the same end effector, so their relative pose is constant); a camera never seen with p is
   refused (named).

The result is a :class:`~dcc_fg.cluster.CameraCluster` to start :func:`dcc_fg.cluster_calibration.
calibrate_cluster` from; the gauge-held entries of each chain keep the values of its pair calibration.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from numpy.typing import NDArray

from dcc_fg.calibrate import CalibrationOptions
from dcc_fg.cluster import CameraCluster, CameraMount, ChainSpec
from dcc_fg.cluster_data import ClusterDataset
from dcc_fg.global_fit import calibrate_global
from dcc_fg.init import mean_pose, pnp_pose
from dcc_fg.util.errors import stage
from factors import chain

FloatArray = NDArray[np.float64]
REFERENCE = "cam0"


def _pnp(data: ClusterDataset, i: int, camera: str) -> FloatArray:
    obs = data.snapshots[i].observations[camera]
    return pnp_pose(data.cameras[camera], data.target_points[obs.ids], obs.pixels)


def static_extrinsics(data: ClusterDataset, static: list[str]) -> dict[str, FloatArray]:
    """``T_cs`` (4x4) of the static cameras reachable from cam0 through co-observations (step 1)."""
    known = {REFERENCE: np.eye(4)}
    cache: dict[tuple[int, str], FloatArray] = {}

    def pose(i: int, c: str) -> FloatArray:
        if (i, c) not in cache:
            cache[(i, c)] = _pnp(data, i, c)
        return cache[(i, c)]

    with stage("PnP", hint="check the camera intrinsics and the target description"):
        changed = True
        while changed:
            changed = False
            for c in static:
                if c in known:
                    continue
                best: tuple[int, str] | None = None
                for r in known:
                    n = len(data.co_observations(c, r))
                    if n and (best is None or n > best[0]):
                        best = (n, r)
                if best is None:
                    continue
                r = best[1]
                rel = [pose(i, c) @ chain.inv_se3(pose(i, r)) for i in data.co_observations(c, r)]
                known[c] = mean_pose(np.array(rel)) @ known[r]
                changed = True
    return known


def auto_initialize_cluster(
    data: ClusterDataset,
    mounts: Mapping[str, str | None],
    joints: Mapping[str, int],
    chain_order: list[str] | None = None,
) -> CameraCluster:
    """Initial values of every unknown of the cluster (module docstring).

    Args:
        data: the snapshots (snapshot ``joints`` are ignored).
        mounts: camera -> chain name, None for a static camera (cam0 static).
        joints: chain -> L.
        chain_order: the chains' order (default: ``joints``'s order).

    Raises:
        ValueError: a camera with no co-observation linking it to cam0, a chain no static camera
            shares snapshots with, a chain camera never seen with the chain's primary camera.
    """
    order = list(chain_order or joints)
    cams = sorted(mounts, key=lambda c: int(c[3:]))
    static = [c for c in cams if mounts[c] is None]
    T_cs = static_extrinsics(data, static)
    lost = [c for c in static if c not in T_cs]
    if lost:
        raise ValueError(f"{data.source}: static camera(s) {', '.join(lost)} never share a snapshot with cam0 "
                         "(directly or through other static cameras): their extrinsics are undetermined")  # fmt: skip
    chains: list[ChainSpec] = []
    tau_d: dict[str, FloatArray] = {}
    opts = CalibrationOptions(compute_covariance=False)
    for ch in order:
        L = int(joints[ch])
        on = [c for c in cams if mounts[c] == ch]
        if not on:
            raise ValueError(f"chain {ch}: no camera is mounted on it")
        score = {r: sum(len(data.co_observations(r, c)) for c in on) for r in static}
        ref = max(static, key=lambda r: (score[r], r == REFERENCE))
        if score[ref] == 0:
            raise ValueError(f"{data.source}: no static camera shares a snapshot with the cameras of chain {ch}")
        primary = max(on, key=lambda c: len(data.co_observations(ref, c)))
        pair, _ = data.pair(ref, primary)
        for s in pair.snapshots:
            s.joints = None
        res = calibrate_global(pair, L, opts)
        cal = res.calibration
        T_bs = cal.T_bs() @ T_cs[ref]
        chains.append(ChainSpec(ch, chain.tau_from_se3(T_bs), cal.dh.copy()))
        tau_d[primary] = cal.tau_d.copy()
        T_pe = cal.T_de()
        for c in on:
            if c == primary:
                continue
            shared = data.co_observations(primary, c)
            if shared:
                rel = [_pnp(data, i, c) @ chain.inv_se3(_pnp(data, i, primary)) for i in shared]
                tau_d[c] = chain.tau_from_se3(mean_pose(np.array(rel)) @ T_pe)
                continue
            raise ValueError(
                f"{data.source}: camera {c} of chain {ch} never sees the target together with {primary} (the "
                "chain's best-observed camera); the automatic initialization needs such snapshots to place it"
            )
    mounts_out = []
    for c in cams:
        ch = mounts[c]
        if ch is None:
            mounts_out.append(
                CameraMount(c, None, T_cs=None if c == REFERENCE else T_cs[c], camera=data.cameras.get(c))
            )
        else:
            mounts_out.append(CameraMount(c, ch, tau_d=tau_d[c], camera=data.cameras.get(c)))
    return CameraCluster(tuple(mounts_out), tuple(chains))
