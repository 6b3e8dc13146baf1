"""Benchmark: target detection on one process vs ``--jobs N`` processes on a large calibration bag.

The bag of ``bench_memory.py`` (``--frames`` image pairs, default 2,000: 640x480 ``mono8``, a 9x6
chessboard at random poses in both cameras, ROS2 sqlite3, about 1.2 GB; rendered once, not timed) is read
and detected with :func:`dcc_fg.sources.dataset.load_dataset` in a fresh Python process per run:
``--jobs 1`` (today's serial path) and ``--jobs N`` (default 2, the process pool of
:mod:`dcc_fg.sources.parallel_detection`). Each run reports

* frames per second (image pairs read and detected / time inside the process, imports excluded);
* peak memory: the process's own ``VmHWM`` and, for the pool, the peak of each of its processes (fork
  server and workers, sampled from ``/proc`` every 0.2 s); the sum bounds what the run held at once;
* the detections (stamps, corner ids, pixels) written to a file.

The parent asserts that both runs detected exactly the same corners in the same order (bit for bit) and
prints the speed-up ``fps(N) / fps(1)`` (target: >= 1.7 on 2 cores) and the memory. Runs alternate
``--repeat`` times (default 1) and the median speed-up is printed: machines here are shared and noisy.

Usage: ``python benchmarks/bench_detection.py [--frames 2000] [--jobs 2] [--repeat 1] [--workdir DIR]``
"""

from __future__ import annotations

import argparse
import json
import os
import pickle
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_memory import peak_rss_bytes, write_inputs  # noqa: E402

from dcc_fg.sources.dataset import load_dataset  # noqa: E402


def _descendants(pid: int) -> list[int]:
    """Every process below ``pid`` (the pool's fork server and its workers), from /proc."""
    parent: dict[int, int] = {}
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                parent[int(d.name)] = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, ValueError, IndexError):
                continue
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        kids = [c for c, pp in parent.items() if pp == p]
        out += kids
        todo += kids
    return out


def _hwm_bytes(pid: int) -> int:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


class WorkerMemory:
    """Samples the peak RSS (VmHWM) of this process's descendants every 0.2 s while a run goes on."""

    def __init__(self) -> None:
        self.peak: dict[int, int] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)

    def _loop(self) -> None:
        me = os.getpid()
        while not self._stop.wait(0.2):
            for pid in _descendants(me):
                self.peak[pid] = max(self.peak.get(pid, 0), _hwm_bytes(pid))

    def __enter__(self) -> WorkerMemory:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()


def child(workdir: Path, bag: str, jobs: int, out: Path) -> dict[str, Any]:
    """One detection run in this process: timing, memory, and the detections pickled to ``out``."""
    t = time.perf_counter()
    with WorkerMemory() as workers:
        data = load_dataset(
            bag, workdir / "camchain.yaml", workdir / "target.yaml", progress=False, jobs=jobs, min_common_points=0
        )
    dt = time.perf_counter() - t
    snaps = [(s.timestamp_ns, s.static.ids, s.static.pixels, s.dynamic.ids, s.dynamic.pixels) for s in data.snapshots]
    out.write_bytes(pickle.dumps(snaps))
    kids = sorted(workers.peak.values())
    return {
        "jobs": jobs,
        "pairs": len(snaps),
        "time_s": dt,
        "fps": len(snaps) / dt,
        "peak_rss_bytes": peak_rss_bytes(),
        "worker_peak_rss_bytes": kids[-1] if kids else 0,
        "descendants_peak_rss_sum_bytes": sum(kids),
    }


def run(workdir: Path, bag: str, jobs: int, out: Path) -> dict[str, Any]:
    cmd = [sys.executable, str(Path(__file__).resolve()), "--child", str(jobs), "--workdir", str(workdir)]
    cmd += ["--bag", bag, "--result", str(out)]
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        raise RuntimeError(f"--jobs {jobs} run failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def same_detections(a: Path, b: Path) -> bool:
    x, y = pickle.loads(a.read_bytes()), pickle.loads(b.read_bytes())
    return len(x) == len(y) and all(
        p[0] == q[0] and all(np.array_equal(u, v) for u, v in zip(p[1:], q[1:], strict=True))
        for p, q in zip(x, y, strict=True)
    )


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=2000, help="image pairs in the bag (default 2000)")
    p.add_argument("--jobs", type=int, default=2, help="processes of the pooled run (default 2)")
    p.add_argument("--repeat", type=int, default=1, help="alternating serial/pooled run pairs (default 1)")
    p.add_argument("--workdir", help="folder for the bag (default: a temporary folder); an existing bag is reused")
    p.add_argument("--child", type=int, help=argparse.SUPPRESS)
    p.add_argument("--bag", help=argparse.SUPPRESS)
    p.add_argument("--result", help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    if a.child is not None:
        print(json.dumps(child(Path(a.workdir), a.bag, a.child, Path(a.result))))
        return 0
    with tempfile.TemporaryDirectory() as tmp:
        workdir = Path(a.workdir or tmp)
        marker = workdir / "bench_detection.json"
        if marker.is_file() and json.loads(marker.read_text()).get("frames") == a.frames:
            inputs = json.loads(marker.read_text())
        else:
            t = time.perf_counter()
            inputs = write_inputs(workdir, a.frames, "ros2", "sqlite3") | {"frames": a.frames}
            marker.write_text(json.dumps(inputs))
            print(
                f"rendered {a.frames} pairs ({inputs['bag_bytes'] / 2**20:.0f} MiB) in {time.perf_counter() - t:.0f} s"
            )
        speedups = []
        for r in range(a.repeat):
            serial = run(workdir, inputs["bag"], 1, workdir / "serial.pkl")
            pooled = run(workdir, inputs["bag"], a.jobs, workdir / "pooled.pkl")
            if not same_detections(workdir / "serial.pkl", workdir / "pooled.pkl"):
                print("FAIL: the pooled run's detections differ from the serial run's")
                return 1
            speedups.append(pooled["fps"] / serial["fps"])
            for res in (serial, pooled):
                print(
                    f"run {r + 1} --jobs {res['jobs']}: {res['pairs']} pairs in {res['time_s']:.1f} s = "
                    f"{res['fps']:.1f} pairs/s; peak RSS {res['peak_rss_bytes'] / 2**20:.0f} MiB"
                    + (
                        f" + {res['descendants_peak_rss_sum_bytes'] / 2**20:.0f} MiB in the pool's processes (largest "
                        f"{res['worker_peak_rss_bytes'] / 2**20:.0f} MiB)"
                        if res["jobs"] > 1
                        else ""
                    )
                )
        s = float(np.median(speedups))
        print("identical detections (stamps, ids, pixels bit for bit) in every run: yes")
        print(
            f"speed-up --jobs {a.jobs} / --jobs 1: {s:.2f} (median of {len(speedups)}; target >= 1.7 on 2 cores: "
            f"{'met' if s >= 1.7 else 'NOT met'})"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
