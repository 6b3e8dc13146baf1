"""Benchmark: landmark persistence over several flights, the defaults against the previous ``all`` + 1.5 s.

For every seed in ``--seeds``, a ``dcc`` flight of ``--duration`` seconds (the paper's pattern, the gimbal
moving freely; body trajectory, IMU noise and textures from the seed) is rendered into a ROS2 bag (not
timed; ``--keep DIR`` keeps and reuses the bags, ``DIR/seed<N>/moving``) and run twice through
:func:`dcc_fg.vio.pipeline.run_vio_bag` with the front end in its own process, alternating: with the
previous defaults (every landmark persistent, 1.5 s window: :data:`bench_vio.PREVIOUS_PERSISTENT`,
:data:`bench_vio.PREVIOUS_LAG`) and with today's (``persistent_landmarks='auto'``, which on these
synchronized cameras resolves to no persistent landmark and a 2.5 s window). The front-end process is deterministic
(:mod:`dcc_fg.vio.worker`), so each run's accuracy is that of the configuration, not of the machine's load.

Printed: one line per flight (real-time factors, translation and joint RMSE of both, their ratios) and the
ratios over all flights: pooled (RMS over the flights of the defaults over RMS of the previous defaults),
mean, min and max per flight, and the median wall-time ratio. One flight decides little: its joint-1 RMSE
ratio ranged 0.92-1.21 over eight flights.

Usage: ``python benchmarks/bench_vio_persistence.py [--seeds 0-7] [--duration 60] [--keep DIR] [--json OUT]``
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_vio  # noqa: E402
import bench_vio_cluster as cluster_bench  # noqa: E402


def parse_seeds(text: str) -> list[int]:
    """``0-7`` or ``0,3,5`` (or a mix) as a list of seeds."""
    seeds: list[int] = []
    for part in text.split(","):
        lo, _, hi = part.partition("-")
        seeds += list(range(int(lo), int(hi) + 1)) if hi else [int(lo)]
    if not seeds:
        raise ValueError(f"--seeds '{text}' names no seed")
    return seeds


def _metrics(r: dict[str, Any]) -> dict[str, float]:
    """Translation RMSE (%) and, for runs with joint angles (``dcc``), each joint's RMSE (rad)."""
    out = {"translation_rmse": r["normalized_translation_rmse_percent"]}
    for j, x in enumerate(r["joint_rmse_rad"] or ()):
        out[f"joint_{j + 1}_rmse"] = x
    return out


def add_flight_arguments(p: argparse.ArgumentParser) -> None:
    """The flags of the flight family both VIO comparisons run: --seeds, --duration, --keep, --json."""
    p.add_argument("--seeds", default="0-7", help="flight seeds, e.g. 0-7 or 0,2,5 (default 0-7)")
    p.add_argument("--duration", type=float, default=60.0, help="flight duration, s (default 60)")
    p.add_argument("--keep", help="write (and reuse) the flights in this folder (default: a temporary one)")
    p.add_argument("--json", help="also write the runs and ratios to this JSON file")


def flights(a: argparse.Namespace, moving: bool = True) -> Iterator[tuple[int, Any]]:
    """(seed, flight) for every seed of ``a.seeds`` (:func:`bench_vio._flight`, gimbal moving or
    locked), written under ``a.keep`` or a temporary folder removed afterwards."""
    cfg = cluster_bench.flight_config(a.duration)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(a.keep or tmp)
        for seed in parse_seeds(a.seeds):
            folder = root / f"seed{seed}"
            folder.mkdir(parents=True, exist_ok=True)
            yield seed, bench_vio._flight(folder / ("moving" if moving else "locked"), cfg, seed, moving=moving)


def pair_line(seed: int, first: dict[str, Any], second: dict[str, Any]) -> str:
    """One line per flight: real-time factor, translation RMSE and (runs with joint angles) joint RMSEs,
    first run -> second run."""
    m0, m1 = _metrics(first), _metrics(second)
    joints = "".join(
        f"  joint {j} {m0[f'joint_{j}_rmse']:.2e} -> {m1[f'joint_{j}_rmse']:.2e}"
        for j in (1, 2)
        if f"joint_{j}_rmse" in m0 and f"joint_{j}_rmse" in m1
    )
    return (
        f"seed {seed}: real-time factor {first['real_time_factor']:.3f} -> {second['real_time_factor']:.3f}  "
        f"transl. {m0['translation_rmse']:.4f} -> {m1['translation_rmse']:.4f} %" + (joints + " rad" if joints else "")
    )


def summarize(pairs: list[tuple[dict[str, Any], dict[str, Any]]]) -> dict[str, Any]:
    """Ratios of the second run of each pair over the first (:func:`bench_vio._ratios` per pair): pooled
    RMS, mean, min, max per metric (the joints' only when every run has them); median wall-time and
    main-process CPU ratios."""
    per_pair = [bench_vio._ratios(fast, ref) for ref, fast in pairs]
    out: dict[str, Any] = {}
    metrics = [_metrics(r) for pair in pairs for r in pair]
    for key in [k for k in metrics[0] if all(k in m for m in metrics)]:
        a = np.array([_metrics(ref)[key] for ref, _ in pairs])
        b = np.array([_metrics(fast)[key] for _, fast in pairs])
        ratio = np.array([r[key] for r in per_pair])
        out[key] = {
            "pooled": float(np.sqrt(np.mean(b**2)) / np.sqrt(np.mean(a**2))),
            "mean": float(np.mean(ratio)),
            "min": float(np.min(ratio)),
            "max": float(np.max(ratio)),
        }
    out["wall_median"] = float(np.median([r["wall"] for r in per_pair]))
    out["main_cpu_median"] = float(np.median([r["main_cpu"] for r in per_pair]))
    out["real_time_factor_median"] = [float(np.median([p[k]["real_time_factor"] for p in pairs])) for k in (0, 1)]
    return out


def report(pairs: list[tuple[dict[str, Any], dict[str, Any]]], label: str, json_path: str | None) -> dict[str, Any]:
    """Print the ratios over all pairs (:func:`summarize`) after ``label`` and write them with the runs to
    ``json_path`` (if given); returns them."""
    out = summarize(pairs)
    print(
        f"{len(pairs)} flights, {label}: "
        + ", ".join(
            f"{k} pooled {v['pooled']:.3f} (mean {v['mean']:.3f}, {v['min']:.2f}-{v['max']:.2f})"
            for k, v in out.items()
            if isinstance(v, dict)
        )
        + f"; wall time median {out['wall_median']:.2f}, main-process CPU median {out['main_cpu_median']:.2f}; "
        f"median real-time factor {out['real_time_factor_median'][0]:.3f} -> {out['real_time_factor_median'][1]:.3f}"
    )
    out["runs"] = [list(p) for p in pairs]
    if json_path:
        Path(json_path).write_text(json.dumps(out, indent=1))
    return out


def main(argv: list[str] | None = None) -> dict[str, Any]:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_flight_arguments(p)
    a = p.parse_args(argv)
    pairs = []
    for seed, fb in flights(a):
        previous = {"persistent": bench_vio.PREVIOUS_PERSISTENT, "lag": bench_vio.PREVIOUS_LAG}
        ref = bench_vio.run_mode(fb, "dcc", True, **previous)  # type: ignore[arg-type]
        fast = bench_vio.run_mode(fb, "dcc", True)
        pairs.append((ref, fast))
        print(pair_line(seed, ref, fast), flush=True)
    label = (
        f"defaults ({pairs[-1][1]['persistent_landmarks']} persistent, {pairs[-1][1]['lag']:g} s) / "
        f"previous defaults ({bench_vio.PREVIOUS_PERSISTENT}, {bench_vio.PREVIOUS_LAG:g} s)"
    )
    return report(pairs, label, a.json)


if __name__ == "__main__":
    main()
