"""Benchmark: the whole VIO of another dcc-fg checkout against this one, over several flights.

For issue 18's before/after: check out the code from before the work (``git worktree add ../before
5eea12d``) and pass it as ``--old``. For every seed in ``--seeds`` a flight of ``--duration`` seconds (the
paper's pattern; ``--mode dcc``: the gimbal moving freely, ``scc``: locked at its mid position) is rendered
with this checkout (not timed; ``--keep DIR`` keeps and reuses the bags, ``DIR/seed<N>/moving`` or
``locked``, as ``bench_vio_persistence.py`` and ``bench_vio.py`` do),
then run once with each checkout, alternating, each run in a fresh process
(``benchmarks/vio_run_child.py`` with ``PYTHONPATH`` set to the checkout), with each checkout's defaults
and the front end in its own process. Times are the child's wall time for the whole pipeline (bag reading,
front end, smoother) over the data duration.

Printed: one line per flight (real-time factor, translation and joint RMSE of both) and the ratios of
this checkout over the old one over all flights: pooled accuracy (RMS over the flights), mean, min and
max per flight, median wall-time and main-process CPU ratios and the median real-time factors. Checkouts
from before the deterministic front-end process (3a874ef) give different accuracy from run to run, so
one flight decides nothing; the pooled ratios over eight do.

Usage: ``python benchmarks/bench_vio_revision.py --old DIR [--mode dcc|scc] [--seeds 0-7] [--duration 60]
[--keep DIR] [--json OUT]``
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_vio_persistence as persistence  # noqa: E402

HERE = Path(__file__).resolve().parent
THIS_CHECKOUT = HERE.parent


def run_checkout(checkout: Path, flight: Path, mode: str = "dcc") -> dict[str, Any]:
    """One run of ``flight`` (a rendered flight folder) with the dcc-fg of ``checkout``, in a fresh process."""
    env = dict(os.environ, PYTHONPATH=str(checkout))
    # cwd: checkouts before the worker's ``-P`` start their front-end process with ``python -m``, which
    # imports the working directory's dcc_fg first; run in the checkout so that it is the same one
    proc = subprocess.run(
        [sys.executable, str(HERE / "vio_run_child.py"), str(flight), mode],
        env=env,
        cwd=checkout,
        capture_output=True,
        text=True,
    )
    if proc.returncode != 0:
        tail = "\n".join(proc.stderr.strip().splitlines()[-5:])
        raise RuntimeError(f"{checkout}: the run of {flight} failed (exit {proc.returncode}):\n{tail}")
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    if Path(out["code"]) != checkout.resolve():
        raise RuntimeError(f"the child imported dcc_fg from {out['code']}, not from {checkout}")
    return out


def main(argv: list[str] | None = None) -> dict[str, Any]:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--old", required=True, help="root of the other dcc-fg checkout (holds dcc_fg/)")
    p.add_argument("--mode", choices=("dcc", "scc"), default="dcc", help="VIO mode (default dcc)")
    persistence.add_flight_arguments(p)
    a = p.parse_args(argv)
    old = Path(a.old).resolve()
    if not (old / "dcc_fg" / "__init__.py").is_file():
        p.error(f"--old {a.old}: no dcc_fg package there (give the root of a dcc-fg checkout)")
    pairs = []
    for seed, fb in persistence.flights(a, moving=a.mode == "dcc"):
        before = run_checkout(old, fb.bag.parent, a.mode)
        after = run_checkout(THIS_CHECKOUT, fb.bag.parent, a.mode)
        pairs.append((before, after))
        print(persistence.pair_line(seed, before, after), flush=True)
    return persistence.report(pairs, f"this checkout / {old}", a.json)


if __name__ == "__main__":
    main()
