"""Download and unpack a TUM RGB-D archive (``.tgz``) safely and atomically."""

from __future__ import annotations

import hashlib
import http.client
import logging
import shutil
import tarfile
import tempfile
import urllib.request
from pathlib import Path
from typing import Callable

from atlas_pipeline.errors import DatasetError
from atlas_pipeline.sensors.tum import check_tum_layout

logger = logging.getLogger(__name__)

__all__ = ["download_file", "download_tum_archive"]


def download_file(url: str, dest: Path, sha256: str | None = None, timeout_s: float = 60.0,
                  log: Callable[[str], None] | None = None) -> Path:
    """Stream ``url`` to ``dest`` (via a temporary file), checking ``sha256`` when given."""
    log = log or logger.info
    dest.parent.mkdir(parents=True, exist_ok=True)
    h = hashlib.sha256()
    tmp = dest.with_name(dest.name + ".part")
    try:
        with urllib.request.urlopen(url, timeout=timeout_s) as resp, open(tmp, "wb") as out:
            total = int(resp.headers.get("Content-Length") or 0)
            done, next_report = 0, 0
            while True:
                chunk = resp.read(1 << 20)
                if not chunk:
                    break
                out.write(chunk)
                h.update(chunk)
                done += len(chunk)
                if done >= next_report:
                    of = f" of {total / 1e6:.1f}" if total else ""
                    log(f"downloaded {done / 1e6:.1f}{of} MB from {url}")
                    next_report = done + (50 << 20)
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


def download_tum_archive(url: str, dest_dir: Path, sha256: str | None = None,
                         log: Callable[[str], None] | None = None) -> Path:
    """Download a TUM ``.tgz`` and unpack its sequence folder into ``dest_dir``.

    The archive is unpacked with tarfile's ``data`` filter (no absolute paths, no ``..``, no links
    out of the folder) into a temporary folder, checked for the TUM layout, then renamed into place.
    """
    dest_dir = Path(dest_dir)
    dest_dir.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix=f".{dest_dir.name}.", dir=dest_dir.parent) as tmp:
        archive = download_file(url, Path(tmp) / "archive.tgz", sha256=sha256, log=log)
        out = Path(tmp) / "unpacked"
        out.mkdir()
        try:
            with tarfile.open(archive, "r:*") as tar:
                tar.extractall(out, filter="data")
        except (tarfile.TarError, OSError) as exc:
            raise DatasetError(archive, f"cannot unpack archive from {url}: {exc}") from exc
        # TUM archives hold one top folder (rgbd_dataset_freiburg1_xyz/); accept a flat one too.
        tops = list(out.iterdir())
        if not tops:
            raise DatasetError(archive, f"archive from {url} is empty")
        seq = tops[0] if len(tops) == 1 and tops[0].is_dir() else out
        check_tum_layout(seq)
        if dest_dir.exists():
            shutil.rmtree(dest_dir)
        seq.rename(dest_dir)
    (log or logger.info)(f"unpacked {url} into {dest_dir}")
    return dest_dir
