"""Benchmark: the cost of one poll of a growing image folder in ``dcc-fg calibrate --incremental``.

A rendered chessboard calibration of ``--pairs`` image pairs (PNG,
:func:`dcc_fg.sim.write_dataset.write_calibration_dataset`) is copied into a folder that grows: all but
the last pair first (one cold poll reads them), then the last pair arrives and the poll that picks it
up is timed, ``--repeat`` times (the pair is removed and written again, with a new modification time,
between repetitions), two ways in this process:

* today's :class:`~dcc_fg.commands.calibrate_incremental.SnapshotSource`: image files already read (same
  path, size, modification time) are neither decoded nor detected again;
* the baseline, the previous behaviour: every image of the folder decoded again at each poll, detections
  cached by image content (``load_dataset`` with the content-keyed detector and no file cache).

Printed: median poll time of each and their ratio; asserted: both give the same snapshots.

Usage: ``python benchmarks/bench_incremental_poll.py [--pairs 200] [--repeat 3] [--keep DIR]``
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from dcc_fg.commands.calibrate import ReaderOptions
from dcc_fg.commands.calibrate_incremental import SnapshotSource
from dcc_fg.sim.write_dataset import CalibrationSimSpec, write_calibration_dataset
from dcc_fg.sources.dataset import load_dataset


def main(argv: list[str] | None = None) -> dict[str, Any]:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--pairs", type=int, default=200)
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--keep", help="render into this folder (reused when it holds the same number of pairs)")
    a = p.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(a.keep or tmp)
        sim = root / "rendered"
        spec = CalibrationSimSpec("checkerboard", "folder", seed=3, n_snapshots=a.pairs)
        if not (sim / "images" / "cam0").is_dir() or len(list((sim / "images" / "cam0").glob("*.png"))) != a.pairs:
            shutil.rmtree(sim, ignore_errors=True)
            t0 = time.perf_counter()
            write_calibration_dataset(sim, spec)
            print(f"rendered {a.pairs} pairs in {time.perf_counter() - t0:.1f} s (not timed below)")
        images, camchain, target = sim / "images", str(sim / "camchain.yaml"), str(sim / "target.yaml")
        files = {cam: sorted((images / cam).glob("*.png")) for cam in ("cam0", "cam1")}
        grow = root / "growing"
        shutil.rmtree(grow, ignore_errors=True)
        for cam, fs in files.items():
            (grow / cam).mkdir(parents=True)
            for f in fs[:-1]:
                shutil.copy2(f, grow / cam / f.name)
        source = SnapshotSource(grow, camchain, target, ReaderOptions())
        t0 = time.perf_counter()
        first = source.poll()
        cold = time.perf_counter() - t0
        new_t, old_t = [], []
        for _ in range(a.repeat):
            for cam, fs in files.items():  # the last pair arrives (again)
                (grow / cam / fs[-1].name).unlink(missing_ok=True)
                shutil.copy(fs[-1], grow / cam / fs[-1].name)
            source._seen.clear()  # noqa: SLF001 - every snapshot counts as new: the same work each repetition
            t0 = time.perf_counter()
            now = source.poll()
            new_t.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            old = load_dataset(grow, camchain=camchain, target=target, detector=source._detect, progress=False)  # noqa: SLF001
            old_t.append(time.perf_counter() - t0)
            assert len(now) == len(old.snapshots) == a.pairs
            for s, o in zip(now, old.snapshots, strict=True):
                assert s.timestamp_ns == o.timestamp_ns and np.array_equal(s.static.pixels, o.static.pixels)
        new_med, old_med = statistics.median(new_t), statistics.median(old_t)
        print(f"cold poll of {len(first)} pairs: {cold:.2f} s")
        print(
            f"poll picking up 1 new pair of {a.pairs}: {new_med:.3f} s (files read once) vs {old_med:.3f} s "
            f"(every image decoded again, detections by content): ratio {old_med / new_med:.1f}x "
            f"(median of {a.repeat})"
        )
    return {"cold_s": cold, "poll_s": new_med, "baseline_poll_s": old_med, "ratio": old_med / new_med}


if __name__ == "__main__":
    main()
