"""``dcc-fg evaluate OUT --ground-truth GT``: score a VIO run against ground truth (Tables IV-V).

The evaluation (``OUT/evaluation.json``) and its figures (``OUT/vio_*.png``) are written as one set
attached to the ``vio`` result folder OUT (:class:`~dcc_fg.io.output_set.OutputSet` with command
``evaluate``): the previous evaluation's files are replaced together, nothing is written when the
evaluation fails, and a new ``dcc-fg vio`` run into OUT removes them (they would be stale).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from dcc_fg.commands import common
from dcc_fg.io.output_set import OutputSet
from dcc_fg.io.outputs import write_json
from dcc_fg.io.tum import read_tum
from dcc_fg.plots.vio_output import write_vio_figures
from dcc_fg.vio.evaluate import evaluate_folder, evaluate_trajectory, format_evaluation, load_ground_truth

#: A segment needs this many poses for an aligned APE (SE(3) alignment of fewer is degenerate).
MIN_SEGMENT_POSES = 5

EVALUATE_SUMMARY = "score a VIO run (trajectory.tum, joint_angles.csv) against ground truth"
EVALUATE_DESCRIPTION = (
    "APE/RPE with evo (SE(3) alignment; Sim(3) for mono runs), normalized translation RMSE (%% of "
    "distance) and rotation RMSE (rad/m) as in the paper's Table IV, joint-angle RMSE per joint (Table V). "
    "Writes OUT/evaluation.json and the figures OUT/vio_*.png together, replacing those of an earlier evaluation."
)


def evaluation(out: Path, ground_truth: Path, align: str = "auto") -> dict[str, Any]:
    """The content of ``evaluation.json`` for the VIO output folder ``out``:
    :func:`dcc_fg.vio.evaluate.evaluate_folder`, plus each trajectory segment on its own after a
    restart of the smoother."""
    result = evaluate_folder(out, ground_truth, align)
    segments = segment_evaluations(out, ground_truth, result["alignment"])
    if segments:
        result["segments"] = segments
        result["note"] = (
            "the smoother restarted: the whole-trajectory numbers align every segment with one transform; "
            "'segments' aligns each on its own"
        )
    return result


def segment_evaluations(out: Path, ground_truth: Path, align: str) -> list[dict[str, Any]]:
    """APE of each ``trajectory_segment_K.tum`` (written after a restart of the smoother), each aligned on
    its own; segments with fewer than :data:`MIN_SEGMENT_POSES` poses are listed without numbers."""
    found = sorted(out.glob("trajectory_segment_*.tum"), key=lambda p: int(p.stem.rsplit("_", 1)[1]))
    if not found:
        return []
    gt = load_ground_truth(ground_truth)
    results = []
    for path in found:
        t, T = read_tum(path)
        entry: dict[str, Any] = {"file": path.name, "keyframes": len(t)}
        if len(t) >= MIN_SEGMENT_POSES:
            entry.update(evaluate_trajectory(t, T, gt, align))
        results.append(entry)
    return results


def evaluate_command(args: argparse.Namespace) -> int:
    out = Path(args.out)
    outputs = OutputSet(out, "evaluate", {"--ground-truth": args.ground_truth}, option="OUT")
    with outputs:
        result = evaluation(out, Path(args.ground_truth), args.align)
        write_json(outputs.path / "evaluation.json", result)
        saved = write_vio_figures(out, Path(args.ground_truth), align=result["alignment"], figure_dir=outputs.path)
    print(format_evaluation(result))
    for path in [out / "evaluation.json", *(outputs.final(p) for p in saved.paths.values())]:
        print(f"wrote {path}")
    return 0


def add_parser(sub: Any, parent: argparse.ArgumentParser) -> None:
    e = common.add_command(sub, "evaluate", parent, EVALUATE_SUMMARY, EVALUATE_DESCRIPTION, evaluate_command)
    e.add_argument(
        "out",
        help="output folder of dcc-fg vio (trajectory.tum, summary.json, joint_angles.csv); evaluation.json and "
        "vio_*.png are written into it together, only when the evaluation succeeds",
    )
    e.add_argument(
        "--ground-truth",
        required=True,
        help="TUM file (t tx ty tz qx qy qz qw, body frame) or ROS1/ROS2 bag with /ground_truth/pose "
        "(geometry_msgs/PoseStamped) and /ground_truth/joints (sensor_msgs/JointState)",
    )
    e.add_argument(
        "--align", default="auto", choices=["auto", "se3", "sim3", "none"], help="default: sim3 for mono, else se3"
    )
