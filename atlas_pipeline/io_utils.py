"""Atomic, crash-consistent file and folder writes; the output policy; process locks; content hashes.

Every artifact is written under a temporary name in the same folder and renamed into place, so a
crash or a bad input half-way never leaves a truncated file where a good one used to be.

Folders are swapped in three renames, each named so that an interrupted swap can be finished or
undone by the next writer or reader of the same target (:func:`recover_dir`)::

    .<name>.<pid>-<id>.tmp   being written (incomplete: removed once its process is gone)
    .<name>.<pid>-<id>.new   complete, about to replace <name> (rolled forward if <name> is missing)
    .<name>.<pid>-<id>.old   the previous <name>, being retired (rolled back if <name> is missing)

Folders the project writes carry a marker file (:data:`MARKER_NAME`) that says what kind of folder
it is and which entries the project wrote. The output policy (:func:`check_output_dir`) only
replaces an empty folder or a folder of the same kind holding nothing but the project's files.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import errno
import fcntl
import hashlib
import json
import logging
import os
import re
import shutil
import socket
import uuid
from pathlib import Path
from typing import Any, Iterable, Iterator

from atlas_pipeline.errors import AtlasError, ConfigError, OutputPolicyError, WriteError

logger = logging.getLogger(__name__)

__all__ = [
    "MARKER_NAME",
    "ARTIFACT_KIND",
    "ARTIFACT_RECORD",
    "read_marker",
    "atomic_path",
    "atomic_dir",
    "stage_dir",
    "commit_dir",
    "recover_dir",
    "sweep_stale_files",
    "discard_own_staging",
    "folder_kind",
    "foreign_entries",
    "check_output_dir",
    "check_output_file",
    "check_writable",
    "env_folder",
    "ProcessLock",
    "LockedError",
    "process_alive",
    "write_bytes_atomic",
    "write_text_atomic",
    "write_json_atomic",
    "sha256_file",
    "sha256_files",
]

# Hidden so that bundle checksum tables and copies skip it; JSON: {"kind", "files", "writer", ...}.
MARKER_NAME = ".atlas-gs.json"
MARKER_VERSION = 1
# The Dagster IO manager's folders (kind and record file), named here so a library reader can tell
# the live artifact from a user's copy of it.
ARTIFACT_KIND = "artifact"
ARTIFACT_RECORD = "_artifact.json"
_STAGE_SUFFIXES = ("tmp", "new", "old")
# A probe write before expensive work: big enough to hit a full disk, small enough to be free.
_PROBE_BYTES = 64 * 1024
# Below this much free space an artifact folder is refused before work starts: the smallest
# artifacts are a few MB, bundles and videos tens; twice the previous version is asked on top.
MIN_FREE_BYTES = 64 * 1024 * 1024


def _staging_re(name: str) -> re.Pattern[str]:
    return re.compile(rf"^\.{re.escape(name)}\.(\d+)-([0-9a-f]{{8}})\.({'|'.join(_STAGE_SUFFIXES)})$")


def _write_error(path: Path, exc: OSError) -> WriteError:
    return WriteError(path, exc.strerror or str(exc), exc.errno)


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success rename it onto ``path``.

    The temporary name keeps the file's suffix so tools that look at it (ffmpeg, PLY writers)
    still recognise the format. An OS error while writing names ``path``.
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise _write_error(path.parent, exc) from exc
    sweep_stale_files(path)
    tmp = path.with_name(f".{path.stem}.{os.getpid()}-{uuid.uuid4().hex[:8]}.tmp{path.suffix}")
    _OWN_STAGING.add(tmp)
    try:
        yield tmp
        os.replace(tmp, path)
    except OSError as exc:
        raise _write_error(path, exc) from exc
    finally:
        _OWN_STAGING.discard(tmp)
        if tmp.exists():
            tmp.unlink()


# Staging folders and temporary files this process is writing: what a command ended at once (Ctrl-C)
# removes before it exits (discard_own_staging). A swap under way is not among them: its .new and
# .old folders are what the next open rolls forward or back.
_OWN_STAGING: set[Path] = set()


def discard_own_staging() -> None:
    """Remove this process's staging folders and temporary files now (an interrupted command's last
    act); the targets they were to replace stay as they were."""
    mine = f".{os.getpid()}-"
    for p in list(_OWN_STAGING):
        if mine not in p.name:  # a forked child's copy of its parent's entries
            continue
        with contextlib.suppress(OSError):
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p)
            else:
                p.unlink(missing_ok=True)
    _OWN_STAGING.clear()


def sweep_stale_files(path: str | Path) -> list[str]:
    """Remove temporary files of ``path`` (``.<stem>.<pid>-<id>.tmp<suffix>``) whose writer died."""
    path = Path(path)
    pattern = re.compile(rf"^\.{re.escape(path.stem)}\.(\d+)-[0-9a-f]{{8}}\.tmp{re.escape(path.suffix)}$")
    removed = []
    try:
        siblings = list(path.parent.iterdir())
    except OSError:
        return removed
    for p in siblings:
        m = pattern.match(p.name)
        if m and not process_alive(int(m.group(1))) and p.is_file():
            p.unlink(missing_ok=True)
            removed.append(p.name)
    if removed:
        logger.info("%s: removed %d temporary file(s) left by a killed writer", path, len(removed))
    return removed


# ---- folders: stage, commit, recover -------------------------------------------------------------


def _sibling(path: Path, token: str, suffix: str) -> Path:
    return path.with_name(f".{path.name}.{token}.{suffix}")


def _token(staged: Path) -> str:
    """``<pid>-<id>`` of a staging folder name."""
    return staged.name.rsplit(".", 2)[-2]


def stage_dir(path: str | Path) -> Path:
    """Create and return an empty temporary folder beside ``path`` (finished swaps are repaired first)."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        recover_dir(path)
        tmp = _sibling(path, f"{os.getpid()}-{uuid.uuid4().hex[:8]}", "tmp")
        _OWN_STAGING.add(tmp)
        tmp.mkdir(mode=0o755)
    except OSError as exc:
        raise _write_error(path, exc) from exc
    return tmp


def _write_marker(folder: Path, kind: str, extra: dict[str, Any] | None = None) -> None:
    files = sorted(p.name for p in folder.iterdir() if p.name != MARKER_NAME)
    marker = {"writer": "atlas-gs", "version": MARKER_VERSION, "kind": kind, "files": files, **(extra or {})}
    (folder / MARKER_NAME).write_text(json.dumps(marker, indent=1) + "\n", encoding="utf-8")


def _fsync_dir(folder: Path) -> None:
    with contextlib.suppress(OSError):
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def commit_dir(staged: Path, path: str | Path, kind: str, marker_extra: dict[str, Any] | None = None) -> Path:
    """Swap the complete folder ``staged`` (from :func:`stage_dir`) into place at ``path``.

    Writes the marker, renames ``staged`` to ``.new`` (now known complete), moves the previous
    ``path`` aside to ``.old``, renames ``.new`` onto ``path`` and removes ``.old``. A crash at any
    point leaves either the old or the new folder at ``path``, or a state :func:`recover_dir`
    turns into one of them.
    """
    path = Path(path)
    if not staged.is_dir():
        raise WriteError(staged, "staged folder vanished before commit")
    token = _token(staged)
    new, old = _sibling(path, token, "new"), _sibling(path, token, "old")
    try:
        _write_marker(staged, kind, marker_extra)
        os.replace(staged, new)
        _OWN_STAGING.discard(staged)
        _fsync_dir(path.parent)
        if os.path.lexists(path):
            os.replace(path, old)
            os.replace(new, path)
            _fsync_dir(path.parent)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(new, path)
            _fsync_dir(path.parent)
    except OSError as exc:
        raise _write_error(path, exc) from exc
    return path


def discard_dir(staged: Path) -> None:
    """Remove a staging folder after a failure (best effort: recovery removes it otherwise)."""
    _OWN_STAGING.discard(staged)
    shutil.rmtree(staged, ignore_errors=True)


def process_alive(pid: int) -> bool:
    """Whether a process with ``pid`` exists on this machine (zombies count as gone)."""
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    try:  # a zombie holds its pid but will never finish a swap
        with open(f"/proc/{pid}/stat", "rb") as f:
            return f.read().split(b")")[-1].split()[0] != b"Z"
    except OSError:
        return True


def recover_dir(path: str | Path) -> list[str]:
    """Finish or undo interrupted swaps of ``path`` and remove staging left by dead processes.

    * ``path`` missing and a ``.new`` (complete) of a dead process exists: roll forward.
    * ``path`` missing and only an ``.old`` exists: roll back.
    * then every ``.tmp`` / ``.new`` / ``.old`` of a dead process is removed.

    Staging of live processes (another writer at work) is left alone. Returns what was done.
    """
    path = Path(path)
    parent = path.parent
    if not parent.is_dir():
        return []
    pattern = _staging_re(path.name)
    dead: dict[str, list[Path]] = {s: [] for s in _STAGE_SUFFIXES}
    try:
        entries = list(parent.iterdir())
    except OSError:
        return []
    for p in entries:
        m = pattern.match(p.name)
        if m and not process_alive(int(m.group(1))):
            dead[m.group(3)].append(p)
    done: list[str] = []
    if not any(dead.values()):
        return done
    if not os.path.lexists(path):
        by_age = lambda q: q.stat().st_mtime_ns  # noqa: E731 - newest complete version wins
        if dead["new"]:
            src = max(dead["new"], key=by_age)
            os.replace(src, path)
            dead["new"].remove(src)
            done.append(f"rolled forward {src.name} -> {path.name}")
        elif dead["old"]:
            src = max(dead["old"], key=by_age)
            os.replace(src, path)
            dead["old"].remove(src)
            done.append(f"rolled back {src.name} -> {path.name}")
    for suffix in _STAGE_SUFFIXES:
        for p in dead[suffix]:
            shutil.rmtree(p, ignore_errors=True) if p.is_dir() else p.unlink(missing_ok=True)
            done.append(f"removed {p.name}")
    for what in done:
        logger.warning("%s: repaired an interrupted write: %s", path, what)
    return done


@contextlib.contextmanager
def atomic_dir(path: str | Path, kind: str = "folder", marker_extra: dict[str, Any] | None = None) -> Iterator[Path]:
    """Yield a fresh temporary folder beside ``path``; on success swap it into place.

    The caller decides beforehand whether ``path`` may be replaced (:func:`check_output_dir`). At
    every moment one complete version exists on disk (or is restored by :func:`recover_dir`).
    """
    path = Path(path)
    tmp = stage_dir(path)
    try:
        try:
            yield tmp
        except OSError as exc:
            raise _write_error(_failed_path(exc, tmp, path), exc) from exc
        except WriteError as exc:
            staged = _as_target(exc.path, tmp, path)
            if staged is None:
                raise
            said = str(exc)
            reason = said[len(f"{exc.path}: "):] if said.startswith(f"{exc.path}: ") else said
            raise WriteError(staged, reason, exc.errno) from exc
        commit_dir(tmp, path, kind, marker_extra)
    finally:
        if tmp.exists():
            discard_dir(tmp)


def _as_target(p: str | Path, staged: Path, target: Path) -> Path | None:
    """Where ``p``, a path inside the staging folder ``staged``, ends up once ``staged`` becomes
    ``target``; None for a path outside it."""
    try:
        return target / Path(os.path.abspath(p)).relative_to(os.path.abspath(staged))
    except ValueError:
        return None


def _failed_path(exc: OSError, staged: Path, target: Path) -> Path:
    """The path an OS error met while a folder was staged should name: the output being written
    (as the user will know it, under ``target``) when the error names one (``shutil.copyfile``
    names its source first, its destination second), else the file it names (an input that could
    not be read), else ``target``."""
    named = [Path(os.fsdecode(n)) for n in (exc.filename, exc.filename2) if isinstance(n, (str, bytes, os.PathLike))]
    for name in named:
        if (out := _as_target(name, staged, target)) is not None:
            return out
    return named[0] if named else target


# ---- output policy -----------------------------------------------------------------------------


def read_marker(folder: Path) -> dict[str, Any] | None:
    """The marker of an Atlas-GS folder (kind, files, what its writer added), None if it has none."""
    return _read_marker(Path(folder))


def _read_marker(folder: Path) -> dict[str, Any] | None:
    p = folder / MARKER_NAME
    try:
        marker = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not isinstance(marker, dict) or marker.get("writer") != "atlas-gs" or not isinstance(marker.get("kind"), str):
        return None
    return marker


def folder_kind(folder: str | Path) -> str | None:
    """The kind of Atlas-GS folder at ``folder`` (``world_bundle``, ``artifact`` ...), None if not one."""
    folder = Path(folder)
    marker = _read_marker(folder)
    return marker["kind"] if marker is not None else None


def foreign_entries(folder: str | Path) -> list[str]:
    """Entries of ``folder`` the project did not write (all of them when it has no marker)."""
    folder = Path(folder)
    marker = _read_marker(folder)
    ours = {MARKER_NAME, *map(str, marker.get("files") or [])} if marker is not None else set()
    return sorted(p.name for p in folder.iterdir() if p.name not in ours)


def _overlaps(a: Path, b: Path) -> bool:
    return a == b or b.is_relative_to(a)


def check_output_dir(path: str | Path, kind: str, inputs: Iterable[str | Path] = (), force: bool = False,
                     what: str = "--output") -> Path | None:
    """Decide whether ``path`` may be replaced by a new folder of ``kind``; raise if not.

    Allowed: a missing or empty folder, or an Atlas-GS folder of the same kind that holds only
    files the project wrote. Never allowed: a path that is, or contains, one of ``inputs`` (the
    command reads it), a symbolic link, a file. Anything else is refused unless ``force``; then it
    is moved aside to a visible ``<name>.replaced-<UTC time>`` folder (never deleted), whose path
    is returned.
    """
    path = Path(path).expanduser()
    resolved = path.resolve()
    for inp in inputs:
        if inp is None:
            continue
        r = Path(inp).expanduser().resolve()
        if _overlaps(resolved, r):
            raise OutputPolicyError(path, f"{what} is {'the same folder as' if r == resolved else 'a folder holding'} "
                                          f"the input {inp} of this command; choose another {what}, nothing was changed")
    recover_dir(path)
    if not os.path.lexists(path):
        return None
    if path.is_symlink():
        raise OutputPolicyError(path, f"{what} is a symbolic link; refusing to replace it (give the real folder)")
    if not path.is_dir():
        raise OutputPolicyError(path, f"{what} exists and is a file, not a folder; refusing to replace it")
    try:
        entries = list(path.iterdir())
    except OSError as exc:
        raise _write_error(path, exc) from exc
    if not entries:
        return None
    have = folder_kind(path)
    foreign = foreign_entries(path)
    if have == kind and not foreign:
        return None
    if have == kind:
        reason = (f"is an Atlas-GS {kind} but also holds {len(foreign)} entr{'y' if len(foreign) == 1 else 'ies'} "
                  f"atlas-gs did not write ({', '.join(foreign[:3])}{', ...' if len(foreign) > 3 else ''})")
    elif have is not None:
        reason = f"holds an Atlas-GS {have}, not a {kind}"
    else:
        reason = (f"exists and was not written by atlas-gs ({len(entries)} entr{'y' if len(entries) == 1 else 'ies'}, "
                  f"e.g. {sorted(p.name for p in entries)[0]!r})")
    if not force:
        raise OutputPolicyError(path, f"{what} {reason}; refusing to replace it. Choose a new or empty folder, "
                                      "or pass --force to move it aside (it is never deleted)")
    backup = _move_aside(path, path.name, "")
    logger.warning("%s %s; moved it aside to %s (--force)", path, reason, backup)
    return backup


def prepare_output_dir(output: str | Path, kind: str, inputs: Iterable[str | Path | None], force: bool) -> Path:
    """``output`` as a folder a command of ``kind`` may write: the output policy
    (:func:`check_output_dir`) and the writability of its parent checked before any expensive work."""
    out = Path(output).expanduser()
    check_output_dir(out, kind, inputs, force)
    check_writable(out.parent)
    return out


def _move_aside(path: Path, stem: str, suffix: str) -> Path:
    """Rename ``path`` to a free, visible ``<stem>.replaced-<UTC time>[-n]<suffix>`` beside it."""
    stamp = _dt.datetime.now(_dt.timezone.utc).strftime("%Y%m%dT%H%M%SZ")
    backup = path.with_name(f"{stem}.replaced-{stamp}{suffix}")
    n = 1
    while os.path.lexists(backup):
        n += 1
        backup = path.with_name(f"{stem}.replaced-{stamp}-{n}{suffix}")
    try:
        os.replace(path, backup)
    except OSError as exc:
        raise _write_error(path, exc) from exc
    return backup


def check_output_file(path: str | Path, inputs: Iterable[str | Path] = (), force: bool = False,
                      is_ours: Any = None, what: str = "--output") -> Path | None:
    """Decide whether the file ``path`` may be (over)written; raise if not.

    Allowed: a missing file, or one ``is_ours(path)`` recognises as written by the project. Never:
    one of ``inputs``, a folder, a link. Anything else is refused unless ``force``; then it is
    moved aside to ``<stem>.replaced-<UTC time><suffix>`` (never deleted), whose path is returned.
    """
    path = Path(path).expanduser()
    resolved = path.resolve()
    for inp in inputs:
        if inp is not None and _overlaps(Path(inp).expanduser().resolve(), resolved):
            raise OutputPolicyError(path, f"{what} is (inside) the input {inp} of this command; choose another {what}")
    if not os.path.lexists(path):
        return None
    if path.is_symlink() or not path.is_file():
        raise OutputPolicyError(path, f"{what} exists and is not a regular file; refusing to replace it")
    if is_ours is not None and is_ours(path):
        return None
    if not force:
        raise OutputPolicyError(path, f"{what} exists and was not written by atlas-gs; refusing to overwrite it. "
                                      "Choose another name, or pass --force to move it aside (it is never deleted)")
    backup = _move_aside(path, path.stem, path.suffix)
    logger.warning("%s was not written by atlas-gs; moved it aside to %s (--force)", path, backup)
    return backup


def check_writable(folder: str | Path, min_free_bytes: int = MIN_FREE_BYTES) -> None:
    """Fail now, naming ``folder``, if a file cannot be written there or the disk is nearly full.

    Called before expensive work so a read-only or full output folder is found in milliseconds,
    not after the work is done.
    """
    folder = Path(folder)
    existing = folder
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    try:
        folder.mkdir(parents=True, exist_ok=True)
        probe = folder / f".atlas-gs-probe.{os.getpid()}-{uuid.uuid4().hex[:8]}.tmp"
        try:
            with open(probe, "wb") as f:
                f.write(b"\0" * _PROBE_BYTES)
                f.flush()
                os.fsync(f.fileno())
        finally:
            probe.unlink(missing_ok=True)
        free = shutil.disk_usage(folder).free
    except OSError as exc:
        raise WriteError(folder if folder.exists() else existing, f"cannot write here: {exc.strerror or exc}", exc.errno) from exc
    if free < min_free_bytes:
        raise WriteError(folder, f"only {free / 2**20:.0f} MiB free, at least {min_free_bytes / 2**20:.0f} MiB "
                                 "needed for this output", errno.ENOSPC)


def env_folder(name: str, value: str) -> Path:
    """The folder the environment variable ``name`` (set to ``value``) names, absolute; made later
    when missing. A ConfigError naming the variable and the path when that path, or the first part
    of it that exists, is not a folder (a file: every folder made under it would fail naming a
    child path instead)."""
    path = Path(value).expanduser().resolve()
    existing = path
    while not os.path.lexists(existing) and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        what = "a file" if existing.is_file() else "not a folder"
        where = f"{existing} is {what}" if existing == path else f"{existing}, a part of that path, is {what}"
        raise ConfigError(f"{name}={value}: {where}; point {name} at a folder (it is made when missing)")
    return path


# ---- process locks -----------------------------------------------------------------------------


class LockedError(AtlasError):
    """Another live process holds the lock."""


class ProcessLock:
    """An exclusive, non-blocking lock on a file, held until :meth:`release` or the process exits.

    ``fcntl.flock`` locks die with their process, so a killed holder never leaves a stale lock.
    Re-entrant within one process (one run's steps share it). The file holds the holder's
    description (JSON) for the error message of whoever finds it taken.
    """

    _held: dict[str, int] = {}

    def __init__(self, path: str | Path):
        self.path = Path(path)

    def holder(self) -> dict[str, Any]:
        try:
            data = json.loads(self.path.read_text(encoding="utf-8") or "{}")
            return data if isinstance(data, dict) else {}
        except (OSError, ValueError):
            return {}

    def acquire(self, info: dict[str, Any]) -> bool:
        """Take the lock (True), or find it already ours (False); raise LockedError if taken."""
        key = str(self.path.resolve())
        if key in self._held:
            return False
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            raise _write_error(self.path, exc) from exc
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            h = self.holder()
            raise LockedError(f"{self.path}: held by {h.get('what', 'another process')} (pid {h.get('pid', '?')} on "
                              f"{h.get('host', '?')}, since {h.get('since', '?')})") from None
        record = {"pid": os.getpid(), "host": socket.gethostname(),
                  "since": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"), **info}
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps(record).encode(), 0)
        self._held[key] = fd
        return True

    def release(self) -> None:
        fd = self._held.pop(str(self.path.resolve()), None)
        if fd is not None:
            with contextlib.suppress(OSError):
                os.ftruncate(fd, 0)
            os.close(fd)  # closing the descriptor releases the flock


# ---- files -------------------------------------------------------------------------------------


def write_bytes_atomic(path: str | Path, data: bytes) -> Path:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def write_text_atomic(path: str | Path, text: str) -> Path:
    return write_bytes_atomic(path, text.encode("utf-8"))


def write_json_atomic(path: str | Path, obj: Any) -> Path:
    return write_text_atomic(path, json.dumps(obj, indent=2, sort_keys=False, allow_nan=False) + "\n")


def sha256_file(path: str | Path, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while True:
            b = f.read(chunk)
            if not b:
                break
            h.update(b)
    return h.hexdigest()


def sha256_files(paths: list[Path], names: list[str] | None = None) -> str:
    """One hash over several files' names and contents, in the given order."""
    h = hashlib.sha256()
    for i, p in enumerate(paths):
        h.update((names[i] if names else p.name).encode())
        h.update(b"\0")
        with open(p, "rb") as f:
            while True:
                b = f.read(1 << 20)
                if not b:
                    break
                h.update(b)
        h.update(b"\0")
    return h.hexdigest()
