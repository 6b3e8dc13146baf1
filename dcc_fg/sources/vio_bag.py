"""Read a VIO bag: IMU samples and synchronized camera frames, merged in time order.

:class:`VioBag` makes a first pass over the bag that reads the whole IMU topic (a few MB even
for an hour at 200 Hz) and the image header stamps, validates them and pairs the static and
gimbal image stamps; iterating makes a second pass that decodes the images as they come and
yields, in time order, :class:`~dcc_fg.data.vio.ImuSamples` chunks (every IMU sample up to and
including the next frame's time) and :class:`VioFrame` objects.  Only the images waiting for
their partner are held in memory.

Bad input (each named by bag, topic and time):

* a missing IMU or image topic, or a topic of the wrong message type: ``ValueError`` listing
  the bag's topics;
* IMU samples with non-finite values or beyond the sensor's range (``ImuConfig.acc_range``,
  ``gyro_range``: 16 g and 2000 deg/s by default): dropped, with a warning giving the count
  (``ValueError`` if more than ``max_bad_imu_fraction`` of them are bad);
* exact duplicate messages (an IMU sample with the stamp and values of the one before it, an
  image with the stamp of an earlier image on its topic): dropped with a log line, not counted as bad;
* an IMU rate too low for preintegration or camera frames far outside the IMU's time span (a
  clock offset): ``ValueError`` with the measured rate / offsets
  (:func:`~dcc_fg.data.vio.check_imu_against_frames`);
* IMU stamps that go backwards or repeat: the offending samples are dropped with a warning
  (``ValueError`` beyond ``max_bad_imu_fraction``);
* image stamps out of record order: frames are processed in stamp order (logged with the count);
* a gimbal stream that stops, drops frames or starts late: static frames without a gimbal partner are
  kept as static-only frames (logged with the count); a gimbal topic with no partner at all is an error;
* gaps: an IMU gap longer than ``max_imu_gap_s`` or an image gap longer than
  ``max_image_gap_s`` is logged, listed in :attr:`VioBag.imu_gaps` / :attr:`VioBag.image_gaps`,
  and the first frame after an image gap (or after an IMU gap ending before it) carries
  ``after_gap=True`` so the estimator can re-initialize instead of integrating across it.

Pairing (unsynchronized cameras): each static image is paired with the gimbal image nearest to it in
*exposure time* on the IMU clock, ``stamp + t_offset`` with the start values of the time offsets
(``time_offsets_ns``), one to one, within ``tolerance_ns`` (None: half the slower camera's median
frame period, so every static frame of a free-running gimbal camera finds its nearest partner). The
smoother accounts for the gap between the two stamps (:mod:`dcc_fg.vio.backend.exposure`).

Further cameras (``extra_topics``, an N-camera cluster): the cameras of a cluster are triggered
together, so each further image is paired with the static image by ``stamp + t_s`` (the static
camera's time offset) on both sides, one to one, within ``tolerance_ns`` (None: half the slower of
the two cameras' median frame periods); a static frame without a partner carries None for that
camera. A missing, empty or never-pairing further topic is a ``ValueError`` naming the bag and the
topic, raised by the constructor before any image is decoded; only the paired images are decoded.

Units: ns, m/s^2 (``linear_acceleration``), rad/s (``angular_velocity``).
"""

from __future__ import annotations

import logging
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from dcc_fg.data.vio import (
    GYRO_RANGE_RAD_S,
    STANDARD_GRAVITY,
    ImuSamples,
    check_imu_against_frames,
    imu_out_of_range,
)
from dcc_fg.detection import to_gray8
from dcc_fg.io.bags import ImuImageStamps, scan_imu_and_image_stamps, stream_image_groups
from dcc_fg.io.pairing import median_period_ms, pair_timestamps, stamp_jitter_s

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class VioFrame:
    """One frame: the static image and its gimbal partner, grey 8-bit (``dynamic`` None in a static-only
    bag or when the gimbal camera has no image near this one).

    ``timestamp_ns`` is the static image's stamp, ``dynamic_timestamp_ns`` the gimbal image's (they
    differ for unsynchronized cameras); ``after_gap`` marks the first frame after an image or IMU gap.
    ``dynamic_between`` are the gimbal images without a static partner taken since the previous frame's
    gimbal image (a gimbal camera faster than the static one), oldest first, with their stamps
    ``dynamic_between_ns``: the front end tracks through them so that its gimbal tracks step from
    image to image. ``extra`` are the further cameras' images (aligned with ``VioBag.extra_topics``;
    None where a camera has no image paired with this frame), ``extra_timestamps_ns`` their stamps
    (0 where None).
    """

    timestamp_ns: int
    static: NDArray[np.uint8]
    dynamic: NDArray[np.uint8] | None = None
    dynamic_timestamp_ns: int = 0
    after_gap: bool = False
    dynamic_between: tuple[NDArray[np.uint8], ...] = ()
    dynamic_between_ns: tuple[int, ...] = ()
    extra: tuple[NDArray[np.uint8] | None, ...] = ()
    extra_timestamps_ns: tuple[int, ...] = ()


@dataclass
class ImuCheck:
    """What the IMU validation found."""

    n_read: int = 0
    non_finite: int = 0
    out_of_range: int = 0
    duplicates: int = 0
    out_of_order: int = 0
    gaps: list[tuple[int, int]] = field(default_factory=list)


def validate_imu(
    t_ns: NDArray[np.int64],
    acc: NDArray[np.float64],
    gyro: NDArray[np.float64],
    where: str,
    max_gap_s: float = 0.05,
    max_bad_fraction: float = 0.01,
    acc_range: float = 16.0 * STANDARD_GRAVITY,
    gyro_range: float = GYRO_RANGE_RAD_S,
) -> tuple[ImuSamples, ImuCheck]:
    """Drop non-finite, out-of-range (``acc_range`` m/s^2, ``gyro_range`` rad/s per axis), exactly
    duplicated and non-increasing samples (in bag order), find gaps; see the module docstring.

    Raises:
        ValueError: naming ``where`` when there are no usable samples or too many bad ones.
    """
    check = ImuCheck(n_read=int(t_ns.shape[0]))
    if check.n_read == 0:
        raise ValueError(f"{where}: no IMU messages")
    finite = np.all(np.isfinite(acc), axis=1) & np.all(np.isfinite(gyro), axis=1)
    check.non_finite = int((~finite).sum())
    if check.non_finite:
        first = int(t_ns[np.flatnonzero(~finite)[0]])
        log.warning("%s: dropped %d IMU samples with NaN/inf values (first at %d ns)", where, check.non_finite, first)
    beyond = imu_out_of_range(acc, gyro, acc_range, gyro_range) & finite
    check.out_of_range = int(beyond.sum())
    if check.out_of_range:
        i = int(np.flatnonzero(beyond)[0])
        log.warning(
            "%s: dropped %d IMU samples beyond the sensor's range (|acc| > %.1f m/s^2 or |gyro| > %.2f rad/s on an "
            "axis; first at %d ns: acc %s, gyro %s)",
            where,
            check.out_of_range,
            acc_range,
            gyro_range,
            int(t_ns[i]),
            np.array2string(acc[i], precision=3),
            np.array2string(gyro[i], precision=3),
        )
    keep = finite & ~beyond
    dup = _exact_duplicates(t_ns, acc, gyro) & keep
    check.duplicates = int(dup.sum())
    if check.duplicates:
        log.warning(
            "%s: dropped %d exact duplicate IMU messages (first at %d ns)",
            where,
            check.duplicates,
            int(t_ns[np.flatnonzero(dup)[0]]),
        )
    keep &= ~dup
    finite = keep.copy()
    # a sample must be later than every kept sample before it (running maximum of kept stamps)
    kept_t = np.where(finite, t_ns, np.iinfo(np.int64).min)
    prev_max = np.maximum.accumulate(np.concatenate([[np.iinfo(np.int64).min], kept_t[:-1]]))
    backwards = finite & (t_ns <= prev_max)
    check.out_of_order = int(backwards.sum())
    if check.out_of_order:
        i = int(np.flatnonzero(backwards)[0])
        log.warning(
            "%s: dropped %d IMU samples whose stamps go backwards or repeat (first at %d ns, after %d ns)",
            where,
            check.out_of_order,
            int(t_ns[i]),
            int(prev_max[i]),
        )
    keep &= ~backwards
    bad = check.n_read - check.duplicates - int(keep.sum())
    if bad > max_bad_fraction * (check.n_read - check.duplicates) or keep.sum() < 2:
        raise ValueError(
            f"{where}: {bad} of {check.n_read - check.duplicates} IMU samples are unusable "
            f"({check.non_finite} NaN/inf, {check.out_of_range} beyond the sensor's range, {check.out_of_order} with "
            "stamps going backwards or repeating)"
        )
    t, a, g = t_ns[keep], acc[keep], gyro[keep]
    dt = np.diff(t)
    for i in np.flatnonzero(dt > max_gap_s * 1e9):
        check.gaps.append((int(t[i]), int(t[i + 1])))
        log.warning("%s: IMU gap of %.3f s from %d ns to %d ns", where, dt[i] / 1e9, int(t[i]), int(t[i + 1]))
    return ImuSamples(t_ns=t, acc=a, gyro=g), check


def _exact_duplicates(
    t_ns: NDArray[np.int64], acc: NDArray[np.float64], gyro: NDArray[np.float64]
) -> NDArray[np.bool_]:
    """True for each sample that repeats the stamp and values of the message before it on the topic
    (a recorder or a merge writing one message twice); a repeated stamp with other values, or
    further away, is a clock problem handled as out of order."""
    n = int(t_ns.shape[0])
    out = np.zeros(n, dtype=bool)
    if n > 1:
        out[1:] = (t_ns[1:] == t_ns[:-1]) & np.all(acc[1:] == acc[:-1], axis=1) & np.all(gyro[1:] == gyro[:-1], axis=1)
    return out


def first_of_each_stamp(stamps: list[int]) -> list[int]:
    """Indices of the first message of each distinct stamp (later messages with the same stamp are
    duplicates), in message order."""
    seen: set[int] = set()
    out = []
    for i, t in enumerate(stamps):
        if t not in seen:
            seen.add(t)
            out.append(i)
    return out


class VioBag:
    """IMU and image frames of a ROS1/ROS2 bag, streamed in time order (module docstring).

    Args:
        path: ROS1 ``.bag`` file or ROS2 bag folder.
        imu_topic: ``sensor_msgs/Imu`` topic.
        static_topic: static-camera image topic (``Image`` or ``CompressedImage``).
        dynamic_topic: gimbal-camera image topic, or None (static camera only).
        tolerance_ns: pairing tolerance of the two image streams (None: half the slower camera's frame period).
        time_offsets_ns: start values of the static and gimbal camera's time offsets (``t_imu = stamp +
            offset``), ns: images are paired by ``stamp + offset``.
        max_image_gap_s, max_imu_gap_s: longer gaps are reported (logged, ``after_gap``).
        max_bad_imu_fraction: more bad IMU samples than this fraction is an error.
        acc_range, gyro_range: the IMU's range per axis (m/s^2, rad/s; ``ImuConfig.acc_range`` and
            ``gyro_range``); samples beyond are dropped. None: no range check (only non-finite values).
        extra_topics: image topics of further cameras (run index 2, 3, ...), paired with the static
            images (module docstring); their pairing numbers are in :attr:`extra_pairing_statistics`.
        scan: the bag's first pass (:func:`~dcc_fg.io.bags.scan_imu_and_image_stamps` of these topics)
            when it has been made already, e.g. by the process that starts the front end's (:attr:`scan`
            holds it): not read again. None: read here.
    """

    def __init__(
        self,
        path: str | Path,
        imu_topic: str,
        static_topic: str,
        dynamic_topic: str | None = None,
        tolerance_ns: int | None = None,
        time_offsets_ns: tuple[int, int] = (0, 0),
        max_image_gap_s: float = 0.5,
        max_imu_gap_s: float = 0.05,
        max_bad_imu_fraction: float = 0.01,
        acc_range: float | None = None,
        gyro_range: float | None = None,
        extra_topics: Sequence[str] = (),
        scan: ImuImageStamps | None = None,
    ) -> None:
        self.path = Path(path)
        self.imu_topic, self.static_topic, self.dynamic_topic = imu_topic, static_topic, dynamic_topic
        self.extra_topics = tuple(extra_topics)
        image_topics = [static_topic] + ([dynamic_topic] if dynamic_topic else []) + list(self.extra_topics)
        repeated = sorted({t for t in image_topics if image_topics.count(t) > 1})
        if repeated:
            raise ValueError(
                f"{self.path}: image topic {', '.join(repeated)} is given for more than one camera "
                f"(static {static_topic}, gimbal {dynamic_topic}, further cameras {', '.join(self.extra_topics)})"
            )
        if scan is None:
            scan = scan_imu_and_image_stamps(self.path, imu_topic, image_topics)
        elif set(scan.image_stamps) != set(image_topics):
            raise ValueError(
                f"{self.path}: the given first pass has image topics {', '.join(sorted(scan.image_stamps))}, "
                f"not {', '.join(sorted(image_topics))}"
            )
        self.scan = scan
        where = f"{self.path}: topic {imu_topic}"
        self.imu, self.imu_check = validate_imu(
            scan.imu_t_ns,
            scan.imu_acc,
            scan.imu_gyro,
            where,
            max_imu_gap_s,
            max_bad_imu_fraction,
            np.inf if acc_range is None else acc_range,
            np.inf if gyro_range is None else gyro_range,
        )
        self.imu_gaps = self.imu_check.gaps
        # exact duplicate images (same topic, same stamp): pair and decode only the first of each
        self._first: dict[str, list[int]] = {}
        self._stamps: dict[str, list[int]] = {}
        self.duplicate_images = 0
        for topic, stamps in scan.image_stamps.items():
            first = first_of_each_stamp(stamps)
            self._first[topic] = first
            self._stamps[topic] = [stamps[i] for i in first]
            if len(first) < len(stamps):
                self.duplicate_images += len(stamps) - len(first)
                log.warning(
                    "%s: topic %s: dropped %d image messages whose stamp repeats an earlier image's",
                    self.path,
                    topic,
                    len(stamps) - len(first),
                )
        for topic in image_topics:
            backwards = int(np.count_nonzero(np.diff(np.asarray(self._stamps[topic], dtype=np.int64)) < 0))
            if backwards:
                log.warning(
                    "%s: topic %s: the header stamp goes backwards %d times in record order; frames are processed "
                    "in stamp order",
                    self.path,
                    topic,
                    backwards,
                )
        self.time_offsets_ns = (int(time_offsets_ns[0]), int(time_offsets_ns[1]))
        self.tolerance_ns = tolerance_ns
        self.pairing_statistics: dict[str, float | int | None] | None = None
        self._pairs = self._pair_images(tolerance_ns)
        #: per further topic: pairing numbers (:meth:`~dcc_fg.io.pairing.Pairing.statistics`, the
        #: gimbal fields naming the further camera) and its partner index per static image (-1: none)
        self.extra_pairing_statistics: dict[str, dict[str, float | int | None]] = {}
        self._extra_partner: list[dict[int, int]] = [
            self._pair_extra(topic, tolerance_ns) for topic in self.extra_topics
        ]
        self._between = self._gimbal_images_between()
        s = self._stamps[static_topic]
        self.frame_times = np.array(sorted(s[i] for i, _ in self._pairs), dtype=np.int64)
        self.image_gaps: list[tuple[int, int]] = []
        dt = np.diff(self.frame_times)
        for i in np.flatnonzero(dt > max_image_gap_s * 1e9):
            gap = (int(self.frame_times[i]), int(self.frame_times[i + 1]))
            self.image_gaps.append(gap)
            log.warning("%s: image gap of %.3f s from %d ns to %d ns", self.path, dt[i] / 1e9, *gap)
        self._gap_starts = self._frames_after_gaps()
        check_imu_against_frames(self.imu.t_ns, self.frame_times, where)

    # -- first-pass helpers ----------------------------------------------------------------------
    def _pair_images(self, tolerance_ns: int | None) -> list[tuple[int, int]]:
        """``(static index, dynamic index)`` per frame, by exposure time (module docstring); dynamic -1
        for a static frame without a gimbal partner and in a static-only bag."""
        s_topic, d_topic = self.static_topic, self.dynamic_topic
        s = self._stamps[s_topic]
        if not s:
            raise ValueError(f"{self.path}: topic {s_topic} has no messages")
        if not d_topic:
            return [(i, -1) for i in range(len(s))]
        d = self._stamps[d_topic]
        if not d:
            raise ValueError(f"{self.path}: topic {d_topic} has no messages")
        if tolerance_ns is None:
            periods = [p for p in (median_period_ms(s), median_period_ms(d)) if p is not None]
            tolerance_ns = int(0.5 * max(periods) * 1e6) if periods else 0
            self.tolerance_ns = tolerance_ns
        t_s, t_d = self.time_offsets_ns
        pairing = pair_timestamps(np.asarray(s) + t_s, np.asarray(d) + t_d, tolerance_ns)
        if not pairing.pairs:
            raise ValueError(
                f"{self.path}: no image of {s_topic} has a partner on {d_topic} within {tolerance_ns / 1e6:g} ms "
                f"(stamps + time offsets {t_s / 1e6:g}, {t_d / 1e6:g} ms); check the gimbal topic's stamps, the "
                "time offsets and the pairing tolerance"
            )
        if pairing.unpaired_static or pairing.unpaired_dynamic:
            log.warning(
                "%s: %s; static frames without a partner are used without the gimbal camera",
                self.path,
                pairing.summary(s_topic, d_topic),
            )
        self.pairing_statistics = pairing.statistics()
        paired = {i for i, _ in pairing.pairs}
        return sorted(pairing.pairs + [(i, -1) for i in range(len(s)) if i not in paired], key=lambda p: s[p[0]])

    def _pair_extra(self, topic: str, tolerance_ns: int | None) -> dict[int, int]:
        """Static image index -> index of its partner on the further camera ``topic`` (module docstring)."""
        s = self._stamps[self.static_topic]
        e = self._stamps[topic]
        if not e:
            raise ValueError(f"{self.path}: topic {topic} (a further camera) has no messages")
        if tolerance_ns is None:
            periods = [p for p in (median_period_ms(s), median_period_ms(e)) if p is not None]
            tolerance_ns = int(0.5 * max(periods) * 1e6) if periods else 0
        t_s = self.time_offsets_ns[0]
        pairing = pair_timestamps(np.asarray(s) + t_s, np.asarray(e) + t_s, tolerance_ns)
        if not pairing.pairs:
            raise ValueError(
                f"{self.path}: no image of {self.static_topic} has a partner on {topic} (a further camera) within "
                f"{tolerance_ns / 1e6:g} ms; check the topic's stamps and the pairing tolerance"
            )
        if pairing.unpaired_static or pairing.unpaired_dynamic:
            log.warning(
                "%s: %s; static frames without a partner are used without that camera",
                self.path,
                pairing.summary(self.static_topic, topic),
            )
        self.extra_pairing_statistics[topic] = pairing.statistics()
        return dict(pairing.pairs)

    def _gimbal_images_between(self) -> dict[int, list[int]]:
        """Per frame (position in the pairs), the unpaired gimbal images (indices) since the previous
        paired gimbal image, by gimbal stamp; unpaired images after the last paired one are not used."""
        d_topic = self.dynamic_topic
        if not d_topic:
            return {}
        d = np.asarray(self._stamps[d_topic], dtype=np.int64)
        paired = sorted((int(d[j]), n) for n, (_, j) in enumerate(self._pairs) if j >= 0)
        used = {j for _, j in self._pairs if j >= 0}
        paired_stamps = np.array([t for t, _ in paired], dtype=np.int64)
        out: dict[int, list[int]] = {}
        for j in sorted((j for j in range(d.size) if j not in used), key=lambda j: int(d[j])):
            pos = int(np.searchsorted(paired_stamps, d[j], side="right"))
            if pos < len(paired) and pos > 0:  # between two paired gimbal images
                out.setdefault(paired[pos][1], []).append(j)
        return out

    @property
    def gimbal_images_between(self) -> int:
        """Gimbal images without a static partner that the front end tracks through."""
        return sum(len(v) for v in self._between.values())

    def _frames_after_gaps(self) -> set[int]:
        """Frame stamps that come first after an image gap or after an IMU gap."""
        out = {b for _, b in self.image_gaps}
        for _, b in self.imu_gaps:
            k = int(np.searchsorted(self.frame_times, b))
            if k < self.frame_times.size:
                out.add(int(self.frame_times[k]))
        return out

    def __len__(self) -> int:
        return len(self._pairs)

    def stamp_jitter(self) -> tuple[float, float]:
        """1-sigma (s) of the static and gimbal image stamps around a regular grid
        (:func:`~dcc_fg.io.pairing.stamp_jitter_s`; the static camera's twice in a static-only bag)."""
        static = stamp_jitter_s(self._stamps[self.static_topic])
        return static, stamp_jitter_s(self._stamps[self.dynamic_topic]) if self.dynamic_topic else static

    def period_s(self, topic: str) -> float | None:
        """Median frame period of an image topic, s (None for fewer than two images)."""
        p = median_period_ms(self._stamps[topic])
        return None if p is None else p / 1e3

    @property
    def duration_s(self) -> float:
        """Time span of the frames, seconds."""
        return float(self.frame_times[-1] - self.frame_times[0]) / 1e9 if self.frame_times.size > 1 else 0.0

    # -- streaming -------------------------------------------------------------------------------
    def __iter__(self) -> Iterator[ImuSamples | VioFrame]:
        """Second pass: IMU chunks and frames in time order (IMU up to and including each frame time)."""
        imu = self.imu
        imu_pos = 0
        pending = self._pending_frames()
        for frame in pending:
            end = int(np.searchsorted(imu.t_ns, frame.timestamp_ns, side="right"))
            if end > imu_pos:
                yield ImuSamples(imu.t_ns[imu_pos:end], imu.acc[imu_pos:end], imu.gyro[imu_pos:end])
                imu_pos = end
            yield frame
        if imu_pos < len(imu):
            yield ImuSamples(imu.t_ns[imu_pos:], imu.acc[imu_pos:], imu.gyro[imu_pos:])

    def frames(self) -> Iterator[VioFrame]:
        """Only the frames, in time order."""
        yield from self._pending_frames()

    def _pending_frames(self) -> Iterator[VioFrame]:
        """Frames in static-stamp order, even where the bag's record order differs."""
        s_topic, d_topic = self.static_topic, self.dynamic_topic
        topics = [s_topic] + ([d_topic] if d_topic else []) + list(self.extra_topics)
        first_s = self._first[s_topic]
        n_frames = len(self._pairs)
        first_e = [self._first[topic] for topic in self.extra_topics]
        n_e = len(self.extra_topics)

        def partners(i: int) -> tuple[int, ...]:  # message index per further topic of static image i
            return tuple(f[p[i]] if i in p else -1 for f, p in zip(first_e, self._extra_partner, strict=True))

        # groups 0..n_frames-1: the frames; then one group per gimbal image between frames
        extra_of: dict[int, tuple[int, int]] = {}  # group -> (frame, position among its images between)
        if d_topic:
            first_d = self._first[d_topic]
            groups: list[tuple[int, ...]] = [
                (first_s[i], first_d[j] if j >= 0 else -1, *partners(i)) for i, j in self._pairs
            ]
            for n, js in sorted(self._between.items()):
                for pos, j in enumerate(js):
                    extra_of[len(groups)] = (n, pos)
                    groups.append((-1, first_d[j], *([-1] * n_e)))
        else:
            groups = [(first_s[i], *partners(i)) for i, _ in self._pairs]
        off = 2 if d_topic else 1  # position of the first further topic in ``topics``
        order = sorted(range(n_frames), key=lambda n: self._stamps[s_topic][self._pairs[n][0]])
        rank = {n: r for r, n in enumerate(order)}
        between: dict[int, dict[int, tuple[NDArray[np.uint8], int]]] = {}
        waiting: dict[int, VioFrame] = {}  # frames whose images between have not all been read yet
        ready: dict[int, VioFrame] = {}
        next_out = 0

        def complete(n: int) -> bool:
            return len(between.get(n, {})) == len(self._between.get(n, ()))

        for g, images in stream_image_groups(self.path, topics, groups, to_gray8):
            if g in extra_of:
                n, pos = extra_of[g]
                img = images[1]
                assert img is not None
                between.setdefault(n, {})[pos] = (img.image, img.stamp_ns)
                if n not in waiting or not complete(n):
                    continue
                frame = waiting.pop(n)
            else:
                n = g
                s_img = images[0]
                assert s_img is not None
                d = images[1] if d_topic else None
                d_img, d_ts = (d.image, d.stamp_ns) if d is not None else (None, 0)
                ex = images[off : off + n_e]
                frame = VioFrame(
                    s_img.stamp_ns,
                    s_img.image,
                    d_img,
                    d_ts,
                    s_img.stamp_ns in self._gap_starts,
                    extra=tuple(None if x is None else x.image for x in ex),
                    extra_timestamps_ns=tuple(0 if x is None else x.stamp_ns for x in ex),
                )
                if not complete(n):
                    waiting[n] = frame
                    continue
            got = between.pop(n, {})
            steps = [got[p] for p in sorted(got)]
            ready[rank[n]] = replace(
                frame, dynamic_between=tuple(i for i, _ in steps), dynamic_between_ns=tuple(t for _, t in steps)
            )
            while next_out in ready:
                yield ready.pop(next_out)
                next_out += 1
        while next_out in ready:
            yield ready.pop(next_out)
            next_out += 1
