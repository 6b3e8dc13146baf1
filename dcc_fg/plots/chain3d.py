"""3D sketch of a gimbal chain: frames s, b, joint frames, e, d as RGB triads, joint axes, the target.

Everything is expressed in the static-camera frame ``s`` (metres). The plot axes show
``x_s`` (right), ``z_s`` (the static camera's viewing direction) and ``-y_s`` (up in the image), so a
camera looking forward appears upright.
"""

from __future__ import annotations

import numpy as np
from matplotlib.figure import Figure
from mpl_toolkits.mplot3d.axes3d import Axes3D
from numpy.typing import NDArray

from dcc_fg.model import GimbalCalibration
from dcc_fg.plots.common import new_figure
from factors import chain

FloatArray = NDArray[np.float64]
AXIS_COLORS = ("tab:red", "tab:green", "tab:blue")


def chain_frames(cal: GimbalCalibration, theta: FloatArray) -> dict[str, FloatArray]:
    """Poses ``T_s<frame>`` (4x4, frame -> s) of s, b, the intermediate joint frames 1..L-1, e and d.

    DH frame 0 is the base ``b`` and frame L the end effector ``e``; ``T_bl = A_1 ... A_l``.
    """
    theta = np.asarray(theta, dtype=float).reshape(cal.n_joints)
    T_sb = chain.inv_se3(cal.T_bs())
    frames: dict[str, FloatArray] = {"s": np.eye(4), "b": T_sb}
    T = T_sb.copy()
    for link, ((d, a, alpha), th) in enumerate(zip(cal.dh, theta, strict=True), start=1):
        T = T @ chain.dh_link(th, d, a, alpha)
        if link < cal.n_joints:
            frames[str(link)] = T.copy()
    frames["e"] = T.copy()
    frames["d"] = chain.inv_se3(cal.T_ds(theta))
    return frames


def joint_axes(cal: GimbalCalibration, theta: FloatArray) -> list[tuple[FloatArray, FloatArray]]:
    """Per joint l: (point, unit direction) of its rotation axis in s (z axis of DH frame l-1)."""
    theta = np.asarray(theta, dtype=float).reshape(cal.n_joints)
    T = chain.inv_se3(cal.T_bs())
    out = []
    for (d, a, alpha), th in zip(cal.dh, theta, strict=True):
        out.append((T[:3, 3].copy(), T[:3, 2].copy()))
        T = T @ chain.dh_link(th, d, a, alpha)
    return out


def merge_coincident(frames: dict[str, FloatArray], tol: float = 1e-9) -> dict[str, FloatArray]:
    """Frames with the same pose drawn once, labelled ``"b = e"`` (e.g. base and end effector when L = 0)."""
    out: dict[str, FloatArray] = {}
    for name, T in frames.items():
        same = next((k for k, U in out.items() if np.allclose(T, U, atol=tol)), None)
        if same is None:
            out[name] = T
        else:
            out[f"{same} = {name}"] = out.pop(same)
    return out


def _view(p: FloatArray) -> FloatArray:
    """s coordinates -> plot coordinates (x, z, -y)."""
    p = np.atleast_2d(p)
    return np.stack([p[:, 0], p[:, 2], -p[:, 1]], axis=1)


def draw_chain(
    ax: Axes3D, cal: GimbalCalibration, theta: FloatArray, scale: float | None, target: FloatArray | None
) -> None:
    """Draw the chain at ``theta`` (rad) on ``ax``: triads of length ``scale`` (m; None: from the chain's
    extent), joint axes and, if given, the target corners ``target`` ((N, 3) in s, metres)."""
    frames = chain_frames(cal, theta)
    origins = np.array([T[:3, 3] for T in frames.values()])
    extent = float(np.ptp(origins, axis=0).max()) if len(origins) > 1 else 0.1
    pts = [_view(origins)]
    if target is not None:
        pts.append(_view(target))
        extent = max(extent, float(np.ptp(np.concatenate(pts), axis=0).max()))
    scale = scale if scale is not None else max(0.02, (0.1 if target is not None else 0.25) * extent)
    for name, T in merge_coincident(frames).items():
        o = T[:3, 3]
        for k in range(3):
            seg = _view(np.stack([o, o + scale * T[:3, k]]))
            ax.plot(seg[:, 0], seg[:, 1], seg[:, 2], color=AXIS_COLORS[k], lw=2)
        v = _view(o + 0.25 * scale * (T[:3, 0] + T[:3, 1]))[0]
        ax.text(v[0], v[1], v[2], name, fontsize=11 if target is None else 8, fontweight="bold")
    path = _view(origins)
    ax.plot(path[:, 0], path[:, 1], path[:, 2], color="0.4", ls="--", lw=1)
    for j, (p, u) in enumerate(joint_axes(cal, theta), start=1):
        seg = _view(np.stack([p - 1.6 * scale * u, p + 1.6 * scale * u]))
        ax.plot(seg[:, 0], seg[:, 1], seg[:, 2], color="k", ls="-.", lw=1.2, label="joint axes" if j == 1 else None)
        pts.append(seg)
    if target is not None:
        v = _view(target)
        ax.scatter(v[:, 0], v[:, 1], v[:, 2], s=4, color="0.3", label="target corners")
    allp = np.concatenate(pts)
    center = 0.5 * (allp.max(axis=0) + allp.min(axis=0))
    half = 0.5 * float(np.ptp(allp, axis=0).max()) + scale
    ax.set_xlim(center[0] - half, center[0] + half)
    ax.set_ylim(center[1] - half, center[1] + half)
    ax.set_zlim(center[2] - half, center[2] + half)
    ax.set_box_aspect((1, 1, 1))
    ax.set_xlabel("x_s (m)")
    ax.set_ylabel("z_s (m)")
    ax.set_zlabel("-y_s (m)")
    ax.view_init(elev=20, azim=-60)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="upper left", fontsize=8)


def chain_figure(
    cal: GimbalCalibration,
    theta: FloatArray,
    T_st: FloatArray | None = None,
    target_points: FloatArray | None = None,
    axis_length: float | None = None,
) -> Figure:
    """3D sketch of the chain at joint angles ``theta`` (radians) in the static-camera frame.

    Draws one RGB triad (x red, y green, z blue) per frame with its label, the chain as a dashed
    polyline through the frame origins, each joint axis as a black dash-dotted line. When ``T_st``
    (4x4, target -> s) and ``target_points`` ((N, 3) in the target frame, metres) are given, a second
    panel shows the same chain with the target corners.
    """
    with_target = T_st is not None and target_points is not None
    fig = new_figure(13.0 if with_target else 7.5, 6.5)
    ax = fig.add_subplot(1, 2 if with_target else 1, 1, projection="3d")
    draw_chain(ax, cal, theta, axis_length, None)
    th = ", ".join(f"{np.degrees(t):.1f}" for t in np.atleast_1d(theta))
    ax.set_title(f"Gimbal chain, θ = [{th}] deg" if cal.n_joints else "Rigid pair (L = 0)")
    if with_target:
        T = np.asarray(T_st, float)
        P = np.asarray(target_points, float) @ T[:3, :3].T + T[:3, 3]
        ax2 = fig.add_subplot(1, 2, 2, projection="3d")
        draw_chain(ax2, cal, theta, None, P)
        ax2.set_title("with the target of this snapshot")
    fig.suptitle("Estimated chain in the static-camera frame s (triads: x red, y green, z blue)")
    return fig
