"""The command-line demo: outputs exist, parse and read back."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dcc_fg import load_calibration
from dcc_fg.cli import main
from dcc_fg.io.outputs import read_joint_angles_csv


@pytest.mark.slow
def test_demo_writes_outputs(tmp_path, capsys) -> None:
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "Table I" in text and "Table II" in text and "Table III" in text and "T_ds" in text
    cal = load_calibration(out / "calibration.yaml")
    t, th = read_joint_angles_csv(out / "joint_angles.csv")
    assert th.shape == (81, 2) and t.shape == (81,)
    T = cal.T_ds(th[0])
    assert T.shape == (4, 4) and np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3))
    summary = json.loads((out / "summary.json").read_text())
    gt = summary["ground_truth_errors"]
    assert set(gt) == {"bundle", "two_way"}
    assert summary["calibration"]["reprojection_error_px"]["all"]["count"] == 81 * 63 * 2
    assert len(list(out.glob("calibration_*.png"))) == 6  # the demo saves its calibration figures
    assert summary["dcc_fg_version"] and summary["command"] == "demo" and summary["options"]["joints"] == 2


def test_cli_reports_bad_input_cleanly(tmp_path, capsys) -> None:
    rc = main(["validate", str(tmp_path / "missing"), "--calibration", str(tmp_path / "nope.yaml")])
    assert rc == 2
    assert "nope.yaml" in capsys.readouterr().err
