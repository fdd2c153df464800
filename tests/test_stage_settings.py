"""The config fields each stage reads: every field read by some stage, the fit's by the world only."""

from atlas_pipeline.config import PipelineConfig
from atlas_pipeline.stage_settings import STAGE_READS, STAGES, stage_settings

ALL_BUT_BUNDLES = [s for s in STAGES if s not in ("world_bundle", "revisit_bundle")]


def _leaves() -> set[str]:
    return set(stage_settings(PipelineConfig(), "world_bundle"))


def test_every_field_but_check_thresholds_is_read_by_a_stage_that_computes():
    read = set().union(*(stage_settings(PipelineConfig(), s) for s in ALL_BUT_BUNDLES))
    assert _leaves() - read == {"localization.max_ate_m"}  # a blocking check's bound versions nothing


def test_the_world_reads_the_fit_and_the_map_settings_and_the_tracker_does_not():
    world, tracker = stage_settings(PipelineConfig(), "gaussian_world"), stage_settings(PipelineConfig(), "keyframes")
    for name in ("mapping.fit.epochs", "mapping.fit.lr_position_m", "mapping.colour_refinement.iterations",
                 "mapping.fill_depth_holes", "mapping.colour_delay_compensation", "mapping.max_depth_m"):
        assert name in world and name not in tracker, name
    assert "localization.photometric_weight" in tracker and "mapping.loop_closure" in tracker
    assert "localization.colour_delay_compensation" in stage_settings(PipelineConfig(), "render_evaluation")


def test_a_change_moves_exactly_the_stages_that_read_it():
    base, changed = PipelineConfig(), PipelineConfig().with_overrides({"mapping.fill_depth_holes": False})
    moved = [s for s in STAGES if stage_settings(base, s) != stage_settings(changed, s)]
    assert moved == ["gaussian_world", "world_bundle", "revisit_bundle"]


def test_every_stage_declares_its_reads():
    assert set(STAGE_READS) == set(STAGES)
