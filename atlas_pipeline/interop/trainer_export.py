"""A recording with its poses for GPU trainers: a COLMAP model or a nerfstudio ``transforms.json``.

Both layouts (``atlas-gs export WORLD --format colmap|nerfstudio --output DIR``)::

    DIR/images/frame_000123.png     colour, undistorted (copied as is when already so); a frame of
                                    another recording than the bundle's own (an extended world's
                                    keyframes) carries its tag: a-1b2c3d4e_frame_000004.png
    DIR/depths/frame_000123.png     depth, 16-bit PNG, millimetres (0 = no reading)
    DIR/sparse/0/cameras.{txt,bin}  colmap: one PINHOLE camera
    DIR/sparse/0/images.{txt,bin}   colmap: each frame's world-to-camera pose
    DIR/sparse/0/points3D.{txt,bin} colmap: the Gaussians' centres and colours
    DIR/transforms.json             nerfstudio: intrinsics, frames (OpenGL camera-to-world), depth unit
    DIR/points3D.ply                nerfstudio: the same points (its ``ply_file_path``)
    DIR/export.json                 what was exported: world, dataset, pose source, frames, counts

The folder obeys the output policy (new, empty, or an export atlas-gs wrote; ``--force`` moves
anything else aside) and is assembled beside its target and swapped in whole. The Dagster assets
``colmap_export`` / ``nerfstudio_export`` hold the same tree as one zip (artifact folders are flat).
"""

from __future__ import annotations

import json
import logging
import shutil
import tempfile
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from atlas_pipeline.errors import ArtifactError, ConfigError
from atlas_pipeline.interop.colmap import write_colmap_model
from atlas_pipeline.interop.frames import ExportSource
from atlas_pipeline.interop.nerfstudio import nerfstudio_transforms
from atlas_pipeline.io_utils import atomic_dir, atomic_path, check_output_dir, check_writable, write_json_atomic

logger = logging.getLogger(__name__)

__all__ = ["TRAINER_FORMATS", "EXPORT_KIND", "write_trainer_export", "write_trainer_files", "TrainerExport",
           "DEPTH_PNG_UNITS_PER_M", "seed_points"]

TRAINER_FORMATS = ("colmap", "nerfstudio")
EXPORT_KIND = "export"  # output-policy kind (io_utils marker) of every export folder
DEPTH_PNG_UNITS_PER_M = 1000.0  # millimetres: nerfstudio's default depth_unit_scale_factor (0.001)
DEPTH_PNG_MAX = np.iinfo(np.uint16).max
# Gaussians below this opacity are mostly fit residue, not surface: left out of the seed points.
MIN_SEED_OPACITY = 0.05
SPARSE_DIR = Path("sparse") / "0"  # where gsplat's and Inria's trainers look for the model
ZIP_DATE = (1980, 1, 1, 0, 0, 0)  # zip entries' time: a fixed one, so equal exports are equal bytes
_COPYABLE_SUFFIXES = (".png",)


def seed_points(field) -> tuple[np.ndarray, np.ndarray]:
    """``(xyz [P, 3] float64, rgb [P, 3] uint8)``: the centres and colours of the Gaussians at
    least :data:`MIN_SEED_OPACITY` opaque (all of them when none is)."""
    keep = field.opacities >= MIN_SEED_OPACITY
    if not keep.any():
        keep = np.ones(len(field), bool)
    return field.positions[keep].astype(np.float64), field.colors[keep]


def _write_png(path: Path, img: np.ndarray) -> None:
    import imageio.v3 as iio

    with atomic_path(path) as tmp:
        iio.imwrite(tmp, img, extension=".png")


def _write_frames(directory: Path, src: ExportSource, log: Callable[[str], None]) -> tuple[list[str], list[str]]:
    """Colour and depth of every exported frame into ``images/`` and ``depths/``; returns their
    paths relative to ``directory``."""
    (directory / "images").mkdir()
    (directory / "depths").mkdir()
    images, depths = [], []
    for k, i in enumerate(src.frame_indices.tolist()):
        m = src.manifest_of(k)  # the recording this frame is one of
        cam = m.camera
        name = src.frame_name(k)
        rgb_out, depth_out = directory / "images" / name, directory / "depths" / name
        source = m.rgb_path(i)
        if not cam.distortion and m.colour_camera == cam and source.suffix.lower() in _COPYABLE_SUFFIXES:
            m.read_rgb(i)  # checked (size, type) as every reader of the frames checks it
            shutil.copyfile(source, rgb_out)
        else:
            _write_png(rgb_out, src.pinhole_rgb(k))
        depth_m = src.pinhole_depth_m(k)
        raw = np.clip(np.rint(depth_m.astype(np.float64) * DEPTH_PNG_UNITS_PER_M), 0, DEPTH_PNG_MAX)
        _write_png(depth_out, raw.astype(np.uint16))
        images.append(f"images/{name}")
        depths.append(f"depths/{name}")
        if (k + 1) % 50 == 0:
            log(f"exported {k + 1}/{len(src.frame_indices)} frames")
    return images, depths


def _write_points_ply(path: Path, xyz: np.ndarray, rgb: np.ndarray) -> None:
    from plyfile import PlyData, PlyElement

    rows = np.zeros(len(xyz), [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"),
                               ("blue", "u1")])
    rows["x"], rows["y"], rows["z"] = xyz.T
    rows["red"], rows["green"], rows["blue"] = rgb.T
    with atomic_path(path) as tmp:
        PlyData([PlyElement.describe(rows, "vertex")], byte_order="<",
                comments=["Atlas-GS: Gaussian centres and colours"]).write(str(tmp))


def write_trainer_files(directory: Path, src: ExportSource, fmt: str,
                        log: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Write the ``fmt`` layout (module docstring) into the existing, empty ``directory``;
    returns the summary written as ``export.json``."""
    log = log or logger.info
    if fmt not in TRAINER_FORMATS:
        raise ConfigError(f"--format must be one of {', '.join(TRAINER_FORMATS)}, got {fmt!r}")
    cam = src.camera
    images, depths = _write_frames(directory, src, log)
    xyz, rgb = seed_points(src.field)
    if fmt == "colmap":
        write_colmap_model(directory / SPARSE_DIR, cam, [Path(p).name for p in images], src.T_world_cam, xyz, rgb)
    else:
        _write_points_ply(directory / "points3D.ply", xyz, rgb)
        write_json_atomic(directory / "transforms.json", nerfstudio_transforms(
            cam, images, depths, src.T_world_cam, "points3D.ply", 1.0 / DEPTH_PNG_UNITS_PER_M))
    summary = {
        "format": fmt, "map_id": src.map_id, "dataset": src.manifest.dataset, "pose_source": src.pose_source,
        "n_images": int(len(images)), "n_points3D": int(len(xyz)), "camera": cam.to_dict(),
        "depth": {"folder": "depths", "format": "png uint16", "units_per_m": DEPTH_PNG_UNITS_PER_M, "no_reading": 0},
        "frame_indices": [int(i) for i in src.frame_indices],
        # which recording each frame is one of (an extended world's keyframes come from several)
        "recordings": src.recordings_summary(),
        "frame_recordings": [int(j) for j in src.frame_recording],
    }
    write_json_atomic(directory / "export.json", summary)
    return summary


def write_trainer_export(output: str | Path, src: ExportSource, fmt: str, force: bool = False,
                         inputs: tuple = (), log: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Write the trainer export folder ``output`` atomically (output policy checked first; ``inputs`` are
    never replaced); returns the summary."""
    if fmt not in TRAINER_FORMATS:
        raise ConfigError(f"--format must be one of {', '.join(TRAINER_FORMATS)}, got {fmt!r}")
    output = Path(output).expanduser()
    check_output_dir(output, EXPORT_KIND, [*inputs, *(m.root for m in src.recordings)], force)
    check_writable(output.parent)
    with atomic_dir(output, kind=EXPORT_KIND) as tmp:
        summary = write_trainer_files(tmp, src, fmt, log)
    return summary


def _zip_tree(tree: Path, zip_path: Path) -> None:
    """``tree`` as a zip with sorted entries and fixed times (equal trees give equal bytes); PNGs
    are stored (already compressed), text deflated."""
    with atomic_path(zip_path) as tmp, zipfile.ZipFile(tmp, "w") as zf:
        for p in sorted(q for q in tree.rglob("*") if q.is_file()):
            info = zipfile.ZipInfo(p.relative_to(tree).as_posix(), ZIP_DATE)
            info.compress_type = zipfile.ZIP_STORED if p.suffix == ".png" else zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            with open(p, "rb") as f:
                zf.writestr(info, f.read())


@dataclass
class TrainerExport:
    """The artifact of the ``colmap_export`` / ``nerfstudio_export`` assets: ``<format>.zip`` (the
    folder ``write_trainer_export`` writes; unzip it to train) and ``export.json`` beside it."""

    fmt: str
    summary: dict[str, Any]
    source: ExportSource | None = None  # only while computing; load() gives the summary alone

    @classmethod
    def build(cls, src: ExportSource, fmt: str) -> "TrainerExport":
        if fmt not in TRAINER_FORMATS:
            raise ConfigError(f"format must be one of {', '.join(TRAINER_FORMATS)}, got {fmt!r}")
        return cls(fmt, {}, src)

    def save(self, directory: Path) -> list[Path]:
        if self.source is None:
            raise ArtifactError("a loaded TrainerExport holds no frames to write again")
        with tempfile.TemporaryDirectory(dir=directory, prefix=".tree-") as tree:
            self.summary = write_trainer_files(Path(tree), self.source, self.fmt)
            zip_path = directory / f"{self.fmt}.zip"
            _zip_tree(Path(tree), zip_path)
        js = write_json_atomic(directory / "export.json", self.summary)
        return [zip_path, js]

    @classmethod
    def load(cls, directory: Path) -> "TrainerExport":
        from atlas_pipeline.safe_arrays import load_json_object_checked

        path = directory / "export.json"
        if not path.is_file():
            raise ArtifactError(f"{directory}: export.json missing")
        summary = load_json_object_checked(path)
        fmt = summary.get("format")
        if fmt not in TRAINER_FORMATS or not (directory / f"{fmt}.zip").is_file():
            raise ArtifactError(f"{path}: format {fmt!r} is not one of {', '.join(TRAINER_FORMATS)}, or its zip is missing")
        return cls(fmt, summary)
