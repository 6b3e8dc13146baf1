"""Benchmark: ``dcc-fg batch`` on 2 simulated short flights x 3 modes (dcc, scc, mono) on a local Dask cluster.

The study (written into the output folder as ``study.yaml``): two flights of ``--duration`` seconds
(one 16 m x 8 m loop each, seeds 0 and 1, ``--scale`` x 640x480 images; the ``scc`` runs fly the same
body trajectory with the gimbal locked, so 4 flights are rendered) in ``dcc``, ``scc`` and ``mono``,
plus a run on a corrupt bag (random bytes) that must fail without stopping the others. Measured, in
one invocation of this script:

1. the study on ``--workers`` (default 2) worker processes: the table, and its wall time against the
   serial sum of the tasks' own times (renderings and runs) -- the ratio ``dcc-fg batch`` prints;
2. the same study again: every finished run reused (only the broken one is retried), its wall time;
3. unless ``--no-baseline``: the study from scratch on 1 worker (a fresh folder), the honest serial
   wall time; ``serial wall / parallel wall`` is the speed-up the second worker buys (the serial sum
   of step 1 is measured while the workers share the cores, so it overstates a serial run somewhat).

Machines here are shared and noisy: compare the ratios, not the absolute times.

Usage: ``python benchmarks/bench_batch.py [--duration 12] [--scale 1.0] [--workers 2] [--keep DIR]
[--no-baseline]``
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path
from typing import Any

import yaml

from dcc_fg.batch import BatchOptions, BatchResult, load_study, run_study
from dcc_fg.batch.table import markdown_by_mode, markdown_runs
from dcc_fg.data.vio import ImuConfig
from dcc_fg.sim.flight_bag import scaled_flight_calibration
from dcc_fg.sim.trajectory import default_static_mount
from dcc_fg.util.logs import configure_logging


def write_study(folder: Path, duration: float, scale: float) -> Path:
    """``study.yaml`` and the broken run's inputs (a corrupt bag, a valid calibration, a ground truth)."""
    folder.mkdir(parents=True, exist_ok=True)
    rng_bytes = bytes((i * 7919 + 13) % 251 for i in range(20_000))
    (folder / "corrupt.bag").write_bytes(b"#ROSBAG V2.0\n" + rng_bytes)
    cal = scaled_flight_calibration(scale).to_dict()
    cal["imu"] = ImuConfig(T_sI=default_static_mount()).to_dict()
    (folder / "calibration.yaml").write_text(yaml.safe_dump(cal, sort_keys=False))
    (folder / "ground_truth.tum").write_text("1600000000.0 0 0 0 0 0 0 1\n")
    study = {
        "defaults": {"modes": ["dcc", "scc", "mono"], "options": {"keyframe_every": 3}},
        "runs": [
            {"name": "flight-a", "simulate": {"kind": "flight", "duration": duration, "seed": 0, "scale": scale}},
            {"name": "flight-b", "simulate": {"kind": "flight", "duration": duration, "seed": 1, "scale": scale}},
            {"name": "corrupt", "bag": "corrupt.bag", "calibration": "calibration.yaml",
             "ground_truth": "ground_truth.tum", "modes": ["dcc"]},
        ],
    }  # fmt: skip
    path = folder / "study.yaml"
    path.write_text(yaml.safe_dump(study, sort_keys=False))
    return path


def timed_study(path: Path, out: Path, workers: int) -> tuple[BatchResult, float]:
    """One ``dcc-fg batch`` invocation (the command's code path) and its end-to-end wall time (s)."""
    t0 = time.perf_counter()
    result = run_study(load_study(path), BatchOptions(out, workers=workers))
    return result, time.perf_counter() - t0


def schedule_text(result: BatchResult) -> str:
    """Per worker: tasks in start order (label, start relative to the first task, seconds) and busy time."""
    tasks = [t for t in result.schedule if t.get("started_unix") is not None]
    if not tasks:
        return "(no tasks ran)"
    t0 = min(t["started_unix"] for t in tasks)
    end = max(t["started_unix"] + (t["seconds"] or 0.0) for t in tasks)
    lines = []
    for worker in sorted({t["worker"] for t in tasks}):
        mine = sorted((t for t in tasks if t["worker"] == worker), key=lambda t: t["started_unix"])
        busy = sum(t["seconds"] or 0.0 for t in mine)
        steps = ", ".join(f"{t['label'][:24]} @{t['started_unix'] - t0:.1f}s {t['seconds'] or 0:.1f}s" for t in mine)
        lines.append(f"  worker {worker}: busy {busy:.1f} of {end - t0:.1f} s: {steps}")
    return "\n".join(lines)


def summary(result: BatchResult, total_s: float) -> dict[str, Any]:
    return {"executed": result.executed, "reused": result.reused, "failed": result.failed,
            "simulated": result.simulated, "workers": result.workers, "wall_s": result.wall_s,
            "startup_s": result.startup_s, "serial_sum_s": result.serial_s, "speedup": result.speedup,
            "end_to_end_s": total_s}  # fmt: skip


def main(argv: list[str] | None = None) -> dict[str, Any]:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--duration", type=float, default=12.0, help="flight duration, s (default 12: one short loop)")
    p.add_argument("--scale", type=float, default=1.0, help="image resolution relative to 640x480 (default 1)")
    p.add_argument("--workers", type=int, default=2, help="Dask worker processes (default 2)")
    p.add_argument("--keep", help="write the study into this folder (default: a temporary one)")
    p.add_argument("--no-baseline", action="store_true", help="skip the 1-worker run of the whole study")
    a = p.parse_args(argv)
    configure_logging(0, quiet=True)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(a.keep or tmp)
        path = write_study(root, a.duration, a.scale)
        out: dict[str, Any] = {"duration_s": a.duration, "scale": a.scale}

        first, total = timed_study(path, root / "out", a.workers)
        out["parallel"] = summary(first, total)
        print(f"== dcc-fg batch {path} --workers {a.workers}: 2 flights x (dcc, scc, mono) + a corrupt bag ==")
        print(markdown_runs(first.rows))
        print()
        print(markdown_by_mode(first.rows))
        print()
        print(first.timing_text())
        print(f"end to end (cluster start-up and table included): {total:.1f} s")
        print("schedule:\n" + schedule_text(first))
        broken = [r for r in first.rows if r["status"] != "ok"]
        for r in broken:
            print(f"failing run reported: {r['name']} ({r['mode']}): {r['error']}")
        ok = sum(r["status"] == "ok" for r in first.rows)
        others = ok == len(first.rows) - len(broken)
        print(f"{ok} of {len(first.rows)} runs ok; the failing run did not stop the others: {others}")

        again, total_again = timed_study(path, root / "out", a.workers)
        out["rerun"] = summary(again, total_again)
        print("\n== the same study again ==")
        print(again.timing_text())
        print(f"re-run: {again.reused} runs reused (not redone), {again.executed} retried (the failing one), "
              f"{total_again:.1f} s end to end vs {total:.1f} s for the first invocation")  # fmt: skip

        if not a.no_baseline:
            serial, total_serial = timed_study(path, root / "out_serial", 1)
            out["serial"] = summary(serial, total_serial)
            print("\n== the same study from scratch on 1 worker (serial baseline) ==")
            print(serial.timing_text())
            ratio = serial.wall_s / first.wall_s
            out["serial_wall_over_parallel_wall"] = ratio
            print(
                f"speed-up of {a.workers} workers: serial wall {serial.wall_s:.1f} s / parallel wall "
                f"{first.wall_s:.1f} s = {ratio:.2f}x (end to end {total_serial:.1f} s / {total:.1f} s = "
                f"{total_serial / total:.2f}x); serial sum / wall of the parallel run: {first.speedup:.2f}x"
            )
        print(json.dumps(out, indent=2))
    return out


if __name__ == "__main__":
    main()
