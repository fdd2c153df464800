"""Asset checks that gate bad results before they reach the bundle.

Each is a check spec of the asset it checks, evaluated by that asset on its artifact in every run:
on the value it computed, or on the artifact reloaded when it was reused (a real evaluation against
the run's threshold, never a replay). Every check is blocking: when it fails, Dagster does not run
the assets downstream of the checked one.
"""

import tempfile
from pathlib import Path

import numpy as np
import pyarrow as pa
from dagster import AssetCheckResult, AssetCheckSeverity, AssetCheckSpec, MetadataValue

from atlas_pipeline.gaussian_world.field import GaussianField
from atlas_pipeline.scene_memory.binary import read_gaussian_binary, write_gaussian_binary
from atlas_pipeline.scene_memory.ply import read_gaussian_ply, write_gaussian_ply
from atlas_pipeline.transition_log.transitions import TRANSITIONS_SCHEMA

GAUSSIANS_VALID = AssetCheckSpec(
    "gaussians_finite_and_nonempty", asset="gaussian_world", blocking=True,
    description="The world has Gaussians, every value is finite, opacities lie in (0, 1].",
)
BUNDLE_ROUNDTRIP = AssetCheckSpec(
    "bundle_reload_identical", asset="world_bundle", blocking=True,
    description="gaussians.bin and gaussians.ply reload to the same Gaussians bit for bit.",
)
ATE_BOUND = AssetCheckSpec(
    "ate_within_bound", asset="localization_report", blocking=True,
    description="ATE RMSE of the estimated trajectory is at most localization.max_ate_m (where ground truth exists).",
)
TRANSITIONS_SCHEMA_OK = AssetCheckSpec(
    "transitions_schema", asset="transitions", blocking=True,
    description="The transitions table has exactly TRANSITIONS_SCHEMA's columns and types, and at least one row.",
)


def check_gaussians(field: GaussianField) -> AssetCheckResult:
    finite = field.is_finite()
    ok = len(field) > 0 and finite and bool(np.all((field.opacities > 0) & (field.opacities <= 1)))
    return AssetCheckResult(check_name=GAUSSIANS_VALID.name, passed=ok, severity=AssetCheckSeverity.ERROR,
                            metadata={"n_gaussians": len(field), "finite": finite})


def check_bundle_roundtrip(field: GaussianField) -> AssetCheckResult:
    """Write both encodings and read them back; the bundle writer uses the same functions."""
    with tempfile.TemporaryDirectory(prefix="atlas_roundtrip.") as tmp:
        ply = read_gaussian_ply(write_gaussian_ply(field, Path(tmp) / "g.ply"), allow_empty=True)
        binf = read_gaussian_binary(write_gaussian_binary(field, Path(tmp) / "g.bin"))
    ok_ply, ok_bin = ply.equals(field), binf.equals(field)
    return AssetCheckResult(check_name=BUNDLE_ROUNDTRIP.name, passed=ok_ply and ok_bin,
                            severity=AssetCheckSeverity.ERROR,
                            metadata={"ply_identical": ok_ply, "bin_identical": ok_bin, "n_gaussians": len(field)})


def check_ate(summary: dict, max_ate_m: float) -> AssetCheckResult:
    """Pass when the ATE RMSE is at most ``max_ate_m``; without ground truth there is nothing to grade.
    A localization that stopped early (the world does not contain the frames) fails, with its reason."""
    if summary.get("outcome", "complete") != "complete":
        return AssetCheckResult(check_name=ATE_BOUND.name, passed=False, severity=AssetCheckSeverity.ERROR,
                                description=str(summary.get("stopped_reason") or "localization stopped early"),
                                metadata={"outcome": str(summary.get("outcome")), "max_ate_m": max_ate_m})
    ate = summary.get("ate_rmse_m")
    if ate is None or not np.isfinite(ate):
        return AssetCheckResult(check_name=ATE_BOUND.name, passed=True, severity=AssetCheckSeverity.ERROR,
                                description="no ground truth for this dataset (fewer than 3 graded frames): not graded",
                                metadata={"graded": False, "max_ate_m": max_ate_m})
    ok = bool(ate <= max_ate_m)
    return AssetCheckResult(
        check_name=ATE_BOUND.name, passed=ok, severity=AssetCheckSeverity.ERROR,
        description=f"ATE RMSE {ate:.4f} m {'<=' if ok else '>'} bound {max_ate_m} m",
        metadata={"graded": True, "ate_rmse_m": float(ate), "max_ate_m": max_ate_m,
                  "n_graded": int(summary.get("n_graded", 0))})


def check_transitions_schema(table: pa.Table) -> AssetCheckResult:
    expected = {f.name: str(f.type) for f in TRANSITIONS_SCHEMA}
    actual = {f.name: str(f.type) for f in table.schema}
    missing = sorted(set(expected) - set(actual))
    extra = sorted(set(actual) - set(expected))
    wrong = sorted(n for n in set(expected) & set(actual) if expected[n] != actual[n])
    ok = not missing and not extra and not wrong and table.num_rows > 0
    problems = ([f"missing {missing}"] if missing else []) + ([f"unexpected {extra}"] if extra else []) + \
        [f"{n}: {actual[n]} instead of {expected[n]}" for n in wrong] + (["no rows"] if table.num_rows == 0 else [])
    return AssetCheckResult(check_name=TRANSITIONS_SCHEMA_OK.name, passed=ok, severity=AssetCheckSeverity.ERROR,
                            description="schema matches" if ok else "; ".join(problems),
                            metadata={"n_rows": table.num_rows, "n_columns": table.num_columns,
                                      "problems": MetadataValue.json(problems)})


__all__ = ["GAUSSIANS_VALID", "BUNDLE_ROUNDTRIP", "ATE_BOUND", "TRANSITIONS_SCHEMA_OK", "check_gaussians",
           "check_bundle_roundtrip", "check_ate", "check_transitions_schema"]
