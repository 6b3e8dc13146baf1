"""The study file of ``dcc-fg batch``: read, validated as a whole, expanded into run tasks.

The schema is documented in :mod:`dcc_fg.batch`. Every check happens here, before any run starts:
unknown keys, wrong types, unknown modes, duplicate names, missing files, VIO options that
:class:`~dcc_fg.commands.vio.VioConfig` refuses, and ``scc`` runs without locked joint angles. A
refusal is a :class:`~dcc_fg.util.config.ConfigError` (a ``ValueError``: exit code 2) naming the
study file and the field, e.g. ``study.yaml: runs[1] (flight-b).modes[0]: unknown mode 'stereo'``.

Nothing here opens a bag: a corrupt recording is a failed *run*, reported in the table, not a
refused study.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from dcc_fg.commands.vio import VioConfig, check_config, config_text_vio
from dcc_fg.sim.trajectory import JointMotion
from dcc_fg.util.config import ConfigError, from_dict, to_plain
from dcc_fg.vio.backend import VioOptions

#: VIO modes a run may list (``dcc-fg vio --mode``).
MODES = ("dcc", "scc", "mono")
TOP_KEYS = ("out", "defaults", "runs")
DEFAULT_KEYS = ("modes", "options", "vio")
RUN_KEYS = ("name", "simulate", "bag", "calibration", "ground_truth", "imu_yaml", "camchain", "modes", "options", "vio")
BAG_KEYS = ("bag", "calibration", "ground_truth", "imu_yaml", "camchain")
SIM_KEYS = ("kind", "duration", "pattern", "seed", "scale", "gimbal", "format", "noise")
#: Smoother fields the study sets itself (``options`` may not): the field -> what sets it instead.
DERIVED_OPTIONS = {"mode": "the run's 'modes' list", "sigma": "vio.run.pixel_sigma (pixels)"}
#: VioConfig sections ``vio:`` may set (``smoother`` is ``options``).
VIO_SECTIONS = ("run", "topics", "frontend", "output")
#: A flight's hover and ramp, s (:class:`~dcc_fg.sim.trajectory.FlightConfig`): its duration must exceed them.
MIN_DURATION_S = 4.0
NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")
#: Length of the hexadecimal spec hash in folder names.
HASH_LENGTH = 12


def spec_hash(data: Any) -> str:
    """A stable hash of plain data (sorted-key JSON, SHA-256, first :data:`HASH_LENGTH` hex digits)."""
    text = json.dumps(to_plain(data), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:HASH_LENGTH]


def fingerprint(path: Path) -> list[Any]:
    """Size and modification time (ns) of a file, or of every file under a folder (a ROS2 bag), so a
    changed input gives a new spec hash."""
    if path.is_dir():
        files = sorted(p for p in path.rglob("*") if p.is_file())
        return [[str(p.relative_to(path)), p.stat().st_size, p.stat().st_mtime_ns] for p in files]
    st = path.stat()
    return [st.st_size, st.st_mtime_ns]


@dataclass(frozen=True)
class FlightSpec:
    """A simulated flight (:func:`dcc_fg.sim.flight_bag.write_flight`).

    ``pattern`` ``short``: one 16 m x 8 m loop (~48 m) flown in ``duration`` s
    (:meth:`~dcc_fg.sim.trajectory.FlightConfig.short`; below ~8 s the corners exceed the smoother's
    30 m/s ``max_speed``); ``loops``: the paper's two 30 m x 15 m loops (~180 m) in ``duration`` s.
    ``seed`` seeds the IMU noise, the textures and the image noise; ``scale`` is the image resolution
    relative to 640x480; ``gimbal`` ``moving`` (sinusoids and slews) or ``locked`` at its mid
    position; ``noise`` the image noise in grey levels (1 sigma); ``format`` ``ros1`` | ``ros2``.
    """

    duration: float = 20.0
    pattern: str = "short"
    seed: int = 0
    scale: float = 1.0
    gimbal: str = "moving"
    format: str = "ros2"
    noise: float = 2.0

    def key(self) -> dict[str, Any]:
        return {"kind": "flight", **dataclasses.asdict(self)}

    @property
    def folder_name(self) -> str:
        """The flight's folder under ``OUT/data``: readable prefix plus the spec hash."""
        return f"flight-s{self.seed}-{self.gimbal}-{spec_hash(self.key())}"


@dataclass(frozen=True)
class BagSpec:
    """A recording and its files (absolute paths): ``bag`` (ROS1 ``.bag`` or ROS2 folder), the
    ``calibration`` YAML, the ``ground_truth`` (TUM file, body frame, or a bag with
    ``/ground_truth/pose``), optional Kalibr ``imu_yaml`` and ``camchain``."""

    bag: str
    calibration: str
    ground_truth: str
    imu_yaml: str | None = None
    camchain: str | None = None

    def key(self) -> dict[str, Any]:
        files = {k: v for k, v in dataclasses.asdict(self).items() if v is not None}
        return {"kind": "bag", "files": files, "fingerprints": {k: fingerprint(Path(v)) for k, v in files.items()}}


@dataclass(frozen=True)
class RunTask:
    """One run and mode of the study: its data, its full VIO configuration and where it goes.

    ``run_id`` = ``NAME-MODE-HASH`` is the run's folder name under ``OUT/runs``; ``spec_hash`` hashes the
    data (a flight's settings, or the files' paths, sizes and times) and the effective VIO options,
    not the name: the same spec under another name is another folder, an edited spec a new hash.
    """

    name: str
    mode: str
    data: FlightSpec | BagSpec
    config: VioConfig
    spec_hash: str

    @property
    def run_id(self) -> str:
        return f"{self.name}-{self.mode}-{self.spec_hash}"

    def spec(self) -> dict[str, Any]:
        """The plain spec that was hashed (also stored in the run's ``result.json``)."""
        return {"data": self.data.key(), "mode": self.mode, "options": config_text_vio(self.config)}


@dataclass(frozen=True)
class Study:
    """A validated study: the file, the output folder (None: must come from ``--out``), the tasks in
    file order (runs, then modes)."""

    path: Path
    out: Path | None
    tasks: tuple[RunTask, ...]

    def inputs(self) -> dict[str, str]:
        """Every input file of the study by role (for the output-folder checks)."""
        found = {"STUDY": str(self.path)}
        for t in self.tasks:
            if isinstance(t.data, BagSpec):
                for k, v in dataclasses.asdict(t.data).items():
                    if v is not None:
                        found[f"{t.name}.{k}"] = v
        return found


def _mapping(value: Any, where: str) -> Mapping[str, Any]:
    if not isinstance(value, Mapping):
        raise ConfigError(f"{where}: expected a mapping, got {type(value).__name__} {value!r}")
    return value


def _known(data: Mapping[str, Any], keys: tuple[str, ...], where: str) -> None:
    unknown = sorted(str(k) for k in data if k not in keys)
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {', '.join(unknown)}; known: {', '.join(keys)}")


def _number(value: Any, where: str, minimum: float, integer: bool = False) -> float:
    ok = isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
    if not ok or (integer and float(value) != int(value)):
        raise ConfigError(f"{where}: expected {'an integer' if integer else 'a number'}, got {value!r}")
    if value < minimum:
        raise ConfigError(f"{where}: must be >= {minimum:g}, got {value!r}")
    return float(value)


def _choice(value: Any, choices: tuple[str, ...], where: str) -> str:
    if value not in choices:
        raise ConfigError(f"{where}: expected one of {', '.join(choices)}, got {value!r}")
    return str(value)


def parse_simulate(data: Any, where: str) -> list[FlightSpec]:
    """The ``simulate:`` mapping as one flight per seed (``seed`` may be a list)."""
    data = _mapping(data, where)
    _known(data, SIM_KEYS, where)
    _choice(data.get("kind", "flight"), ("flight",), f"{where}.kind")
    spec = FlightSpec()
    pattern = _choice(data.get("pattern", spec.pattern), ("short", "loops"), f"{where}.pattern")
    duration = _number(data.get("duration", 90.0 if pattern == "loops" else spec.duration), f"{where}.duration", 0)
    if duration <= MIN_DURATION_S:
        raise ConfigError(
            f"{where}.duration: must exceed {MIN_DURATION_S:g} s (1 s hover + 3 s ramp), got {duration:g}"
        )
    scale = _number(data.get("scale", spec.scale), f"{where}.scale", 0.1)
    if scale > 2.0:
        raise ConfigError(f"{where}.scale: must be within [0.1, 2], got {scale:g}")
    seeds = data.get("seed", spec.seed)
    seed_list = seeds if isinstance(seeds, list) else [seeds]
    if not seed_list:
        raise ConfigError(f"{where}.seed: an empty list")
    checked = [int(_number(s, f"{where}.seed", 0, integer=True)) for s in seed_list]
    if len(set(checked)) != len(checked):
        raise ConfigError(f"{where}.seed: repeated seeds {checked}")
    common = {
        "duration": duration,
        "pattern": pattern,
        "scale": scale,
        "gimbal": _choice(data.get("gimbal", spec.gimbal), ("moving", "locked"), f"{where}.gimbal"),
        "format": _choice(data.get("format", spec.format), ("ros1", "ros2"), f"{where}.format"),
        "noise": _number(data.get("noise", spec.noise), f"{where}.noise", 0.0),
    }
    return [FlightSpec(seed=s, **common) for s in checked]


def _path(value: Any, base: Path, where: str, must_exist: bool = True) -> str:
    if not isinstance(value, str) or not value:
        raise ConfigError(f"{where}: expected a path, got {value!r}")
    p = Path(value).expanduser()
    p = (p if p.is_absolute() else base / p).resolve()
    if must_exist and not p.exists():
        raise ConfigError(f"{where}: {p} not found")
    return str(p)


def parse_bag(data: Mapping[str, Any], base: Path, where: str) -> BagSpec:
    """The ``bag``, ``calibration``, ``ground_truth`` (+ ``imu_yaml``, ``camchain``) keys of a run."""
    for key in ("calibration", "ground_truth"):
        if key not in data:
            raise ConfigError(f"{where}: a bag run needs '{key}'")
    paths = {k: _path(data[k], base, f"{where}.{k}") for k in BAG_KEYS if data.get(k) is not None}
    if not Path(paths["calibration"]).is_file():
        raise ConfigError(f"{where}.calibration: {paths['calibration']} is not a file")
    return BagSpec(**paths)


def parse_modes(value: Any, where: str) -> tuple[str, ...]:
    if isinstance(value, str):
        value = [value]
    if not isinstance(value, list) or not value:
        raise ConfigError(f"{where}: expected a non-empty list of modes ({', '.join(MODES)}), got {value!r}")
    modes = tuple(_choice(m, MODES, f"{where}[{i}]") for i, m in enumerate(value))
    if len(set(modes)) != len(modes):
        raise ConfigError(f"{where}: repeated modes {list(modes)}")
    return modes


def parse_config(options: Any, vio: Any, where: str) -> VioConfig:
    """The run's :class:`VioConfig`: ``vio`` sections over the batch defaults (front end inline: the
    parallelism is across runs), ``options`` over the smoother's defaults."""
    vio = dict(_mapping(vio if vio is not None else {}, f"{where}.vio"))
    _known(vio, VIO_SECTIONS, f"{where}.vio")
    run = dict(_mapping(vio.get("run") or {}, f"{where}.vio.run"))
    run.setdefault("frontend_worker", "inline")
    config = from_dict(VioConfig, {**vio, "run": run}, f"{where}.vio")
    options = _mapping(options if options is not None else {}, f"{where}.options")
    for key, instead in DERIVED_OPTIONS.items():
        if key in options:
            raise ConfigError(f"{where}.options.{key}: set by the study; use {instead}")
    smoother = from_dict(VioOptions, options, f"{where}.options", config.smoother)
    config = dataclasses.replace(config, smoother=smoother)
    check_config(config, f"{where}.vio")
    return config


def locked_joints(data: FlightSpec | BagSpec, config: VioConfig, where: str) -> tuple[float, ...]:
    """The locked joint angles (rad) of an ``scc`` run: ``options.theta_fixed``, else a simulated
    flight's mid position, else the calibration's ``flight.joints_locked`` (simulated recordings)."""
    if config.smoother.theta_fixed is not None:
        return tuple(config.smoother.theta_fixed)
    if isinstance(data, FlightSpec):
        return tuple(float(x) for x in JointMotion().mid)
    try:
        cal = yaml.safe_load(Path(data.calibration).read_text())
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        raise ConfigError(
            f"{where}.calibration: {data.calibration} unreadable ({' '.join(str(exc).split())})"
        ) from None
    locked = (cal.get("flight") or {}).get("joints_locked") if isinstance(cal, dict) else None
    if not isinstance(locked, list) or not locked:
        raise ConfigError(f"{where}.modes: scc needs the locked joint angles: give options.theta_fixed (rad)")
    return tuple(float(x) for x in locked)


def check_joint_counts(data: FlightSpec | BagSpec, config: VioConfig, where: str) -> None:
    """A simulated flight's gimbal has ``len(JointMotion().mid)`` joints: joint-angle options of another
    length are refused now, not after the flight is rendered (a bag's calibration is checked by its run)."""
    if not isinstance(data, FlightSpec):
        return
    n = len(JointMotion().mid)
    for key in ("theta_fixed", "theta_initial"):
        value = getattr(config.smoother, key)
        if value is not None and len(value) != n:
            raise ConfigError(f"{where}.options.{key}: the simulated gimbal has {n} joints, got {list(value)} (rad)")


def run_tasks(name: str, data: FlightSpec | BagSpec, modes: tuple[str, ...], config: VioConfig,
              where: str) -> list[RunTask]:  # fmt: skip
    """One task per mode; an ``scc`` run of a simulated flight flies it with the gimbal locked (the paper's
    SCC), at the angles it is held at."""
    check_joint_counts(data, config, where)
    tasks = []
    for mode in modes:
        smoother = dataclasses.replace(config.smoother, mode=mode)
        task_data = data
        if mode == "scc":
            smoother = dataclasses.replace(smoother, theta_fixed=locked_joints(data, config, where))
            if isinstance(data, FlightSpec):
                task_data = dataclasses.replace(data, gimbal="locked")
        cfg = dataclasses.replace(config, smoother=smoother)
        key = {"data": task_data.key(), "mode": mode, "options": config_text_vio(cfg)}
        tasks.append(RunTask(name, mode, task_data, cfg, spec_hash(key)))
    return tasks


def parse_run(entry: Any, defaults: Mapping[str, Any], base: Path, where: str) -> list[RunTask]:
    """The tasks of one ``runs`` entry (a list of seeds gives one run per seed, named ``NAME-seedN``)."""
    entry = _mapping(entry, where)
    _known(entry, RUN_KEYS, where)
    name = entry.get("name")
    if not isinstance(name, str) or not NAME_RE.match(name):
        raise ConfigError(f"{where}.name: expected a name of letters, digits, '_', '.', '-', got {name!r}")
    where = f"{where} ({name})"
    has_bag = "bag" in entry
    if has_bag == ("simulate" in entry):
        raise ConfigError(f"{where}: give exactly one of 'bag' (a recording) or 'simulate' (a simulated flight)")
    if not has_bag:
        extra = [k for k in BAG_KEYS if k in entry]
        if extra:
            raise ConfigError(f"{where}.{extra[0]}: only for a 'bag' run (a simulated flight brings its own)")
    modes = parse_modes(entry.get("modes", defaults.get("modes", ["dcc"])), f"{where}.modes")
    options = {**defaults.get("options", {}), **_mapping(entry.get("options") or {}, f"{where}.options")}
    vio = {**defaults.get("vio", {}), **_mapping(entry.get("vio") or {}, f"{where}.vio")}
    config = parse_config(options, vio, where)
    if has_bag:
        return run_tasks(name, parse_bag(entry, base, where), modes, config, where)
    flights = parse_simulate(entry["simulate"], f"{where}.simulate")
    if len(flights) == 1:
        return run_tasks(name, flights[0], modes, config, where)
    return [t for f in flights for t in run_tasks(f"{name}-seed{f.seed}", f, modes, config, where)]


def parse_study(data: Any, path: Path) -> Study:
    """Validate the parsed YAML of the study file ``path`` (paths relative to its folder)."""
    where = str(path)
    data = _mapping(data, where)
    _known(data, TOP_KEYS, where)
    base = path.resolve().parent
    defaults = dict(_mapping(data.get("defaults") or {}, f"{where}: defaults"))
    _known(defaults, DEFAULT_KEYS, f"{where}: defaults")
    for key in ("options", "vio"):
        defaults[key] = dict(_mapping(defaults.get(key) or {}, f"{where}: defaults.{key}"))
    runs = data.get("runs")
    if not isinstance(runs, list) or not runs:
        raise ConfigError(f"{where}: runs: expected a non-empty list of runs")
    tasks: list[RunTask] = []
    for i, entry in enumerate(runs):
        tasks += parse_run(entry, defaults, base, f"{where}: runs[{i}]")
    ids = [(t.name, t.mode) for t in tasks]
    repeated = sorted({f"{n} ({m})" for n, m in ids if ids.count((n, m)) > 1})
    if repeated:
        raise ConfigError(f"{where}: runs: repeated run names: {', '.join(repeated)}")
    out = data.get("out")
    out_path = Path(_path(out, base, f"{where}: out", must_exist=False)) if out is not None else None
    return Study(path.resolve(), out_path, tuple(tasks))


def load_study(path: str | Path) -> Study:
    """Read and validate a study file (module docstring); FileNotFoundError or ConfigError."""
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"{p}: study file not found")
    try:
        data = yaml.safe_load(p.read_bytes().decode("utf-8"))
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{p}: not a text file (byte offset {exc.start} is not UTF-8); expected YAML") from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"{p}: malformed YAML: {' '.join(str(exc).split())}") from None
    return parse_study(data, p)
