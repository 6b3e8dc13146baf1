"""VIO output files: one trajectory.tum, plus one file per segment after a restart of the smoother."""

from __future__ import annotations

import json

import numpy as np

from dcc_fg.io.tum import read_tum
from dcc_fg.vio.backend.options import VioResult
from dcc_fg.vio.backend.outputs import segment_bounds, write_vio_outputs


def _result(segments: list[dict]) -> VioResult:
    n = 10
    t = (np.arange(n, dtype=np.int64) + 1) * 100_000_000
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, 0, 3] = np.arange(n, dtype=float)
    stats = {"segments": segments, "segment_count": len(segments)}
    return VioResult(t, T, np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 2)), "dcc", stats)


def test_one_segment_writes_no_segment_files(tmp_path):
    res = _result([{"start_ns": 100_000_000, "reason": "start"}])
    assert segment_bounds(res) == []
    write_vio_outputs(tmp_path, res)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["joint_angles.csv", "summary.json", "trajectory.tum"]


def test_restart_writes_each_segment_on_its_own(tmp_path):
    res = _result([{"start_ns": 100_000_000, "reason": "start"}, {"start_ns": 600_000_000, "reason": "IMU gap"}])
    write_vio_outputs(tmp_path, res)
    whole = read_tum(tmp_path / "trajectory.tum")
    first, second = read_tum(tmp_path / "trajectory_segment_1.tum"), read_tum(tmp_path / "trajectory_segment_2.tum")
    assert len(whole[0]) == 10 and len(first[0]) == 5 and len(second[0]) == 5
    np.testing.assert_array_equal(np.concatenate([first[0], second[0]]), whole[0])
    assert json.loads((tmp_path / "summary.json").read_text())["segment_count"] == 2
