"""Identities of files on disk: a dataset folder's signature, and whether an artifact's files are intact.

The orchestration that uses them (data versions, reuse) is in ``assets/versioning.py``; the library
never imports Dagster.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path
from typing import Any, Mapping

from atlas_pipeline.io_utils import sha256_file

__all__ = ["dataset_signature", "files_intact"]


def dataset_signature(root: Path) -> str:
    """Cheap identity of a recording on disk (a folder, or a file such as a ``.bag``): relative name,
    size and modification time of every file, none read. Editing, adding or removing a file gives a
    new signature; ``missing`` when there is nothing."""
    root = Path(root)
    if root.is_file():
        walk = [(str(root.parent), [], [root.name])]
    elif root.is_dir():
        walk = os.walk(root)
    else:
        return "missing"
    h = hashlib.sha256()
    for dirpath, dirnames, filenames in walk:
        dirnames[:] = sorted(d for d in dirnames if not d.startswith("."))
        for name in sorted(n for n in filenames if not n.startswith(".")):
            p = Path(dirpath) / name
            st = p.stat()
            h.update(f"{p.relative_to(root.parent if root.is_file() else root).as_posix()}:{st.st_size}:{st.st_mtime_ns};".encode())
    return h.hexdigest()[:32]


def files_intact(directory: Path, files: Mapping[str, Mapping[str, Any]]) -> bool:
    """True when every recorded file (``{name: {bytes, mtime_ns, sha256}}``) exists with its bytes:
    size and modification time as recorded count as unchanged (no read), otherwise the sha256 decides."""
    for name, rec in files.items():
        p = Path(directory) / name
        try:
            st = p.stat()
        except FileNotFoundError:
            return False
        if st.st_size != rec.get("bytes"):
            return False
        if rec.get("mtime_ns") != st.st_mtime_ns and sha256_file(p) != rec.get("sha256"):
            return False
    return True
