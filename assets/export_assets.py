"""What other tools read from a partition's world, as assets of their own group (``exports``):
``colmap_export`` and ``nerfstudio_export`` (GPU trainers), ``world_mesh`` (TSDF mesh) and
``occupancy_map`` (ROS map_server grid). Each unpacks its inputs, calls ``atlas_pipeline.interop``
and attaches metadata (a preview image for the mesh and the grid).

They read no config (the library's defaults: 2 cm voxels, 5 cm cells), so they have no
``settings/<asset>``; they are current while their code version and their inputs' data versions
are unchanged. They are left out of ``atlas_gs_all`` (a plain ``atlas-gs run`` does not compute
them); the job ``atlas_gs_exports`` materializes them, or
``dagster asset materialize --select 'group:exports' --partition synthetic -m assets.definitions``.
"""


from dagster import (AssetExecutionContext, AssetsDefinition, DataVersion, MetadataValue, Output,
                     PartitionsDefinition, asset)

from assets.io_managers import Reused
from assets.runs import tag_run_process
from assets.versioning import changes, data_version, record, versioned
from atlas_pipeline.gaussian_world.builder import GaussianWorld
from atlas_pipeline.interop.exports import build_mesh, build_occupancy
from atlas_pipeline.interop.frames import source_from_world
from atlas_pipeline.interop.trainer_export import TrainerExport, seed_points
from atlas_pipeline.localization.localizer import LocalizationReport
from atlas_pipeline.sensors.tum import FrameManifest
from atlas_pipeline.viz.plots import markdown_image

EXPORT_GROUP = "exports"
IO = "artifact_io"


def _reuse(context: AssetExecutionContext) -> Output | None:
    """The latest materialization when nothing it depends on changed and its files are intact
    (Dagster's staleness rule, as :func:`assets.versioning.reuse`, without settings); else None."""
    store, key, p, inst = context.resources.artifact_io, context.asset_key, context.partition_key, context.instance
    name = key.path[-1]
    store.lock_partition(p, context.run.run_id)
    tag_run_process(inst, context.run.run_id)
    code = context.assets_def.get_asset_spec(key).code_version
    why = changes(inst, key, p, code, context.assets_def.asset_deps[key]) or (
        [] if store.intact(name, p) else ["artifact files changed or missing"])
    if why:
        context.log.info(f"computing {name} [{p}]: {'; '.join(why)}")
        store.prepare(name, p)
        return None
    last = record(inst, key, p)
    context.log.info(f"reused cached {name} [{p}]: code and inputs unchanged since run {last.run_id}")
    return Output(Reused(name, p), data_version=DataVersion(data_version(last)),
                  metadata={**last.asset_materialization.metadata, "reused": True, "reused_from_run": last.run_id})


def build_export_assets(partitions_def: PartitionsDefinition) -> list[AssetsDefinition]:
    def export_asset(name: str, description: str):
        return asset(name=name, code_version="1", description=description, partitions_def=partitions_def,
                     io_manager_key=IO, group_name=EXPORT_GROUP)

    def trainer(fmt: str):
        @export_asset(f"{fmt}_export", f"The recording for GPU trainers as {fmt} (one zip: images, millimetre depth, "
                                       "the model at the localization's poses); unzip it to train.")
        def _trainer(context: AssetExecutionContext, raw_dataset: FrameManifest, gaussian_world: GaussianWorld,
                     localization_report: LocalizationReport):
            if (out := _reuse(context)) is not None:
                return out
            src = source_from_world(gaussian_world.field, raw_dataset, gaussian_world.keyframe_indices,
                                    gaussian_world.T_world_cam_keyframes, localization_report, "estimated",
                                    gaussian_world.pose_source, gaussian_world.map_id)
            return versioned(context, TrainerExport.build(src, fmt), {
                "n_images": int(len(src.frame_indices)), "n_points3D": int(len(seed_points(src.field)[0])),
                "pose_source": src.pose_source})

        return _trainer

    @export_asset("world_mesh", "Triangle mesh of the world: the keyframes' depth (from the dataset, at the keyframe "
                                "poses) fused into a TSDF of 2 cm voxels, marching cubes; mesh.ply and mesh.glb with "
                                "vertex colours.")
    def world_mesh(context: AssetExecutionContext, raw_dataset: FrameManifest, gaussian_world: GaussianWorld):
        if (out := _reuse(context)) is not None:
            return out
        art = build_mesh(_keyframe_source(raw_dataset, gaussian_world), log=context.log.info)
        return versioned(context, art, {"n_vertices": art.info["n_vertices"], "n_triangles": art.info["n_triangles"],
                                        "voxel_m": art.info["voxel_m"],
                                        "preview": MetadataValue.md(markdown_image(art.preview_png,
                                                                                   "mesh from the first keyframe"))})

    @export_asset("occupancy_map", "2D occupancy grid for navigation (ROS map_server PGM + YAML, Nav2 loads it): "
                                   "floor from the map, obstacles in a height band, free space from the keyframes' "
                                   "camera rays.")
    def occupancy_map(context: AssetExecutionContext, raw_dataset: FrameManifest, gaussian_world: GaussianWorld):
        if (out := _reuse(context)) is not None:
            return out
        art = build_occupancy(_keyframe_source(raw_dataset, gaussian_world), log=context.log.info)
        return versioned(context, art, {"n_free": art.info["n_free"], "n_occupied": art.info["n_occupied"],
                                        "resolution_m": art.info["resolution_m"],
                                        "preview": MetadataValue.md(markdown_image(art.preview_png,
                                                                                   "occupancy grid, +y up"))})

    return [trainer("colmap"), trainer("nerfstudio"), world_mesh, occupancy_map]


def _keyframe_source(raw_dataset: FrameManifest, gaussian_world: GaussianWorld):
    """The world's keyframes at their mapping poses, with the dataset's frames: what the mesh and
    the occupancy grid are built from."""
    return source_from_world(gaussian_world.field, raw_dataset, gaussian_world.keyframe_indices,
                             gaussian_world.T_world_cam_keyframes, None, "keyframes", map_id=gaussian_world.map_id,
                             recordings=gaussian_world.recordings,
                             keyframe_recording=gaussian_world.keyframe_recording)
