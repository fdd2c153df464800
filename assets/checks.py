"""Asset checks that gate bad results before they reach the bundle.

Checks run inside the asset that produces the value (``check_specs``), because Dagster's separate
``@asset_check`` functions cannot load one partition of a partitioned asset. Blocking checks stop
downstream assets when they fail.
"""

import tempfile
from pathlib import Path

import numpy as np
from dagster import AssetCheckResult, AssetCheckSeverity, AssetCheckSpec

from atlas_pipeline.gaussian_world.field import GaussianField
from atlas_pipeline.scene_memory.binary import read_atlasgs1, write_atlasgs1
from atlas_pipeline.scene_memory.ply import read_gaussian_ply, write_gaussian_ply

GAUSSIANS_VALID = AssetCheckSpec(
    "gaussians_finite_and_nonempty", asset="gaussian_world", blocking=True,
    description="The world has Gaussians, every value is finite, opacities lie in (0, 1].",
)
BUNDLE_ROUNDTRIP = AssetCheckSpec(
    "bundle_reload_identical", asset="world_bundle", blocking=True,
    description="gaussians.bin and gaussians.ply reload to the same Gaussians bit for bit.",
)


def check_gaussians(field: GaussianField) -> AssetCheckResult:
    finite = field.is_finite()
    ok = len(field) > 0 and finite and bool(np.all((field.opacities > 0) & (field.opacities <= 1)))
    return AssetCheckResult(check_name=GAUSSIANS_VALID.name, passed=ok, severity=AssetCheckSeverity.ERROR,
                            metadata={"n_gaussians": len(field), "finite": finite})


def check_bundle_roundtrip(field: GaussianField) -> AssetCheckResult:
    """Write both encodings and read them back; the bundle writer uses the same functions."""
    with tempfile.TemporaryDirectory(prefix="atlas_roundtrip.") as tmp:
        ply = read_gaussian_ply(write_gaussian_ply(field, Path(tmp) / "g.ply"))
        binf = read_atlasgs1(write_atlasgs1(field, Path(tmp) / "g.bin"))
    ok_ply, ok_bin = ply.equals(field), binf.equals(field)
    return AssetCheckResult(check_name=BUNDLE_ROUNDTRIP.name, passed=ok_ply and ok_bin,
                            severity=AssetCheckSeverity.ERROR,
                            metadata={"ply_identical": ok_ply, "bin_identical": ok_bin, "n_gaussians": len(field)})
