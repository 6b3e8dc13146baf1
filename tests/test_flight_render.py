"""Flight renderer: image geometry against the camera model's forward projection, determinism, sky."""

from __future__ import annotations

import cv2
import numpy as np

from dcc_fg.sim.flight_render import SKY, TexturedPlane, WorldRenderer, planes_from_world
from dcc_fg.sim.trajectory import FlightConfig, World
from factors.camera import CameraModel

CAM = CameraModel((460.0, 455.0, 322.0, 238.0), "radtan", (-0.28, 0.07, 0.0005, -0.0003), (640, 480))


def _looking_down(height: float) -> np.ndarray:
    """T_cW of a camera ``height`` m above the ground looking straight down (x right = world x)."""
    T = np.eye(4)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])
    T[:3, 3] = -T[:3, :3] @ np.array([5.0, 4.0, height])
    return T


def test_image_follows_the_forward_projection() -> None:
    """World points projected with CameraModel.project (strong EuRoC-like radtan distortion) land
    where the rendered image shows their texture: the renderer's per-pixel rays invert the model."""
    ground = TexturedPlane((0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (10.0, 8.0), 3)
    r = WorldRenderer([ground], texel=0.02)
    T = _looking_down(2.0)
    img = r.render(CAM, T, noise_sigma=0.0).astype(np.float32)
    rng = np.random.default_rng(0)
    P = np.column_stack([rng.uniform(3.6, 6.4, 400), rng.uniform(2.9, 5.1, 400), np.zeros(400)])
    uv, _ = CAM.project(P @ T[:3, :3].T + T[:3, 3], jacobian=False)
    ok = CAM.in_image(uv, margin=2)
    uv, P = uv[ok], P[ok]
    shown = cv2.remap(img, uv[:, :1].astype(np.float32), uv[:, 1:].astype(np.float32), cv2.INTER_LINEAR).ravel()
    ax = r.offsets[0, 0] + P[:, 0] / r.texel
    ay = r.offsets[0, 1] + (ground.size[1] - P[:, 1]) / r.texel
    tex = cv2.remap(r.mips[0], ax[:, None].astype(np.float32), ay[:, None].astype(np.float32), cv2.INTER_LINEAR)
    err = np.abs(shown - tex.ravel())
    assert uv.shape[0] > 300
    # corners of the image are displaced by tens of pixels by this distortion; rendering with the
    # principal point moved by one pixel raises the 95th percentile to ~19 grey levels (checked)
    assert np.median(err) < 2.0 and np.percentile(err, 95) < 8.0, (np.median(err), np.percentile(err, 95))
    far = np.linalg.norm(uv - [322.0, 238.0], axis=1) > 250
    assert far.sum() > 20 and np.median(err[far]) < 3.0


def test_deterministic_textures_and_sky() -> None:
    cfg = FlightConfig.short(10.0)
    world = World.around(cfg)
    a = WorldRenderer(planes_from_world(world), seed=1).render(CAM, _looking_down(3.0), 0.0)
    b = WorldRenderer(planes_from_world(world), seed=1).render(CAM, _looking_down(3.0), 0.0)
    c = WorldRenderer(planes_from_world(world), seed=2).render(CAM, _looking_down(3.0), 0.0)
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    assert a.std() > 40  # high-contrast texture
    up = np.eye(4)
    up[:3, 3] = [0.0, 0.0, -20.0]  # camera z (optical axis) = world z: looking up from 20 m
    sky = WorldRenderer(planes_from_world(world), seed=1).render(CAM, up, 0.0)
    assert np.all(sky == int(SKY))
