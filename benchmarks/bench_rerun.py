"""Benchmark: what ``--rerun FILE.rrd`` costs (issue 17: a recording in under 1.2x the run's time).

Two commands, each run without and with ``--rerun`` in this process (``dcc_fg.cli.main``), alternating
``--repeat`` times (default 2); the ratio of the medians of the wall times is printed:

* ``dcc-fg demo`` (the paper's simulated 2-DOF study: 81 calibration and 81 validation snapshots,
  calibrations and validation; the recording holds the bundle calibration's 81 snapshots: corners,
  reprojections, the chain's frames, joint-angle and residual series);
* ``dcc-fg vio`` on a rendered ``--duration`` s flight (default 20 s, ``dcc``; rendered once, not timed; the
  recording holds the keyframes, trajectory, truth, joint angles and whatever per-frame tracks and
  landmarks the VIO recording logs).

The ``.rrd`` size is printed too. Needs rerun-sdk (``pip install dcc-fg[viz]``).

Usage: ``python benchmarks/bench_rerun.py [--duration 20] [--repeat 2] [--keep DIR]``
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from dcc_fg.cli import main as cli
from dcc_fg.sim.flight_bag import write_flight
from dcc_fg.sim.trajectory import FlightConfig


def timed(argv: list[str]) -> float:
    t = time.perf_counter()
    code = cli(argv)
    if code != 0:
        raise RuntimeError(f"dcc-fg {' '.join(argv)} exited {code}")
    return time.perf_counter() - t


def compare(name: str, argv_for: Callable[[str, Path | None], list[str]], rrd: Path, repeat: int) -> float:
    plain, recorded = [], []
    for r in range(repeat):
        plain.append(timed(argv_for(f"plain{r}", None)))
        recorded.append(timed(argv_for(f"rec{r}", rrd)))
    ratio = float(np.median(recorded) / np.median(plain))
    print(
        f"{name}: {np.median(plain):.2f} s without, {np.median(recorded):.2f} s with --rerun "
        f"({rrd.stat().st_size / 2**20:.1f} MiB .rrd): ratio {ratio:.2f} (target < 1.2)"
    )
    return ratio


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--duration", type=float, default=20.0, help="flight duration, s (default 20)")
    p.add_argument("--repeat", type=int, default=2, help="alternating runs per variant (default 2)")
    p.add_argument("--keep", help="folder for the flight and the outputs (default: temporary)")
    a = p.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(a.keep or tmp)
        root.mkdir(parents=True, exist_ok=True)

        def demo_argv(tag: str, rrd: Path | None) -> list[str]:
            return ["demo", "--out", str(root / f"demo_{tag}"), "-q"] + (["--rerun", str(rrd)] if rrd else [])

        fb = write_flight(root / "flight", "ros2", FlightConfig.short(a.duration), seed=0)

        def vio_argv(tag: str, rrd: Path | None) -> list[str]:
            argv = ["vio", str(fb.bag), "--calibration", str(fb.calibration), "--out", str(root / f"vio_{tag}"), "-q"]
            return argv + (["--rerun", str(rrd)] if rrd else [])

        ratios = [
            compare("demo", demo_argv, root / "demo.rrd", a.repeat),
            compare(f"vio ({a.duration:g} s flight)", vio_argv, root / "vio.rrd", a.repeat),
        ]
    worst = max(ratios)
    print(f"largest ratio {worst:.2f}: {'met' if worst < 1.2 else 'NOT met'} (target < 1.2)")
    return 0 if worst < 1.2 else 1


if __name__ == "__main__":
    sys.exit(main())
