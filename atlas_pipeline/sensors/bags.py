"""ROS 1 / ROS 2 bags and RealSense ``.bag`` recordings, read with the pure-Python ``rosbags``.

A bag is converted once into a TUM-layout folder under ``<data>/bag_imports/`` (``rgb/``,
``depth/``, ``rgb.txt``, ``depth.txt``, ``bag_import.json``), written atomically
(:func:`atlas_pipeline.io_utils.stage_dir` + ``commit_dir(kind="bag_import")``), and read as TUM.
The conversion is reused while the bag's fingerprint (size, mtime and sha256 of the first MiB of
each of its files) and the import options are unchanged.

What is read:

* colour: ``sensor_msgs/Image`` (``rgb8``, ``bgr8``, ``rgba8``, ``bgra8``) or
  ``sensor_msgs/CompressedImage`` (JPEG or PNG);
* depth: ``sensor_msgs/Image`` ``16UC1`` / ``mono16`` (millimetres, or RealSense's
  ``Depth Units`` option when the bag records it) or ``32FC1`` (metres; NaN / inf / <= 0 = none).
  The cache stores uint16 millimetres (depth scale 1000); depth beyond 65.535 m is dropped;
* ``sensor_msgs/CameraInfo``: the depth stream's K (and plumb-bob distortion) is the manifest's
  camera. Colour is assumed registered to depth (as RealSense's ``aligned_depth_to_color`` and
  ``/align`` streams are: same centre and orientation); when its size or K differs (K from its
  own camera_info) it is resampled onto the depth camera as ScanNet colour is. Unaligned RealSense
  streams are therefore misaligned by the colour-depth baseline (a few pixels at 1 m).

Topics are detected when unambiguous (one depth-encoded Image topic, one colour topic; an
``aligned`` depth topic and a raw over a compressed colour topic break ties), otherwise the
registry keys ``rgb_topic`` / ``depth_topic`` (and ``camera_info_topic``) choose. Frames are
stamped by their header (the bag's receive time when a topic's header stamps are all zero) and
paired by nearest stamp within 20 ms, as TUM's ``associate.py``.
"""

from __future__ import annotations

import hashlib
import io
import json
import logging
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from atlas_pipeline.errors import DatasetError
from atlas_pipeline.io_utils import commit_dir, discard_dir, stage_dir
from atlas_pipeline.sensors.camera import CameraIntrinsics
from atlas_pipeline.sensors.tum import MAX_ASSOCIATION_DT_S, FrameManifest, associate, load_tum_sequence

logger = logging.getLogger(__name__)

__all__ = ["BAG_DEPTH_SCALE", "bag_fingerprint", "bag_cache_dir", "import_bag", "load_bag_sequence"]

BAG_IMPORT_VERSION = 1  # bump when the conversion changes: older caches are rebuilt
BAG_DEPTH_SCALE = 1000.0  # the cache's depth PNGs are uint16 millimetres
MAX_DEPTH_MM = 65535  # uint16: farther readings are dropped (0)
FINGERPRINT_BYTES = 1 << 20  # sha256 of each bag file's first MiB (with size and mtime)
DEFAULT_DEPTH_UNIT_M = 0.001  # 16UC1 depth is millimetres (REP 118)
# RealSense .bag files record the depth unit as an option (librealsense rosbag format).
REALSENSE_DEPTH_UNITS_RE = re.compile(r"/option/Depth[ _]Units/value$")
MANIFEST_NAME = "bag_import.json"

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
# encoding -> (channels, BGR order)
COLOUR_ENCODINGS = {"rgb8": (3, False), "bgr8": (3, True), "rgba8": (4, False), "bgra8": (4, True)}
DEPTH_ENCODINGS = {"16uc1": "u2", "mono16": "u2", "32fc1": "f4"}


def _file_fingerprint(path: Path) -> dict[str, Any]:
    st = path.stat()
    h = hashlib.sha256()
    with open(path, "rb") as f:
        h.update(f.read(FINGERPRINT_BYTES))
    return {"name": path.name, "size": st.st_size, "mtime_ns": st.st_mtime_ns, "sha256_first_mib": h.hexdigest()}


def _bag_files(path: Path) -> list[Path]:
    """The files of a bag: the ``.bag`` file, or a ROS 2 folder's ``metadata.yaml`` and storage files."""
    if path.is_file():
        return [path]
    if path.is_dir() and (path / "metadata.yaml").is_file():
        storage = sorted(p for p in path.iterdir() if p.suffix in (".db3", ".mcap") and p.is_file())
        if not storage:
            raise DatasetError(path, "ROS 2 bag folder has no .db3 or .mcap file")
        return [path / "metadata.yaml", *storage]
    raise DatasetError(path, "not a bag: expected a .bag file or a ROS 2 bag folder (metadata.yaml + .db3/.mcap)")


def bag_fingerprint(path: Path) -> list[dict[str, Any]]:
    """Size, mtime and sha256 of the first MiB of every file of the bag at ``path``."""
    try:
        return [_file_fingerprint(p) for p in _bag_files(Path(path))]
    except OSError as exc:
        raise DatasetError(path, f"cannot read bag ({exc.strerror or exc})") from None


def bag_cache_dir(path: Path, cache_root: Path) -> Path:
    """The conversion folder of the bag at ``path``: ``<cache_root>/<stem>-<hash of its path>``."""
    resolved = str(Path(path).resolve())
    stem = re.sub(r"[^a-z0-9_-]+", "-", Path(resolved).stem.lower()).strip("-_")[:40] or "bag"
    return Path(cache_root) / f"{stem}-{hashlib.sha256(resolved.encode()).hexdigest()[:12]}"


# ---- topics --------------------------------------------------------------------------------------


@dataclass
class _Topic:
    name: str
    msgtype: str
    connections: list
    encoding: str = ""  # Image encoding or CompressedImage format (lower case)


def _first(reader, topic: _Topic):
    for con, _t, raw in reader.messages(connections=topic.connections):
        return reader.deserialize(raw, con.msgtype)
    return None


def _common_prefix(a: str, b: str) -> int:
    n = 0
    for x, y in zip(a.strip("/").split("/"), b.strip("/").split("/")):
        if x != y:
            break
        n += 1
    return n


def _pick(candidates: list[_Topic], what: str, key: str, path: Path, prefer) -> _Topic:
    if len(candidates) == 1:
        return candidates[0]
    if not candidates:
        raise DatasetError(path, f"no {what} topic found")
    preferred = [t for t in candidates if prefer(t)]
    if len(preferred) == 1:
        return preferred[0]
    names = ", ".join(sorted(t.name for t in candidates))
    raise DatasetError(path, f"several {what} topics ({names}); choose one with the registry key '{key}' "
                             f"(--{key.replace('_', '-')})")


def _choose_topics(reader, path: Path, rgb_topic: str | None, depth_topic: str | None) -> tuple[_Topic, _Topic, dict]:
    topics: dict[str, _Topic] = {}
    for con in reader.connections:
        t = topics.setdefault(con.topic, _Topic(con.topic, con.msgtype, []))
        t.connections.append(con)
    for t in topics.values():
        if t.msgtype == IMAGE:
            msg = _first(reader, t)
            t.encoding = str(getattr(msg, "encoding", "")).lower() if msg is not None else ""
        elif t.msgtype == COMPRESSED:
            msg = _first(reader, t)
            t.encoding = str(getattr(msg, "format", "")).lower() if msg is not None else ""
    depth_ok = [t for t in topics.values() if t.msgtype == IMAGE and t.encoding in DEPTH_ENCODINGS]
    colour_ok = [t for t in topics.values()
                 if (t.msgtype == IMAGE and t.encoding in COLOUR_ENCODINGS)
                 or (t.msgtype == COMPRESSED and "compresseddepth" not in t.encoding
                     and ("jpeg" in t.encoding or "jpg" in t.encoding or "png" in t.encoding))]
    for given, ok, what in ((depth_topic, depth_ok, "depth"), (rgb_topic, colour_ok, "colour")):
        if given is not None and given not in {t.name for t in ok}:
            if given in topics:
                t = topics[given]
                raise DatasetError(path, f"topic {given} ({t.msgtype}, {t.encoding or 'no messages'}) is not a "
                                         f"supported {what} stream")
            raise DatasetError(path, f"{what} topic {given} is not in the bag (topics: {', '.join(sorted(topics))})")
    depth = (topics[depth_topic] if depth_topic else
             _pick(depth_ok, "depth (16UC1 / 32FC1 Image)", "depth_topic", path, lambda t: "aligned" in t.name))
    colour = (topics[rgb_topic] if rgb_topic else
              _pick(colour_ok, "colour (rgb8/bgr8/rgba8/bgra8 Image or JPEG/PNG CompressedImage)", "rgb_topic", path,
                    lambda t: t.msgtype == IMAGE))
    return colour, depth, topics


def _camera_info_topic(topics: dict[str, _Topic], image_topic: str, given: str | None, path: Path) -> _Topic | None:
    infos = [t for t in topics.values() if t.msgtype == CAMERA_INFO]
    if given is not None:
        if given not in topics or topics[given].msgtype != CAMERA_INFO:
            raise DatasetError(path, f"camera_info topic {given} is not a sensor_msgs/CameraInfo topic of the bag")
        return topics[given]
    if not infos:
        return None
    if len(infos) == 1:
        return infos[0]
    winner = _nearest_info(infos, image_topic)
    if winner is None:
        names = ", ".join(sorted(t.name for t in infos))
        raise DatasetError(path, f"cannot tell which camera_info belongs to {image_topic} ({names}); "
                                 "choose it with the registry key 'camera_info_topic'")
    return winner


def _nearest_info(infos: list[_Topic], image_topic: str) -> _Topic | None:
    """The camera_info topic sharing the longest namespace with ``image_topic`` (``/cam/depth/info``
    for ``/cam/depth/image_raw``; RealSense ``.../Depth_0/info/camera_info`` for
    ``.../Depth_0/image/data``); None when no single one does."""
    scores = [_common_prefix(t.name, image_topic) for t in infos]
    best = max(scores, default=0)
    winners = [t for t, s in zip(infos, scores) if s == best]
    return winners[0] if best > 0 and len(winners) == 1 else None


def _camera_from_info(msg, topic: str, path: Path) -> CameraIntrinsics:
    # ROS 2 names the fields k, d; ROS 1 (and RealSense bags) K, D.
    K = np.asarray(msg.k if hasattr(msg, "k") else getattr(msg, "K", ()), dtype=np.float64).ravel()
    D = np.asarray(msg.d if hasattr(msg, "d") else getattr(msg, "D", ()), dtype=np.float64).ravel()
    model = str(getattr(msg, "distortion_model", "") or "")
    if K.shape != (9,):
        raise DatasetError(path, f"{topic}: camera_info K has {K.size} values, expected 9")
    distortion: tuple[float, ...] = ()
    if D.size and np.any(D != 0):
        if model == "plumb_bob" and D.size == 5:
            distortion = tuple(float(x) for x in D)
        else:
            logger.warning("%s: %s distortion %s of model %r is ignored", path, topic, D.tolist(), model)
    try:
        return CameraIntrinsics(int(msg.width), int(msg.height), float(K[0]), float(K[4]), float(K[2]), float(K[5]),
                                BAG_DEPTH_SCALE, distortion)
    except Exception as exc:  # ConfigError: zero size, non-positive focal length
        raise DatasetError(path, f"{topic}: invalid camera_info ({exc})") from None


# ---- decoding ------------------------------------------------------------------------------------


def _stamp(msg, bag_time_ns: int) -> tuple[float, float]:
    """``(header stamp, bag receive time)`` in seconds."""
    st = msg.header.stamp
    return float(st.sec) + float(st.nanosec) * 1e-9, bag_time_ns * 1e-9


def _rows(msg, channels: int, itemsize: int, where: str, path: Path) -> np.ndarray:
    """The ``[H, W * channels * itemsize]`` bytes of an Image message (row padding dropped)."""
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    data = np.frombuffer(memoryview(msg.data), dtype=np.uint8)
    row = w * channels * itemsize
    if h <= 0 or w <= 0 or step < row or data.size < step * (h - 1) + row:
        raise DatasetError(path, f"{where}: image {w}x{h} step {step} does not fit its {data.size} bytes")
    if data.size < step * h:
        data = np.concatenate([data, np.zeros(step * h - data.size, np.uint8)])
    return data[: step * h].reshape(h, step)[:, :row]


def _decode_colour(msg, msgtype: str, where: str, path: Path) -> np.ndarray:
    """RGB ``[H, W, 3]`` uint8 of a colour message."""
    if msgtype == COMPRESSED:
        from PIL import Image

        try:
            with Image.open(io.BytesIO(bytes(msg.data))) as im:
                im = im.convert("RGB")
                return np.asarray(im, dtype=np.uint8)
        except Exception as exc:  # Pillow raises many types for corrupt data
            raise DatasetError(path, f"{where}: cannot decode compressed image ({type(exc).__name__}: {exc})") from None
    enc = str(msg.encoding).lower()
    if enc not in COLOUR_ENCODINGS:
        raise DatasetError(path, f"{where}: colour encoding {msg.encoding!r} (topic changed encoding?)")
    ch, bgr = COLOUR_ENCODINGS[enc]
    img = _rows(msg, ch, 1, where, path).reshape(int(msg.height), int(msg.width), ch)[..., :3]
    return np.ascontiguousarray(img[..., ::-1] if bgr else img)


def _decode_depth_mm(msg, unit_m: float, where: str, path: Path) -> np.ndarray:
    """Depth ``[H, W]`` uint16 millimetres of a depth message (0 = no reading)."""
    enc = str(msg.encoding).lower()
    if enc not in DEPTH_ENCODINGS:
        raise DatasetError(path, f"{where}: depth encoding {msg.encoding!r} (topic changed encoding?)")
    kind = DEPTH_ENCODINGS[enc]
    dtype = np.dtype((">" if int(msg.is_bigendian) else "<") + kind)
    raw = _rows(msg, 1, dtype.itemsize, where, path).copy().view(dtype).reshape(int(msg.height), int(msg.width))
    if kind == "u2" and abs(unit_m - 0.001) < 1e-12:
        return raw.astype(np.uint16)
    metres = raw.astype(np.float64) * (unit_m if kind == "u2" else 1.0)
    mm = np.where(np.isfinite(metres) & (metres > 0), np.rint(metres * 1000.0), 0.0)
    mm[mm > MAX_DEPTH_MM] = 0.0
    return mm.astype(np.uint16)


def _write_png(path: Path, img: np.ndarray) -> None:
    from PIL import Image

    Image.fromarray(img).save(path, format="PNG", compress_level=1)  # speed over size: a cache


# ---- conversion ----------------------------------------------------------------------------------


ROS1_MAGIC = b"#ROSBAG V2.0\n"
# A chunk's uncompressed size may claim at most this many times its stored bytes (bz2 of an
# all-zero depth image reaches a few hundred); beyond it the claim is corrupt, not data.
ROS1_MAX_CHUNK_RATIO = 2000
_ROS1_LEN = 4  # every length in a ROS 1 bag is a little-endian uint32


def check_ros1_record_sizes(path: Path) -> None:
    """Walk the records of a ROS 1 bag (v2.0) and refuse one whose header, field or data length
    runs past the end of the file, or a chunk that claims more uncompressed bytes than its data
    can hold, before a reader allocates what a corrupt length claims. Reads headers only.

    Raises :class:`DatasetError` naming the file, the record's byte offset and the length at fault.
    """
    size = path.stat().st_size
    with open(path, "rb") as f:
        if f.read(len(ROS1_MAGIC)) != ROS1_MAGIC:
            return  # not a ROS 1 bag: the reader says what it is
        pos = len(ROS1_MAGIC)
        while pos < size:
            header_len = _ros1_length(f, path, pos, size, "header length")
            header = f.read(header_len)
            fields = _ros1_fields(header, path, pos)
            data_at = pos + _ROS1_LEN + header_len
            data_len = _ros1_length(f, path, data_at, size, "data length")
            if fields.get(b"op") == b"\x05" and len(fields.get(b"size", b"")) == _ROS1_LEN:  # a chunk
                claimed = int.from_bytes(fields[b"size"], "little")
                if claimed > ROS1_MAX_CHUNK_RATIO * max(data_len, 1):
                    raise DatasetError(path, f"cannot read bag, corrupt: the chunk at byte {pos} claims {claimed} uncompressed "
                                             f"bytes from {data_len} stored")
            pos = data_at + _ROS1_LEN + data_len
            f.seek(pos)


def _ros1_length(f, path: Path, at: int, size: int, what: str) -> int:
    """A uint32 length at byte ``at`` whose bytes must follow within the file's ``size``."""
    raw = f.read(_ROS1_LEN)
    if len(raw) < _ROS1_LEN:
        raise DatasetError(path, f"cannot read bag, corrupt: truncated record at byte {at} (no {what})")
    n = int.from_bytes(raw, "little")
    if at + _ROS1_LEN + n > size:
        raise DatasetError(path, f"cannot read bag, corrupt: the {what} {n} at byte {at} runs past the end of the file "
                                 f"({size} bytes)")
    return n


def _ros1_fields(header: bytes, path: Path, at: int) -> dict[bytes, bytes]:
    """``{name: value}`` of a record header (``len name=value`` fields), lengths checked."""
    out, i = {}, 0
    while i < len(header):
        if i + _ROS1_LEN > len(header):
            raise DatasetError(path, f"cannot read bag, corrupt: truncated header field in the record at byte {at}")
        n = int.from_bytes(header[i:i + _ROS1_LEN], "little")
        i += _ROS1_LEN
        if i + n > len(header):
            raise DatasetError(path, f"cannot read bag, corrupt: a header field of {n} bytes overruns the record at byte {at}")
        name, eq, value = header[i:i + n].partition(b"=")
        if not eq:
            raise DatasetError(path, f"cannot read bag, corrupt: a header field without '=' in the record at byte {at}")
        out[name] = value
        i += n
    return out


def _open_reader(path: Path):
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    if path.is_file():
        check_ros1_record_sizes(path)

    # ROS 1 bags carry their message definitions; ROS 2 bags without them use Humble's.
    return AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))


def _depth_unit(reader, topics: dict[str, _Topic]) -> float:
    for t in topics.values():
        if REALSENSE_DEPTH_UNITS_RE.search(t.name):
            msg = _first(reader, t)
            val = float(getattr(msg, "data", 0.0) or 0.0) if msg is not None else 0.0
            if np.isfinite(val) and 0 < val < 1:
                return val
    return DEFAULT_DEPTH_UNIT_M


def _stamps(reader, topic: _Topic, path: Path) -> np.ndarray:
    """Stamps ``[M]`` (seconds) of a topic's messages in bag order."""
    header, bag = [], []
    for k, (con, t, raw) in enumerate(reader.messages(connections=topic.connections)):
        try:
            h, b = _stamp(reader.deserialize(raw, con.msgtype), t)
        except Exception as exc:
            raise DatasetError(path, f"{topic.name} message {k}: cannot deserialize ({type(exc).__name__}: {exc})") from None
        header.append(h)
        bag.append(b)
    ts = np.asarray(header if any(header) else bag, dtype=np.float64)
    if not any(header) and header:
        logger.warning("%s: %s has no header stamps; using the bag's receive times", path, topic.name)
    return ts


def _unique_sorted(ts: np.ndarray) -> np.ndarray:
    """Indices of messages kept: sorted by stamp (microseconds, as the list files print them),
    the first of equal stamps kept."""
    us = np.rint(ts * 1e6)
    order = np.argsort(us, kind="stable")
    keep = np.ones(len(order), bool)
    keep[1:] = np.diff(us[order]) > 0
    return order[keep]


def import_bag(path: str | Path, cache_root: str | Path, rgb_topic: str | None = None, depth_topic: str | None = None,
               camera_info_topic: str | None = None, camera: CameraIntrinsics | None = None) -> tuple[Path, CameraIntrinsics]:
    """Convert the bag at ``path`` into a TUM folder under ``cache_root`` (reused when unchanged).

    ``camera`` is the depth camera when the bag has no camera_info for it (its depth scale is
    ignored: the cache is millimetres). Returns ``(folder, depth camera with depth scale 1000)``.
    """
    path = Path(path).expanduser().resolve()
    fingerprint = bag_fingerprint(path)
    options = {"rgb_topic": rgb_topic, "depth_topic": depth_topic, "camera_info_topic": camera_info_topic,
               "camera": camera.to_dict() if camera is not None else None}
    folder = bag_cache_dir(path, Path(cache_root))
    record_path = folder / MANIFEST_NAME
    if record_path.is_file():
        try:
            record = json.loads(record_path.read_text(encoding="utf-8"))
            if (record.get("version") == BAG_IMPORT_VERSION and record.get("bag_files") == fingerprint
                    and record.get("options") == options):
                logger.info("%s: reusing its conversion in %s", path, folder)
                return folder, CameraIntrinsics.from_dict(record["camera"])
        except (ValueError, KeyError, TypeError, OSError) as exc:
            logger.warning("%s: unreadable conversion record (%s); converting again", record_path, exc)
        except Exception as exc:  # ConfigError of a hand-edited camera
            logger.warning("%s: invalid conversion record (%s); converting again", record_path, exc)
    staged = stage_dir(folder)
    try:
        record = _convert(path, staged, options)
        record.update({"version": BAG_IMPORT_VERSION, "bag": str(path), "bag_files": fingerprint, "options": options})
        (staged / MANIFEST_NAME).write_text(json.dumps(record, indent=1) + "\n", encoding="utf-8")
        commit_dir(staged, folder, kind="bag_import", marker_extra={"bag": str(path), "bag_files": fingerprint})
    except BaseException:
        discard_dir(staged)
        raise
    return folder, CameraIntrinsics.from_dict(record["camera"])


def _convert(path: Path, out: Path, options: dict[str, Any]) -> dict[str, Any]:
    try:
        reader = _open_reader(path)
        reader.open()
    except DatasetError:
        raise
    except Exception as exc:  # rosbags' reader errors (bad header, unknown storage, truncated)
        raise DatasetError(path, f"cannot read bag ({type(exc).__name__}: {exc})") from None
    try:
        return _convert_open(reader, path, out, options)
    except DatasetError:
        raise
    except Exception as exc:  # a corrupt chunk / record deep inside rosbags
        raise DatasetError(path, f"cannot read bag ({type(exc).__name__}: {exc})") from None
    finally:
        reader.close()


def _convert_open(reader, path: Path, out: Path, options: dict[str, Any]) -> dict[str, Any]:
    colour, depth, topics = _choose_topics(reader, path, options["rgb_topic"], options["depth_topic"])
    info = _camera_info_topic(topics, depth.name, options["camera_info_topic"], path)
    if info is not None:
        msg = _first(reader, info)
        cam = _camera_from_info(msg, info.name, path)
    elif options["camera"] is not None:
        c = dict(options["camera"], depth_scale=BAG_DEPTH_SCALE)
        cam = CameraIntrinsics.from_dict(c)
    else:
        raise DatasetError(path, f"no sensor_msgs/CameraInfo for {depth.name}; give the camera in the registry "
                                 "('camera', or --intrinsics)")
    colour_info = None  # the colour stream's own camera_info, when it has one other than depth's
    if info is not None:
        near = _nearest_info([t for t in topics.values() if t.msgtype == CAMERA_INFO], colour.name)
        if near is not None and near.name != info.name:
            colour_info = _camera_from_info(_first(reader, near), near.name, path)
    unit = _depth_unit(reader, topics)
    logger.info("%s: colour %s, depth %s (%s, unit %g m), camera_info %s", path, colour.name, depth.name,
                depth.encoding, unit, info.name if info else "from the registry")

    t_rgb = _stamps(reader, colour, path)
    t_depth = _stamps(reader, depth, path)
    keep_rgb, keep_depth = _unique_sorted(t_rgb), _unique_sorted(t_depth)
    pairs = associate(t_rgb[keep_rgb], t_depth[keep_depth], MAX_ASSOCIATION_DT_S)
    if len(pairs) < 2:
        raise DatasetError(path, f"{len(pairs)} colour/depth pairs within {MAX_ASSOCIATION_DT_S * 1000:.0f} ms "
                                 f"({len(t_rgb)} on {colour.name}, {len(t_depth)} on {depth.name}); need 2")
    rgb_out = {int(keep_rgb[i]): k for k, (i, _) in enumerate(pairs)}  # message ordinal -> frame
    depth_out = {int(keep_depth[j]): k for k, (_, j) in enumerate(pairs)}
    (out / "rgb").mkdir()
    (out / "depth").mkdir()
    colour_cam = None
    for topic, wanted in ((colour, rgb_out), (depth, depth_out)):
        for k, (con, _t, raw) in enumerate(reader.messages(connections=topic.connections)):
            if k not in wanted:
                continue
            where = f"{topic.name} message {k}"
            msg = reader.deserialize(raw, con.msgtype)
            frame = wanted[k]
            if topic is depth:
                mm = _decode_depth_mm(msg, unit, where, path)
                if mm.shape != (cam.height, cam.width):
                    raise DatasetError(path, f"{where}: depth is {mm.shape[1]}x{mm.shape[0]}, its camera_info "
                                             f"says {cam.width}x{cam.height}")
                _write_png(out / "depth" / f"{frame:06d}.png", mm)
                continue
            rgb = _decode_colour(msg, topic.msgtype, where, path)
            if colour_cam is None:
                colour_cam = _colour_camera(rgb.shape, colour_info, cam, where, path)
            elif rgb.shape[:2] != (colour_cam.height, colour_cam.width):
                raise DatasetError(path, f"{where}: colour is {rgb.shape[1]}x{rgb.shape[0]}, earlier frames "
                                         f"{colour_cam.width}x{colour_cam.height}")
            if colour_cam is not cam:
                from atlas_pipeline.sensors.images import resample_rgb

                rgb = resample_rgb(rgb, colour_cam, cam)
            _write_png(out / "rgb" / f"{frame:06d}.png", rgb)
    rgb_lines = [f"{t_rgb[keep_rgb[i]]:.6f} rgb/{k:06d}.png" for k, (i, _) in enumerate(pairs)]
    depth_rows = sorted((t_depth[keep_depth[j]], k) for k, (_, j) in enumerate(pairs))
    depth_lines = [f"{t:.6f} depth/{k:06d}.png" for t, k in depth_rows]
    head = f"# converted by atlas-gs from {path.name}\n# timestamp filename\n"
    (out / "rgb.txt").write_text(head + "\n".join(rgb_lines) + "\n", encoding="utf-8")
    (out / "depth.txt").write_text(head + "\n".join(depth_lines) + "\n", encoding="utf-8")
    return {"rgb_topic": colour.name, "depth_topic": depth.name, "camera_info_topic": info.name if info else None,
            "depth_encoding": depth.encoding, "depth_unit_m": unit, "n_frames": len(pairs),
            "colour_resampled": colour_cam is not None and colour_cam is not cam, "camera": cam.to_dict()}


def _colour_camera(shape: tuple, info: CameraIntrinsics | None, depth: CameraIntrinsics, where: str,
                   path: Path) -> CameraIntrinsics:
    """The colour camera: its camera_info when it differs from the depth camera, else the depth camera."""
    h, w = shape[:2]
    if info is not None:
        if (info.width, info.height) != (w, h):
            raise DatasetError(path, f"{where}: colour is {w}x{h}, its camera_info says {info.width}x{info.height}")
        same = (info.fx, info.fy, info.cx, info.cy, w, h) == (depth.fx, depth.fy, depth.cx, depth.cy,
                                                             depth.width, depth.height)
        return depth if same else info
    if (w, h) != (depth.width, depth.height):
        raise DatasetError(path, f"{where}: colour is {w}x{h}, depth {depth.width}x{depth.height}, and there is no "
                                 "colour camera_info to resample it with")
    return depth


def load_bag_sequence(path: str | Path, dataset: str, cache_root: str | Path, max_frames: int | None = None,
                      camera: CameraIntrinsics | None = None, rgb_topic: str | None = None,
                      depth_topic: str | None = None, camera_info_topic: str | None = None) -> FrameManifest:
    """The :class:`FrameManifest` of a bag: converted (or reused) by :func:`import_bag`, read as TUM."""
    folder, cam = import_bag(path, cache_root, rgb_topic, depth_topic, camera_info_topic, camera)
    manifest = load_tum_sequence(folder, cam, dataset, max_frames)
    record = json.loads((folder / MANIFEST_NAME).read_text(encoding="utf-8"))
    manifest.source = {"layout": "bag", "path": str(Path(path).expanduser().resolve()), "cache": str(folder),
                       "max_frames": max_frames, "rgb_topic": record.get("rgb_topic"),
                       "depth_topic": record.get("depth_topic"), "camera_info_topic": record.get("camera_info_topic")}
    return manifest
