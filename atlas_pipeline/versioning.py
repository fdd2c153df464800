"""Identities of files on disk: a dataset folder's signature, and whether an artifact's files are intact.

The orchestration that uses them (data versions, reuse) is in ``assets/versioning.py``; the library
never imports Dagster.
"""

from __future__ import annotations

import hashlib
import json
import os
import stat
from pathlib import Path
from typing import Any, Mapping

from atlas_pipeline.errors import WriteError
from atlas_pipeline.io_utils import sha256_file, write_json_atomic

__all__ = ["dataset_signature", "signature_cache_path", "file_identity", "verify_files", "files_intact"]


# A file's identity as the filesystem keeps it: size, modification time, inode and change time. The
# change time cannot be set back by cp -p, rsync -t or tar x (every write or rename-into-place moves
# it), so a file whose identity is unchanged holds the bytes hashed before.
SIGNATURE_CACHE_VERSION = 1
_SIGNATURE_CACHE_MAX_BYTES = 64 << 20  # the cache of a million-file dataset is ~150 MB; beyond, hash anew


def _identity(st: os.stat_result) -> list[int]:
    return [st.st_size, st.st_mtime_ns, st.st_ino, st.st_ctime_ns]


def _read_cache(path: Path | None, root: Path) -> dict[str, list]:
    if path is None:
        return {}
    try:
        if path.stat().st_size > _SIGNATURE_CACHE_MAX_BYTES:
            return {}
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}  # no cache, or a damaged one: hash again (it only ever saves reads)
    if not isinstance(data, dict) or data.get("version") != SIGNATURE_CACHE_VERSION or data.get("root") != str(root):
        return {}
    files = data.get("files")
    return files if isinstance(files, dict) else {}


def signature_cache_path(cache_dir: Path, root: Path) -> Path:
    """Where :func:`dataset_signature` keeps the content hashes of the recording at ``root``."""
    key = hashlib.sha256(str(Path(root).resolve()).encode()).hexdigest()[:24]
    return Path(cache_dir) / f"{key}.json"


def dataset_signature(root: Path, cache_dir: Path | None = None) -> str:
    """Identity of a recording on disk (a folder, or a file such as a ``.bag``): relative name, size
    and sha256 of every file. Editing, adding or removing a file gives a new signature, also when its
    size and modification time are restored (``cp -p``, ``rsync -t``, ``tar x``); touching one does not.
    ``missing`` when there is nothing.

    Cost: each file's content hash is cached in ``cache_dir`` (never in the recording) by its size,
    modification time, inode and change time, so only files whose identity changed are read again;
    without ``cache_dir`` every file is read. Entries that are not regular files (FIFOs, sockets)
    are never opened: their name and type count.
    """
    root = Path(root)
    if root.is_file():
        base, walk = root.parent, [(str(root.parent), [], [root.name])]
    elif root.is_dir():
        base, walk = root, os.walk(root)
    else:
        return "missing"
    resolved = root.resolve()
    cache_path = signature_cache_path(cache_dir, resolved) if cache_dir is not None else None
    cache, fresh = _read_cache(cache_path, resolved), {}
    h = hashlib.sha256()
    for dirpath, dirnames, filenames in walk:
        dirnames[:] = sorted(d for d in dirnames if not d.startswith("."))
        for name in sorted(n for n in filenames if not n.startswith(".")):
            p = Path(dirpath) / name
            rel = p.relative_to(base).as_posix()
            try:
                st = p.stat()
            except OSError:  # a dangling link: its name counts, the reader reports it
                h.update(f"{rel}:missing;".encode())
                continue
            if not stat.S_ISREG(st.st_mode):
                h.update(f"{rel}:{stat.S_IFMT(st.st_mode):o};".encode())
                continue
            ident = _identity(st)
            old = cache.get(rel)
            digest = old[4] if isinstance(old, list) and len(old) == 5 and old[:4] == ident else sha256_file(p)
            fresh[rel] = [*ident, digest]
            h.update(f"{rel}:{st.st_size}:{digest};".encode())
    if cache_path is not None and fresh != cache:
        try:
            cache_path.parent.mkdir(parents=True, exist_ok=True)
            write_json_atomic(cache_path, {"version": SIGNATURE_CACHE_VERSION, "root": str(resolved), "files": fresh})
        except (OSError, WriteError):
            pass  # a cache that cannot be written costs reads next time, never a wrong signature
    return h.hexdigest()[:32]


def file_identity(path: Path) -> dict[str, int]:
    """What :func:`files_intact` compares before reading a file: size, modification time, inode and
    change time (see :data:`SIGNATURE_CACHE_VERSION` for why the change time)."""
    st = Path(path).stat()
    return {"bytes": st.st_size, "mtime_ns": st.st_mtime_ns, "ino": st.st_ino, "ctime_ns": st.st_ctime_ns}


def verify_files(directory: Path, files: Mapping[str, Mapping[str, Any]]) -> tuple[bool, dict[str, dict[str, Any]]]:
    """Whether every recorded file (``{name: {bytes, sha256, mtime_ns, ino, ctime_ns}}``) exists with
    its bytes, and the records with each file's identity as found. A file whose identity is the
    recorded one is unchanged (no read); any other is read and its sha256 decides, so a byte
    changed with the modification time restored (``touch -d``, ``cp -p``) is found."""
    updated: dict[str, dict[str, Any]] = {}
    for name, rec in files.items():
        p = Path(directory) / name
        try:
            ident = file_identity(p)
        except OSError:
            return False, {}
        if ident["bytes"] != rec.get("bytes"):
            return False, {}
        if any(rec.get(k) != v for k, v in ident.items()) and sha256_file(p) != rec.get("sha256"):
            return False, {}
        updated[name] = {**rec, **ident}
    return True, updated


def files_intact(directory: Path, files: Mapping[str, Mapping[str, Any]]) -> bool:
    """True when every recorded file exists with its bytes (:func:`verify_files`)."""
    return verify_files(directory, files)[0]
