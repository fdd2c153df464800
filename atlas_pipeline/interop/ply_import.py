"""A Gaussian-splat PLY made elsewhere (3DGS layout) as a world bundle of this pipeline.

Spherical harmonics (``f_rest_*``, view-dependent colour up to degree 3) are kept: the bundle's
PLY and ``gaussians.bin`` carry them and the renderer evaluates them per view. The keyframe fit
and colour refinement are degree 0 and keep them unchanged.

The imported world has no recording behind it: no dataset (``null`` in metadata.json), no
keyframes, no anchor, poses "imported". It can be localized in (the first frame relocalized with no
prior pose, or started at a given ``--start-pose``), relocalized against, rendered and extended like
a built one; ``voxel_m`` is the map resolution the tracker assumes when it samples the world.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from atlas_pipeline.errors import ConfigError
from atlas_pipeline.io_utils import prepare_output_dir

logger = logging.getLogger(__name__)

IMPORT_CREATED_BY = "atlas-gs import-ply"


@dataclass(frozen=True)
class ImportedWorld:
    """What an import wrote: the bundle folder and the splats it holds."""

    bundle: Path
    n_gaussians: int
    anisotropic: bool
    sh_degree: int = 0  # degree of the view-dependent colour kept (0: none)


def imported_metadata(src: Path, voxel_m: float, isotropic: bool, sh_degree: int = 0) -> dict[str, Any]:
    """``metadata.json`` of a bundle imported from the PLY ``src``: its origin (path and size), the
    assumed map resolution, the SH degree of its colour, and a lineage with no dataset or run."""
    from atlas_pipeline.scene_memory.metadata import bundle_lineage

    return {
        "name": src.stem, "partition": None,
        "dataset": None,
        "gaussians": {"voxel_size_m": float(voxel_m), "isotropic": isotropic, "n_keyframes": 0,
                      "pose_source": "imported", "sh_degree": int(sh_degree)},
        "imported_from": {"path": str(src.resolve()), "bytes": src.stat().st_size},
        "lineage": bundle_lineage(IMPORT_CREATED_BY),
    }


def import_gaussian_ply(ply: str | Path, output: str | Path, voxel_m: float, force: bool = False) -> ImportedWorld:
    """Read the PLY ``ply`` (refusing missing properties, NaN/inf, short files) and write it as the
    world bundle ``output`` under the output policy (``force``: a foreign folder is moved aside)."""
    from atlas_pipeline.scene_memory.bundle import BUNDLE_KIND, write_world_bundle
    from atlas_pipeline.scene_memory.ply import read_gaussian_ply

    if not (np.isfinite(voxel_m) and voxel_m > 0):
        raise ConfigError(f"--voxel must be a finite number > 0, got {voxel_m}")
    src = Path(ply)
    prepare_output_dir(output, BUNDLE_KIND, [src], force)
    field = read_gaussian_ply(src)
    meta = imported_metadata(src, voxel_m, field.is_isotropic, field.sh_degree)
    bundle = write_world_bundle(output, field, meta, inputs=[src])
    logger.info("%s: %d Gaussians imported, view-dependent colour of SH degree %d kept", src, len(field),
                field.sh_degree)
    return ImportedWorld(bundle=Path(bundle), n_gaussians=len(field), anisotropic=not field.is_isotropic,
                         sh_degree=field.sh_degree)
