"""``dcc-fg simulate calibration --cluster PRESET``: an N-camera cluster data set (corner level).

Writes the detection-folder layout of :func:`dcc_fg.sim.cluster_scene.write_cluster_dataset`
(``OUT/detections/cam0 .. camN-1/<ns>.csv``, ``OUT/cluster.yaml``, ``OUT/target.yaml``,
``OUT/ground_truth.yaml``); the corners are simulated (no images are rendered). Read it back with
:func:`dcc_fg.cluster_data.read_cluster_detections` and calibrate with
:func:`dcc_fg.cluster_calibration.calibrate_cluster`.
"""

from __future__ import annotations

import argparse

from dcc_fg.sim.cluster_scene import PRESETS, ClusterSceneConfig, simulate_cluster, write_cluster_dataset
from dcc_fg.sim.write_dataset import default_target

CLUSTER_HELP = (
    f"simulate an N-camera cluster instead ({', '.join(PRESETS)}): stereo+gimbal = cam0 + cam1 static stereo, "
    "cam2 on a 2-DOF gimbal; gimbal-pair = cam0 static, cam1 + cam2 on one 2-DOF gimbal; two-gimbals = cam0 "
    "static, cam1 and cam2 on two gimbals. Writes simulated corners (not images) as OUT/detections/camK/<ns>.csv "
    "(AprilGrid target) with OUT/cluster.yaml, OUT/target.yaml, OUT/ground_truth.yaml"
)


def simulate_cluster_command(args: argparse.Namespace) -> int:
    """The ``--cluster`` branch of ``dcc-fg simulate calibration``."""
    refused = [
        flag
        for flag, given in (
            ("--random-mechanism", args.random_mechanism is not None),
            ("--joints", args.joints is not None),
            ("--format ros1/ros2", args.format != "folder"),
            ("--motion continuous", args.motion != "held"),
        )
        if given
    ]
    if refused:
        raise ValueError(
            f"--cluster writes a held-snapshot detection folder of its preset: {', '.join(refused)} not allowed"
        )
    if args.target == "checkerboard":
        raise ValueError("--cluster writes yac detection files, which need an AprilGrid target (--target aprilgrid)")
    cfg = ClusterSceneConfig(n_snapshots=args.snapshots, target=default_target("aprilgrid"))
    sim = simulate_cluster(args.cluster, args.seed, cfg)
    out = write_cluster_dataset(args.out, sim)
    counts = ", ".join(f"{c} {n}" for c, n in sim.data.observation_counts().items())
    print(
        f"simulated {len(sim.data.snapshots)} snapshots of the {args.cluster} cluster (views per camera: {counts})\n"
        f"wrote {out.detections}, {out.cluster}, {out.target}, {out.ground_truth}"
    )
    return 0
