"""``dcc-fg calibrate`` / ``validate`` on a small rendered data set: summary, unpaired frames, bad input.

Every bad input must give a clear error naming the file / topic / field, exit code != 0, and leave
an existing OUT/calibration.yaml unchanged (nothing half-written).
"""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import yaml

import dcc_fg.commands.common
from dcc_fg.cli import main
from dcc_fg.io.bag_writer import write_ros1_bag
from dcc_fg.io.folders import ImageFolder
from dcc_fg.sim.write_dataset import CalibrationSimSpec, RenderedCalibration, write_calibration_dataset

SENTINEL = "sentinel: previous calibration\n"


@pytest.fixture(scope="module")
def small(tmp_path_factory: pytest.TempPathFactory) -> RenderedCalibration:
    spec = CalibrationSimSpec("checkerboard", "folder", seed=5, n_snapshots=12)
    return write_calibration_dataset(tmp_path_factory.mktemp("small"), spec)


def _args(r: RenderedCalibration, data: Path, out: Path, **over: Path) -> list[str]:
    files = {"camchain": r.camchain, "target": r.target, "gimbal": r.gimbal, **over}
    argv = ["calibrate", str(data), "--out", str(out)]
    for k, v in files.items():
        argv += [f"--{k}", str(v)]
    return argv


def test_calibrate_prints_summary_and_reports_unpaired_frames(small: RenderedCalibration, tmp_path, capsys) -> None:  # noqa: ANN001
    data = tmp_path / "images"
    shutil.copytree(small.data, data)
    sorted((data / "cam1").glob("*.png"))[3].unlink()  # one static frame loses its partner
    out = tmp_path / "out"
    assert main(_args(small, data, out)) == 0
    captured = capsys.readouterr()
    text = captured.out
    assert "11 image pairs; unpaired frames: 1 cam0, 0 cam1" in text
    assert "snapshots: 11 used, 0 rejected" in text
    assert "RMS/axis px" in text and "static" in text and "dynamic" in text
    assert "observability (information matrix)" in text and "held fixed to remove the gauge" in text
    assert "T_ds 1-sigma per snapshot: rotation median" in text
    assert "detect" not in captured.err  # no progress bar when stderr is not a terminal
    # validate the same frames with the calibration's own intrinsics (no --camchain)
    out2 = tmp_path / "val"
    argv = ["validate", str(data), "--calibration", str(out / "calibration.yaml"), "--target", str(small.target)]
    assert main([*argv, "--out", str(out2), "--quiet"]) == 0
    assert capsys.readouterr().out == ""  # --quiet: no table
    assert (out2 / "joint_angles.csv").is_file()


def _fails(argv: list[str], out: Path, capsys: pytest.CaptureFixture[str], *needles: str) -> None:
    out.mkdir(parents=True, exist_ok=True)
    (out / "calibration.yaml").write_text(SENTINEL)
    assert main(argv) != 0
    err = capsys.readouterr().err
    for needle in needles:
        assert needle in err, f"{needle!r} not in {err!r}"
    assert (out / "calibration.yaml").read_text() == SENTINEL
    assert sorted(p.name for p in out.iterdir()) == ["calibration.yaml"]  # nothing else written


def test_bag_with_a_missing_topic(small: RenderedCalibration, tmp_path, capsys) -> None:  # noqa: ANN001
    bag = write_ros1_bag(tmp_path / "small.bag", list(ImageFolder(small.data))[:3])
    chain = yaml.safe_load(small.camchain.read_text())
    chain["cam1"]["rostopic"] = "/gimbal_cam/image_raw"
    camchain = tmp_path / "camchain.yaml"
    camchain.write_text(yaml.safe_dump(chain))
    _fails(_args(small, bag, tmp_path / "out", camchain=camchain), tmp_path / "out", capsys, "/gimbal_cam/image_raw")


def test_camchain_without_cam1(small: RenderedCalibration, tmp_path, capsys) -> None:  # noqa: ANN001
    chain = yaml.safe_load(small.camchain.read_text())
    del chain["cam1"]
    camchain = tmp_path / "camchain_one.yaml"
    camchain.write_text(yaml.safe_dump(chain))
    argv = _args(small, small.data, tmp_path / "out", camchain=camchain)
    _fails(argv, tmp_path / "out", capsys, "camchain_one.yaml", "cam1")


def test_camchain_missing_a_field(small: RenderedCalibration, tmp_path, capsys) -> None:  # noqa: ANN001
    chain = yaml.safe_load(small.camchain.read_text())
    del chain["cam0"]["distortion_coeffs"]
    camchain = tmp_path / "camchain_bad.yaml"
    camchain.write_text(yaml.safe_dump(chain))
    argv = _args(small, small.data, tmp_path / "out", camchain=camchain)
    _fails(argv, tmp_path / "out", capsys, "camchain_bad.yaml", "cam0", "distortion_coeffs")


def test_target_missing_a_field(small: RenderedCalibration, tmp_path, capsys) -> None:  # noqa: ANN001
    tgt = yaml.safe_load(small.target.read_text())
    del tgt["targetRows"]
    target = tmp_path / "target_bad.yaml"
    target.write_text(yaml.safe_dump(tgt))
    argv = _args(small, small.data, tmp_path / "out", target=target)
    _fails(argv, tmp_path / "out", capsys, "target_bad.yaml", "targetRows")


def test_corrupt_image(small: RenderedCalibration, tmp_path, capsys) -> None:  # noqa: ANN001
    data = tmp_path / "images"
    shutil.copytree(small.data, data)
    broken = sorted((data / "cam1").glob("*.png"))[5]
    broken.write_bytes(b"\x89PNG\r\n\x1a\n" + b"\x00" * 100)  # PNG signature, no image
    _fails(_args(small, data, tmp_path / "out"), tmp_path / "out", capsys, str(broken), "does not decode")


def test_malformed_yaml(small: RenderedCalibration, tmp_path, capsys) -> None:  # noqa: ANN001
    gimbal = tmp_path / "gimbal_bad.yaml"
    gimbal.write_text("joints: [2\ntau_s: ]")
    _fails(
        _args(small, small.data, tmp_path / "out", gimbal=gimbal), tmp_path / "out", capsys, "YAML", "gimbal_bad.yaml"
    )


@pytest.mark.parametrize("quiet", [False, True])
def test_progress_bar_on_a_terminal_unless_quiet(
    small: RenderedCalibration,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    quiet: bool,
) -> None:
    """The bar goes to stderr on a terminal; --quiet turns it off.  (A run that stops after detection:
    no pair has 1000 common corners, which also checks --min-common-points.)"""
    monkeypatch.setattr(dcc_fg.commands.common, "stderr_is_terminal", lambda: True)
    argv = _args(small, small.data, tmp_path / "out") + ["--min-common-points", "1000"] + (["--quiet"] if quiet else [])
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "at least 1000 common target points" in err
    assert ("detect images:" in err and "pair/s" in err) != quiet


# The remaining bad inputs of issue 3, each through the whole command (error text, exit code,
# nothing written to OUT).


def test_truncated_bag(small: RenderedCalibration, tmp_path, capsys) -> None:  # noqa: ANN001
    bag = write_ros1_bag(tmp_path / "cut.bag", list(ImageFolder(small.data))[:4])
    data = bag.read_bytes()
    bag.write_bytes(data[: int(0.7 * len(data))])
    _fails(_args(small, bag, tmp_path / "out"), tmp_path / "out", capsys, "cut.bag", "truncated or corrupt bag")


def test_target_never_detected(small: RenderedCalibration, tmp_path, capsys) -> None:  # noqa: ANN001
    import cv2
    import numpy as np

    data = tmp_path / "images"
    shutil.copytree(small.data, data)
    for png in data.glob("cam*/*.png"):
        img = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(png), np.full_like(img, 128))  # same size, no board
    _fails(_args(small, data, tmp_path / "out"), tmp_path / "out", capsys, "never detected", "cam0", "cam1")


def test_timestamps_that_never_pair(small: RenderedCalibration, tmp_path, capsys) -> None:  # noqa: ANN001
    data = tmp_path / "images"
    shutil.copytree(small.data, data)
    for png in sorted((data / "cam1").glob("*.png"), reverse=True):  # every dynamic frame half a period (50 ms) later
        png.rename(png.with_name(f"{int(png.stem) + 50_000_000}.png"))
    _fails(_args(small, data, tmp_path / "out"), tmp_path / "out", capsys, "never pair", "cam0", "cam1")


def test_joint_that_never_moves(tmp_path, capsys) -> None:  # noqa: ANN001
    """A recording in which joint 2 is locked (detections folder + joints.csv): with --gimbal the
    command names joint 2 as unobservable; with the automatic initialization (no gimbal.yaml, no
    joint readings) it says that the images alone do not tell which joint never moves."""
    import numpy as np

    from dcc_fg.io.camchain import CamchainEntry, camchain_to_yaml
    from dcc_fg.sim.calibration_scene import SceneConfig, simulate_calibration, simulate_snapshots
    from dcc_fg.sources.detections import write_detection_csv
    from dcc_fg.targets import TargetGeometry

    grid = TargetGeometry.aprilgrid(6, 5, 0.06, 0.3)
    sim = simulate_calibration(2, SceneConfig(n_calibration=20, n_validation=1, target=grid))
    locked = np.column_stack([sim.joints_calibration[:, 0], np.zeros(20)])
    data, _, _ = simulate_snapshots(sim.truth, locked, sim.config, np.random.default_rng(0), "locked")
    root = tmp_path / "detections"
    for cam in ("cam0", "cam1"):
        (root / cam).mkdir(parents=True)
    for s in data.snapshots:
        write_detection_csv(root / "cam0" / f"{s.timestamp_ns}.csv", s.timestamp_ns, s.static, grid)
        write_detection_csv(root / "cam1" / f"{s.timestamp_ns}.csv", s.timestamp_ns, s.dynamic, grid)
    lines = ["timestamp_ns,theta_1,theta_2"] + [
        f"{s.timestamp_ns},{t[0]:.9f},{t[1]:.9f}" for s, t in zip(data.snapshots, locked, strict=True)
    ]
    (root / "joints.csv").write_text("\n".join(lines) + "\n")
    camchain = tmp_path / "camchain.yaml"
    camchain.write_text(
        camchain_to_yaml({"cam0": CamchainEntry(data.static_camera), "cam1": CamchainEntry(data.dynamic_camera)})
    )
    gimbal = tmp_path / "gimbal.yaml"
    sim.initial.save(gimbal)
    base = ["calibrate", str(root), "--camchain", str(camchain)]
    out = tmp_path / "out"
    _fails([*base, "--gimbal", str(gimbal), "--out", str(out)], out, capsys, "joint 2 never moves", "unobservable")
    (root / "joints.csv").unlink()
    out = tmp_path / "out_auto"
    _fails([*base, "--joints", "2", "--out", str(out)], out, capsys, "never moves", "images alone do not tell which")
