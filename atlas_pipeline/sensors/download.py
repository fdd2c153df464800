"""Download and unpack a TUM RGB-D archive (``.tgz``) safely and atomically."""

from __future__ import annotations

import hashlib
import http.client
import logging
import os
import tarfile
import tempfile
import urllib.parse
import urllib.request
import zlib
from pathlib import Path, PurePosixPath
from typing import Callable

from atlas_pipeline.errors import DatasetError
from atlas_pipeline.progress import Progress
from atlas_pipeline.sensors.tum import check_tum_layout

logger = logging.getLogger(__name__)

__all__ = ["download_file", "download_tum_archive"]

# Limits of a TUM archive: ~2-10k PNGs of < 1 MB each, 0.5-3 GB in all. Well past any real one,
# well short of filling a disk.
MAX_ARCHIVE_MEMBERS = 200_000
MAX_MEMBER_BYTES = 1 << 30
MAX_UNPACKED_BYTES = 64 << 30
MAX_NAME_BYTES = 255  # NAME_MAX of Linux file systems
_COPY_CHUNK_BYTES = 1 << 20
BYTES_PER_MB = 1e6
DOWNLOAD_LOG_EVERY_S = 5.0  # the run log gets a line every 5 s of a download (a terminal gets a bar)


def download_file(url: str, dest: Path, sha256: str | None = None, timeout_s: float = 60.0,
                  log: Callable[[str], None] | None = None) -> Path:
    """Stream ``url`` to ``dest`` (via a temporary file), checking ``sha256`` when given."""
    dest.parent.mkdir(parents=True, exist_ok=True)
    h = hashlib.sha256()
    tmp = dest.with_name(dest.name + ".part")
    try:
        with urllib.request.urlopen(url, timeout=timeout_s) as resp, open(tmp, "wb") as out:
            total = int(resp.headers.get("Content-Length") or 0)
            done = 0
            # named by the URL's file, never by the temporary file it goes to
            name = PurePosixPath(urllib.parse.urlsplit(url).path).name or url
            with Progress(f"downloading {name}", total / BYTES_PER_MB if total else None, log,
                          every_s=DOWNLOAD_LOG_EVERY_S, unit="MB") as progress:
                while True:
                    chunk = resp.read(_COPY_CHUNK_BYTES)
                    if not chunk:
                        break
                    out.write(chunk)
                    h.update(chunk)
                    done += len(chunk)
                    progress.update(len(chunk) / BYTES_PER_MB)
        if total and done != total:
            raise DatasetError(dest, f"download of {url} truncated: {done} of {total} bytes")
        if sha256 and h.hexdigest() != sha256.lower():
            raise DatasetError(dest, f"checksum mismatch for {url}: got {h.hexdigest()}, expected {sha256}")
        tmp.replace(dest)
        return dest
    except (OSError, http.client.HTTPException) as exc:  # IncompleteRead is an HTTPException
        raise DatasetError(dest, f"cannot download {url}: {exc!r}") from exc
    finally:
        if tmp.exists():
            tmp.unlink()


def _unpack_error(archive: Path, url: str, member: str | None, why: str) -> DatasetError:
    where = f" member {member[:200]!r}" if member is not None else ""
    return DatasetError(archive, f"cannot unpack archive from {url}:{where} {why}")


def _member_path(archive: Path, url: str, member: tarfile.TarInfo) -> PurePosixPath | None:
    """The member's name as a relative path inside the destination, or None for the archive's
    root entry (``./``). Refuses absolute names, ``..``, NUL bytes, backslashes (Windows paths)
    and components too long for a file name."""
    name = member.name
    if not name or "\x00" in name or "\\" in name:
        raise _unpack_error(archive, url, name, "has an invalid name")
    p = PurePosixPath(name)
    if p.is_absolute():
        raise _unpack_error(archive, url, name, "has an absolute path")
    if ".." in p.parts:
        raise _unpack_error(archive, url, name, "has a '..' component (would leave the destination folder)")
    parts = [q for q in p.parts if q != "."]
    if any(len(os.fsencode(q)) > MAX_NAME_BYTES for q in parts):
        raise _unpack_error(archive, url, name, f"has a path component longer than {MAX_NAME_BYTES} bytes")
    return PurePosixPath(*parts) if parts else None


def _checked_members(archive: Path, url: str, tar: tarfile.TarFile) -> list[tuple[tarfile.TarInfo, PurePosixPath]]:
    """Every member with its relative path, after refusing anything but regular files and
    folders (links, devices, fifos, sparse files), duplicate names, a file that is also a folder,
    and sizes past ``MAX_MEMBER_BYTES`` / ``MAX_UNPACKED_BYTES``. Nothing is written here."""
    checked: list[tuple[tarfile.TarInfo, PurePosixPath]] = []
    seen: dict[PurePosixPath, bool] = {}  # path -> is a folder
    total = 0
    for member in tar:
        if len(checked) >= MAX_ARCHIVE_MEMBERS:
            raise _unpack_error(archive, url, None, f"more than {MAX_ARCHIVE_MEMBERS} members")
        rel = _member_path(archive, url, member)
        if member.issym() or member.islnk():
            raise _unpack_error(archive, url, member.name, f"is a link (to {member.linkname[:200]!r}); "
                                "TUM archives hold only files and folders")
        if member.issparse() or not (member.isreg() or member.isdir()):
            raise _unpack_error(archive, url, member.name, "is not a regular file or folder "
                                "(device, fifo or sparse file)")
        if rel is None:
            if member.isdir():
                continue  # "./": the destination itself
            raise _unpack_error(archive, url, member.name, "is a file without a name")
        if member.isreg():
            if member.size < 0 or member.size > MAX_MEMBER_BYTES:
                raise _unpack_error(archive, url, member.name, f"is {member.size} bytes (at most {MAX_MEMBER_BYTES})")
            total += member.size
            if total > MAX_UNPACKED_BYTES:
                raise _unpack_error(archive, url, member.name, f"unpacks past {MAX_UNPACKED_BYTES} bytes in all")
        if rel in seen and not (seen[rel] and member.isdir()):  # a folder may be listed twice
            raise _unpack_error(archive, url, member.name, "appears twice in the archive")
        seen[rel] = member.isdir()
        checked.append((member, rel))
    # A member below a name that is a file (in either order) would fail half-way through unpacking.
    files = {rel for rel, is_dir in seen.items() if not is_dir}
    for member, rel in checked:
        clash = next((q for q in rel.parents if q in files), None)
        if clash is not None:
            raise _unpack_error(archive, url, member.name, f"lies inside {str(clash)!r}, which is a file")
    return checked


def _extract_checked(archive: Path, url: str, tar: tarfile.TarFile, out: Path) -> None:
    """Write the checked members under ``out`` ourselves: folders 0o755, files 0o644 (no modes,
    owners or links from the archive), each file created new (``O_EXCL | O_NOFOLLOW``) inside ``out``."""
    root = out.resolve()
    for member, rel in _checked_members(archive, url, tar):
        target = out.joinpath(*rel.parts)
        if member.isdir():
            target.mkdir(mode=0o755, parents=True, exist_ok=True)
            continue
        target.parent.mkdir(mode=0o755, parents=True, exist_ok=True)
        if not target.parent.resolve().is_relative_to(root):  # cannot happen without links; checked anyway
            raise _unpack_error(archive, url, member.name, "would be written outside the destination folder")
        src = tar.extractfile(member)
        if src is None:
            raise _unpack_error(archive, url, member.name, "has no data")
        fd = os.open(target, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o644)
        written = 0
        with src, os.fdopen(fd, "wb") as dst:
            while chunk := src.read(_COPY_CHUNK_BYTES):
                dst.write(chunk)
                written += len(chunk)
                if written > member.size:
                    break
        if written != member.size:
            raise _unpack_error(archive, url, member.name, f"holds {written} bytes, its header says {member.size}")


def _refuse_existing(dest_dir: Path) -> None:
    """Never replace or merge into existing data: only a missing or empty folder is a destination."""
    if dest_dir.is_symlink() or (dest_dir.exists() and (not dest_dir.is_dir() or any(dest_dir.iterdir()))):
        raise DatasetError(dest_dir, "already exists and is not an empty folder; will not overwrite it "
                                     "(move it away, or point the dataset at another path)")


def download_tum_archive(url: str, dest_dir: Path, sha256: str | None = None,
                         log: Callable[[str], None] | None = None) -> Path:
    """Download a TUM ``.tgz`` and unpack its sequence folder into ``dest_dir``.

    ``dest_dir`` must not exist or be an empty folder: existing data is never deleted. Every
    member is checked before anything is written (only regular files and folders, relative names
    without ``..``, bounded sizes; see :func:`_checked_members`), then files are written by this
    code, not by ``tarfile.extractall``, into a temporary folder beside ``dest_dir``; the result is
    checked for the TUM layout and renamed into place.
    """
    dest_dir = Path(dest_dir)
    _refuse_existing(dest_dir)  # before spending a download on it
    dest_dir.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix=f".{dest_dir.name}.", dir=dest_dir.parent) as tmp:
        archive = download_file(url, Path(tmp) / "archive.tgz", sha256=sha256, log=log)
        out = Path(tmp) / "unpacked"
        out.mkdir()
        try:
            with tarfile.open(archive, "r:*") as tar:
                _extract_checked(archive, url, tar, out)
        except DatasetError:
            raise
        except (tarfile.TarError, OSError, EOFError, zlib.error, ValueError, UnicodeError) as exc:
            raise DatasetError(archive, f"cannot unpack archive from {url}: {exc}") from exc
        # TUM archives hold one top folder (rgbd_dataset_freiburg1_xyz/); accept a flat one too.
        tops = list(out.iterdir())
        if not tops:
            raise DatasetError(archive, f"archive from {url} is empty")
        seq = tops[0] if len(tops) == 1 and tops[0].is_dir() else out
        check_tum_layout(seq)
        _refuse_existing(dest_dir)  # something may have appeared during the download
        try:
            seq.rename(dest_dir)  # onto a missing or empty folder only
        except OSError as exc:
            raise DatasetError(dest_dir, f"cannot move the unpacked archive into place: {exc}") from exc
    (log or logger.info)(f"unpacked {url} into {dest_dir}")
    return dest_dir
