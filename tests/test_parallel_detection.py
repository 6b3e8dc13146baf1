"""Detection on every core (``--jobs``): the ordered bounded pool, and the same detections as the serial
path, bit for bit and in the same order, for image folders, bags, unsynchronized streams and intrinsics."""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from dcc_fg.cli import main
from dcc_fg.data import CalibrationDataset
from dcc_fg.detection import detect_target
from dcc_fg.intrinsics import detect_views
from dcc_fg.io.camchain import load_camchain
from dcc_fg.sim.write_dataset import CalibrationSimSpec, RenderedCalibration, write_calibration_dataset
from dcc_fg.sources.dataset import load_dataset, load_streams
from dcc_fg.sources.parallel_detection import pool_jobs
from dcc_fg.targets import load_target
from dcc_fg.util.parallel import ordered_map, resolve_jobs, usable_cores


def _slow_square(x: int) -> int:
    """Later items finish first (sleep shorter): the pool must still yield in input order."""
    time.sleep(0.02 * (5 - x % 5))
    return x * x


def _fail_at_7(x: int) -> int:
    if x == 7:
        raise ValueError("item 7 is bad")
    return x


def test_ordered_map_keeps_order_bounds_memory_and_raises_in_place() -> None:
    read: list[int] = []

    def items(n: int) -> Iterator[int]:
        for i in range(n):
            read.append(i)
            yield i

    out = []
    ahead = []
    for r in ordered_map(_slow_square, items(20), jobs=2, window=4):
        out.append(r)
        ahead.append(len(read) - len(out))  # items read but not yet yielded
    assert out == [i * i for i in range(20)]
    assert max(ahead) <= 4  # never more than the window in flight
    got = []
    with pytest.raises(ValueError, match="item 7 is bad"):
        for r in ordered_map(_fail_at_7, range(12), jobs=2):
            got.append(r)
    assert got == list(range(7))  # everything before the bad item, in order
    # in chunks of 3 items per task: the same order, at most window * chunk items in flight, and the
    # bad item still raises at its own place (items 6 of its chunk [6, 7, 8] is yielded first)
    read.clear()
    out, ahead = [], []
    for r in ordered_map(_slow_square, items(20), jobs=2, window=2, chunk=3):
        out.append(r)
        ahead.append(len(read) - len(out))
    assert out == [i * i for i in range(20)] and max(ahead) <= 2 * 3
    got = []
    with pytest.raises(ValueError, match="item 7 is bad"):
        for r in ordered_map(_fail_at_7, range(12), jobs=2, chunk=3):
            got.append(r)
    assert got == list(range(7))
    assert list(ordered_map(_slow_square, iter(range(6)), jobs=1)) == [i * i for i in range(6)]
    assert resolve_jobs(0) == resolve_jobs(None) == usable_cores() >= 1 and resolve_jobs(3) == 3
    with pytest.raises(ValueError, match="--jobs must be >= 0"):
        resolve_jobs(-1)


class _Collect(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.append(record.getMessage())


def test_a_detector_that_cannot_be_pickled_runs_serially() -> None:
    # a handler on the module's logger: the CLI tests may have stopped dcc_fg's loggers propagating
    logger = logging.getLogger("dcc_fg.sources.parallel_detection")
    handler, level = _Collect(), logger.level
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    try:
        assert pool_jobs(lambda img, tgt: detect_target(img, tgt), 2) == 1  # noqa: PLW0108
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)
    assert any("not a module-level function" in m for m in handler.messages)
    assert pool_jobs(detect_target, 2) == 2 and pool_jobs(detect_target, 1) == 1


def _same(a: CalibrationDataset, b: CalibrationDataset) -> None:
    assert len(a.snapshots) == len(b.snapshots) > 0
    for s, t in zip(a.snapshots, b.snapshots, strict=True):
        assert s.timestamp_ns == t.timestamp_ns
        assert (s.joints is None and t.joints is None) or np.array_equal(s.joints, t.joints)
        for o, p in ((s.static, t.static), (s.dynamic, t.dynamic)):
            assert np.array_equal(o.ids, p.ids) and np.array_equal(o.pixels, p.pixels)  # bit for bit


@pytest.fixture(scope="module")
def rendered(tmp_path_factory: pytest.TempPathFactory) -> dict[str, RenderedCalibration]:
    root = tmp_path_factory.mktemp("pool")
    return {
        "folder": write_calibration_dataset(
            root / "f", CalibrationSimSpec("checkerboard", "folder", seed=3, n_snapshots=10)
        ),
        "ros2": write_calibration_dataset(root / "b", CalibrationSimSpec("aprilgrid", "ros2", seed=4, n_snapshots=8)),
        "ros1": write_calibration_dataset(
            root / "r1", CalibrationSimSpec("checkerboard", "ros1", seed=5, n_snapshots=8)
        ),
    }


@pytest.mark.parametrize("kind", ["folder", "ros2", "ros1"])
def test_load_dataset_gives_the_serial_detections_on_two_processes(
    rendered: dict[str, RenderedCalibration], kind: str
) -> None:
    r = rendered[kind]
    chain = load_camchain(r.camchain)
    serial = load_dataset(r.data, chain, r.target, progress=False, jobs=1)
    pooled = load_dataset(r.data, chain, r.target, progress=False, jobs=2)
    _same(serial, pooled)


@pytest.mark.parametrize(("kind", "where"), [("ros2", r"topic .* at \d+ ns"), ("folder", r"cam1/\d+\.png")])
def test_a_wrong_image_size_is_refused_alike_by_the_workers(
    rendered: dict[str, RenderedCalibration], kind: str, where: str
) -> None:
    """The workers that read the bag or the files themselves check each image against the camchain's
    resolution and raise the serial path's error, naming the message or the file."""
    r = rendered[kind]
    chain = load_camchain(r.camchain)
    cam1 = chain["cam1"]
    w, h = cam1.camera.resolution
    chain["cam1"] = dataclasses.replace(cam1, camera=dataclasses.replace(cam1.camera, resolution=(w + 2, h)))
    messages = []
    for jobs in (1, 2):
        with pytest.raises(ValueError, match=rf"{where}: image is {w}x{h} but the camchain's cam1") as e:
            load_dataset(r.data, chain, r.target, progress=False, jobs=jobs)
        messages.append(str(e.value))
    assert messages[0] == messages[1]


def test_streams_and_intrinsics_give_the_serial_detections(rendered: dict[str, RenderedCalibration]) -> None:
    r = rendered["folder"]
    a = load_streams(r.data, r.camchain, r.target, progress=False, jobs=1)
    b = load_streams(r.data, r.camchain, r.target, progress=False, jobs=2)
    for s, t in ((a.static, b.static), (a.dynamic, b.dynamic)):
        assert np.array_equal(s.stamps_ns, t.stamps_ns)
        assert all(np.array_equal(o.pixels, p.pixels) for o, p in zip(s.observations, t.observations, strict=True))
    target = load_target(r.target)
    v1, res1, n1, _ = detect_views(r.data, "cam1", target, every=2, progress=False, jobs=1)
    v2, res2, n2, _ = detect_views(r.data, "cam1", target, every=2, progress=False, jobs=2)
    assert (res1, n1) == (res2, n2) and n1 == 5 and [v.timestamp_ns for v in v1] == [v.timestamp_ns for v in v2]
    assert all(np.array_equal(x.observation.pixels, y.observation.pixels) for x, y in zip(v1, v2, strict=True))


def test_cli_refuses_negative_jobs(rendered: dict[str, RenderedCalibration], tmp_path: Path, capsys) -> None:  # noqa: ANN001
    r = rendered["folder"]
    code = main(
        ["intrinsics", str(r.data), "--target", str(r.target), "--out", str(tmp_path / "c.yaml"), "--jobs", "-2"]
    )
    assert code == 2 and "--jobs must be >= 0" in capsys.readouterr().err
    assert not (tmp_path / "c.yaml").exists()
