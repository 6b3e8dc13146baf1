"""Pack an EuRoC / ASL folder into a ROS1 or ROS2 bag plus a calibration.yaml for ``dcc-fg vio``.

Usage::

    python datasets/pack_euroc.py ../shared/data/euroc_v1_01_micro/MicroEurocDataset OUT [--ros 1|2]

writes ``OUT/euroc.bag`` (ROS1) or ``OUT/euroc/`` (ROS2) with ``/imu0``, ``/cam0/image_raw`` (static)
and ``/cam1/image_raw`` (cam1 as a one-joint gimbal camera locked at EuRoC's extrinsics, theta = 0),
and ``OUT/calibration.yaml`` (see :mod:`dcc_fg.io.euroc`, :mod:`dcc_fg.sources.euroc`).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from dcc_fg.io.euroc import pack_euroc_bag
from dcc_fg.sources.euroc import load_euroc, write_euroc_calibration


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("root", help="ASL folder (mav0 or its parent)")
    p.add_argument("out", help="output folder")
    p.add_argument("--ros", type=int, default=2, choices=[1, 2], help="bag format (default 2)")
    args = p.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    bag = pack_euroc_bag(args.root, out / ("euroc.bag" if args.ros == 1 else "euroc"), ros=args.ros)
    cal = write_euroc_calibration(load_euroc(args.root), out / "calibration.yaml")
    print(f"wrote {bag} and {cal}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
