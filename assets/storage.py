"""Artifacts on object storage (``s3://``, ``gs://``, any fsspec URL), with the local folder's promises.

An object store has no rename, so the local directory swap (:func:`atlas_pipeline.io_utils.commit_dir`)
cannot be used. Instead every version of an artifact is immutable and content-addressed, and one
small object names the current one::

    <root>/<asset>/<partition>/_current.json              the pointer (the only object ever overwritten)
    <root>/<asset>/<partition>/v-<content hash, 24 hex>/  one complete version:
        _artifact.json                                    its record (type, files, sha256 of each)
        <the artifact's files>                            Parquet, npz, JSON, PLY, MP4 ... as on disk

Writing (:meth:`ObjectStore.publish`): the artifact is written and hashed in a local staging folder
(the library's ``save`` writes files), then uploaded under a fresh ``v-<hash>/`` prefix, record
first, then publish by a single PUT of ``_current.json`` holding the record (a PUT of one object is
atomic: readers see the old pointer or the new one, never half). A crash before that PUT leaves the
old version current and an unreferenced prefix. Reading (:meth:`ObjectStore.fetch`) goes through the
pointer only, and every file's sha256 is checked against it (into a local, content-addressed cache);
a missing or changed object is an error naming it, never a silently wrong artifact.

Garbage: after a publish, ``v-*`` prefixes other than the current and previous version are deleted,
and only when they are ours: their ``_artifact.json`` names this asset and partition and they hold
nothing but the files it lists. Keeping the previous version means a reader that read the old
pointer just before the swap still finds its files. Anything else under the partition's prefix is
refused before work starts (:meth:`ObjectStore.check_prefix`), as the local output policy refuses
a folder holding files atlas-gs did not write.

Credentials and endpoints come from the environment as the storage library reads them (for S3:
``AWS_ACCESS_KEY_ID``, ``AWS_SECRET_ACCESS_KEY``, ``AWS_ENDPOINT_URL`` for an S3-compatible server),
plus ``$ATLAS_STORAGE_OPTIONS`` (a JSON object of fsspec options) for anything else; every worker
reads its own environment, so nothing secret travels in run config.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import re
import shutil
import tempfile
from functools import lru_cache
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

from atlas_pipeline.errors import ArtifactError, ConfigError, OutputPolicyError, WriteError
from atlas_pipeline.io_utils import atomic_dir, sha256_file

logger = logging.getLogger("atlas_gs.storage")

POINTER_NAME = "_current.json"
RECORD_NAME = "_artifact.json"
POINTER_FORMAT = "atlas-gs-artifact-pointer"
POINTER_FORMAT_VERSION = 1
VERSION_PREFIX = "v-"
VERSION_HASH_CHARS = 24  # as the data version: 96 bits of the content hash name a version
_VERSION_RE = re.compile(rf"^{VERSION_PREFIX}[0-9a-f]{{{VERSION_HASH_CHARS}}}$")
_FILE_NAME_RE = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.\-]*$")  # a record's file names: plain, no folders
MAX_POINTER_BYTES = 4 * 1024 * 1024  # a pointer holds one record; larger is not one of ours
CACHE_KIND = "artifact_cache"  # output-policy kind of a fetched version in the local cache
STORAGE_OPTIONS_ENV = "ATLAS_STORAGE_OPTIONS"
SCRATCH_ENV = "ATLAS_SCRATCH_DIR"


def is_remote(root: str | os.PathLike) -> bool:
    """Whether ``root`` is an object-store URL (``s3://``, ``gs://`` ...), not a local or mounted path.
    (One-letter schemes are Windows drive letters; ``file://`` is a local path.)"""
    scheme = urlsplit(str(root)).scheme
    return len(scheme) > 1 and scheme != "file"


def local_scratch() -> Path:
    """This machine's folder for staging uploads, the download cache and partition locks of remote
    roots: ``$ATLAS_SCRATCH_DIR``, else ``<tmp>/atlas-gs-<uid>``."""
    env = os.environ.get(SCRATCH_ENV)
    return Path(env) if env else Path(tempfile.gettempdir()) / f"atlas-gs-{os.getuid()}"


def root_key(root: str) -> str:
    """A short stable name of a remote root, for its local cache and lock folders."""
    return hashlib.sha256(str(root).rstrip("/").encode()).hexdigest()[:16]


def storage_options() -> dict[str, Any]:
    text = os.environ.get(STORAGE_OPTIONS_ENV, "").strip()
    if not text:
        return {}
    try:
        opts = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ConfigError(f"${STORAGE_OPTIONS_ENV}: invalid JSON at column {exc.colno}: {exc.msg}") from None
    if not isinstance(opts, dict):
        raise ConfigError(f"${STORAGE_OPTIONS_ENV}: expected a JSON object of fsspec options")
    return opts


@lru_cache(maxsize=8)
def object_store(root: str) -> "ObjectStore":
    return ObjectStore(root, storage_options())


def _version_name(content_hash: str) -> str:
    return VERSION_PREFIX + content_hash[:VERSION_HASH_CHARS]


class ObjectStore:
    """The artifacts under one object-store root (see the module docstring for the layout)."""

    def __init__(self, root: str, options: dict[str, Any] | None = None):
        try:
            from upath import UPath
        except ImportError as exc:  # pragma: no cover - universal-pathlib comes with dagster
            raise ConfigError(f"artifacts root {root}: needs universal-pathlib (pip install 'atlas-gs[distributed]')") from exc
        try:
            self.root = UPath(str(root).rstrip("/"), **(options or {}))
            self.fs = self.root.fs
        except (ImportError, ValueError) as exc:
            raise ConfigError(f"artifacts root {root}: no file system for it ({exc}); for s3:// install "
                              "'atlas-gs[distributed]' (s3fs)") from exc
        self.url = str(self.root)
        self.cache = local_scratch() / "cache" / root_key(self.url)

    # -- names -------------------------------------------------------------------------------------

    def prefix(self, asset: str, partition: str):
        return self.root / asset / partition

    def _key(self, p) -> str:
        """The file system's own name of a UPath (``bucket/key`` for S3)."""
        return p.path

    # -- reading ------------------------------------------------------------------------------------

    def read_pointer(self, asset: str, partition: str) -> dict[str, Any] | None:
        """The partition's pointer (None when there is none yet); an object that is not one of our
        pointers is an error naming it."""
        where = self.prefix(asset, partition) / POINTER_NAME
        try:
            info = self.fs.info(self._key(where))
        except FileNotFoundError:
            return None
        if info.get("size", 0) > MAX_POINTER_BYTES:
            raise ArtifactError(f"{where}: {info['size']} bytes, not an atlas-gs pointer (at most {MAX_POINTER_BYTES})")
        try:
            data = json.loads(self.fs.cat_file(self._key(where)))
        except FileNotFoundError:
            return None
        except (ValueError, UnicodeDecodeError) as exc:
            raise ArtifactError(f"{where}: not valid JSON ({exc})") from None
        if not isinstance(data, dict) or data.get("format") != POINTER_FORMAT:
            raise ArtifactError(f"{where}: not an atlas-gs artifact pointer (format {POINTER_FORMAT!r} expected)")
        rec, cur = data.get("record"), data.get("current")
        if not isinstance(rec, dict) or not isinstance(rec.get("files"), dict) or not isinstance(cur, str) \
                or not _VERSION_RE.match(cur) or _version_name(str(rec.get("content_hash", ""))) != cur:
            raise ArtifactError(f"{where}: field 'current' or 'record' missing or inconsistent")
        for name in rec["files"]:
            if not _FILE_NAME_RE.match(str(name)) or name in (RECORD_NAME, POINTER_NAME):
                raise ArtifactError(f"{where}: field 'record.files' names {name!r}, not a plain file name")
        return data

    def record(self, asset: str, partition: str) -> dict[str, Any]:
        ptr = self.read_pointer(asset, partition)
        if ptr is None:
            raise ArtifactError(f"{self.prefix(asset, partition)}: no {POINTER_NAME}; materialize the asset first")
        return ptr["record"]

    def intact(self, asset: str, partition: str) -> bool:
        """Whether the current version's objects are all there with the sizes the pointer lists (the
        sha256 of each is checked when it is read)."""
        try:
            ptr = self.read_pointer(asset, partition)
        except ArtifactError:
            return False
        if ptr is None:
            return False
        vdir = self.prefix(asset, partition) / ptr["current"]
        self.fs.invalidate_cache(self._key(vdir))
        try:
            found = self.fs.find(self._key(vdir), detail=True)
        except FileNotFoundError:
            return False
        sizes = {k.rsplit("/", 1)[-1]: v.get("size") for k, v in found.items()}
        return all(sizes.get(n) == f.get("bytes") for n, f in ptr["record"]["files"].items())

    def fetch(self, asset: str, partition: str) -> tuple[Path, dict[str, Any]]:
        """A local copy of the current version (folder, record): downloaded into the local cache,
        every file's sha256 checked against the pointer; a verified cached copy is used as is."""
        ptr = self.read_pointer(asset, partition)
        if ptr is None:
            raise ArtifactError(f"{self.prefix(asset, partition)}: no {POINTER_NAME}; materialize the asset first")
        rec, version = ptr["record"], ptr["current"]
        local = self.cache / asset / partition / version
        if not (local.is_dir() and self._verified(local, rec, raise_on_error=False)):
            vdir = self.prefix(asset, partition) / version
            local.parent.mkdir(parents=True, exist_ok=True)
            with atomic_dir(local, kind=CACHE_KIND) as tmp:
                for name in rec["files"]:
                    try:
                        self.fs.get_file(self._key(vdir / name), str(tmp / name))
                    except FileNotFoundError:
                        raise ArtifactError(f"{vdir / name}: missing (listed by {self.prefix(asset, partition) / POINTER_NAME})") from None
                (tmp / RECORD_NAME).write_text(json.dumps(rec, indent=2) + "\n")
                self._verified(tmp, rec, remote=vdir)
        self._evict(asset, partition, keep=version)
        return local, rec

    @staticmethod
    def _verified(folder: Path, rec: dict[str, Any], raise_on_error: bool = True, remote=None) -> bool:
        for name, f in rec["files"].items():
            p = folder / name
            ok = p.is_file() and p.stat().st_size == f.get("bytes") and sha256_file(p) == f.get("sha256")
            if not ok:
                if raise_on_error:
                    raise ArtifactError(f"{(remote / name) if remote is not None else p}: content differs from "
                                        f"its record (sha256 {f.get('sha256', '?')[:16]}...); not used")
                return False
        return True

    def _evict(self, asset: str, partition: str, keep: str) -> None:
        """Drop other cached versions of this partition (the cache folder is ours alone)."""
        base = self.cache / asset / partition
        for p in base.iterdir() if base.is_dir() else ():
            if p.name != keep and _VERSION_RE.match(p.name) and p.is_dir():
                shutil.rmtree(p, ignore_errors=True)

    # -- writing ------------------------------------------------------------------------------------

    def check_prefix(self, asset: str, partition: str) -> None:
        """Before computing: refuse a partition prefix holding objects atlas-gs did not write (the
        object-store form of the output policy), and fail now when the root cannot be written."""
        base = self.prefix(asset, partition)
        self.fs.invalidate_cache(self._key(base))
        try:
            entries = self.fs.ls(self._key(base), detail=False)
        except FileNotFoundError:
            entries = []
        foreign = [e.rsplit("/", 1)[-1] for e in entries
                   if e.rsplit("/", 1)[-1] != POINTER_NAME and not _VERSION_RE.match(e.rsplit("/", 1)[-1])]
        if foreign:
            raise OutputPolicyError(self._key(base), f"(bucket/key) holds {len(foreign)} object(s) atlas-gs did not write "
                                          f"({', '.join(sorted(foreign)[:3])}); refusing to write the {asset} artifact there")
        self.read_pointer(asset, partition)  # a foreign _current.json is an error naming it
        probe = self.root / f".atlas-gs-probe-{os.getpid()}-{os.urandom(4).hex()}"
        try:
            self.fs.pipe_file(self._key(probe), b"probe")
            self.fs.rm_file(self._key(probe))
        except OSError as exc:
            raise WriteError(self._key(self.root), f"(bucket/key of {self.url}) cannot write here: {exc}", getattr(exc, "errno", None)) from exc

    def publish(self, staging: Path, record: dict[str, Any]) -> bool:
        """Upload the staged folder as a new version and make it current (True), or find the same
        content current and intact already (False: nothing written)."""
        asset, partition = record["asset"], record["partition"]
        base, version = self.prefix(asset, partition), _version_name(record["content_hash"])
        old = self.read_pointer(asset, partition)
        if old is not None and old["current"] == version and self.intact(asset, partition):
            return False
        vdir = base / version
        try:
            # The record first: it declares which objects belong to the version (what garbage
            # collection may delete), even if the upload stops half-way.
            self.fs.put_file(str(staging / RECORD_NAME), self._key(vdir / RECORD_NAME))
            for name in record["files"]:
                self.fs.put_file(str(staging / name), self._key(vdir / name))
            previous = (old["current"] if old["current"] != version else old.get("previous")) if old else None
            pointer = {"format": POINTER_FORMAT, "format_version": POINTER_FORMAT_VERSION, "current": version,
                       "previous": previous, "record": record}
            # The publication: one PUT of one small object, atomic for every reader.
            self.fs.pipe_file(self._key(base / POINTER_NAME), (json.dumps(pointer, indent=1) + "\n").encode())
        except OSError as exc:
            raise WriteError(self._key(vdir), f"(bucket/key) cannot upload the {asset} artifact: {exc}", getattr(exc, "errno", None)) from exc
        self.collect_garbage(asset, partition, keep={version, previous})
        return True

    def collect_garbage(self, asset: str, partition: str, keep: set[str | None]) -> list[str]:
        """Delete this partition's versions not in ``keep`` that are ours (record names this asset
        and partition; nothing but its files); returns the deleted version names."""
        base = self.prefix(asset, partition)
        self.fs.invalidate_cache(self._key(base))
        try:
            entries = self.fs.ls(self._key(base), detail=False)
        except FileNotFoundError:
            return []
        deleted = []
        for e in entries:
            name = e.rsplit("/", 1)[-1]
            if not _VERSION_RE.match(name) or name in keep:
                continue
            vdir = base / name
            try:
                objects = {k.rsplit("/", 1)[-1] for k in self.fs.find(self._key(vdir))}
                rec = json.loads(self.fs.cat_file(self._key(vdir / RECORD_NAME)))
            except (FileNotFoundError, ValueError, UnicodeDecodeError):
                logger.warning("%s: no readable %s; not ours to delete, left alone", vdir, RECORD_NAME)
                continue
            listed = set(rec.get("files", {})) | {RECORD_NAME} if isinstance(rec, dict) else set()
            if not isinstance(rec, dict) or rec.get("asset") != asset or rec.get("partition") != partition \
                    or not objects <= listed:
                logger.warning("%s: holds objects atlas-gs did not list; left alone", vdir)
                continue
            self.fs.rm(self._key(vdir), recursive=True)
            deleted.append(name)
        return deleted
