"""One entry point for every export of a world (``atlas-gs export WORLD --format F --output DIR``):
the trainer layouts (``colmap``, ``nerfstudio``: :mod:`.trainer_export`), the TSDF ``mesh``
(:mod:`.mesh`) and the ``occupancy`` grid (:mod:`.occupancy`). Options are checked before any frame
is read; the output folder obeys the output policy and is swapped in whole."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable

from atlas_pipeline.errors import ConfigError
from atlas_pipeline.interop.frames import ExportSource
from atlas_pipeline.interop.mesh import MESH_VOXEL_M, WorldMesh, check_voxel, mesh_info, mesh_preview_png, tsdf_mesh
from atlas_pipeline.interop.occupancy import (OCCUPANCY_RESOLUTION_M, OccupancyMap, check_resolution, occupancy_grid,
                                              occupancy_info, occupancy_preview_png)
from atlas_pipeline.interop.trainer_export import EXPORT_KIND, TRAINER_FORMATS, write_trainer_files
from atlas_pipeline.io_utils import atomic_dir, check_output_dir, check_writable

__all__ = ["EXPORT_FORMATS", "DEFAULT_POSES", "write_export", "build_mesh", "build_occupancy"]

EXPORT_FORMATS = (*TRAINER_FORMATS, "mesh", "occupancy")
# The mesh and the grid are made of what the world was mapped from; trainers get every placed frame.
DEFAULT_POSES = {"colmap": "auto", "nerfstudio": "auto", "mesh": "keyframes", "occupancy": "keyframes"}


def check_format(fmt: str) -> str:
    if fmt not in EXPORT_FORMATS:
        raise ConfigError(f"--format must be one of {', '.join(EXPORT_FORMATS)}, got {fmt!r}")
    return fmt


def build_mesh(src: ExportSource, voxel_m: float = MESH_VOXEL_M, log: Callable[[str], None] | None = None) -> WorldMesh:
    """The TSDF mesh of ``src`` with its summary and a preview from the first frame."""
    mesh = tsdf_mesh(src, voxel_m, log=log)
    cam = src.manifest.camera
    return WorldMesh(mesh, mesh_info(mesh, src, voxel_m),
                     mesh_preview_png(mesh, src.T_world_cam[0], cam.K, cam.width, cam.height))


def build_occupancy(src: ExportSource, resolution_m: float = OCCUPANCY_RESOLUTION_M,
                    log: Callable[[str], None] | None = None) -> OccupancyMap:
    occ = occupancy_grid(src, resolution_m, log=log)
    return OccupancyMap(occ, occupancy_info(occ, src), occupancy_preview_png(occ))


def write_export(output: str | Path, src: ExportSource, fmt: str, force: bool = False, inputs: tuple = (),
                 voxel_m: float = MESH_VOXEL_M, resolution_m: float = OCCUPANCY_RESOLUTION_M,
                 log: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Write ``fmt`` of ``src`` into the folder ``output``; returns its summary (``export.json``,
    ``mesh.json`` or ``occupancy.json``)."""
    check_format(fmt)
    check_voxel(voxel_m)
    check_resolution(resolution_m)
    output = Path(output).expanduser()
    check_output_dir(output, EXPORT_KIND, [*inputs, *(m.root for m in src.recordings)], force)
    check_writable(output.parent)
    with atomic_dir(output, kind=EXPORT_KIND) as tmp:
        if fmt in TRAINER_FORMATS:
            return write_trainer_files(tmp, src, fmt, log)
        art = build_mesh(src, voxel_m, log) if fmt == "mesh" else build_occupancy(src, resolution_m, log)
        art.save(tmp)
        return {"format": fmt, **art.info}
