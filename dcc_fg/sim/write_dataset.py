"""Write a complete rendered calibration data set: images (folder or bag) + configuration + truth.

``dcc-fg simulate calibration --out OUT`` (:func:`write_calibration_dataset` with a
:class:`CalibrationSimSpec`) simulates the
paper's scenario (:mod:`dcc_fg.sim.calibration_scene`: geometry, cameras, joint sampling, board
placement, perturbed initial kinematics, all seeded), renders every snapshot's two images through
the true camera models (:mod:`dcc_fg.sim.render`) and writes::

    OUT/images/cam0/<ns>.png, OUT/images/cam1/<ns>.png    --format folder
    OUT/images.bag                                        --format ros1
    OUT/images_bag/  (metadata.yaml + .db3 or .mcap)      --format ros2
    OUT/camchain.yaml      Kalibr camchain: cam0 static, cam1 dynamic, rostopic /cam0/image_raw, /cam1/image_raw
    OUT/target.yaml        Kalibr target
    OUT/gimbal.yaml        initial kinematics, perturbed from the truth as the simulator does
                           (translations + N(0, 0.03 m), angles + N(0, 10 deg))
    OUT/ground_truth.yaml  the truth (format below)

With ``random_mechanism=SEED`` (``--random-mechanism SEED``) the scenario is member ``SEED`` of the
randomized family (:mod:`dcc_fg.sim.mechanism_family`: its kinematics, joint ranges, cameras,
target and board distances, L drawn unless ``n_joints`` is given); its corner-level scene is
:func:`~dcc_fg.sim.mechanism_family.simulate_member` (seeded by ``SEED``), ``seed`` then only seeds
the image noise, and ``target`` is not used.

No joint angles are written with the images (an encoderless recording).  The dynamic image of
each snapshot is stamped ``DYNAMIC_STAMP_OFFSET_NS`` after the static one (a realistic trigger
skew well inside the default 5 ms pairing tolerance).

``ground_truth.yaml`` (angles in radians, lengths in metres, transforms 4x4 row-major, ``T_ab``
maps points from frame b into frame a)::

    format: dcc-fg ground truth 1
    seed, scene: {...}, render: {...}     # how the data were made
    random_mechanism: SEED, mechanism: {...}  # only with --random-mechanism: the family member's
                                             # description, plus achieved_half_range_deg and
                                             # achieved_std_deg of the true angles simulated
    data: images | images.bag | images_bag
    target: {Kalibr target}
    kinematics: {joints, tau_s, tau_d, dh}   # the true mechanism (gimbal.yaml schema)
    snapshots:                               # one per image pair, in time order
      - timestamp_ns: ...                    # static image stamp (= the snapshot time)
        dynamic_timestamp_ns: ...
        theta: [...]                         # true joint angles
        theta_guess: [...]                   # the simulator's perturbed guesses (not written with the images)
        T_ds: [[...] x4]                     # true static -> dynamic camera
        T_st: [[...] x4]                     # true target -> static camera (the rendered pose)

With ``--motion continuous`` (``spec.motion``, :mod:`dcc_fg.sim.calibration_motion`) the board
and the gimbal keep moving through the snapshots (the waypoints) while each camera records at its
own rate, phase, time offset and stamp jitter (``spec.timing``, :mod:`dcc_fg.sim.timing`; convention
``t_true = t_stamp + t_offset``, an image exposed at true time t is stamped ``t - t_offset``). Each
image is rendered at its true exposure time; the bag's record time is the exposure time, the
header stamp the camera's stamp; the image folder names files by their stamps. Times are
``CONTINUOUS_T0_NS`` (1 s) + the recording's time. ``ground_truth.yaml`` then keeps every key above
(so :func:`load_ground_truth` reads it) and adds::

    snapshots:                      # one per STATIC image (no longer per waypoint)
      - timestamp_ns: ...           # the static image's header stamp
        dynamic_timestamp_ns: ...   # the nearest gimbal header stamp (null if none)
        exposure_ns: ...            # the static image's true exposure time
        theta, T_ds, T_st: ...      # truth at that exposure time; theta_guess: []
    motion:
      mode: continuous
      timing: {convention, rates_hz: {static, dynamic}, phase_s, time_offsets_s: {static, dynamic},
               stamp_jitter_s}
      t0_ns: 1000000000
      duration_s: ...
      limits: {max_target_rate_deg_s, max_target_speed_m_s, max_joint_rate_deg_s, min_segment_s}
      waypoints: [{exposure_ns, theta, T_st}]   # the path passes through them at rest
    images:
      static:  [{stamp_ns, exposure_ns, theta, T_st, T_ds, visible}]   # every image, exposure order
      dynamic: [{stamp_ns, exposure_ns, theta, T_st, T_ds, visible}]

(``visible``: every corner inside that camera's image.) Held mode (the default) writes exactly the
files described above, and refuses non-default timing.

:func:`load_ground_truth` reads it back.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np
import yaml
from numpy.typing import NDArray

from dcc_fg.io.bag_writer import BagWriter, image_message, write_ros1_bag, write_ros2_bag
from dcc_fg.io.camchain import CamchainEntry, camchain_to_yaml
from dcc_fg.io.folders import FramePair, write_image_folder
from dcc_fg.io.output_set import OutputSet
from dcc_fg.io.outputs import write_text_atomic
from dcc_fg.model import GimbalCalibration
from dcc_fg.sim.calibration_motion import ContinuousMotion, MotionLimits, corners_visible
from dcc_fg.sim.calibration_scene import SceneConfig, SimulatedCalibration, simulate_calibration
from dcc_fg.sim.mechanism_family import FamilyMember, achieved_spread, family_member, simulate_member
from dcc_fg.sim.render import BoardTexture, RenderConfig, aprilgrid_view_flip, make_texture, render_view
from dcc_fg.sim.timing import CameraTiming
from dcc_fg.targets import TargetGeometry

FloatArray = NDArray[np.float64]
Format = Literal["folder", "ros1", "ros2"]
Motion = Literal["held", "continuous"]

STATIC_TOPIC = "/cam0/image_raw"
DYNAMIC_TOPIC = "/cam1/image_raw"
DYNAMIC_STAMP_OFFSET_NS = 500_000  # 0.5 ms
DATA_NAMES = {"folder": "images", "ros1": "images.bag", "ros2": "images_bag"}
#: Stamps and exposure times of a continuous recording are this plus the recording's time (ns).
CONTINUOUS_T0_NS = 1_000_000_000


def default_target(kind: str) -> TargetGeometry:
    """The rendered boards.

    * ``checkerboard``: 10 x 7 inner corners, 0.06 m squares.  The corner-level scene's 9 x 7
      board is 180-degree symmetric including its square colours, so no detector can give its
      corners the same ids in both cameras; one more column (odd x even) makes the orientation
      unambiguous at the same square size and row count.
    * ``aprilgrid``: 6 x 6 tag36h11 tags of 0.06 m, spacing ratio 0.3 (0.45 m square, 144 corners).
    """
    if kind == "checkerboard":
        return TargetGeometry.checkerboard(10, 7, 0.06)
    if kind == "aprilgrid":
        return TargetGeometry.aprilgrid(6, 6, 0.06, 0.3)
    raise ValueError(f"--target must be checkerboard or aprilgrid, got '{kind}'")


def scene_config(target: TargetGeometry, n_snapshots: int = 81, n_joints: int = 2) -> SceneConfig:
    """The corner-level scene a rendered data set is made from (no validation set)."""
    return SceneConfig(n_joints=n_joints, n_calibration=n_snapshots, n_validation=0, target=target)


@dataclass
class RenderedCalibration:
    """What :func:`write_calibration_dataset` wrote.

    Attributes:
        sim: the corner-level simulation the images were rendered from (same seed and scene:
            ``sim.calibration_set`` is the corner-level data set of the same scenario, with the
            corner ids of ``sim.config.target`` in the unflipped board pose).
        data: the image folder / bag written.
        camchain, target, gimbal, ground_truth: the files written.
        T_st: (K, 4, 4) the rendered (true) target poses in the static camera (held: per snapshot;
            continuous: per static image, at its true exposure time).
        render_time_s: wall time of rendering and writing the images.
        images: continuous motion only: images written per camera (static, gimbal).
    """

    sim: SimulatedCalibration
    data: Path
    camchain: Path
    target: Path
    gimbal: Path
    ground_truth: Path
    T_st: FloatArray
    render_time_s: float
    images: tuple[int, int] | None = None


def _rendered_poses(sim: SimulatedCalibration) -> FloatArray:
    """The target poses to render: the simulator's, with an AprilGrid turned to face the cameras."""
    tg = sim.config.target
    if tg.target_type == "aprilgrid":
        return np.array([T @ aprilgrid_view_flip(tg) for T in sim.T_st_calibration])
    return sim.T_st_calibration.copy()


def _frames(
    sim: SimulatedCalibration, T_st: FloatArray, render: RenderConfig, rng: np.random.Generator
) -> Iterator[FramePair]:
    cams = (sim.truth.static_camera, sim.truth.dynamic_camera)
    assert cams[0] is not None and cams[1] is not None
    texture = make_texture(sim.config.target, render.texel_m)
    for k, snap in enumerate(sim.calibration_set.snapshots):
        T_ds = sim.truth.T_ds(sim.joints_calibration[k])
        img_s = render_view(cams[0], T_st[k], texture, render, rng)
        img_d = render_view(cams[1], T_ds @ T_st[k], texture, render, rng)
        ts = int(snap.timestamp_ns)
        yield FramePair(ts, img_s, img_d, None, "", "", ts + DYNAMIC_STAMP_OFFSET_NS)


def _kinematics_dict(cal: GimbalCalibration) -> dict[str, Any]:
    return {
        "joints": cal.n_joints,
        "tau_s": [float(x) for x in cal.tau_s],
        "tau_d": [float(x) for x in cal.tau_d],
        "dh": [[float(x) for x in row] for row in cal.dh],
    }


def _matrix(T: FloatArray) -> list[list[float]]:
    return [[float(x) for x in row] for row in T]


@dataclass(frozen=True)
class CalibrationSimSpec:
    """What :func:`write_calibration_dataset` simulates and how it writes it.

    Attributes:
        target: ``checkerboard`` or ``aprilgrid`` (see :func:`default_target`); not used with
            ``random_mechanism``.
        fmt: ``folder``, ``ros1`` or ``ros2``.
        seed: seed of the scene and of the image noise (only of the image noise with
            ``random_mechanism``).
        n_snapshots: image pairs (the scene's jittered grid over the joint space).
        n_joints: L in {0, 1, 2, 3}; None: 2, or drawn by the family with ``random_mechanism``
            (which allows 1 to 3).
        render: image formation (noise, blur, ...).
        storage: ROS2 storage plugin.
        random_mechanism: seed of a member of the randomized mechanism family
            (:func:`~dcc_fg.sim.mechanism_family.family_member`), None for the pinned scene.
        motion: ``held`` (snapshots, today's data sets) or ``continuous`` (the board and the gimbal
            move through the snapshots while both cameras record, :mod:`dcc_fg.sim.calibration_motion`).
        timing: the cameras' rates, phase, time offsets and stamp jitter
            (:class:`~dcc_fg.sim.timing.CameraTiming`); only ``continuous`` accepts a non-default one.
        limits: peak rates of the continuous motion.
    """

    target: str = "checkerboard"
    fmt: Format = "folder"
    seed: int = 0
    n_snapshots: int = 81
    n_joints: int | None = None
    render: RenderConfig = field(default_factory=RenderConfig)
    storage: Literal["sqlite3", "mcap"] = "sqlite3"
    random_mechanism: int | None = None
    motion: Motion = "held"
    timing: CameraTiming = field(default_factory=CameraTiming)
    limits: MotionLimits = field(default_factory=MotionLimits)


def _write_images(data: Path, frames: Iterator[FramePair], spec: CalibrationSimSpec) -> None:
    """The image pairs as an image folder or a ROS1 / ROS2 bag (``spec.fmt``)."""
    if spec.fmt == "folder":
        write_image_folder(data, frames)
    elif spec.fmt == "ros1":
        write_ros1_bag(data, frames, STATIC_TOPIC, DYNAMIC_TOPIC)
    else:
        write_ros2_bag(data, frames, STATIC_TOPIC, DYNAMIC_TOPIC, storage=spec.storage)


def _ground_truth_dict(
    sim: SimulatedCalibration,
    T_st: FloatArray,
    spec: CalibrationSimSpec,
    data: Path,
    member: FamilyMember | None = None,
) -> dict[str, Any]:
    """The content of ``ground_truth.yaml`` (format in the module docstring)."""
    cfg = sim.config
    tg = cfg.target
    head: dict[str, Any] = {"format": "dcc-fg ground truth 1", "seed": spec.seed}
    if member is not None:
        spread = achieved_spread(sim)
        head["random_mechanism"] = member.seed
        head["mechanism"] = {
            **member.description,
            "achieved_half_range_deg": spread["half_range_deg"],
            "achieved_std_deg": spread["std_deg"],
        }
    return {
        **head,
        "scene": {
            "joints": sim.truth.n_joints,
            "snapshots": spec.n_snapshots,
            "distance_range_m": list(cfg.distance_range),
            "board_tilt_max_rad": cfg.board_tilt,
            "board_roll_max_rad": cfg.board_roll,
            "margin_px": cfg.margin_px,
        },
        "render": asdict(spec.render),
        "data": data.name,
        "target": tg.to_kalibr(),
        "kinematics": _kinematics_dict(sim.truth),
        "snapshots": [
            {
                "timestamp_ns": int(s.timestamp_ns),
                "dynamic_timestamp_ns": int(s.timestamp_ns) + DYNAMIC_STAMP_OFFSET_NS,
                "theta": [float(x) for x in sim.joints_calibration[k]],
                "theta_guess": [float(x) for x in (s.joints if s.joints is not None else [])],
                "T_ds": _matrix(sim.truth.T_ds(sim.joints_calibration[k])),
                "T_st": _matrix(T_st[k]),
            }
            for k, s in enumerate(sim.calibration_set.snapshots)
        ],
    }


@dataclass(frozen=True)
class ContinuousImage:
    """One image of a continuous recording: ``camera`` 0 (static) or 1 (gimbal), header stamp and
    true exposure time (ns, with :data:`CONTINUOUS_T0_NS`), and the truth at the exposure: joint
    angles ``theta`` (L,), ``T_st`` and ``T_ds`` (4, 4), and whether every corner is in view."""

    camera: int
    stamp_ns: int
    exposure_ns: int
    theta: FloatArray
    T_st: FloatArray
    T_ds: FloatArray
    visible: bool = True


def continuous_images(
    sim: SimulatedCalibration, T_st: FloatArray, spec: CalibrationSimSpec
) -> tuple[ContinuousMotion, list[ContinuousImage]]:
    """The motion through the snapshots and both cameras' images with their truth, in exposure order
    (static first on ties); stamp jitter drawn from ``spec.seed``."""
    tg = sim.config.target
    motion = ContinuousMotion(T_st, sim.joints_calibration, tg.points.mean(axis=0), spec.limits)
    streams = spec.timing.streams(int(round(motion.duration * 1e9)), np.random.default_rng([spec.seed, 15]))
    cams = (sim.truth.static_camera, sim.truth.dynamic_camera)
    assert cams[0] is not None and cams[1] is not None
    images = []
    for st in streams:
        T, theta = motion.evaluate(st.exposure_ns / 1e9)
        for k in range(len(st)):
            T_ds = sim.truth.T_ds(theta[k])
            T_ct = T[k] if st.camera == 0 else T_ds @ T[k]
            images.append(
                ContinuousImage(
                    st.camera,
                    CONTINUOUS_T0_NS + int(st.stamp_ns[k]),
                    CONTINUOUS_T0_NS + int(st.exposure_ns[k]),
                    theta[k],
                    T[k],
                    T_ds,
                    corners_visible(cams[st.camera], T_ct, tg.points),
                )
            )
    images.sort(key=lambda im: (im.exposure_ns, im.camera))
    return motion, images


def _render_continuous(
    sim: SimulatedCalibration, images: list[ContinuousImage], render: RenderConfig, rng: np.random.Generator
) -> Iterator[NDArray[np.uint8]]:
    cams = (sim.truth.static_camera, sim.truth.dynamic_camera)
    assert cams[0] is not None and cams[1] is not None
    texture: BoardTexture = make_texture(sim.config.target, render.texel_m)
    for im in images:
        T_ct = im.T_st if im.camera == 0 else im.T_ds @ im.T_st
        yield render_view(cams[im.camera], T_ct, texture, render, rng)


def _write_continuous(
    data: Path, images: list[ContinuousImage], rendered: Iterator[NDArray[np.uint8]], spec: CalibrationSimSpec
) -> None:
    """The images of a continuous recording: ``cam0/<stamp>.png`` and ``cam1/<stamp>.png`` (folder) or
    a bag with record time = true exposure time and header stamp = the camera's stamp."""
    topics, frame_ids, dirs = (STATIC_TOPIC, DYNAMIC_TOPIC), ("cam0", "cam1"), ("cam0", "cam1")
    if spec.fmt == "folder":
        for c in (0, 1):
            stamps = [im.stamp_ns for im in images if im.camera == c]
            if len(set(stamps)) != len(stamps):
                raise ValueError(
                    f"--stamp-jitter {spec.timing.stamp_jitter} s gives two {frame_ids[c]} images the same stamp: "
                    "an image folder cannot hold both (use a bag format or less jitter)"
                )
        for d in dirs:
            (data / d).mkdir(parents=True, exist_ok=True)
        for im, img in zip(images, rendered, strict=True):
            path = data / dirs[im.camera] / f"{im.stamp_ns}.png"
            if not cv2.imwrite(str(path), img):
                raise ValueError(f"{path}: could not write image")
        return
    with BagWriter(data, 1 if spec.fmt == "ros1" else 2, spec.storage, overwrite=False) as bag:
        for im, img in zip(images, rendered, strict=True):
            msgtype, msg = image_message(bag.typestore, img, im.stamp_ns, frame_ids[im.camera])
            bag.write(topics[im.camera], msgtype, im.exposure_ns, msg)


def _image_truth(im: ContinuousImage) -> dict[str, Any]:
    return {
        "stamp_ns": im.stamp_ns,
        "exposure_ns": im.exposure_ns,
        "theta": [float(x) for x in im.theta],
        "T_st": _matrix(im.T_st),
        "T_ds": _matrix(im.T_ds),
        "visible": im.visible,
    }


def _continuous_truth(
    sim: SimulatedCalibration, T_st: FloatArray, motion: ContinuousMotion, images: list[ContinuousImage],
    spec: CalibrationSimSpec,
) -> dict[str, Any]:  # fmt: skip
    """The ``motion``, ``images`` and ``snapshots`` entries of a continuous recording's ground truth."""
    static = [im for im in images if im.camera == 0]
    dynamic = [im for im in images if im.camera == 1]
    d_stamps = np.array([im.stamp_ns for im in dynamic], dtype=np.int64)
    snapshots = []
    for im in static:
        partner = None
        if d_stamps.size:
            j = int(np.argmin(np.abs(d_stamps - im.stamp_ns)))
            partner = int(d_stamps[j])
        snapshots.append(
            {
                "timestamp_ns": im.stamp_ns,
                "dynamic_timestamp_ns": partner,
                "exposure_ns": im.exposure_ns,
                "theta": [float(x) for x in im.theta],
                "theta_guess": [],
                "T_ds": _matrix(im.T_ds),
                "T_st": _matrix(im.T_st),
            }
        )
    return {
        "motion": {
            "mode": "continuous",
            "timing": spec.timing.to_dict(),
            "t0_ns": CONTINUOUS_T0_NS,
            "duration_s": motion.duration,
            "limits": spec.limits.to_dict(),
            "waypoints": [
                {
                    "exposure_ns": CONTINUOUS_T0_NS + int(round(t * 1e9)),
                    "theta": [float(x) for x in sim.joints_calibration[k]],
                    "T_st": _matrix(T_st[k]),
                }
                for k, t in enumerate(motion.t_waypoints)
            ],
        },
        "images": {"static": [_image_truth(im) for im in static], "dynamic": [_image_truth(im) for im in dynamic]},
        "snapshots": snapshots,
    }


def write_calibration_dataset(
    out: str | Path, spec: CalibrationSimSpec | None = None, force: bool = False
) -> RenderedCalibration:
    """Simulate, render and write a calibration data set (layout in the module docstring).

    The files are written as one output set (:class:`~dcc_fg.io.output_set.OutputSet`, command
    ``simulate calibration``): into a staging folder, moved into ``out`` only when everything is written.

    Args:
        out: output folder (created). It must not hold any of the data set's names (``images``,
            ``camchain.yaml``, ...) nor be another command's result folder.
        spec: what to simulate and write (default :class:`CalibrationSimSpec`: 81 checkerboard
            image pairs of the 2-joint scene in an image folder, seed 0; with
            ``spec.random_mechanism`` the family member of that seed).
        force: replace a data set written earlier into ``out`` by ``simulate calibration``.

    Raises:
        ValueError: unknown target/format, a random mechanism with a number of joints outside
            1-3 or a negative seed, or ``out`` already holds a data set (without ``force``).
    """
    spec = spec or CalibrationSimSpec()
    if spec.fmt not in DATA_NAMES:
        raise ValueError(f"--format must be folder, ros1 or ros2, got '{spec.fmt}'")
    if spec.n_snapshots < 1:
        raise ValueError(f"--snapshots must be >= 1, got {spec.n_snapshots}")
    if spec.motion not in ("held", "continuous"):
        raise ValueError(f"--motion must be held or continuous, got '{spec.motion}'")
    if spec.motion == "held" and not spec.timing.is_default:
        raise ValueError(
            "--rates, --phase, --time-offsets and --stamp-jitter need --motion continuous (held snapshots are "
            "recorded as image pairs)"
        )
    if spec.motion == "continuous" and spec.n_snapshots < 2:
        raise ValueError(
            f"--motion continuous moves between snapshots: --snapshots must be >= 2, got {spec.n_snapshots}"
        )
    out = Path(out)
    outputs = OutputSet(
        out,
        "simulate calibration",
        replace_previous=force,
        replace_hint="pass --force to replace the data set simulated there before",
        replace_unowned=False,
    )
    member = None
    if spec.random_mechanism is not None:
        member = family_member(spec.random_mechanism, spec.n_joints, spec.n_snapshots)
        tg = member.scene.target
        sim = simulate_member(member)
    else:
        tg = default_target(spec.target)
        n_joints = 2 if spec.n_joints is None else spec.n_joints
        sim = simulate_calibration(spec.seed, scene_config(tg, spec.n_snapshots, n_joints))
    T_st = _rendered_poses(sim)
    rng = np.random.default_rng([spec.seed, 1])  # image noise, independent of the scene's stream
    continuous = None
    if spec.motion == "continuous":
        continuous = continuous_images(sim, T_st, spec)
    with outputs:
        stage = outputs.path
        data = stage / DATA_NAMES[spec.fmt]
        t0 = time.perf_counter()
        if continuous is None:
            _write_images(data, _frames(sim, T_st, spec.render, rng), spec)
        else:
            _write_continuous(data, continuous[1], _render_continuous(sim, continuous[1], spec.render, rng), spec)
        render_time = time.perf_counter() - t0

        cams = (sim.truth.static_camera, sim.truth.dynamic_camera)
        assert cams[0] is not None and cams[1] is not None
        paths = {name: stage / f"{name}.yaml" for name in ("camchain", "target", "gimbal", "ground_truth")}
        entries = {"cam0": CamchainEntry(cams[0], STATIC_TOPIC), "cam1": CamchainEntry(cams[1], DYNAMIC_TOPIC)}
        write_text_atomic(paths["camchain"], camchain_to_yaml(entries))
        write_text_atomic(paths["target"], yaml.safe_dump(tg.to_kalibr(), sort_keys=False))
        write_text_atomic(paths["gimbal"], yaml.safe_dump(_kinematics_dict(sim.initial), sort_keys=False))
        truth = _ground_truth_dict(sim, T_st, spec, data, member)
        if continuous is None:
            write_text_atomic(paths["ground_truth"], yaml.safe_dump(truth, sort_keys=False))
        else:
            truth.update(_continuous_truth(sim, T_st, *continuous, spec))
            text = yaml.dump(truth, Dumper=getattr(yaml, "CSafeDumper", yaml.SafeDumper), sort_keys=False)
            write_text_atomic(paths["ground_truth"], text)
    final = {name: out / p.name for name, p in paths.items()}
    images = None
    if continuous is not None:
        static = [im for im in continuous[1] if im.camera == 0]
        T_st = np.array([im.T_st for im in static]).reshape(-1, 4, 4)
        images = (len(static), len(continuous[1]) - len(static))
    return RenderedCalibration(
        sim, out / data.name, final["camchain"], final["target"], final["gimbal"], final["ground_truth"], T_st,
        render_time, images,
    )  # fmt: skip


@dataclass
class GroundTruth:
    """``ground_truth.yaml`` read back.

    Attributes:
        kinematics: the true mechanism (no intrinsics).
        timestamps_ns: (K,) static image stamps.
        theta: (K, L) true joint angles, rad.
        T_ds: (K, 4, 4) true static -> dynamic transforms.
        T_st: (K, 4, 4) true target -> static camera poses.
        raw: the whole YAML mapping.
    """

    kinematics: GimbalCalibration
    timestamps_ns: NDArray[np.int64]
    theta: FloatArray
    T_ds: FloatArray
    T_st: FloatArray
    raw: dict[str, Any]

    def theta_at(self, timestamps_ns: NDArray[np.int64]) -> FloatArray:
        """True joint angles at the given snapshot stamps (ValueError for an unknown stamp)."""
        index = {int(t): k for k, t in enumerate(self.timestamps_ns)}
        missing = [int(t) for t in timestamps_ns if int(t) not in index]
        if missing:
            raise ValueError(f"timestamps not in the ground truth: {missing[:5]}")
        return self.theta[[index[int(t)] for t in timestamps_ns]]


def load_ground_truth(path: str | Path) -> GroundTruth:
    """Read ``ground_truth.yaml`` (see the module docstring)."""
    path = Path(path)
    with path.open() as f:
        d = yaml.safe_load(f)
    if not isinstance(d, dict) or d.get("format") != "dcc-fg ground truth 1":
        raise ValueError(f"{path}: not a dcc-fg ground truth file (format: dcc-fg ground truth 1)")
    kin = GimbalCalibration.from_dict(d["kinematics"], f"{path}: kinematics")
    snaps = d["snapshots"]
    L = kin.n_joints
    return GroundTruth(
        kinematics=kin,
        timestamps_ns=np.array([s["timestamp_ns"] for s in snaps], dtype=np.int64),
        theta=np.array([s["theta"] for s in snaps], dtype=float).reshape(len(snaps), L),
        T_ds=np.array([s["T_ds"] for s in snaps], dtype=float).reshape(-1, 4, 4),
        T_st=np.array([s["T_st"] for s in snaps], dtype=float).reshape(-1, 4, 4),
        raw=d,
    )
