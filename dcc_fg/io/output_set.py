"""Output sets: a command's files written as one set, never over an input, never half-written.

Every ``dcc-fg`` command that writes a folder (``calibrate``, ``validate``, ``vio``, ``demo``,
``simulate calibration|flight``, and ``evaluate`` into a ``vio`` folder) writes through an
:class:`OutputSet`::

    outputs = OutputSet(out, "calibrate", inputs={"DATA": data, "--gimbal": gimbal})  # checks, no side effect
    with outputs as staging:             # creates the hidden staging folder (proves OUT is writable)
        ...compute...
        write_files(staging.path)        # every output goes into the staging folder
    # committed here: the previous run's outputs of this command removed, the new ones moved in,
    # the manifest OUT/.dcc_fg_manifest.json written last

1. **Before any work** (:meth:`OutputSet.check`, run by the constructor): OUT is not a file, is not an
   input and is not inside an input folder, holds no input (the outputs could replace or shadow it),
   is not the result folder of another command, and its nearest existing ancestor is a writable
   folder. A refusal is an :class:`OutputPathError` (a ``ValueError``) naming the option and path.
2. **Writing**: into a staging folder on the same file system (``OUT/.dcc_fg_staging.*`` when OUT
   exists, else ``.OUT.dcc_fg_staging.*`` beside it, renamed to OUT at the end). Any exception inside
   the ``with`` block, ``KeyboardInterrupt`` included, removes the staging folder (and the parent
   folders the set created): OUT is exactly as it was.
3. **Commit**: the entries listed in the previous manifest of the same command (or, for a folder of
   an older version without manifest, the command's known output names, :data:`KNOWN_OUTPUTS`) are
   removed, so no stale report, figure or evaluation stays beside the new result; files a user put
   there are left alone. The new entries are renamed into place and the manifest is written last.
   Ctrl-C during these few renames is deferred until the set is complete; an error rolls them back.

A folder's owner is the command in its manifest; for folders of older versions the ``command`` of
its ``summary.json``, or the layout of a simulated data set. ``evaluate`` *attaches* its files
(``evaluation.json``, ``vio_*.png``) to a ``vio`` folder: they are listed under ``attached`` in the
``vio`` manifest and removed when ``vio`` writes a new result there.

Single-file outputs (``intrinsics --out camchain.yaml --summary S.json``, ``config --out``) use
:class:`OutputFiles`: the same checks, temporary files beside the targets, renamed together.
This module is pure file handling (io layer): no estimator types.
"""

from __future__ import annotations

import errno
import fnmatch
import json
import os
import secrets
import shutil
import signal
import socket
import threading
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from types import FrameType, TracebackType
from typing import Any

from dcc_fg.util.provenance import package_version

#: The manifest of a result folder: which command wrote it and which entries belong to that run.
MANIFEST = ".dcc_fg_manifest.json"
MANIFEST_FORMAT = "dcc-fg output set 1"
STAGING_TAG = ".dcc_fg_staging."
REPLACED_TAG = ".dcc_fg_replaced."

_CALIBRATION_OUTPUTS = ("calibration.yaml", "joint_angles.csv", "summary.json", "report.pdf", "calibration_*.png")
#: Output names (glob patterns of top-level entries) of each command as written by versions without a
#: manifest; they identify what a re-run replaces in such a folder.
KNOWN_OUTPUTS: dict[str, tuple[str, ...]] = {
    "calibrate": _CALIBRATION_OUTPUTS,
    "validate": _CALIBRATION_OUTPUTS,
    "demo": _CALIBRATION_OUTPUTS,
    "vio": ("trajectory.tum", "trajectory_segment_*.tum", "joint_angles.csv", "summary.json"),
    "evaluate": ("evaluation.json", "vio_*.png"),
    "simulate calibration": (
        "images",
        "images.bag",
        "images_bag",
        "camchain.yaml",
        "target.yaml",
        "gimbal.yaml",
        "ground_truth.yaml",
    ),
    "simulate flight": ("flight", "flight.bag", "calibration.yaml", "ground_truth.tum", "ground_truth_joints.csv"),
}

#: Commands that write into the result folder of another command (``evaluate`` into ``vio``).
ATTACHED_TO: dict[str, str] = {"evaluate": "vio"}


class OutputPathError(ValueError):
    """``--out`` cannot be used (refused before any work; nothing written)."""


class OutputWriteError(OSError):
    """Writing or committing the outputs failed (disk full, permission denied...); OUT is unchanged."""

    def __init__(self, message: str, code: int = 0) -> None:
        super().__init__(code, message)
        self.message = message

    def __str__(self) -> str:
        return self.message


# ----------------------------------------------------------------------------------------------
# who owns a folder


@dataclass(frozen=True)
class FolderOwner:
    """The command whose result folder ``folder`` is, and the entries of its last run.

    Attributes:
        command: e.g. ``calibrate``; None for a folder no dcc-fg command identifies as its own.
        entries: top-level names that belong to that run (present ones only).
        attached: per attached command (``evaluate``), its entries (present ones only).
        evidence: what identified it (the manifest, ``summary.json``, the layout), for messages.
        manifest: the parsed manifest, if there is one.
    """

    command: str | None
    entries: tuple[str, ...] = ()
    attached: dict[str, tuple[str, ...]] = field(default_factory=dict)
    evidence: str = ""
    manifest: dict[str, Any] | None = None


def _plain_name(name: Any) -> bool:
    return isinstance(name, str) and name not in ("", ".", "..", MANIFEST) and "/" not in name and "\\" not in name


def _present(folder: Path, names: Iterable[str]) -> tuple[str, ...]:
    return tuple(n for n in names if _plain_name(n) and os.path.lexists(folder / n))


def _known(folder: Path, command: str) -> tuple[str, ...]:
    """The entries of ``folder`` that match the known output names of ``command``."""
    patterns = KNOWN_OUTPUTS.get(command, ())
    names = sorted(os.listdir(folder)) if folder.is_dir() else []
    return tuple(n for n in names if any(fnmatch.fnmatchcase(n, p) for p in patterns))


def read_manifest(folder: Path) -> dict[str, Any] | None:
    """The manifest of ``folder`` (None when it has none); OutputPathError when it is unreadable."""
    path = folder / MANIFEST
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise OutputPathError(
            f"{path}: not a readable dcc-fg manifest ({' '.join(str(exc).split())}); remove it or choose another --out"
        ) from None
    if not (isinstance(data, dict) and isinstance(data.get("command"), str) and isinstance(data.get("files"), list)):
        raise OutputPathError(f"{path}: not a dcc-fg manifest (expected 'command' and 'files'); remove it or choose "
                              "another --out")  # fmt: skip
    return data


def _summary_command(folder: Path) -> str | None:
    path = folder / "summary.json"
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return None
    command = data.get("command") if isinstance(data, dict) else None
    return command if isinstance(command, str) else None


def folder_owner(folder: str | Path) -> FolderOwner:
    """Which command's result folder ``folder`` is (see the module docstring)."""
    folder = Path(folder)
    if not folder.is_dir():
        return FolderOwner(None)
    manifest = read_manifest(folder)
    if manifest is not None:
        attached_raw = manifest.get("attached") or {}
        attached = {
            str(cmd): _present(folder, files)
            for cmd, files in (attached_raw.items() if isinstance(attached_raw, dict) else [])
            if isinstance(files, list)
        }
        return FolderOwner(manifest["command"], _present(folder, manifest["files"]), attached, str(folder / MANIFEST),
                           manifest)  # fmt: skip
    command = _summary_command(folder)
    evidence = f"the 'command' of {folder / 'summary.json'}"
    names = set(os.listdir(folder))
    if command is None and "trajectory.tum" in names:
        command, evidence = "vio", f"{folder / 'trajectory.tum'}"
    if command is None and "ground_truth.yaml" in names and names & {"images", "images.bag", "images_bag"}:
        command, evidence = "simulate calibration", f"{folder / 'ground_truth.yaml'} beside the images"
    if command is None and "ground_truth.tum" in names and names & {"flight", "flight.bag"}:
        command, evidence = "simulate flight", f"{folder / 'ground_truth.tum'} beside the flight bag"
    if command is None:
        return FolderOwner(None)
    attached = {c: _known(folder, c) for c, owner in ATTACHED_TO.items() if owner == command}
    return FolderOwner(command, _known(folder, command), attached, evidence)


# ----------------------------------------------------------------------------------------------
# checks


def _resolve(path: str | Path) -> Path:
    return Path(path).expanduser().resolve()


def _inside(path: Path, folder: Path) -> bool:
    return path == folder or path.is_relative_to(folder)


def _nearest_existing(path: Path) -> Path:
    p = path
    while not os.path.lexists(p) and p != p.parent:
        p = p.parent
    return p


def check_writable_location(path: Path, option: str, what: str) -> None:
    """The nearest existing ancestor of ``path`` (``path`` itself if it exists) is a writable folder."""
    base = _nearest_existing(path)
    if not base.is_dir():
        raise OutputPathError(f"{option} {path}: {base} is a file, not a folder; choose a {what} path whose folders "
                              "do not clash with files")  # fmt: skip
    if not os.access(base, os.W_OK | os.X_OK):
        raise OutputPathError(f"{option} {path}: the folder {base} is not writable (permission denied); choose "
                              f"another {what}")  # fmt: skip


def input_conflict(out: Path, inputs: Mapping[str, str | Path | None], option: str = "--out") -> str | None:
    """Why ``out`` (a folder) would replace, shadow or sit inside an input; None when it does not."""
    o = _resolve(out)
    for role, path in inputs.items():
        if path is None:
            continue
        p = _resolve(path)
        if p == o:
            return f"{option} {out} is the input {role} ({path}); choose another {option} folder"
        if _inside(o, p):
            return f"{option} {out} is inside the input {role} folder {path}; choose a {option} folder outside it"
        if _inside(p, o):
            return (
                f"{option} {out} holds the input {role} {path}: the outputs could replace or shadow it; choose "
                f"another {option} folder (e.g. a new sub-folder)"
            )
    return None


# ----------------------------------------------------------------------------------------------
# Ctrl-C during a commit


class DeferredInterrupt:
    """Inside this block a SIGINT (Ctrl-C) is recorded and raised as KeyboardInterrupt at its end.

    Only in the main thread (elsewhere signals cannot be handled; the block runs unprotected).
    """

    def __init__(self) -> None:
        self.received = False
        self.previous: Any = None
        self.active = False

    def _handler(self, signum: int, frame: FrameType | None) -> None:
        self.received = True

    def __enter__(self) -> DeferredInterrupt:
        if threading.current_thread() is threading.main_thread():
            try:
                self.previous = signal.signal(signal.SIGINT, self._handler)
                self.active = True
            except ValueError:
                self.active = False
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if self.active:
            signal.signal(signal.SIGINT, self.previous)
        if self.received and exc is None:
            raise KeyboardInterrupt


def _owner_tag() -> str:
    """``<host>-<pid>``: which process a staging folder belongs to (part of its name)."""
    host = "".join(c for c in socket.gethostname() if c.isalnum())[:24] or "host"
    return f"{host}-{os.getpid()}"


def _new_dir(parent: Path, prefix: str) -> Path:
    """A fresh folder ``parent/<prefix><host>-<pid>.<random>`` (created with the umask's permissions)."""
    for _ in range(100):
        path = parent / f"{prefix}{_owner_tag()}.{secrets.token_hex(4)}"
        try:
            path.mkdir()
            return path
        except FileExistsError:
            continue
    raise OutputWriteError(f"{parent}: cannot create a staging folder (100 names taken)", errno.EEXIST)


def _process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def remove_stale_staging(folder: Path) -> list[Path]:
    """Remove the staging folders in ``folder`` left by runs of this host that were killed (SIGKILL,
    power loss: no chance to clean up); folders of live processes and of other hosts are kept."""
    removed: list[Path] = []
    if not folder.is_dir():
        return removed
    host = _owner_tag().rsplit("-", 1)[0]
    for p in folder.iterdir():
        tag = next((t for t in (STAGING_TAG, REPLACED_TAG) if t in p.name), None)
        if tag is None or not p.is_dir() or p.is_symlink():
            continue
        owner = p.name.split(tag, 1)[1].split(".", 1)[0]
        h, _, pid = owner.rpartition("-")
        if h == host and pid.isdigit() and not _process_alive(int(pid)):
            shutil.rmtree(p, ignore_errors=True)
            removed.append(p)
    return removed


def _write_error(exc: OSError, where: Path, out: Path, option: str) -> OutputWriteError:
    reason = exc.strerror or " ".join(str(exc).split()) or type(exc).__name__
    hint = "free some disk space" if exc.errno in (errno.ENOSPC, errno.EDQUOT) else "check the permissions and space"
    return OutputWriteError(
        f"could not write the outputs of {option} {out}: {where}: {reason}; nothing was written ({hint})",
        exc.errno or 0,
    )


# ----------------------------------------------------------------------------------------------
# the output set of a folder


class OutputSet:
    """The outputs of one run of ``command`` into the folder ``out`` (see the module docstring).

    Args:
        out: the result folder (``--out``; for ``evaluate`` the ``vio`` folder it attaches to).
        command: ``calibrate``, ``validate``, ``vio``, ``demo``, ``evaluate``, ``simulate calibration``,
            ``simulate flight``.
        inputs: option or role -> input path (files or folders; None entries are skipped). For an
            attached command (``evaluate``) an input inside OUT is refused only when the set would
            replace it.
        replace_previous: False: refuse a folder that already holds the outputs of an earlier run of
            ``command``; True: replace them.
        replace_hint: what to say in that refusal (e.g. ``pass --force``).
        option: the option name used in messages.
        replace_unowned: True: a file of the user that has the name of a new output is replaced (a folder
            never is); False: such a name (one of :data:`KNOWN_OUTPUTS`, or met at the commit) is refused.

    Raises:
        OutputPathError: OUT cannot be used (before any work; nothing is touched).
    """

    def __init__(
        self,
        out: str | Path,
        command: str,
        inputs: Mapping[str, str | Path | None] | None = None,
        replace_previous: bool = True,
        replace_hint: str = "",
        option: str = "--out",
        replace_unowned: bool = True,
    ) -> None:
        self.out = Path(out)
        self.command = command
        self.inputs = dict(inputs or {})
        self.replace_previous = replace_previous
        self.replace_hint = replace_hint
        self.replace_unowned = replace_unowned
        self.option = option
        self.attach_to = ATTACHED_TO.get(command)
        self.staging: Path | None = None
        self.created: list[Path] = []
        self.committed: list[Path] = []
        self.done = False
        self.check()

    # -- checks --------------------------------------------------------------------------------

    def check(self) -> FolderOwner:
        """Every check that can fail before the work (see the module docstring); the folder's owner."""
        out, opt = self.out, self.option
        if os.path.lexists(out) and not out.is_dir():
            raise OutputPathError(
                f"{opt} {out}: exists and is a file; {opt} must be a folder (a new or an existing one)"
            )
        if self.attach_to is None:
            conflict = input_conflict(out, self.inputs, opt)
            if conflict:
                raise OutputPathError(conflict)
        else:
            self._check_attached_inputs()
        check_writable_location(out, opt, f"{opt} folder")
        owner = folder_owner(out)
        if self.attach_to is not None:
            if not out.is_dir():
                raise OutputPathError(f"{out}: no such folder (the output folder of dcc-fg {self.attach_to})")
            if owner.command not in (None, self.attach_to):
                raise OutputPathError(
                    f"{out}: is the result folder of 'dcc-fg {owner.command}' (per {owner.evidence}), not of "
                    f"'dcc-fg {self.attach_to}'; {self.command} writes only into {self.attach_to} folders"
                )
            return owner
        if owner.command is not None and owner.command != self.command:
            raise OutputPathError(
                f"{opt} {out}: is the result folder of 'dcc-fg {owner.command}' (per {owner.evidence}); writing "
                f"'dcc-fg {self.command}' outputs there would mix two results; choose another {opt} folder"
            )
        owned = owner.entries if owner.command == self.command else ()
        if not self.replace_previous and owned:
            hint = f" or {self.replace_hint}" if self.replace_hint else ""
            raise OutputPathError(f"{out / owned[0]}: already exists (written by dcc-fg {self.command}); choose an "
                                  f"empty {opt} folder{hint}")  # fmt: skip
        if not self.replace_unowned:
            clash = [n for n in _known(out, self.command) if n not in owned]
            if clash:
                raise OutputPathError(f"{out / clash[0]}: already exists and was not written by dcc-fg "
                                      f"{self.command}; it is left alone: choose an empty {opt} folder")  # fmt: skip
        return owner

    def _check_attached_inputs(self) -> None:
        o = _resolve(self.out)
        patterns = KNOWN_OUTPUTS.get(self.command, ())
        for role, path in self.inputs.items():
            if path is None:
                continue
            p = _resolve(path)
            if _inside(o, p):
                raise OutputPathError(f"{self.out} is inside the input {role} {path}; give the {self.attach_to} "
                                      "output folder")  # fmt: skip
            if p.is_relative_to(o):
                top = p.relative_to(o).parts[0]
                if any(fnmatch.fnmatchcase(top, pat) for pat in patterns) or top == MANIFEST:
                    raise OutputPathError(f"the input {role} {path} would be replaced by the outputs of "
                                          f"{self.command}; move it elsewhere")  # fmt: skip

    # -- staging -------------------------------------------------------------------------------

    @property
    def path(self) -> Path:
        """The staging folder (write every output here)."""
        if self.staging is None:
            raise RuntimeError("OutputSet.path is only available inside 'with OutputSet(...)'")
        return self.staging

    def final(self, path: str | Path) -> Path:
        """Where a staging path ends up after the commit (also valid after it)."""
        return self.out / Path(path).relative_to(self.path)

    def __enter__(self) -> OutputSet:
        self.check()
        out = self.out
        for folder in (out, out.parent):
            remove_stale_staging(folder)
        try:
            if out.is_dir():
                self.staging = _new_dir(out, STAGING_TAG)
            else:
                missing = []
                p = out.parent
                while not p.exists():
                    missing.append(p)
                    p = p.parent
                for d in reversed(missing):
                    d.mkdir()
                    self.created.append(d)
                self.staging = _new_dir(out.parent, f".{out.name}{STAGING_TAG}")
        except OSError as exc:
            self._discard()
            raise _write_error(exc, Path(exc.filename or out), out, self.option) from exc
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if exc is not None:
            self._discard()
            if isinstance(exc, OSError) and not isinstance(exc, OutputWriteError) and self._about_staging(exc):
                raise _write_error(exc, self._final_name(exc.filename), self.out, self.option) from exc
            return
        try:
            self.commit()
        except BaseException:
            self._discard()
            raise

    def _about_staging(self, exc: OSError) -> bool:
        return self.staging is not None and bool(exc.filename) and str(exc.filename).startswith(str(self.staging))

    def _final_name(self, filename: Any) -> Path:
        try:
            return self.final(str(filename))
        except (ValueError, RuntimeError):
            return Path(str(filename))

    def _discard(self) -> None:
        """Remove the staging folder and the parent folders this set created (if still empty)."""
        if self.staging is not None and not self.done:
            shutil.rmtree(self.staging, ignore_errors=True)
        for d in reversed(self.created):
            try:
                d.rmdir()
            except OSError:
                break
        self.created = []

    # -- commit --------------------------------------------------------------------------------

    def manifest(self, entries: list[str], owner: FolderOwner) -> dict[str, Any]:
        """The manifest written with the new entries."""
        now = datetime.now(UTC).isoformat(timespec="seconds")
        if self.attach_to is None:
            return {
                "format": MANIFEST_FORMAT,
                "command": self.command,
                "dcc_fg_version": package_version(),
                "written": now,
                "files": entries,
                "attached": {},
            }
        base = dict(owner.manifest) if owner.manifest is not None else {
            "format": MANIFEST_FORMAT,
            "command": self.attach_to,
            "dcc_fg_version": package_version(),
            "written": None,
            "files": list(owner.entries or _known(self.out, self.attach_to)),
        }  # fmt: skip
        attached = dict(base.get("attached") or {})
        attached[self.command] = entries
        base["attached"] = attached
        return base

    def commit(self) -> list[Path]:
        """Replace the previous outputs of this command in OUT by the staged ones (see the module docstring)."""
        staging = self.path
        entries = sorted(n for n in os.listdir(staging) if n != MANIFEST)
        owner = self.check()
        if self.attach_to is None:
            previous = set(owner.entries) if owner.command == self.command else set()
            if owner.command == self.command:
                for files in owner.attached.values():
                    previous |= set(files)
        else:
            previous = set(owner.attached.get(self.command, ()))
        for name in entries:
            dest = self.out / name
            unowned = name not in previous and os.path.lexists(dest)
            if unowned and (not self.replace_unowned or (dest.is_dir() and not dest.is_symlink())):
                raise OutputPathError(
                    f"{dest}: already exists and was not written by dcc-fg {self.command}; it is left alone, so the "
                    f"outputs cannot be written; move it or choose another {self.option}"
                )
        manifest_text = json.dumps(self.manifest(entries, owner), indent=2) + "\n"
        with DeferredInterrupt():
            if not os.path.lexists(self.out) and self.attach_to is None:
                (staging / MANIFEST).write_text(manifest_text, encoding="utf-8")
                try:
                    os.rename(staging, self.out)
                except OSError as exc:
                    raise _write_error(exc, self.out, self.out, self.option) from exc
                self.done, self.created = True, []
            else:
                self._replace_entries(entries, previous, manifest_text)
        self.committed = [self.out / n for n in entries]
        return self.committed

    def _replace_entries(self, entries: list[str], previous: set[str], manifest_text: str) -> None:
        out, staging = self.out, self.path
        old = [n for n in sorted(previous | set(entries)) if os.path.lexists(out / n)]
        trash = _new_dir(out, REPLACED_TAG) if old else None
        moved_old: list[str] = []
        placed: list[str] = []
        try:
            for name in old:
                assert trash is not None
                os.rename(out / name, trash / name)
                moved_old.append(name)
            for name in entries:
                os.rename(staging / name, out / name)
                placed.append(name)
            tmp = out / f"{MANIFEST}.{secrets.token_hex(4)}.tmp"
            tmp.write_text(manifest_text, encoding="utf-8")
            os.replace(tmp, out / MANIFEST)
        except BaseException as exc:
            for name in reversed(placed):  # roll back: OUT as it was
                os.rename(out / name, staging / name)
            for name in reversed(moved_old):
                assert trash is not None
                os.rename(trash / name, out / name)
            if trash is not None:
                shutil.rmtree(trash, ignore_errors=True)
            for leftover in out.glob(f"{MANIFEST}.*.tmp"):
                leftover.unlink(missing_ok=True)
            if isinstance(exc, OSError) and not isinstance(exc, OutputWriteError):
                raise _write_error(exc, Path(exc.filename or out), out, self.option) from exc
            raise
        if trash is not None:
            shutil.rmtree(trash, ignore_errors=True)
        self.done = True
        shutil.rmtree(staging, ignore_errors=True)


# ----------------------------------------------------------------------------------------------
# single files


class OutputFiles:
    """A few single output files (option -> path) written together: temporary files beside each
    target, renamed into place only when the block succeeds.

    The constructor checks every target before any work: not an existing folder, not an input, not
    inside an input folder, two options not naming the same file, a writable folder. Inside the
    ``with`` block, ``files[option]`` is the temporary path to write (it does not exist yet);
    :meth:`seed` copies an existing target there first (for files that are updated, e.g. a camchain).
    """

    def __init__(self, targets: Mapping[str, str | Path | None], inputs: Mapping[str, str | Path | None] | None = None):
        self.targets = {opt: Path(p) for opt, p in targets.items() if p is not None}
        self.inputs = dict(inputs or {})
        self.staged: dict[str, Path] = {}
        self.check()

    def check(self) -> None:
        seen: dict[Path, str] = {}
        for opt, path in self.targets.items():
            if path.is_dir():
                raise OutputPathError(f"{opt} {path}: is a folder; {opt} names a file")
            r = _resolve(path)
            if r in seen:
                raise OutputPathError(f"{opt} {path}: the same file as {seen[r]}; give two different files")
            seen[r] = opt
            for role, inp in self.inputs.items():
                if inp is None:
                    continue
                p = _resolve(inp)
                if r == p:
                    raise OutputPathError(
                        f"{opt} {path} is the input {role}; it would be replaced; choose another file"
                    )
                if r.is_relative_to(p):
                    raise OutputPathError(f"{opt} {path} is inside the input {role} folder {inp}; choose a file "
                                          "outside it")  # fmt: skip
            check_writable_location(path.parent, opt, "file")

    def __getitem__(self, option: str) -> Path:
        return self.staged[option]

    def seed(self, option: str) -> None:
        """Start the temporary file of ``option`` as a copy of the existing target (if any)."""
        if self.targets[option].is_file():
            shutil.copyfile(self.targets[option], self.staged[option])

    def __enter__(self) -> OutputFiles:
        self.check()
        for opt, path in self.targets.items():
            path.parent.mkdir(parents=True, exist_ok=True)
            self.staged[opt] = path.parent / f".{path.name}{STAGING_TAG}{secrets.token_hex(4)}"
        return self

    def _discard(self) -> None:
        for tmp in self.staged.values():
            tmp.unlink(missing_ok=True)

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if exc is not None:
            self._discard()
            return
        try:
            with DeferredInterrupt():
                for opt, tmp in self.staged.items():
                    if tmp.exists():
                        os.replace(tmp, self.targets[opt])
        except OSError as exc2:
            self._discard()
            reason = exc2.strerror or str(exc2)
            raise OutputWriteError(
                f"could not write {exc2.filename}: {reason}; nothing was replaced", exc2.errno or 0
            ) from exc2
        except BaseException:
            self._discard()
            raise
