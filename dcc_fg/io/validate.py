"""Checks of user input files at load time: every error names the file, the line or field, and the expected form.

The loaders of :mod:`dcc_fg.io`, :mod:`dcc_fg.targets` and :mod:`dcc_fg.model` read their files
through :func:`read_text` / :func:`load_yaml` (a missing file, a folder where a file is expected,
bytes that are not UTF-8, an empty file or malformed YAML each give one ``ValueError`` /
``FileNotFoundError`` naming the file and, for YAML, the line) and check every numeric field with
:func:`number`, :func:`numbers` and :func:`rigid_transform` *before* any estimation, so a NaN focal
length or a zero square size is reported as such and never surfaces later as "SVD did not
converge".  The command line prints these errors as one line and exits 2.

``where`` arguments are ``"<file>: <field>"`` prefixes, e.g. ``"cam.yaml: cam1.intrinsics[0] (fu)"``.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import NDArray

#: Largest ``||R^T R - I||`` (Frobenius) of a rotation block read from a file. A rotation written
#: with 6 decimals is off by ~1e-6, one typed by hand with 4 decimals by ~1e-4; a scaled or sheared
#: matrix, a transposed translation or a wrong row is off by far more than 1e-3.
ROTATION_TOLERANCE = 1e-3

#: A joint angle beyond one turn (rad) cannot come from an encoder reading in radians.
MAX_JOINT_ANGLE_RAD = 2.0 * math.pi


def _describe(value: Any) -> str:
    """``value`` as it would appear in the file (``-450``, ``nan``, ``'abc'``, ``[1, 2]``)."""
    if isinstance(value, float):
        return f"{value:g}"
    if isinstance(value, str):
        return repr(value)
    return str(value)


def read_text(path: str | Path, what: str, expected: str = "") -> str:
    """The text of ``path`` (UTF-8); every failure names the file.

    Args:
        path: the file.
        what: what the file is, for messages (``camchain``, ``target``, ``joints.csv``).
        expected: the expected form, appended to the empty-file message.

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: a folder where a file is expected, bytes that are not UTF-8 (with the byte
            offset), an empty file, or an OS error reading it.
    """
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"{p}: {what} file not found")
    if p.is_dir():
        raise ValueError(f"{p}: is a folder; expected a {what} file")
    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise ValueError(f"{p}: cannot read the {what} file ({exc.strerror or exc})") from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = raw[: exc.start].count(b"\n") + 1
        raise ValueError(
            f"{p}:{line}: not a text file (byte 0x{raw[exc.start]:02x} at offset {exc.start} is not UTF-8); "
            f"expected a {what} file"
        ) from None
    if not text.strip():
        raise ValueError(f"{p}: empty file; expected a {what} file" + (f" ({expected})" if expected else ""))
    return text.removeprefix("\ufeff")


def parse_yaml(text: str, source: str, what: str) -> Any:
    """``yaml.safe_load(text)``; malformed YAML -> ValueError naming ``source`` and the line."""
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        line = f":{mark.line + 1}" if mark is not None else ""
        problem = getattr(exc, "problem", None) or " ".join(str(exc).split())
        raise ValueError(f"{source}{line}: malformed YAML ({problem}); expected a {what} file") from None


def load_yaml(path: str | Path, what: str, expected: str = "") -> dict[str, Any]:
    """A YAML file that must hold a mapping (see :func:`read_text` and :func:`parse_yaml`).

    Raises:
        FileNotFoundError, ValueError: naming the file (and the line for malformed YAML).
    """
    text = read_text(path, what, expected)
    d = parse_yaml(text, str(path), what)
    if not isinstance(d, dict):
        raise ValueError(
            f"{path}: not a YAML mapping (got {type(d).__name__}); expected a {what} file"
            + (f" ({expected})" if expected else "")
        )
    return d


def number(
    value: Any,
    where: str,
    *,
    unit: str = "",
    positive: bool = False,
    nonnegative: bool = False,
    integer: bool = False,
    minimum: float | None = None,
) -> float:
    """``value`` checked to be a finite number (and positive / non-negative / an integer / >= minimum).

    Numbers given as text that parses (``'1e-3'``, which YAML 1.1 reads as a string) are accepted;
    booleans, lists and other text are not.

    Args:
        value: the value read from the file.
        where: ``"<file>: <field>"`` for the message.
        unit: what the number counts, for the message (``pixels``, ``metres``).
        positive, nonnegative, integer, minimum: the constraints.

    Returns:
        The value as a float (an integral one if ``integer``).

    Raises:
        ValueError: ``"<where> must be a <constraint> number of <unit>, got <value>"``.
    """
    phrase = ("positive " if positive else "non-negative " if nonnegative else "") + (
        "integer" if integer else "number"
    )
    if unit:
        phrase += (" count" if integer else "") + f" of {unit}"
    if minimum is not None:
        phrase += f" >= {minimum:g}"
    expected = f"{where} must be {'an' if phrase[0] in 'aeiou' else 'a'} {phrase}"
    if isinstance(value, bool) or not isinstance(value, int | float | str | np.integer | np.floating):
        raise ValueError(f"{expected}, got {_describe(value)}")
    try:
        x = float(value)
    except ValueError:
        raise ValueError(f"{expected}, got {_describe(value)}") from None
    if not math.isfinite(x):
        raise ValueError(f"{expected}, got {_describe(value)}")
    if integer and x != int(x):
        raise ValueError(f"{expected}, got {_describe(value)}")
    if (positive and x <= 0) or (nonnegative and x < 0) or (minimum is not None and x < minimum):
        raise ValueError(f"{expected}, got {_describe(value)}")
    return x


def integer(value: Any, where: str, *, unit: str = "", minimum: int = 0) -> int:
    """``value`` checked to be an integer >= ``minimum`` (``7.0`` is accepted, ``7.5`` is not)."""
    if minimum == 0:
        return int(number(value, where, unit=unit, integer=True, nonnegative=True))
    if minimum == 1:
        return int(number(value, where, unit=unit, integer=True, positive=True))
    return int(number(value, where, unit=unit, integer=True, minimum=minimum))


def numbers(
    value: Any,
    where: str,
    length: int | None = None,
    names: tuple[str, ...] = (),
    *,
    form: str = "",
    allow_null: bool = False,
    **constraints: Any,
) -> list[float]:
    """A list of finite numbers of ``length`` entries, each checked with :func:`number`.

    Args:
        value: the value read from the file.
        where: ``"<file>: <field>"``; entries are named ``<field>[k] (<names[k]>)``.
        length: the required number of entries (None: any).
        names: entry names for the messages.
        form: the expected form for a wrong length, e.g. ``[fu, fv, pu, pv]``.
        allow_null: accept ``null`` entries (returned as NaN), e.g. unobservable 1-sigma values.
        constraints: passed to :func:`number`.
    """
    if not isinstance(value, list | tuple):
        raise ValueError(f"{where} must be a list{' ' + form if form else ''}, got {_describe(value)}")
    if length is not None and len(value) != length:
        raise ValueError(
            f"{where} must have {length} entries{' ' + form if form else ''}, got {len(value)}: {_describe(value)}"
        )
    out = []
    for k, v in enumerate(value):
        if v is None and allow_null:
            out.append(math.nan)
            continue
        name = f" ({names[k]})" if k < len(names) else ""
        out.append(number(v, f"{where}[{k}]{name}", **constraints))
    return out


def rigid_transform(value: Any, where: str) -> NDArray[np.float64]:
    """A 4x4 homogeneous transform: finite, last row ``0 0 0 1``, rotation block orthonormal with det +1.

    Raises:
        ValueError: naming ``where`` and what is wrong (shape, entry, last row, ``||R^T R - I||``, det).
    """
    form = "a 4x4 matrix [[r11, r12, r13, tx], ..., [0, 0, 0, 1]]"
    if not isinstance(value, list | tuple) or len(value) != 4:
        raise ValueError(f"{where} must be {form}, got {_describe(value)}")
    rows = []
    for i, row in enumerate(value):
        rows.append(numbers(row, f"{where}[{i}]", 4, form="(a row of a 4x4 matrix)"))
    T = np.array(rows, dtype=float)
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9):
        raise ValueError(f"{where}: last row must be [0, 0, 0, 1], got {T[3].tolist()}")
    R = T[:3, :3]
    err = float(np.linalg.norm(R.T @ R - np.eye(3)))
    if err > ROTATION_TOLERANCE:
        raise ValueError(
            f"{where}: the 3x3 block is not a rotation (||R^T R - I|| = {err:.3g} > {ROTATION_TOLERANCE:g}); "
            "expected an orthonormal rotation matrix"
        )
    det = float(np.linalg.det(R))
    if det < 0:
        raise ValueError(f"{where}: the 3x3 block is a reflection (det = {det:.3g}); expected a rotation (det +1)")
    return T


def check_joint_angles(angles: NDArray[np.float64], where: str, line_of_row: list[int] | None = None) -> None:
    """Joint angles (N, L) in radians: finite, and within one turn (a value beyond is degrees).

    Args:
        angles: (N, L) angles, radians.
        where: the file (or bag topic); with ``line_of_row`` the message names ``<where>:<line>``.
        line_of_row: the file line of each row.

    Raises:
        ValueError: naming the row (line) and the joint.
    """
    a = np.asarray(angles, dtype=float)
    if a.size == 0:
        return
    a = a.reshape(a.shape[0], -1)
    bad = ~np.isfinite(a)
    if bad.any():
        r, c = (int(x) for x in np.argwhere(bad)[0])
        loc = f"{where}:{line_of_row[r]}" if line_of_row else f"{where}: row {r + 1}"
        raise ValueError(f"{loc}: theta_{c + 1} must be a finite angle in radians, got {_describe(float(a[r, c]))}")
    big = np.abs(a) > MAX_JOINT_ANGLE_RAD
    if big.any():
        r, c = (int(x) for x in np.argwhere(big)[0])
        loc = f"{where}:{line_of_row[r]}" if line_of_row else f"{where}: row {r + 1}"
        raise ValueError(
            f"{loc}: theta_{c + 1} = {a[r, c]:g} is beyond one turn (|theta| > 2*pi); the joint angles look like "
            f"degrees (largest |theta| {np.abs(a).max():g}), but they must be radians (multiply by pi/180)"
        )
