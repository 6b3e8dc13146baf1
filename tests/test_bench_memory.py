"""Smoke test of benchmarks/bench_memory.py on small bags (the 2,000-frame run is not part of CI).

A streaming reader holds a bounded number of images, so the peak RSS of ``load_dataset`` on a
bag must not grow with the number of frames: from 20 to 80 frames a reader that kept every
image would add at least 60 pairs x 2 x 640 x 480 bytes = 36.9 MB; we allow a quarter of that.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

BENCH = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_memory.py"


def _load_bench() -> ModuleType:
    spec = importlib.util.spec_from_file_location("bench_memory", BENCH)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def test_bench_memory_runs_and_streams(tmp_path: Path) -> None:
    bench = _load_bench()
    small = bench.run(frames_n=20, fmt="ros2", workdir=tmp_path / "small", verbose=False)
    assert small["load"]["snapshots"] == 20
    cal = small["calibrate"]
    assert cal["returncode"] == 0 and cal["snapshots"] == 20
    # 20 noise-free rendered pairs, 54 corners each: T_ds to well under a mrad / mm
    assert cal["T_ds_rot_err_mrad"] < 1.0 and cal["T_ds_trans_err_mm"] < 1.0

    big_dir = tmp_path / "big"
    inputs = bench.write_inputs(big_dir, 80, "ros2", "sqlite3")
    big = bench.measure("load", big_dir, inputs["bag"])
    assert big["snapshots"] == 80
    pair_bytes = 2 * bench.SIZE[0] * bench.SIZE[1]
    growth = big["peak_rss_bytes"] - small["load"]["peak_rss_bytes"]
    assert growth < 0.25 * 60 * pair_bytes, f"peak RSS grew by {growth / 2**20:.1f} MiB from 20 to 80 frames"
