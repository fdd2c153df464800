"""Which recording each keyframe of a world comes from, and where its frames are found again.

A world is mapped from one recording (``atlas-gs build``) and may be extended with more
(``build --extend``). Each keyframe keeps its frame index *in its own recording* and which
recording that is. A recording is named by its content: the manifest's content hash (sha256 over
its list files and every image used); its name, folder, frame count and camera are hints where to
find it and how to read it. A folder under the same name whose frames hash differently is another
recording, never a source of a keyframe's image.

``metadata.json`` (and ``world.json`` / ``world.npz`` of a saved :class:`GaussianWorld`) hold::

    recordings: [{name, root, content_hash, n_frames, camera}, ...]
    keyframes:  {indices: [K], T_world_cam: [K x 4 x 4], recording: [K] (index into recordings)}

A bundle written before keyframes named their recording has neither ``recordings`` nor
``keyframes.recording``: every keyframe of a world built from scratch is then read as a frame of
the bundle's ``dataset``. One extended from another bundle (``lineage.parent``) holds its parent's
keyframes first: they are the parent's recording's only where that is proven (the parent bundle is
still on disk, verifies, is the world recorded as the parent, and its keyframes are the first of
this one's); otherwise no keyframe's recording is known and none is read (:data:`UNKNOWN_RECORDING`,
with the reason in :attr:`KeyframeSources.unknown_reason`).

The same recording read to another frame count (``dataset.max_frames`` takes its first frames)
hashes differently; :func:`record_of_frames` tells it apart from another recording by reading it
again at the recorded count.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from atlas_pipeline.errors import AtlasError, BundleFormatError

if TYPE_CHECKING:
    from atlas_pipeline.sensors.tum import FrameManifest

logger = logging.getLogger(__name__)

__all__ = ["RECORDING_KEYS", "UNKNOWN_RECORDING", "recording_record", "same_recording", "recording_index", "KeyframeSources",
           "bundle_keyframe_sources", "join_recordings", "world_keyframe_recordings", "keyframe_indices_of",
           "open_recording", "recording_label", "recording_tag", "is_unknown", "read_frames_at", "record_of_frames"]

RECORDING_KEYS = ("name", "root", "content_hash", "n_frames", "camera")
# The recording of keyframes whose source was never recorded (a world saved before keyframes named
# their recording, extended since): no content to prove any recording is it, so never read.
UNKNOWN_RECORDING: dict[str, Any] = {k: None for k in RECORDING_KEYS}
TAG_HASH_CHARS = 8  # of the content hash in a file-name tag: 4 billion values, names stay short
TAG_NAME_CHARS = 24
LABEL_HASH_CHARS = 12  # of the content hash in a log line
# A parent's keyframe poses and the extended bundle's copies of them are the same float64 numbers
# (both written from the saved world's arrays): equal to far below any pose error.
PARENT_POSE_TOLERANCE = 1e-9
# How deep a chain of older extended bundles is followed (each extension one level): far beyond any
# real lineage, and a chain that loops back ends.
MAX_PARENT_DEPTH = 64


def recording_record(manifest: FrameManifest) -> dict[str, Any]:
    """The JSON record naming ``manifest``'s recording (keys :data:`RECORDING_KEYS`)."""
    return {"name": manifest.dataset, "root": str(manifest.root), "content_hash": manifest.content_hash or None,
            "n_frames": int(manifest.n_frames), "camera": manifest.camera.to_dict()}


def same_recording(a: dict[str, Any] | None, b: dict[str, Any] | None) -> bool:
    """Whether the records ``a`` and ``b`` name one recording: equal, non-empty content hashes.
    Names and folders are never compared; a record without a hash is no proof of anything."""
    ha = (a or {}).get("content_hash")
    hb = (b or {}).get("content_hash")
    return bool(ha) and ha == hb


def is_unknown(record: dict[str, Any] | None) -> bool:
    """Whether ``record`` names no recording at all (no name, folder or content hash): keyframes
    whose recording was never recorded (:data:`UNKNOWN_RECORDING`), which no frames may stand for."""
    return not any((record or {}).get(k) for k in ("name", "root", "content_hash"))


def recording_index(recordings: list[dict[str, Any]], record: dict[str, Any]) -> int | None:
    """Where ``record``'s recording is in ``recordings``: the entry of the same content, else (a
    record without a content hash) the last entry equal to it in every key; None when absent."""
    for j, r in enumerate(recordings):
        if same_recording(r, record):
            return j
    if not record.get("content_hash"):
        equal = [j for j, r in enumerate(recordings) if all(r.get(k) == record.get(k) for k in RECORDING_KEYS)]
        return equal[-1] if equal else None
    return None


def recording_label(record: dict[str, Any]) -> str:
    """``'name' (content hash 1a2b3c4d5e6f, /its/folder)`` for log lines."""
    h = record.get("content_hash")
    parts = [f"content hash {h[:LABEL_HASH_CHARS]}" if h else "no content hash"]
    if record.get("root"):
        parts.append(str(record["root"]))
    return f"'{record.get('name') or 'unnamed'}' ({', '.join(parts)})"


def recording_tag(record: dict[str, Any], index: int) -> str:
    """A short file-name tag of the recording: its name (letters, digits, ``-``) and the first
    :data:`TAG_HASH_CHARS` of its content hash (``rec<index>`` without one), e.g. ``a-1b2c3d4e``."""
    name = re.sub(r"[^A-Za-z0-9-]+", "-", str(record.get("name") or "rec")).strip("-")[:TAG_NAME_CHARS] or "rec"
    h = record.get("content_hash")
    return f"{name}-{h[:TAG_HASH_CHARS]}" if h else f"{name}-rec{index}"


@dataclass
class KeyframeSources:
    """The keyframes of a world and where each comes from.

    Attributes:
        recordings: the recordings' records (keys :data:`RECORDING_KEYS`).
        indices: ``[K]`` int64 frame index of each keyframe in its own recording.
        recording: ``[K]`` int64 index of each keyframe's recording into ``recordings``.
        T_world_cam: ``[K, 4, 4]`` the poses the keyframes were merged at.
        unknown_reason: why the keyframes of an unknown recording (:func:`is_unknown`) have none
            ("" when every keyframe's recording is known, or no reason was recorded).
    """

    recordings: list[dict[str, Any]]
    indices: np.ndarray
    recording: np.ndarray
    T_world_cam: np.ndarray
    unknown_reason: str = ""

    def __len__(self) -> int:
        return len(self.indices)

    def of(self, record: dict[str, Any]) -> np.ndarray:
        """``[k]`` positions of the keyframes that come from ``record``'s recording (by content)."""
        ok = np.array([same_recording(r, record) for r in self.recordings], bool)
        return np.flatnonzero(ok[self.recording]) if len(self.recordings) else np.zeros(0, np.int64)


def _int_list(value: Any, field: str, where: Path) -> np.ndarray:
    if not isinstance(value, list) or not all(isinstance(v, int) and not isinstance(v, bool) and v >= 0
                                              for v in value):
        raise BundleFormatError(where, f"field {field} must be a list of integers >= 0")
    return np.asarray(value, np.int64).reshape(-1)


def _check_record(rec: Any, field: str, where: Path) -> dict[str, Any]:
    types = {"name": str, "root": str, "content_hash": str, "n_frames": int, "camera": dict}
    if not isinstance(rec, dict):
        raise BundleFormatError(where, f"field {field} must be an object with {', '.join(RECORDING_KEYS)}")
    for key, kind in types.items():
        v = rec.get(key)
        if v is not None and (not isinstance(v, kind) or isinstance(v, bool)):
            raise BundleFormatError(where, f"field {field}.{key} must be a {kind.__name__} or null")
    return {k: rec.get(k) for k in RECORDING_KEYS}


def bundle_keyframe_sources(metadata: dict[str, Any], where: str | Path = "metadata.json",
                            _parents: tuple[str, ...] = ()) -> KeyframeSources:
    """The keyframes of a bundle's ``metadata`` (validated; a malformed field is a
    :class:`BundleFormatError` naming it and ``where``). A world with no dataset (imported) has no
    recordings. Without ``recordings`` (an older bundle) every keyframe of a world built from
    scratch is a frame of the bundle's ``dataset``; of an extended world (``lineage.parent``), see
    :func:`_older_extended_sources`. ``_parents``: the bundles already followed up its lineage."""
    from atlas_pipeline.scene_memory.bundle import bundle_keyframe_poses

    where = Path(where)
    kf = metadata.get("keyframes") or {}
    if not isinstance(kf, dict):
        raise BundleFormatError(where, "field keyframes must be an object")
    T = bundle_keyframe_poses(metadata)
    idx = _int_list(kf.get("indices", []), "keyframes.indices", where)
    if len(idx) != len(T):
        raise BundleFormatError(where, f"field keyframes.indices lists {len(idx)} frames, keyframes.T_world_cam "
                                       f"{len(T)} poses")
    raw = metadata.get("recordings")
    if raw is None:  # an older bundle
        ds = metadata.get("dataset")
        recs = [_check_record(ds, "dataset", where)] if isinstance(ds, dict) else []
        lineage = metadata.get("lineage")
        parent = lineage.get("parent") if isinstance(lineage, dict) else None
        if recs and parent and len(idx):
            # the bundle itself (``where`` is its metadata.json) is the first a loop would return to
            own_dir = (str(where.parent.resolve()),) if where.name == "metadata.json" and not _parents else ()
            return _older_extended_sources(recs[0], parent, idx, T, where, _parents + own_dir)
        rec_idx = np.zeros(len(idx), np.int64) if recs else np.full(len(idx), -1, np.int64)
        if not recs and len(idx):
            recs, rec_idx = [dict(UNKNOWN_RECORDING)], np.zeros(len(idx), np.int64)
        return KeyframeSources(recs, idx, rec_idx, T)
    if not isinstance(raw, list):
        raise BundleFormatError(where, "field recordings must be a list of recordings")
    recs = [_check_record(r, f"recordings[{j}]", where) for j, r in enumerate(raw)]
    rec_idx = _int_list(kf.get("recording"), "keyframes.recording", where)
    if len(rec_idx) != len(idx):
        raise BundleFormatError(where, f"field keyframes.recording has {len(rec_idx)} entries for {len(idx)} keyframes")
    if len(rec_idx) and rec_idx.max() >= len(recs):
        raise BundleFormatError(where, f"field keyframes.recording names recording {int(rec_idx.max())}, but "
                                       f"recordings lists {len(recs)}")
    return KeyframeSources(recs, idx, rec_idx, T)


def _parent_sources(parent: Any, where: Path, parents: tuple[str, ...]) -> tuple[KeyframeSources | None, str]:
    """The keyframe sources of the bundle ``parent`` (a ``lineage.parent`` record) names, when it
    is provably the world that was extended: on disk, every listed file verified, and its
    ``gaussians.bin`` the one recorded as the parent's. ``(sources, "")``, or ``(None, why not)``."""
    from atlas_pipeline.scene_memory.bundle import verify_bundle_files

    path = parent.get("path") if isinstance(parent, dict) else None
    if not isinstance(path, str) or not path:
        return None, "its lineage.parent records no path"
    pdir = Path(path)
    if not (pdir / "metadata.json").is_file():
        return None, f"its parent bundle {pdir} (lineage.parent.path) is not on disk"
    key = str(pdir.resolve())
    if key in parents or len(parents) >= MAX_PARENT_DEPTH:
        return None, f"its lineage names {pdir} again (a loop)"
    try:
        pmeta = verify_bundle_files(pdir)
    except BundleFormatError as exc:
        return None, f"its parent bundle {pdir} does not verify ({exc})"
    want = parent.get("gaussians_bin_sha256")
    have = (pmeta["files"].get("gaussians.bin") or {}).get("sha256")
    if isinstance(want, str) and want and want != have:
        return None, (f"its parent bundle {pdir} holds another world than the one extended (its gaussians.bin "
                      "is not the one lineage.parent.gaussians_bin_sha256 records)")
    try:
        return bundle_keyframe_sources(pmeta, pdir / "metadata.json", parents + (key,)), ""
    except BundleFormatError as exc:
        return None, f"its parent bundle's keyframes cannot be read ({exc})"


def _older_extended_sources(own: dict[str, Any], parent: Any, idx: np.ndarray, T: np.ndarray, where: Path,
                            parents: tuple[str, ...]) -> KeyframeSources:
    """The keyframes (``idx [K]``, ``T [K, 4, 4]``) of a bundle extended from ``parent`` (its
    ``lineage.parent``) before bundles named each keyframe's recording; ``own``: its dataset's
    record. ``build --extend`` appends the new recording's keyframes to the parent's, so when the
    parent bundle proves to be the world extended (:func:`_parent_sources`) and its keyframes
    (indices and poses) are this bundle's first ones, those are frames of the parent's
    recordings (followed up older lineages the same way) and the rest of ``own``'s. Otherwise
    which keyframe is a frame of which recording is unknown: every keyframe is of
    :data:`UNKNOWN_RECORDING`, never read, and the reason is recorded."""
    pks, why = _parent_sources(parent, where, parents)
    if pks is not None:
        kp = len(pks)
        if kp > len(idx) or not np.array_equal(pks.indices, idx[:kp]) or \
                not np.allclose(pks.T_world_cam, T[:kp], rtol=0.0, atol=PARENT_POSE_TOLERANCE):
            why = (f"the keyframes of its parent bundle {parent.get('path')} are not the first keyframes of this "
                   "one (the parent was changed since it was extended)")
            pks = None
    if pks is None:
        reason = (f"{where} was written before bundles named each keyframe's recording, and it was extended from "
                  f"another bundle whose keyframes come first, but {why}: which recording its {len(idx)} keyframes "
                  "are frames of cannot be proven, so none of their frames is read")
        return KeyframeSources([dict(UNKNOWN_RECORDING)], idx, np.zeros(len(idx), np.int64), T, reason)
    recs = [dict(r) for r in pks.recordings]
    rec_idx = pks.recording.copy()
    if kp < len(idx):
        j = next((k for k, r in enumerate(recs) if same_recording(r, own)), None)
        if j is None:
            recs.append(dict(own))
            j = len(recs) - 1
        rec_idx = np.concatenate([rec_idx, np.full(len(idx) - kp, j, np.int64)])
    return KeyframeSources(recs, idx, rec_idx, T, pks.unknown_reason)


def join_recordings(recordings: list[dict[str, Any]], keyframe_recording: np.ndarray | None, n_keyframes: int,
                    new: dict[str, Any] | None, n_new: int) -> tuple[list[dict[str, Any]], np.ndarray | None]:
    """The recordings of a world of ``n_keyframes`` (``recordings`` and their ``[n_keyframes]``
    indices ``keyframe_recording``, None: not recorded) after ``n_new`` keyframes of the recording
    ``new`` (its record; None: not known) are appended. A recording already listed (same content)
    keeps its entry. Returns ``(recordings, [n_keyframes + n_new] indices)``, or ``([], None)``
    when no keyframe's recording is known at all."""
    if keyframe_recording is None and new is None:
        return [], None
    recs = [dict(r) for r in recordings]
    if keyframe_recording is None:  # keyframes from before recordings were kept: unknown, never guessed
        prev = np.zeros(n_keyframes, np.int64)
        recs = [dict(UNKNOWN_RECORDING)] if n_keyframes else []
    else:
        prev = np.asarray(keyframe_recording, np.int64).reshape(-1)
        if len(prev) != n_keyframes:
            raise ValueError(f"keyframe_recording has {len(prev)} entries for {n_keyframes} keyframes")
    new = dict(new) if new is not None else dict(UNKNOWN_RECORDING)
    j = next((k for k, r in enumerate(recs) if same_recording(r, new)), None)
    if j is None:
        if not n_new:
            return recs, prev
        recs.append(new)
        j = len(recs) - 1
    return recs, np.concatenate([prev, np.full(n_new, j, np.int64)])


def world_keyframe_recordings(world: Any, manifest: FrameManifest) -> tuple[list[dict[str, Any]], np.ndarray]:
    """``(recordings, [K] index per keyframe)`` of ``world`` (a ``GaussianWorld``) for its bundle
    made with ``manifest``: what the world recorded, else (a world that recorded none) every
    keyframe as a frame of ``manifest``."""
    n = len(world.keyframe_indices)
    rec_idx = getattr(world, "keyframe_recording", None)
    if rec_idx is None:
        return [recording_record(manifest)], np.zeros(n, np.int64)
    return [dict(r) for r in world.recordings], np.asarray(rec_idx, np.int64)


def keyframe_indices_of(world: Any, manifest: FrameManifest) -> np.ndarray:
    """``[k]`` frame indices of ``manifest`` that are keyframes of ``world`` (those of its other
    recordings are frames of other recordings); every keyframe for a world that recorded none."""
    rec_idx = getattr(world, "keyframe_recording", None)
    idx = np.asarray(world.keyframe_indices, np.int64)
    if rec_idx is None:
        return idx
    own = recording_index(world.recordings, recording_record(manifest))
    return idx[np.asarray(rec_idx, np.int64) == own] if own is not None else idx[:0]


def _candidates(record: dict[str, Any], reasons: list[str]):
    """Where ``record``'s frames may be: the folder it was read from, then the registered dataset
    of its name (each a ``DatasetEntry``)."""
    from atlas_pipeline.sensors.camera import CameraIntrinsics
    from atlas_pipeline.sensors.layouts import detect_kind
    from atlas_pipeline.sensors.registry import DatasetEntry, load_registry

    name, root = record.get("name"), record.get("root")
    out = []
    if root and Path(root).exists():
        kind = detect_kind(root)
        if kind is None:
            reasons.append(f"{root} is not a recording of a known layout")
        else:
            try:
                cam = CameraIntrinsics.from_dict(record["camera"]) if record.get("camera") else None
            except AtlasError as exc:
                # Read with the layout's default camera instead, its frames would be paired with
                # wrong intrinsics without a word: the folder is not a candidate.
                why = f"its recorded camera (field camera) is not a usable camera ({exc})"
                logger.warning("recording %s: %s; its folder is not read with another camera's intrinsics",
                               recording_label(record), why)
                reasons.append(why)
                cam = None
            if cam is not None or not record.get("camera"):
                out.append(DatasetEntry(name=name or Path(root).name, kind=kind, path=Path(root), camera=cam))  # type: ignore[arg-type]
    elif root:
        reasons.append(f"{root} is not on disk")
    if name:
        try:
            entry = load_registry().get(name)
        except AtlasError as exc:
            reasons.append(f"the dataset registry is unreadable ({exc})")
            entry = None
        if entry is not None and not any(Path(e.path) == Path(entry.path) for e in out):
            out.append(entry)
        elif entry is None and not root:
            reasons.append(f"no dataset '{name}' is registered")
    return out


def open_recording(record: dict[str, Any], generate: bool = True,
                   read_bags: bool = True) -> tuple[FrameManifest | None, str]:
    """The frames of the recording ``record`` names: ``(manifest, "")``, or ``(None, why not)``.

    Looked for in the folder it was read from, then as the registered dataset of its name; a
    candidate counts only when its content hash is the recorded one (a record without one, from
    an older bundle, takes the first readable candidate). ``generate``: a synthetic dataset
    missing on disk is generated (deterministic, never a download); ``read_bags``: a bag is read
    (converted once, which takes minutes for a long one)."""
    from atlas_pipeline.sensors.registry import ensure_dataset_files, read_dataset_manifest
    from atlas_pipeline.sensors.layouts import recording_exists

    if not record.get("name") and not record.get("root"):
        return None, "the world does not record which recording these keyframes come from"
    reasons: list[str] = []
    want = record.get("content_hash")
    n_frames = record.get("n_frames") if isinstance(record.get("n_frames"), int) and record["n_frames"] > 0 else None
    for entry in _candidates(record, reasons):
        try:
            if entry.kind == "synthetic" and generate:
                ensure_dataset_files(entry)
            elif not recording_exists(entry.kind, entry.path):
                reasons.append(f"{entry.path} is not on disk")
                continue
            if entry.kind == "bag" and not read_bags:
                reasons.append(f"{entry.path} is a bag recording (not converted here)")
                continue
            manifest = read_dataset_manifest(entry, n_frames)
        except AtlasError as exc:
            reasons.append(f"{entry.path} cannot be read ({str(exc)[:200]})")
            continue
        if want and manifest.content_hash != want:
            reasons.append(f"{entry.path} holds other frames (content hash {manifest.content_hash[:LABEL_HASH_CHARS]}"
                           f", recorded {want[:LABEL_HASH_CHARS]})")
            continue
        return manifest, ""
    return None, "; ".join(reasons) or "not on disk and not registered"


def read_frames_at(entry: Any, n_frames: int | None) -> FrameManifest:
    """The first ``n_frames`` frames (None: all) of the recording ``entry`` (a ``DatasetEntry``)
    names, as ``dataset.max_frames`` selects them (a synthetic one generated when missing)."""
    from atlas_pipeline.sensors.registry import ensure_dataset_files, read_dataset_manifest

    return read_dataset_manifest(entry, n_frames, ensure_dataset_files(entry))


def record_of_frames(records: list[Any], manifest: FrameManifest,
                     entry: Any) -> tuple[dict[str, Any] | None, FrameManifest | None]:
    """Which of ``records`` (recording records; others are skipped) names the recording whose
    frames ``manifest`` holds (read from ``entry``, a ``DatasetEntry``), by content:
    ``(record, its frames)``, or ``(None, None)``.

    The same frames (equal content hashes) give ``(record, manifest)``. The same recording read to
    another frame count (``dataset.max_frames``: its first frames, so one selection is the start of
    the other) hashes differently: ``entry`` is read again at the record's ``n_frames`` and counts
    when that has the record's content hash; those frames are returned. Names are never compared."""
    from atlas_pipeline.config import MIN_FRAMES

    dicts = [r for r in records if isinstance(r, dict)]
    mine = recording_record(manifest)
    for r in dicts:
        if same_recording(r, mine):
            return r, manifest
    hash_at: dict[int, str] = {}
    frames_at: dict[int, FrameManifest] = {}
    for r in dicts:
        n = r.get("n_frames")
        if not r.get("content_hash") or not isinstance(n, int) or isinstance(n, bool) or n < MIN_FRAMES \
                or n == manifest.n_frames:
            continue  # a record of as many frames as these, and other content, is another recording
        if n not in hash_at:
            try:
                frames_at[n] = read_frames_at(entry, n)
                hash_at[n] = frames_at[n].content_hash
            except AtlasError as exc:  # fewer frames on disk, unreadable: not that recording
                logger.debug("%s read at %d frames: %s", entry.name, n, exc)
                hash_at[n] = ""
        if hash_at[n] and hash_at[n] == r["content_hash"]:
            return r, frames_at[n]
    return None, None
