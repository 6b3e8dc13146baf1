"""Benchmark: cost of the VIO front end and of the flight renderer, against real time and bare KLT.

A short simulated flight (``FlightConfig.short(30)``, seed 0) is rendered at 640x480 (``--scale 0.5``:
320x240) from ``--start`` s for ``--frames`` frame pairs (20 Hz; the default window contains gimbal
slews), then:

1. rendering: CPU time per image pair (static + gimbal camera);
2. the front end (:class:`dcc_fg.vio.frontend.Frontend`: KLT with forward-backward check in both
   cameras, the two static RANSACs, detection, ORB matching and the rotation RANSAC between the
   cameras): CPU time of the process per frame pair and wall time per frame, and the real-time
   factor ``front-end time / data duration`` (the VIO target is a whole pipeline >= 2x faster
   than real time, i.e. total factor <= 0.5, so the front end should stay well below that);
3. baseline in the same process: bare pyramidal KLT (forward only, same 150 corners per camera,
   same window and levels) on the same frames; the ratio says what the rest of the front end costs.

With ``../shared`` present the same is measured on the 95 real EuRoC cam0/cam1 pairs (752x480).
CPU times are reported because the machine is shared: wall times include waiting for a core.

Usage: ``python benchmarks/bench_frontend.py [--frames 200] [--start 4.0]``
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import cv2
import numpy as np

from dcc_fg.sim.flight_bag import scale_camera
from dcc_fg.sim.flight_render import WorldRenderer, planes_from_world, render_flight
from dcc_fg.sim.trajectory import FlightConfig, World, default_static_mount, flight_calibration, simulate_flight
from dcc_fg.sources.euroc import euroc_calibration, load_euroc
from dcc_fg.vio.frontend import Frontend, FrontendConfig

EUROC = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "euroc_v1_01_micro" / "MicroEurocDataset"
FRAME_PERIOD_MS = 50.0


def bare_klt(pairs: list[tuple[np.ndarray, np.ndarray]], cfg: FrontendConfig) -> float:
    """CPU ms per frame pair of forward-only KLT of ``max_features`` corners in both cameras."""
    lk = {"winSize": (cfg.klt_window, cfg.klt_window), "maxLevel": cfg.klt_levels}
    c0 = time.process_time()
    for cam in (0, 1):
        prev = pairs[0][cam]
        pts = cv2.goodFeaturesToTrack(prev, cfg.max_features, cfg.quality_level, cfg.min_distance)
        for pair in pairs[1:]:
            img = pair[cam]
            pts, _, _ = cv2.calcOpticalFlowPyrLK(prev, img, pts, None, **lk)
            prev = img
    return 1e3 * (time.process_time() - c0) / max(len(pairs) - 1, 1)


def run_frontend(frontend: Frontend, frames: list[tuple[int, np.ndarray, np.ndarray]]) -> tuple[float, float]:
    """(CPU ms, wall ms) per frame pair."""
    c0, t0 = time.process_time(), time.perf_counter()
    for t, a, b in frames:
        frontend.process(t, a, b)
    n = max(len(frames), 1)
    return 1e3 * (time.process_time() - c0) / n, 1e3 * (time.perf_counter() - t0) / n


def report(name: str, frames: list[tuple[int, np.ndarray, np.ndarray]], frontend: Frontend) -> dict[str, float]:
    cpu, wall = run_frontend(frontend, frames)
    klt = bare_klt([(a, b) for _, a, b in frames], frontend.config)
    s = frontend.stats.summary()
    print(
        f"{name}: {len(frames)} frame pairs, {frontend.static.camera.resolution[0]}x"
        f"{frontend.static.camera.resolution[1]}"
    )
    print(
        f"  front end: {cpu:.1f} ms CPU per frame pair ({wall:.1f} ms wall), real-time factor "
        f"{cpu / FRAME_PERIOD_MS:.3f} (CPU) / {wall / FRAME_PERIOD_MS:.3f} (wall) at 20 Hz"
    )
    print(
        f"  stages (wall, median ms): static {s['static_ms_median']:.1f}, gimbal {s['dynamic_ms_median']:.1f}, "
        f"matching {s['match_ms_median']:.1f}"
    )
    print(f"  baseline bare KLT: {klt:.1f} ms CPU per frame pair; front end / bare KLT = {cpu / max(klt, 1e-9):.2f}")
    print(
        f"  static RANSAC inlier ratio {s['ransac_inlier_ratio']:.3f} of {int(s['ransac_tested'])} tested, "
        f"{int(s['matches'])} static<->gimbal matches"
    )
    return {"cpu_ms": cpu, "wall_ms": wall, "klt_ms": klt}


def main(argv: list[str] | None = None) -> dict[str, float]:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--frames", type=int, default=200, help="frame pairs to render and track (default 200 = 10 s)")
    p.add_argument("--start", type=float, default=4.0, help="first frame time, s (default 4.0: the first slew)")
    p.add_argument("--scale", type=float, default=1.0, help="image scale relative to 640x480 (0.5: 320x240)")
    args = p.parse_args(argv)
    cfg = FlightConfig.short(30.0)
    truth = simulate_flight(cfg, seed=0)
    cal0 = flight_calibration()
    assert cal0.static_camera is not None and cal0.dynamic_camera is not None
    cal = dataclasses.replace(
        cal0,
        static_camera=scale_camera(cal0.static_camera, args.scale),
        dynamic_camera=scale_camera(cal0.dynamic_camera, args.scale),
    )
    renderer = WorldRenderer(planes_from_world(World.around(cfg)), seed=0)
    k0 = int(round(args.start * 20))
    c0 = time.process_time()
    frames = list(render_flight(renderer, truth, cal, default_static_mount(), frames=slice(k0, k0 + args.frames)))
    render_ms = 1e3 * (time.process_time() - c0) / max(len(frames), 1)
    w, h = cal.static_camera.resolution
    print(f"rendering: {render_ms:.1f} ms CPU per image pair ({w}x{h}, 2 cameras)")
    theta0 = truth.theta[truth.index_of(truth.frame_t_ns[k0])][0]
    out = report("simulated flight", frames, Frontend(cal.static_camera, cal.dynamic_camera, T_ds=cal.T_ds(theta0)))
    out["render_ms"] = render_ms
    if EUROC.is_dir():
        ds = load_euroc(EUROC)
        pairs = dict(ds.images1)
        real = [
            (t, cv2.imread(str(p0), cv2.IMREAD_GRAYSCALE), cv2.imread(str(pairs[t]), cv2.IMREAD_GRAYSCALE))
            for t, p0 in ds.images0
            if t in pairs
        ]
        ecal = euroc_calibration(ds)
        report("EuRoC V1_01 (real)", real, Frontend(ecal.static_camera, ecal.dynamic_camera, T_ds=ecal.T_ds([0.0])))
    return out


if __name__ == "__main__":
    main()
