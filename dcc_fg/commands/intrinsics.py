"""``dcc-fg intrinsics DATA --target T.yaml --camera cam0``: one camera's intrinsics into a camchain."""

from __future__ import annotations

import argparse
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from dcc_fg.commands import common
from dcc_fg.intrinsics import intrinsics_table, run_intrinsics, write_intrinsics_camchain
from dcc_fg.io.bags import is_bag
from dcc_fg.io.output_set import OutputFiles
from dcc_fg.io.outputs import write_json
from dcc_fg.targets import load_target
from dcc_fg.util.parallel import resolve_jobs
from dcc_fg.util.provenance import run_record

INTRINSICS_SUMMARY = "calibrate one camera's intrinsics and write a Kalibr camchain YAML"
INTRINSICS_DESCRIPTION = (
    "Detect the target in one camera's images (bag topic or DATA/<camera>/<timestamp_ns>.png), "
    "calibrate pinhole intrinsics (fx, fy, cx, cy in pixels) and distortion with OpenCV, print the RMS "
    "reprojection error (pixels) and every parameter's 1-sigma, and write/update the camchain entry."
)


@dataclass
class IntrinsicsOptions:
    """Options of ``dcc-fg intrinsics`` (recorded in the ``--summary`` JSON)."""

    camera: str = "cam0"
    model: str = "pinhole-radtan"
    topic: str | None = None
    every: int = 1
    max_views: int = 80
    min_corners: int = 12
    max_rms: float = 2.0
    accept_unhealthy: bool = False


def intrinsics_command(args: argparse.Namespace) -> int:
    """Check the inputs and both output files, calibrate, then write ``--out`` (and ``--summary``)
    together: temporary files renamed into place only when everything succeeded."""
    if not Path(args.target).is_file():
        raise ValueError(f"{args.target}: target file not found")
    outputs = OutputFiles({"--out": args.out, "--summary": args.summary}, {"DATA": args.data, "--target": args.target})
    options = IntrinsicsOptions(
        args.camera,
        args.model,
        args.topic,
        args.every,
        args.max_views,
        args.min_corners,
        args.max_rms,
        args.accept_unhealthy,
    )
    target = load_target(args.target)
    jobs = resolve_jobs(args.jobs)
    with outputs:
        progress = common.progress_wanted(args)
        result = run_intrinsics(args.data, target, out=None, progress=progress, jobs=jobs, **asdict(options))
        health = common.judge_health(result.extra["health"], options.accept_unhealthy)
        bag_topic = (args.topic or f"/{args.camera}/image_raw") if is_bag(Path(args.data)) else None
        outputs.seed("--out")  # an existing camchain keeps its other cameras
        write_intrinsics_camchain(outputs["--out"], args.camera, result, bag_topic)
        if args.summary:
            provenance = run_record("intrinsics", {"data": args.data, "target": args.target}, options)
            write_json(outputs["--summary"], {**provenance, **result.summary(), "health": health})
    print(intrinsics_table(result))
    print(f"wrote {args.out}" + (f", {args.summary}" if args.summary else ""))
    return 0


def add_parser(sub: Any, parent: argparse.ArgumentParser) -> None:
    i = common.add_command(sub, "intrinsics", parent, INTRINSICS_SUMMARY, INTRINSICS_DESCRIPTION, intrinsics_command)
    i.add_argument("data", help="ROS1 .bag, ROS2 bag folder, or a folder with <camera>/<timestamp_ns>.png images")
    i.add_argument("--target", required=True, help="Kalibr target YAML (checkerboard or aprilgrid; metres)")
    i.add_argument("--camera", default="cam0", help="camchain entry and image sub-folder (default cam0)")
    i.add_argument(
        "--jobs",
        type=int,
        default=0,
        metavar="N",
        help="processes detecting the target (default 0: every usable core; 1: this process only; the same "
        "corners either way)",
    )
    i.add_argument(
        "--model",
        default="pinhole-radtan",
        choices=["pinhole-radtan", "pinhole-equidistant"],
        help="pinhole with radial-tangential (k1 k2 p1 p2) or equidistant (k1..k4) distortion",
    )
    i.add_argument("--topic", help="image topic in a bag (default /<camera>/image_raw)")
    i.add_argument("--every", type=int, default=1, help="use every n-th image (default 1)")
    i.add_argument("--max-views", type=int, default=80, help="at most this many views, evenly spaced (default 80)")
    i.add_argument("--min-corners", type=int, default=12, help="corners a view needs to be used (default 12)")
    i.add_argument(
        "--max-rms", type=float, default=2.0, help="a larger RMS reprojection error (px, default 2) fails the "
        "health check (exit 3, nothing written)",
    )  # fmt: skip
    i.add_argument("--accept-unhealthy", action="store_true", help="write a result that failed a health check "
                   "(RMS, principal point, distortion folding inside the image, non-finite values); --summary "
                   "then records health.healthy false with the reasons")  # fmt: skip
    i.add_argument("--out", default="camchain.yaml", help="camchain YAML to write or update (default camchain.yaml; "
                   "its other cameras are kept). Checked before any work (not a folder, not an input); written "
                   "together with --summary only when the calibration succeeds")  # fmt: skip
    i.add_argument("--summary", help="optional JSON file with the parameters, 1-sigma and reprojection error")
